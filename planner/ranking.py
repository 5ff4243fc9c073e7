"""Candidates (hole x target x schedule -> predicted path -> score) and their ranking.

A :class:`Candidate` carries every number the ranking uses, which model produced the path, and why it was
rejected when it was. JSON field names are a public contract: later versions add fields, never rename.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from planner.schedule import TensionSchedule


@dataclass(frozen=True)
class Target:
    """A point to reach: ``position_mm`` (3,) float, mm, LPS (e.g. the centroid of a target ROI)."""

    name: str
    position_mm: tuple[float, float, float]

    def __post_init__(self) -> None:
        if len(self.position_mm) != 3 or not all(np.isfinite(self.position_mm)):
            raise ValueError(f"target {self.name!r}: position must be three finite numbers (mm, LPS)")


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
    model : str
        The model that produced the path (``straight`` or a rod/insertion model name).
    collides : bool
        True when the needle touches or enters an organ at risk or bone.
    reaches : bool
        True when ``reach_error_mm`` is within the plan's reach tolerance.
    reason : str
        Why the candidate is rejected ("" when it is feasible).
    path_mm : (n, 3) float, mm, LPS
        Predicted needle centreline from the hole (first point) to the tip (last point).
    design : str
        Stylet preset ("" for a plain straight needle).
    schedule : TensionSchedule or None
        Tension and roll along the insertion (None for a straight needle).
    worst_reach_mm, worst_clearance_mm, worst_case : float, float, str
        Robustness (see :mod:`planner.robustness`): worst reach error and smallest clearance under
        tension, roll and entry-angle errors, and which error gave them; NaN/"" when not assessed.
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
    model: str
    collides: bool
    reaches: bool
    reason: str
    path_mm: np.ndarray = field(repr=False)
    design: str = ""
    schedule: TensionSchedule | None = field(default=None, repr=False)
    worst_reach_mm: float = float("nan")
    worst_clearance_mm: float = float("nan")
    worst_case: str = ""

    @property
    def feasible(self) -> bool:
        """Reaches its target without touching an organ at risk."""
        return self.reaches and not self.collides

    def to_json(self) -> dict[str, Any]:
        """The candidate as JSON-ready values (mm, N)."""
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
            "model": self.model,
            "collides": self.collides,
            "reaches": self.reaches,
            "feasible": self.feasible,
            "reason": self.reason,
            "entry_position_mm": [round(float(v), 3) for v in self.path_mm[0]],
            "tip_position_mm": [round(float(v), 3) for v in self.path_mm[-1]],
            "design": self.design,
            "schedule": sched,
            "robustness": None if np.isnan(self.worst_reach_mm) else {
                "worst_reach_mm": round(self.worst_reach_mm, 3),
                "worst_clearance_mm": round(self.worst_clearance_mm, 3) if np.isfinite(self.worst_clearance_mm)
                else None,
                "worst_case": self.worst_case},
        }


@dataclass(frozen=True)
class RankWeights:
    """Weights of the feasible candidates' order (lower score ranks first); changing them re-ranks without
    re-solving anything.

    ``score = hole_distance_mm·per_mm_from_centre + peak_tension_n·per_newton + reach_error_mm·per_mm_reach
    − min(clearance_mm, clearance_cap_mm)·per_mm_clearance + steered·steering_cost``. Defaults: 1 per mm from
    the centre (medial entry), 1 per newton, 2 per mm of reach error, 1 per mm of clearance up to 5 mm
    (beyond that more room buys nothing), and 10 for steering at all (a steered needle costs a stylet, a
    tension schedule to follow by hand and more uncertainty, so it must enter at least ~10 mm more medially,
    plus its tension, to rank above a straight needle that reaches cleanly). Robust candidates are preferred:
    1 per mm that the worst-case reach error (see :mod:`planner.robustness`) exceeds the nominal one.
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
        nominal = c.clearance_mm if np.isfinite(c.clearance_mm) else 0.0
        worst = c.worst_clearance_mm if np.isfinite(c.worst_clearance_mm) else nominal
        clear = min(nominal, worst, self.clearance_cap_mm)  # the worst case when assessed
        return (self.per_mm_from_centre * c.hole_distance_mm + self.per_newton * c.peak_tension_n
                + self.per_mm_reach * c.reach_error_mm - self.per_mm_clearance * clear
                + (self.steering_cost if c.steered else 0.0)
                + (self.per_mm_worst_reach * max(0.0, c.worst_reach_mm - c.reach_error_mm)
                   if np.isfinite(c.worst_reach_mm) else 0.0))


def rank_key(c: Candidate, weights: RankWeights = RankWeights()) -> tuple[float, ...]:
    """Feasible candidates first, by :class:`RankWeights` score. Then the infeasible ones, most
    informative first: those that reach but collide, by reach error, then those that miss, by reach error.
    Ties keep a fixed order (by hole id, then design, applied in :func:`rank`): the ranking is deterministic."""
    clear = -round(c.clearance_mm, 6) if np.isfinite(c.clearance_mm) else 0.0
    if c.feasible:  # assessed candidates (the shortlist) first: their score carries the robustness term
        return (0, 0 if np.isfinite(c.worst_reach_mm) else 1, round(weights.score(c), 6),
                round(c.hole_distance_mm, 6))
    return (1 if c.reaches else 2, round(c.reach_error_mm, 6), clear, round(c.hole_distance_mm, 6))


def rank(candidates: Iterable[Candidate], weights: RankWeights = RankWeights()) -> dict[str, tuple[Candidate, ...]]:
    """Candidates grouped by target (targets in name order), each group sorted by :func:`rank_key`."""
    groups: dict[str, list[Candidate]] = {}
    for c in candidates:
        groups.setdefault(c.target, []).append(c)
    return {t: tuple(sorted(sorted(groups[t], key=lambda c: (c.hole_id, c.steered, c.design)),
                            key=lambda c: rank_key(c, weights))) for t in sorted(groups)}


def pareto_front(candidates: Iterable[Candidate]) -> tuple[Candidate, ...]:
    """The feasible candidates not dominated in (hole distance ↓, reach error ↓, clearance ↑)."""
    feas = [c for c in candidates if c.feasible]
    pts = np.array([[c.hole_distance_mm, c.reach_error_mm, -c.clearance_mm] for c in feas]).reshape(-1, 3)
    keep = [i for i in range(len(feas))
            if not np.any(np.all(pts <= pts[i], axis=1) & np.any(pts < pts[i], axis=1))]
    return tuple(feas[i] for i in keep)
