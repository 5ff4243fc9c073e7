"""Candidates: holes x targets -> predicted needle path -> clearance -> score.

A :class:`Candidate` carries every number the ranking uses, which model produced the path, and why it was
rejected when it was. JSON field names are a public contract: later versions add fields, never rename.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from reachplan._arrays import arc_length_mm
from reachplan.planner.geometry.collision import Organ, check_path
from reachplan.planner.steering.insertion import STRAIGHT, ModelInfo
from reachplan.planner.steering.schedule import TensionSchedule
from reachplan.rod_model.design import RodDesign


@dataclass(frozen=True)
class Target:
    """A point to reach (e.g. the centroid of a target ROI).

    Parameters
    ----------
    name : str
        The target's name (the ROI's).
    position_mm : (3,) float, mm, LPS
        The point.

    Raises
    ------
    ValueError
        ``position_mm`` is not three finite numbers.
    """

    name: str
    position_mm: tuple[float, float, float]

    def __post_init__(self) -> None:
        if len(self.position_mm) != 3 or not all(np.isfinite(self.position_mm)):
            raise ValueError(f"target {self.name!r}: position must be three finite numbers (mm, LPS)")


@dataclass(frozen=True, eq=False)
class TissueBand:
    """A steered needle's band of paths over a range of tissue moduli, and its worst case over the band.

    The schedule is the planned one; only the tissue changes (every modulus of the plan scaled alike). Computed by
    :func:`reachplan.planner.steering.tissue_band.assess_band`.

    Parameters
    ----------
    scales : (b,) tuple of float
        The factor on the plan's moduli of each path, increasing; 1 is the planned (nominal) path.
    moduli_pa : (b,) tuple of float, Pa
        The tissue modulus at the needle's tip on each path (the plan's modulus there times the scale).
    paths_mm : (b,) tuple of (n, 3) float, mm, LPS
        Each path, hole (first point) to tip; the nominal one is the needle's own path.
    reach_mm : (b,) tuple of float, mm
        Each path's tip distance from the aim (the target, or the implant needle's planned tip).
    clearance_mm : (b,) tuple of float, mm
        Each path's smallest clearance to an organ at risk (0 when it touches one).
    worst_reach_mm, worst_clearance_mm : float, mm
        The largest reach error and the smallest clearance over the band.
    worst_case : str
        The path that sets the worst case (``"nominal"`` when none is worse), with its modulus.
    model : str
        The insertion model of the band's change of shape (``ModelInfo.label``).
    source : str
        Where the modulus range comes from (a citation, or ASSUMED with the reason).
    """

    scales: tuple[float, ...]
    moduli_pa: tuple[float, ...]
    paths_mm: tuple[np.ndarray, ...] = field(repr=False)
    reach_mm: tuple[float, ...]
    clearance_mm: tuple[float, ...]
    worst_reach_mm: float
    worst_clearance_mm: float
    worst_case: str
    model: str
    source: str

    @staticmethod
    def failed(reason: str, source: str) -> TissueBand:
        """Return a band that could not be computed: no paths, NaN worst case, ``worst_case`` the reason.

        Parameters
        ----------
        reason : str
            Why (the model's failure).
        source : str
            Where the modulus range comes from.

        Returns
        -------
        TissueBand
            Empty, saying ``not computed: <reason>``.
        """
        nan = float("nan")
        return TissueBand((), (), (), (), (), nan, nan, f"not computed: {reason}", "", source)

    def to_json(self) -> dict[str, Any]:
        """Return the band as JSON-ready values (plan.json, ranking.json).

        Returns
        -------
        dict of str to JSON value
            ``moduli_pa`` (Pa), ``scales``, per path ``tip_position_mm`` (mm, LPS), ``reach_mm`` and
            ``clearance_mm`` (mm; None when not finite), ``worst_reach_mm``, ``worst_clearance_mm``, ``worst_case``,
            ``model`` and ``source``.
        """
        def r(v: float) -> float | None:
            return round(float(v), 3) if np.isfinite(v) else None

        return {"scales": [round(s, 4) for s in self.scales], "moduli_pa": [round(m, 1) for m in self.moduli_pa],
                "tip_position_mm": [[round(float(v), 3) for v in p[-1]] for p in self.paths_mm],
                "reach_mm": [r(v) for v in self.reach_mm], "clearance_mm": [r(v) for v in self.clearance_mm],
                "worst_reach_mm": r(self.worst_reach_mm), "worst_clearance_mm": r(self.worst_clearance_mm),
                "worst_case": self.worst_case, "model": self.model, "source": self.source}


@dataclass(frozen=True, eq=False)
class Candidate:
    """One needle candidate for one target, with its score.

    Parameters
    ----------
    target, hole_id : str
    hole_distance_mm : float
        Distance of the hole from the template centre (mm); smaller = more medial.
    reach_error_mm : float
        Distance from the predicted tip to the target point (mm).
    clearance_mm : float
        Smallest surface distance from the needle to any organ at risk or bone (mm); 0 when touching;
        NaN when it was not checked because the candidate does not reach (JSON ``null``, with the reason).
    closest_organ : str
        The organ that sets ``clearance_mm``.
    insertion_depth_mm : float
        Arc length of needle inserted beyond the template plane (mm).
    steered : bool
        False for a straight needle.
    peak_tension_n : float
        Largest tendon tension of the schedule (N); 0 for a straight needle.
    model : ModelInfo
        The model that produced the path, with its settings (:data:`~reachplan.planner.steering.insertion.STRAIGHT`
        for a straight needle); JSON ``model`` is its label, e.g. ``kinematic+planar_beam``.
    collides : bool
        True when the needle touches or enters an organ at risk or bone.
    reaches : bool
        True when ``reach_error_mm`` is within the plan's reach tolerance.
    reason : str
        Why the candidate is rejected ("" when it is feasible).
    failed : bool
        True when a model failed for this candidate (a solve that did not converge, a shape out of range);
        ``reason`` says which and why, and the candidate is not feasible.
    path_mm : (n, 3) float, mm, LPS
        Predicted needle centreline from the hole (first point) to the tip (last point).
    design : RodDesign or None
        The stylet design (None for a plain straight needle); JSON ``design`` is its preset name.
    schedule : TensionSchedule or None
        Tension and roll along the insertion (None for a straight needle).
    contact_depth_mm : float or None
        Insertion depth (arc length from the template plane, mm, to 1 mm) where the needle first touches
        ``closest_organ`` when it collides; None when it does not.
    worst_reach_mm, worst_clearance_mm, worst_case : float, float, str
        Robustness (see :mod:`reachplan.planner.steering.robustness`): worst reach error and smallest clearance under
        tension, roll and entry-angle errors, and which error gave them; NaN/"" when not assessed.
    tissue_band : TissueBand or None
        The path over the plan's range of tissue moduli and its worst case (a steered needle the plan shows); None
        when not computed.
    model_tolerance_mm : float, mm
        The in-tissue tip error the candidate's margins allow its model (:mod:`reachplan.planner.case.fidelity`);
        NaN when no model choice was made (a straight needle, a candidate not feasible on screening).
    model_reason : str
        Why ``model`` solved it, in words ("" when not recorded).
    """

    target: str
    hole_id: str
    hole_distance_mm: float
    reach_error_mm: float
    clearance_mm: float
    closest_organ: str
    insertion_depth_mm: float
    steered: bool
    peak_tension_n: float
    model: ModelInfo
    collides: bool
    reaches: bool
    reason: str
    path_mm: np.ndarray = field(repr=False)
    design: RodDesign | None = field(default=None, repr=False)
    schedule: TensionSchedule | None = field(default=None, repr=False)
    contact_depth_mm: float | None = None
    worst_reach_mm: float = float("nan")
    worst_clearance_mm: float = float("nan")
    worst_case: str = ""
    failed: bool = False
    tissue_band: TissueBand | None = None
    model_tolerance_mm: float = float("nan")
    model_reason: str = ""

    @property
    def feasible(self) -> bool:
        """Reaches its target without touching an organ at risk, and every model solved it."""
        return self.reaches and not self.collides and not self.failed

    @property
    def design_name(self) -> str:
        """The stylet preset's name ("" for a plain straight needle)."""
        return "" if self.design is None else self.design.name

    def to_json(self) -> dict[str, Any]:
        """Return the candidate as JSON-ready values (mm, N, LPS).

        Returns
        -------
        dict of str to JSON value
            Its fields rounded to 1e-3 (``contact_depth_mm`` to 0.1 mm), ``entry_position_mm`` and
            ``tip_position_mm`` (mm, LPS), the schedule as rows (depth mm, tension N, roll deg) and the robustness
            (None when not assessed), the tissue band (:meth:`TissueBand.to_json`; None when not computed);
            ``clearance_mm`` None when not finite.
        """
        sched = None if self.schedule is None else [
            [round(float(d), 3), round(float(t), 3), round(float(r), 3)]
            for d, t, r in zip(self.schedule.depth_mm, self.schedule.tension_n, self.schedule.roll_deg, strict=True)]
        return {
            "target": self.target,
            "hole_id": self.hole_id,
            "hole_distance_mm": round(self.hole_distance_mm, 3),
            "reach_error_mm": round(self.reach_error_mm, 3),
            "clearance_mm": round(self.clearance_mm, 3) if np.isfinite(self.clearance_mm) else None,
            "closest_organ": self.closest_organ,
            "insertion_depth_mm": round(self.insertion_depth_mm, 3),
            "steered": self.steered,
            "peak_tension_n": round(self.peak_tension_n, 3),
            "model": self.model.label,
            "model_tolerance_mm": round(self.model_tolerance_mm, 3) if np.isfinite(self.model_tolerance_mm) else None,
            "model_reason": self.model_reason,
            "collides": self.collides,
            "contact_depth_mm": None if self.contact_depth_mm is None else round(self.contact_depth_mm, 1),
            "reaches": self.reaches,
            "feasible": self.feasible,
            "reason": self.reason,
            "entry_position_mm": [round(float(v), 3) for v in self.path_mm[0]],
            "tip_position_mm": [round(float(v), 3) for v in self.path_mm[-1]],
            "design": self.design_name,
            "schedule": sched,
            "robustness": None if np.isnan(self.worst_reach_mm) else {
                "worst_reach_mm": round(self.worst_reach_mm, 3),
                "worst_clearance_mm": round(self.worst_clearance_mm, 3) if np.isfinite(self.worst_clearance_mm)
                else None,
                "worst_case": self.worst_case},
            "tissue_band": None if self.tissue_band is None else self.tissue_band.to_json(),
        }


def mark_failed(candidate: Candidate, reason: str) -> Candidate:
    """Return the candidate marked as failed (not feasible) with ``reason`` added to its reasons.

    Its numbers stay those of the model that did solve it (``model`` names it).

    Parameters
    ----------
    candidate : Candidate
        The candidate a model failed on.
    reason : str
        Which model failed and why.

    Returns
    -------
    Candidate
        A copy with ``failed=True`` and the reasons joined by ``"; "``.
    """
    return dataclasses.replace(candidate, failed=True, reason="; ".join(r for r in (candidate.reason, reason) if r))


def straight_path(entry_mm: np.ndarray, direction: np.ndarray, depth_mm: float) -> np.ndarray:
    """Return a straight needle from ``entry_mm`` along unit ``direction`` to ``depth_mm``.

    One capsule; collision depths are still resolved to 1 mm by the collision check.

    Parameters
    ----------
    entry_mm : (3,) float, mm, LPS
        The hole's entry point on the template plane.
    direction : (3,) float, unit vector, LPS
        The hole's axis (insertion direction).
    depth_mm : float, mm
        Inserted length.

    Returns
    -------
    (2, 3) float, mm, LPS
        Entry and tip.
    """
    return np.asarray(entry_mm, float) + np.outer([0.0, depth_mm], direction)


def worst_case(nominal: Candidate, scored: Iterable[tuple[str, Candidate]]) -> tuple[float, float, str]:
    """Return the largest reach error, the smallest clearance and what sets the worst case over ``scored``.

    Parameters
    ----------
    nominal : Candidate
        The candidate as planned (its reach error and clearance start the worst case, ``"nominal"``).
    scored : iterable of (str, Candidate)
        Each variant's label and the variant scored (``score_path``).

    Returns
    -------
    worst_reach_mm : float, mm
    worst_clearance_mm : float, mm
    worst : str
        The label of the variant with the largest reach error, or ``"<label>: collides with <organ>"`` of a later
        variant with a smaller clearance that collides.
    """
    worst_reach, worst_clear, worst = nominal.reach_error_mm, nominal.clearance_mm, "nominal"
    for label, c in scored:
        if c.reach_error_mm > worst_reach:
            worst_reach, worst = c.reach_error_mm, label
        if c.clearance_mm < worst_clear:
            worst_clear = c.clearance_mm
            if c.collides:
                worst = f"{label}: collides with {c.closest_organ}"
    return float(worst_reach), float(worst_clear), worst


def score_path(
    target: Target,
    hole_id: str,
    hole_distance_mm: float,
    path_mm: np.ndarray,
    organs: Sequence[Organ],
    needle_radius_mm: float,
    reach_tolerance_mm: float,
    model: ModelInfo,
    steered: bool = False,
    peak_tension_n: float = 0.0,
    reason: str = "",
    design: RodDesign | None = None,
    schedule: TensionSchedule | None = None,
    depth_mm: float | None = None,
    check: bool = True,
) -> Candidate:
    """Score one predicted path: reach error at the target, clearance and collisions against ``organs``.

    Parameters
    ----------
    target : Target
        The point to reach.
    hole_id : str
        The template hole the path enters by.
    hole_distance_mm : float, mm
        Distance of the hole from the template centre.
    path_mm : (n, 3) float, mm, LPS
        Needle centreline from the hole (first point) to the tip (last point).
    organs : sequence of Organ
        Organs at risk and bone to check against.
    needle_radius_mm : float, mm
        Needle radius of the collision check.
    reach_tolerance_mm : float, mm
        A tip within this distance of the target reaches it.
    model : ModelInfo
        The model that produced the path.
    steered : bool
        False for a straight needle.
    peak_tension_n : float, N
        Largest tendon tension of the schedule.
    reason : str
        A reason to carry over (e.g. why the depth was clipped); "" for none.
    design : RodDesign or None
        The stylet design (None for a plain straight needle).
    schedule : TensionSchedule or None
        Tension and roll along the insertion (None for a straight needle).
    depth_mm : float or None, mm
        The inserted arc length; None: the polyline's length.
    check : bool
        False skips the collision check (clearance NaN) for a candidate that does not reach anyway.

    Returns
    -------
    Candidate
        Reach error, clearance (0 when it collides, inf with no organ, NaN unchecked), closest organ, first
        contact depth and the reasons it is rejected.
    """
    tip = path_mm[-1]
    reach = float(np.linalg.norm(tip - np.asarray(target.position_mm)))
    depth = float(arc_length_mm(path_mm)[-1]) if depth_mm is None else depth_mm
    checks = check_path(path_mm, needle_radius_mm, tuple(organs)) if check else ()
    hits = sorted((c for c in checks if c.collides), key=lambda c: (c.contact_s_mm or 0.0, c.organ))
    if hits:
        clearance, organ = 0.0, hits[0].organ
    elif checks:
        nearest = min(checks, key=lambda c: (c.clearance_mm, c.organ))
        clearance, organ = nearest.clearance_mm, nearest.organ
    elif check:
        clearance, organ = float("inf"), ""
    else:
        clearance, organ = float("nan"), ""
    reaches = reach <= reach_tolerance_mm
    reasons = [reason] if reason else []
    if hits:
        reasons.append(f"collides with {hits[0].organ} at depth {hits[0].contact_s_mm or 0.0:.1f} mm")
    if not reaches:
        reasons.append(f"misses the target by {reach:.1f} mm")
    return Candidate(
        target=target.name, hole_id=hole_id, hole_distance_mm=hole_distance_mm, reach_error_mm=reach,
        clearance_mm=clearance, closest_organ=organ, insertion_depth_mm=depth, steered=steered,
        peak_tension_n=peak_tension_n, model=model, collides=bool(hits), reaches=reaches,
        reason="; ".join(reasons), path_mm=path_mm, design=design, schedule=schedule,
        contact_depth_mm=(hits[0].contact_s_mm or 0.0) if hits else None,
    )


def straight_candidates(
    targets: Iterable[Target],
    hole_ids: Sequence[str],
    hole_distances_mm: np.ndarray,
    entry_mm: np.ndarray,
    direction: np.ndarray,
    organs: Sequence[Organ],
    needle_radius_mm: float,
    reach_tolerance_mm: float = 2.0,
    max_depth_mm: float = 200.0,
) -> list[Candidate]:
    """Straight-needle candidates for every hole and target.

    The tip is placed at the target's depth along the hole's axis (the closest approach of a straight
    needle), so the reach error is the target's distance from that axis. Candidates that miss are not
    checked for collisions (clearance NaN, JSON null): they are rejected for the miss, which their reason says.

    Parameters
    ----------
    targets : iterable of Target
        The points to reach.
    hole_ids : sequence of str
        The template holes, ``n_holes`` of them.
    hole_distances_mm : (n_holes,) float, mm
        Distance of each hole from the template centre.
    entry_mm : (n_holes, 3) float, mm, LPS
        Entry point of each hole on the template plane.
    direction : (n_holes, 3) float, unit vectors, LPS
        Axis of each hole.
    organs : sequence of Organ
        What the candidates that reach are checked against.
    needle_radius_mm : float, mm
        Radius of the needles.
    reach_tolerance_mm : float, mm
        Largest tip-to-target distance that still counts as reaching.
    max_depth_mm : float, mm
        Longest insertion; deeper targets are clipped to it (and missed).

    Returns
    -------
    list of Candidate
        One per target and hole, targets in the given order, holes in ``hole_ids`` order.
    """
    out: list[Candidate] = []
    for target in targets:
        t = np.asarray(target.position_mm, float)
        depths = np.einsum("ij,ij->i", t - entry_mm, direction)
        for k, hole_id in enumerate(hole_ids):
            depth = float(depths[k])
            reason = ""
            if depth <= 0.0:
                depth, reason = 1.0, "target lies behind the template plane"
            elif depth > max_depth_mm:
                depth, reason = max_depth_mm, f"target deeper than the needle's {max_depth_mm:.0f} mm"
            path = straight_path(entry_mm[k], direction[k], depth)
            reaches = float(np.linalg.norm(path[-1] - t)) <= reach_tolerance_mm
            out.append(score_path(target, hole_id, float(hole_distances_mm[k]), path, organs, needle_radius_mm,
                                  reach_tolerance_mm, STRAIGHT, reason=reason, check=reaches))
    return out
