"""Rod-model benchmark, in tissue: the in-tissue Cosserat insertion's tip deflection and its chart.

Tip deflection against the tissue modulus and depth, and the kinematic curvature factor fitted per modulus.

Part of ``reachplan bench models`` (:mod:`reachplan.planner.bench.models`).
"""

from __future__ import annotations

import math
import statistics
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from matplotlib.figure import Figure

from reachplan.planner.bench.models_speed import ModelSettings, Row
from reachplan.planner.steering.factors import (
    FACTOR_FRACTIONS,
    TIP_FOLLOWING_MIN_PA,
    curvature_factor,
    factor_schedules,
    fit_factor,
)
from reachplan.planner.steering.kinematic import KinematicInsertion
from reachplan.planner.steering.tissue_rod import TissueRodInsertion
from reachplan.rod_model.beam import PLANAR_BEAM
from reachplan.rod_model.design import preset


@dataclass(frozen=True)
class TissuePoint:
    """One point of the in-tissue chart: a modulus, a schedule, a depth (tip deflections NaN past a failed step).

    Parameters
    ----------
    modulus_pa : float, Pa
        Tissue Young's modulus.
    schedule : str
        The ramp in words.
    depth_mm : float, mm
        Insertion depth.
    tissue_rod_mm, kinematic_mm : float, mm
        Lateral tip deflection of the in-tissue rod, and of the kinematic model with the fitted function.
    tip_following_mm : float, mm
        The kinematic model's at factor 1 (pure tip following: the rigid-tissue limit).
    factor : float
        Kinematic curvature factor fitted to the rod at this modulus (over every schedule and depth).
    function : float
        The fitted function's value (NaN below the tip-following range).
    ms : float, ms
        The insertion's wall time.
    status : str
        ``ok`` or the failure's reason.
    """

    modulus_pa: float
    schedule: str
    depth_mm: float
    tissue_rod_mm: float
    kinematic_mm: float
    tip_following_mm: float
    factor: float
    function: float
    ms: float
    status: str


def _lateral(p: np.ndarray) -> np.ndarray:
    return np.hypot(p[..., 0], p[..., 1])


def tissue(s: ModelSettings, log: Callable[[str], None]) -> tuple[list[TissuePoint], list[Row]]:
    """Insert the planner's design with the in-tissue rod at each modulus and schedule, beside the kinematic model.

    15ga-30j-tip; ramps of 20 mm from the onsets of ``s`` to 60 / 100 % of the maximum tension (the planner's
    schedule family); moduli and depths of ``s``.

    Parameters
    ----------
    s : ModelSettings
        Moduli, depths and onsets of the chart.
    log : callable (str) -> None
        One line per modulus.

    Returns
    -------
    points : list of TissuePoint
        One per modulus, schedule and depth.
    rows : list of Row
        For the speed/accuracy chart: the kinematic model with :func:`curvature_factor` (time per insertion,
        tip error against the rod over the tip-following range) and the rod itself (time per insertion; tip
        error of its 2 mm insertion step against 1 mm, one schedule per modulus).
    """
    design = preset("15ga-30j-tip")
    ramps = factor_schedules(design, s.tissue_onsets_mm)  # the fitted table's ramps, onset-major
    labels = [f"ramp {o:g} mm, {f:.0%}" for o in s.tissue_onsets_mm for f in FACTOR_FRACTIONS]
    schedules = list(zip(labels, ramps, strict=True))
    depths = np.array(s.tissue_depths_mm, dtype=float)
    rows_at = np.round(depths).astype(int)  # rows of a kinematic path at 1 mm steps

    def kinematic(factor: float) -> np.ndarray:
        paths = KinematicInsertion(tissue_factor=factor).insert_array(design, [sc for _, sc in schedules],
                                                                      float(depths[-1]))
        return paths[:, rows_at]  # (S, D, 3)

    out: list[TissuePoint] = []
    kin_err: list[float] = []
    rod_ms: list[float] = []
    step_err: list[float] = []
    t_kin = time.perf_counter()
    follow = kinematic(1.0)  # the rigid-tissue limit
    kin_ms = (time.perf_counter() - t_kin) * 1e3 / len(schedules)
    for e in s.tissue_moduli_pa:
        tips = np.full((len(schedules), len(depths), 3), np.nan)
        status, ms = [], []
        for i, (_, sch) in enumerate(schedules):
            t0 = time.perf_counter()
            final, steps = TissueRodInsertion(tissue_modulus_pa=e).insert_steps(design, sch, float(depths[-1]))
            ms.append((time.perf_counter() - t0) * 1e3)
            got = {round(d, 6): tip for d, tip in steps}
            for j, d in enumerate(depths):
                tips[i, j] = got.get(round(float(d), 6), np.full(3, np.nan))
            status.append("ok" if isinstance(final, np.ndarray) else final.reason)
        rod_ms += ms
        ok = np.all(np.isfinite(tips), axis=-1)
        factor = fit_factor(design, ramps, depths, tips).factor if ok.sum() >= 2 else math.nan
        fn = curvature_factor(e, design) if e >= TIP_FOLLOWING_MIN_PA else math.nan
        kin = kinematic(fn) if math.isfinite(fn) else np.full_like(tips, np.nan)
        if math.isfinite(fn):
            kin_err += list(np.linalg.norm(kin - tips, axis=-1)[ok])
            fine = TissueRodInsertion(tissue_modulus_pa=e, step_mm=1.0).insert_one(design, schedules[0][1],
                                                                                  float(depths[-1]))
            if isinstance(fine, np.ndarray) and ok[0, -1]:
                step_err.append(float(np.linalg.norm(fine[-1] - tips[0, -1])))
        for i, (label, _) in enumerate(schedules):
            for j, d in enumerate(depths):
                out.append(TissuePoint(e, label, float(d), float(_lateral(tips[i, j])), float(_lateral(kin[i, j])),
                                       float(_lateral(follow[i, j])), factor, fn, ms[i],
                                       "ok" if ok[i, j] else status[i]))
        deep = ", ".join(f"{_lateral(t):.1f}" for t in tips[:, -1])
        log(f"tissue_rod E = {e:9.3g} Pa: tips at {depths[-1]:.0f} mm {deep} mm; factor fitted {factor:.3f}, "
            f"function {fn:.3f}; {statistics.median(ms):.0f} ms per insertion")
    rows = [Row(f"kinematic+{PLANAR_BEAM.name} in tissue", "curvature_factor(E) vs tissue_rod", kin_ms,
                max(kin_err, default=math.nan), statistics.median(kin_err) if kin_err else math.nan, 1.0),
            Row("tissue_rod+two_tube_cosserat", "step 2 mm vs 1 mm", statistics.median(rod_ms),
                max(step_err, default=math.nan), statistics.median(step_err) if step_err else math.nan,
                float(np.mean([p.status == "ok" for p in out])))]
    return out, rows


