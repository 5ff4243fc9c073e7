"""Ranking of candidates: per-target order, weights and the Pareto front.

The candidates are :class:`~reachplan.planner.steering.candidates.Candidate` objects; ranking only reorders them
and never re-solves a needle.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np

from reachplan.planner.steering.candidates import Candidate


@dataclass(frozen=True)
class RankWeights:
    """Weights of the feasible candidates' order (lower score ranks first).

    Changing them re-ranks without re-solving anything.
    ``score = hole_distance_mm·per_mm_from_centre + peak_tension_n·per_newton + reach_error_mm·per_mm_reach
    − min(clearance_mm, clearance_cap_mm)·per_mm_clearance + steered·steering_cost``. Defaults: 1 per mm from
    the centre (medial entry), 1 per newton, 2 per mm of reach error, 1 per mm of clearance up to 5 mm
    (beyond that more room buys nothing), and 10 for steering at all (a steered needle costs a stylet, a
    tension schedule to follow by hand and more uncertainty, so it must enter at least ~10 mm more medially,
    plus its tension, to rank above a straight needle that reaches cleanly). Robust candidates are preferred:
    1 per mm that the worst-case reach error (see :mod:`reachplan.planner.steering.robustness`) exceeds the nominal one.

    Parameters
    ----------
    per_mm_from_centre : float, 1/mm
        Score per mm of the hole's distance from the template centre.
    per_newton : float, 1/N
        Score per newton of peak tendon tension.
    per_mm_reach : float, 1/mm
        Score per mm of reach error.
    per_mm_clearance : float, 1/mm
        Score taken off per mm of clearance, up to ``clearance_cap_mm``.
    clearance_cap_mm : float, mm
        Clearance beyond which more room buys nothing.
    steering_cost : float
        Score added for a steered needle.
    per_mm_worst_reach : float, 1/mm
        Score per mm that the worst-case reach error exceeds the nominal one.

    Raises
    ------
    ValueError
        A weight that is negative or not finite.
    """

    per_mm_from_centre: float = 1.0
    per_newton: float = 1.0
    per_mm_reach: float = 2.0
    per_mm_clearance: float = 1.0
    clearance_cap_mm: float = 5.0
    steering_cost: float = 10.0
    per_mm_worst_reach: float = 1.0

    def __post_init__(self) -> None:
        for k, v in dataclasses.asdict(self).items():
            if not (np.isfinite(v) and v >= 0):
                raise ValueError(f"rank weight {k} must be a finite number >= 0, got {v}")

    def score(self, c: Candidate) -> float:
        """Return the score of ``c`` (lower ranks first), with the worst-case clearance and reach when assessed.

        Parameters
        ----------
        c : Candidate
            A candidate; its worst-case numbers count when it was assessed for robustness (finite).

        Returns
        -------
        float
            The weighted score (dimensionless).
        """
        nominal = c.clearance_mm if np.isfinite(c.clearance_mm) else 0.0
        worst = c.worst_clearance_mm if np.isfinite(c.worst_clearance_mm) else nominal
        clear = min(nominal, worst, self.clearance_cap_mm)  # the worst case when assessed
        return (self.per_mm_from_centre * c.hole_distance_mm + self.per_newton * c.peak_tension_n
                + self.per_mm_reach * c.reach_error_mm - self.per_mm_clearance * clear
                + (self.steering_cost if c.steered else 0.0)
                + (self.per_mm_worst_reach * max(0.0, c.worst_reach_mm - c.reach_error_mm)
                   if np.isfinite(c.worst_reach_mm) else 0.0))


def rank_key(c: Candidate, weights: RankWeights = RankWeights()) -> tuple[float, ...]:
    """Return the sort key of ``c``: feasible candidates first, by :class:`RankWeights` score.

    Then the infeasible ones, most informative first: those that reach but collide, by reach error, then those
    that miss, by reach error, then those a model failed to solve.
    Ties keep a fixed order (by hole id, then design, applied in :func:`rank`): the ranking is deterministic.

    Parameters
    ----------
    c : Candidate
        The candidate to place.
    weights : RankWeights
        Weights of the feasible candidates' score.

    Returns
    -------
    tuple of float
        Sort key (group first, then score or reach error in mm, clearance and hole distance in mm, rounded to
        1e-6); smaller ranks first.
    """
    clear = -round(c.clearance_mm, 6) if np.isfinite(c.clearance_mm) else 0.0
    if c.feasible:  # assessed candidates (the shortlist) first: their score carries the robustness term
        return (0, 0 if np.isfinite(c.worst_reach_mm) else 1, round(weights.score(c), 6),
                round(c.hole_distance_mm, 6))
    group = 3 if c.failed else 1 if c.reaches else 2  # a model failed: its numbers are the screening's
    return (group, round(c.reach_error_mm, 6), clear, round(c.hole_distance_mm, 6))


def rank(candidates: Iterable[Candidate], weights: RankWeights = RankWeights()) -> dict[str, tuple[Candidate, ...]]:
    """Candidates grouped by target (targets in name order), each group sorted by :func:`rank_key`.

    Parameters
    ----------
    candidates : iterable of Candidate
        Candidates of any number of targets.
    weights : RankWeights
        Weights of the feasible candidates' score.

    Returns
    -------
    dict of str to tuple of Candidate
        Target name -> its candidates, best first.
    """
    groups: dict[str, list[Candidate]] = {}
    for c in candidates:
        groups.setdefault(c.target, []).append(c)
    return {t: tuple(sorted(sorted(groups[t], key=lambda c: (c.hole_id, c.steered, c.design_name)),
                            key=lambda c: rank_key(c, weights))) for t in sorted(groups)}


def pareto_front(candidates: Iterable[Candidate]) -> tuple[Candidate, ...]:
    """Return the feasible candidates not dominated in (hole distance ↓, reach error ↓, clearance ↑).

    Parameters
    ----------
    candidates : iterable of Candidate
        Candidates of one target; infeasible ones are left out.

    Returns
    -------
    tuple of Candidate
        The non-dominated feasible candidates, in input order.
    """
    feas = [c for c in candidates if c.feasible]
    pts = np.array([[c.hole_distance_mm, c.reach_error_mm, -c.clearance_mm] for c in feas]).reshape(-1, 3)
    keep = [i for i in range(len(feas))
            if not np.any(np.all(pts <= pts[i], axis=1) & np.any(pts < pts[i], axis=1))]
    return tuple(feas[i] for i in keep)
