"""The dose specification point of a volume prescription: a point of the target that receives the prescribed dose.

Eclipse writes the Brachy Application Setup Dose with its Dose Specification Point (300A,00A2): the dose of the plan
per fraction there (rtplan_conventions.md §3; the HDR example specifies it at Point A). reachplan prescribes to a
volume (the dose whose HR-CTV D90 meets the aim), so it specifies that dose at a point inside the target where the
planned dose equals it: on the segment from the target voxel nearest the target's centroid that receives at least the
prescription to the nearest target voxel that receives less, found by bisection. A checker that recomputes the
dose there with TG-43 finds the setup dose.
"""

from __future__ import annotations

import numpy as np

from reachplan.planner.dose.dwells import DwellSet, dose_at_points
from reachplan.planner.dose.tg43 import Tg43Kernel

#: Bisection steps on the segment between the two voxel centres (2^-40 of a few mm: far below 1e-6 mm).
BISECTION_STEPS = 40


def prescription_point(target_points_mm: np.ndarray, dwells: DwellSet, kernel: Tg43Kernel, air_kerma_u: float,
                       dose_gy: float) -> np.ndarray | None:
    """Return a point of the target where ``dwells`` give ``dose_gy``, or None when no target point is on each side.

    Parameters
    ----------
    target_points_mm : (m, 3) float, mm, LPS
        Points of the target volume (its voxel centres).
    dwells : DwellSet
        The plan's dwells with their times per fraction (s).
    kernel : Tg43Kernel
        The TG-43 kernel of the plan's source.
    air_kerma_u : float, U
        Source strength.
    dose_gy : float, Gy
        The prescribed dose per fraction.

    Returns
    -------
    (3,) float, mm, LPS, or None
        A point at which the planned dose per fraction is ``dose_gy`` (to 1e-9 relative), on the segment between
        the hot voxel nearest the target's centroid and the nearest voxel colder than ``dose_gy``; None when every
        target point receives at least ``dose_gy``, or none does.
    """
    pts = np.asarray(target_points_mm, dtype=float).reshape(-1, 3)
    active = dwells.select(dwells.times_s > 0)
    if len(pts) == 0 or len(active) == 0 or not dose_gy > 0:
        return None
    dose = kernel.compiled_dose(pts, active.positions_mm, active.directions, active.times_s) * (air_kerma_u / 360000.0)
    hot, cold = dose >= dose_gy, dose < dose_gy
    if not hot.any() or not cold.any():
        return None
    centre = pts.mean(axis=0)
    hot_pts = pts[hot]
    a = hot_pts[int(np.argmin(np.linalg.norm(hot_pts - centre, axis=1)))]
    cold_pts = pts[cold]
    b = cold_pts[int(np.argmin(np.linalg.norm(cold_pts - a, axis=1)))]

    def excess(p: np.ndarray) -> float:
        return float(dose_at_points(p[None], active, kernel, air_kerma_u)[0]) - dose_gy

    if excess(a) < 0 or excess(b) >= 0:  # the float32 screening disagreed with the float64 dose at the ends
        return None
    for _ in range(BISECTION_STEPS):
        mid = 0.5 * (a + b)
        if excess(mid) >= 0:
            a = mid
        else:
            b = mid
    return a