def tissue_figure(points: list[TissuePoint]) -> Figure:
    """Tip deflection against modulus per schedule at the deepest depth (left); the curvature factor (right).

    Left, dashed: each schedule's tip-following limit (kinematic model at factor 1), which the rod approaches
    in stiff tissue.

    Parameters
    ----------
    points : list of TissuePoint
        The chart's points.

    Returns
    -------
    matplotlib.figure.Figure
    """
    fig = Figure(figsize=(12, 5), layout="tight")
    a1, a2 = fig.subplots(1, 2)
    moduli = sorted({p.modulus_pa for p in points})
    deepest = max(p.depth_mm for p in points)
    for label in dict.fromkeys(p.schedule for p in points):
        pts = sorted((p for p in points if p.schedule == label and p.depth_mm == deepest), key=lambda p: p.modulus_pa)
        (line,) = a1.plot([p.modulus_pa for p in pts], [p.tissue_rod_mm for p in pts], "o-", ms=4, label=label)
        a1.axhline(pts[0].tip_following_mm, color=line.get_color(), ls="--", lw=0.8)
    a1.axvline(TIP_FOLLOWING_MIN_PA, color="k", ls=":", lw=1)
    a1.set_ylabel(f"lateral tip deflection at {deepest:.0f} mm (mm)")
    a1.set_title("15ga-30j-tip, in-tissue Cosserat rod: held (rises), past the peak toward tip following\n"
                 "(dashed: the rigid limit; joints pulled while embedded are also resisted)", fontsize=9)
    fac = [next(p.factor for p in points if p.modulus_pa == e) for e in moduli]
    a2.plot(moduli, fac, "s", label="fitted to the rod (all schedules, depths)")
    grid = np.geomspace(TIP_FOLLOWING_MIN_PA, max([*moduli, 1e7]), 100)
    a2.plot(grid, [curvature_factor(float(e)) for e in grid], "-", label="curvature_factor(E), 15ga-30j-tip (table)")
    a2.axvspan(min(moduli), TIP_FOLLOWING_MIN_PA, color="0.9", label="below the tip-following range")
    a2.set_ylabel("kinematic curvature factor")
    for ax in (a1, a2):
        ax.set(xscale="log", xlabel="tissue Young's modulus (Pa, log)")
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=7)
    return fig
