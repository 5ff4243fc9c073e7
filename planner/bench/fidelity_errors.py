"""The fidelity ladder's in-tissue errors: each insertion model's tip against the planner's reference rod.

For each stylet design and tissue modulus, the ramps a curvature factor is fitted over
(:func:`~reachplan.planner.steering.factors.factor_schedules`: 20 mm ramps from 0-60 mm onsets to 60 / 100 % of
the design's limit) are inserted once with the in-tissue rod at 2, 4 and 8 mm steps to the deepest depth, and the
tips after the steps ending at each depth of :data:`DEPTHS_MM` (multiples of 8 mm, so every step size ends there)
give every rung of :data:`~reachplan.planner.case.fidelity.RUNGS` at once: the reference ``2 P(2) − P(4)`` (the
planner's Richardson extrapolation, :data:`~reachplan.planner.steering.tissue_rod.PLANNER_REFERENCE`), ``P(4)``,
``2 P(4) − P(8)``, ``P(2)``, and the kinematic model at the packaged curvature factor. Each rung's largest and RMS
tip distance from the reference at each depth, and its median CPU time per insertion, is one row of the planner's
package table (:data:`~reachplan.planner.case.fidelity.ERROR_TABLE`). Part of ``reachplan bench fidelity``.
"""

from __future__ import annotations

import os
import statistics
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import replace

import numpy as np

from reachplan.planner.case.fidelity import ErrorRow
from reachplan.planner.steering.factors import design_key, factor_schedules
from reachplan.planner.steering.kinematic import KinematicInsertion
from reachplan.planner.steering.tissue_rod import PLANNER_REFERENCE
from reachplan.rod_model.design import preset

#: Depths (mm) the rungs' tips are compared at: multiples of 8 mm, so 2, 4 and 8 mm steps all end there.
DEPTHS_MM: tuple[float, ...] = (48.0, 72.0, 96.0, 120.0, 144.0)


def _tips(design_name: str, modulus_pa: float, step_mm: float,
          depths: np.ndarray) -> tuple[np.ndarray, list[float]]:
    """(S, D, 3) tips (NaN past a failed step) of the in-tissue rod at ``step_mm``, and seconds per insertion."""
    design = preset(design_name)
    rod = replace(PLANNER_REFERENCE, step_mm=step_mm, richardson=False, tissue_modulus_pa=modulus_pa)
    schedules = factor_schedules(design)
    tips = np.full((len(schedules), len(depths), 3), np.nan)
    seconds = []
    for i, sch in enumerate(schedules):
        t0 = time.process_time()  # CPU: the shared machine's load does not count
        _, steps = rod.insert_steps(design, sch, float(depths[-1]))
        seconds.append(time.process_time() - t0)
        got = {round(d, 6): tip for d, tip in steps}
        for j, d in enumerate(depths):
            tips[i, j] = got.get(round(float(d), 6), np.full(3, np.nan))
    return tips, seconds


def _stats(tips: np.ndarray, ref: np.ndarray) -> tuple[tuple[float, ...], tuple[float, ...]]:
    """Per depth: largest and RMS distance of ``tips`` from ``ref`` ((S, D, 3) each); inf where one is NaN."""
    dist = np.linalg.norm(tips - ref, axis=-1)
    bad = ~np.isfinite(dist)
    worst = np.where(bad.any(axis=0), np.inf, np.nanmax(np.where(bad, 0.0, dist), axis=0))
    rms = np.where(bad.any(axis=0), np.inf, np.sqrt(np.mean(np.where(bad, 0.0, dist) ** 2, axis=0)))
    return tuple(round(float(x), 4) for x in worst), tuple(round(float(x), 4) for x in rms)


def measure(job: tuple[str, float]) -> list[ErrorRow]:
    """Measure every rung for one design and modulus (one worker's job).

    Parameters
    ----------
    job : tuple of (str, float)
        Preset name and tissue Young's modulus (Pa).

    Returns
    -------
    list of ErrorRow
        One per rung of :data:`~reachplan.planner.case.fidelity.RUNGS`, the reference's error 0.
    """
    name, modulus = job
    design = preset(name)
    depths = np.array([d for d in DEPTHS_MM if d <= design.length_mm])
    t2, s2 = _tips(name, modulus, 2.0, depths)
    t4, s4 = _tips(name, modulus, 4.0, depths)
    t8, s8 = _tips(name, modulus, 8.0, depths)
    ref = 2 * t2 - t4
    rows = np.round(depths).astype(int)
    kin = KinematicInsertion(tissue_modulus_pa=modulus).insert_array(design, factor_schedules(design),
                                                                      float(depths[-1]))[:, rows]
    t0 = time.process_time()
    for _ in range(20):
        KinematicInsertion(tissue_modulus_pa=modulus).insert_array(design, factor_schedules(design), float(depths[-1]))
    kin_ms = (time.process_time() - t0) / 20 / len(kin) * 1e3
    ms = {"kinematic": kin_ms, "tissue_rod@4mm": statistics.median(s4) * 1e3,
          "tissue_rod@4+8mm": statistics.median(np.add(s4, s8)) * 1e3, "tissue_rod@2mm": statistics.median(s2) * 1e3,
          "reference": statistics.median(np.add(s2, s4)) * 1e3}
    tips = {"kinematic": kin, "tissue_rod@4mm": t4, "tissue_rod@4+8mm": 2 * t4 - t8, "tissue_rod@2mm": t2,
            "reference": ref}
    key = design_key(design)
    out = []
    for rung, t in tips.items():
        worst, rms = _stats(t, ref)
        out.append(ErrorRow(name, key, float(modulus), rung, tuple(map(float, depths)), worst, rms,
                            round(ms[rung], 4)))
    return out


def measure_all(jobs: list[tuple[str, float]], workers: int | None = None) -> list[ErrorRow]:
    """Measure every (design, modulus) job, on ``workers`` processes (default: every core); rows in job order.

    Parameters
    ----------
    jobs : list of (str, float)
        Preset names and moduli (Pa).
    workers : int or None
        Processes; None: the machine's cores.

    Returns
    -------
    list of ErrorRow
        Every rung of every job.
    """
    if len(jobs) == 1 or workers == 1:
        return [r for job in jobs for r in measure(job)]
    with ProcessPoolExecutor(max_workers=min(len(jobs), workers or os.cpu_count() or 1)) as pool:
        return [r for rows in pool.map(measure, jobs) for r in rows]
