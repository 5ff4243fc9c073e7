"""The outcome of the steering search: every scored candidate and the ranking per target."""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from dataclasses import dataclass

from reachplan.planner.case.config import PlanConfig
from reachplan.planner.ranking import RankWeights, pareto_front, rank
from reachplan.planner.steering.candidates import Candidate

#: a steered needle counts as a clean alternative to a blocked straight one from this clearance (mm) on
CLEAN_CLEARANCE_MM = 2.0


@dataclass(frozen=True, eq=False)
class BlockedNeedle:
    """A straight needle that reaches its target but collides, and the target's clean steered alternative.

    :meth:`PlanResult.blocked_straight` lists them.

    Parameters
    ----------
    straight : Candidate
        The straight candidate (``reaches`` and ``collides``; ``closest_organ`` and ``contact_depth_mm`` say where).
    alternative : Candidate or None
        The target's most medial feasible steered candidate with at least :data:`CLEAN_CLEARANCE_MM` of clearance;
        None when there is none.
    """

    straight: Candidate
    alternative: Candidate | None

    def to_json(self) -> dict[str, object]:
        """Return the row of plan.json's ``blocked_straight`` (mm, N; the candidates' rounding).

        Returns
        -------
        dict
            ``target``, ``hole_id``, ``hole_distance_mm``, ``organ``, ``contact_depth_mm`` and
            ``steered_alternative`` (hole, distance, clearance, organ and peak tension, or None).
        """
        c = self.straight.to_json()
        alt = None if self.alternative is None else self.alternative.to_json()
        return {"target": c["target"], "hole_id": c["hole_id"], "hole_distance_mm": c["hole_distance_mm"],
                "organ": c["closest_organ"], "contact_depth_mm": c["contact_depth_mm"],
                "steered_alternative": None if alt is None else {
                    k: alt[k] for k in ("hole_id", "hole_distance_mm", "clearance_mm", "closest_organ",
                                        "peak_tension_n")}}


@dataclass(frozen=True, eq=False)
class PlanResult:
    """All scored candidates and their ranking per target.

    Parameters
    ----------
    candidates : tuple of Candidate
        Every candidate scored, straight and steered.
    ranking : dict of str to tuple of Candidate
        Per target name, its candidates best first.
    config : PlanConfig
        The settings the plan was made with.
    """

    candidates: tuple[Candidate, ...]
    ranking: dict[str, tuple[Candidate, ...]]
    config: PlanConfig

    def rerank(self, weights: RankWeights) -> PlanResult:
        """Return the same candidates in the order of other weights (nothing is re-solved).

        Parameters
        ----------
        weights : RankWeights
            The score weights to order by (:class:`RankWeights`).

        Returns
        -------
        PlanResult
            The same candidates ranked anew; the config carries ``weights``.
        """
        return PlanResult(self.candidates, rank(self.candidates, weights), dataclasses.replace(self.config,
                                                                                              weights=weights))

    def best(self, target: str, steered: bool) -> Candidate | None:
        """Return the best-ranked feasible straight (or steered) candidate of a target, if any.

        Parameters
        ----------
        target : str
            The target's name.
        steered : bool
            True for a steered needle, False for a straight one.

        Returns
        -------
        Candidate or None
            None when no candidate of that kind is feasible.
        """
        return next((c for c in self.ranking[target] if c.feasible and c.steered == steered), None)

    def blocked_straight(self) -> tuple[BlockedNeedle, ...]:
        """Return the straight needles that reach their target but collide, each with its steered alternative.

        Returns
        -------
        tuple of BlockedNeedle
            In the order of the ranking, target by target.
        """
        out = []
        for cands in self.ranking.values():
            clean = [c for c in cands if c.steered and c.feasible and c.clearance_mm >= CLEAN_CLEARANCE_MM]
            alt = min(clean, key=lambda c: c.hole_distance_mm) if clean else None
            out += [BlockedNeedle(c, alt) for c in cands if not c.steered and c.reaches and c.collides]
        return tuple(out)

    def ranking_json(self) -> dict[str, list[dict[str, object]]]:
        """Return the ranked candidates of every target as JSON-ready values (ranking.json).

        Returns
        -------
        dict of str to list of dict
            Per target, its candidates in rank order (:meth:`Candidate.to_json`, with ``pareto``).
        """
        out: dict[str, list[dict[str, object]]] = {}
        for t, cands in self.ranking.items():
            front = {id(c) for c in pareto_front(cands)}
            out[t] = [{**c.to_json(), "pareto": id(c) in front} for c in cands]
        return out

    def to_json(self) -> dict[str, object]:
        """Return the configuration and, per target, the ranked candidates as JSON-ready values (mm, N, LPS).

        Returns
        -------
        dict of str to object
            ``config`` and, per target, the most medial straight and steered hole distances (mm), the medial gain,
            the best of each kind and every ranked candidate.
        """
        targets: dict[str, object] = {}
        ranked = self.ranking_json()
        for t, cands in self.ranking.items():
            straight, steered = self.best(t, False), self.best(t, True)
            straight_d = [c.hole_distance_mm for c in cands if c.feasible and not c.steered]
            steered_d = [c.hole_distance_mm for c in cands if c.feasible and c.steered
                         and c.clearance_mm >= CLEAN_CLEARANCE_MM]
            targets[t] = {
                "most_medial_straight_mm": round(min(straight_d), 3) if straight_d else None,
                "most_medial_steered_mm": round(min(steered_d), 3) if steered_d else None,
                "medial_gain_mm": round(min(straight_d) - min(steered_d), 3) if straight_d and steered_d else None,
                "best_straight": None if straight is None else straight.to_json(),
                "best_steered": None if steered is None else steered.to_json(),
                "candidates": ranked[t],
            }
        return {"config": dataclasses.asdict(self.config), "targets": targets}


def choose_needles(result: PlanResult, targets: Sequence[str] | None = None,
                   steered: bool | None = None) -> tuple[Candidate, ...]:
    """One needle per target: its top-ranked feasible candidate whose hole no earlier target took.

    ``steered``: True takes steered candidates only, False straight ones only, None either. Targets without a
    feasible candidate (of that kind) on a free hole get none (their ranking says why).

    Parameters
    ----------
    result : PlanResult
        The ranked plan.
    targets : sequence of str or None
        Targets in the order they pick their hole; None: the ranking's order.
    steered : bool or None
        True: steered candidates only; False: straight ones only; None: either.

    Returns
    -------
    tuple of Candidate
        At most one per target, in the order of ``targets``.
    """
    used: set[str] = set()
    out: list[Candidate] = []
    for t in targets or list(result.ranking):
        for c in result.ranking.get(t, ()):
            if c.feasible and c.hole_id not in used and (steered is None or c.steered == steered):
                used.add(c.hole_id)
                out.append(c)
                break
    return tuple(out)
