"""Candidates (hole x target x schedule -> predicted path -> score) and their ranking.

A :class:`Candidate` carries every number the ranking uses, which model produced the path, and why it was
rejected when it was. JSON field names are a public contract: later versions add fields, never rename.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass, field
from typing import Any

import numpy as np


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
        Smallest surface distance from the needle to any organ at risk or bone (mm); 0 when touching.
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

    @property
    def feasible(self) -> bool:
        """Reaches its target without touching an organ at risk."""
        return self.reaches and not self.collides

    def to_json(self) -> dict[str, Any]:
        """The candidate as JSON-ready values (mm, N)."""
        return {
            "target": self.target,
            "hole_id": self.hole_id,
            "hole_distance_mm": round(self.hole_distance_mm, 3),
            "reach_error_mm": round(self.reach_error_mm, 3),
            "clearance_mm": round(self.clearance_mm, 3),
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
        }


def rank_key(c: Candidate) -> tuple[float, ...]:
    """Medial-entry order. Feasible candidates first: the most medial hole, then the smallest reach error,
    then the largest clearance. Then the infeasible ones, most informative first: those that reach but
    collide, by reach error, then those that miss, by reach error. Ties keep a fixed order (by hole id,
    applied in :func:`rank`), so the ranking is deterministic."""
    if c.feasible:
        return (0, round(c.hole_distance_mm, 6), round(c.reach_error_mm, 6), -round(c.clearance_mm, 6))
    return (1 if c.reaches else 2, round(c.reach_error_mm, 6), -round(c.clearance_mm, 6), round(c.hole_distance_mm, 6))


def rank(candidates: Iterable[Candidate]) -> dict[str, tuple[Candidate, ...]]:
    """Candidates grouped by target (targets in name order), each group sorted by :func:`rank_key`."""
    groups: dict[str, list[Candidate]] = {}
    for c in candidates:
        groups.setdefault(c.target, []).append(c)
    return {t: tuple(sorted(sorted(groups[t], key=lambda c: c.hole_id), key=rank_key)) for t in sorted(groups)}
