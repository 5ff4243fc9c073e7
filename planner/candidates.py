"""Candidate enumeration: holes x targets -> predicted needle path -> clearance -> score."""

from __future__ import annotations

from collections.abc import Iterable, Sequence

import numpy as np

from planner.collision import Organ, check_path
from planner.ranking import Candidate, Target
from planner.schedule import TensionSchedule


def straight_path(entry_mm: np.ndarray, direction: np.ndarray, depth_mm: float) -> np.ndarray:
    """A straight needle from ``entry_mm`` along unit ``direction`` to ``depth_mm``: (2, 3) float, mm, LPS
    (one capsule; collision depths are still resolved to 1 mm by the collision check)."""
    return np.asarray(entry_mm, float) + np.outer([0.0, depth_mm], direction)


def score_path(
    target: Target,
    hole_id: str,
    hole_distance_mm: float,
    path_mm: np.ndarray,
    organs: Sequence[Organ],
    needle_radius_mm: float,
    reach_tolerance_mm: float,
    model: str,
    steered: bool = False,
    peak_tension_n: float = 0.0,
    reason: str = "",
    design: str = "",
    schedule: TensionSchedule | None = None,
    depth_mm: float | None = None,
    check: bool = True,
) -> Candidate:
    """Score one predicted path: reach error at the target, clearance and collisions against ``organs``.

    ``depth_mm`` is the inserted arc length (default: the polyline's length); ``check=False`` skips the
    collision check (clearance NaN) for a candidate that does not reach anyway.
    """
    tip = path_mm[-1]
    reach = float(np.linalg.norm(tip - np.asarray(target.position_mm)))
    depth = float(np.sum(np.linalg.norm(np.diff(path_mm, axis=0), axis=1))) if depth_mm is None else depth_mm
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
    entry_mm, direction : (n_holes, 3) float, mm and unit vectors, LPS
    hole_distances_mm : (n_holes,) float, mm
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
                                  reach_tolerance_mm, "straight", reason=reason, check=reaches))
    return out
