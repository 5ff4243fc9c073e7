"""Rod-model benchmark, speed and accuracy, and friction.

Every model and resolution timed on the free-space grid against the converged two-tube reference, batched
throughput, and the friction model against itself (with its hysteresis loop).

Part of ``reachplan bench models`` (:mod:`reachplan.planner.bench.models`, which writes the files); the
benchmark's settings and the chart's rows live here.
"""

from __future__ import annotations

import json
import os
import statistics
import subprocess
import sys
import time
import tracemalloc
from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import Protocol

import numpy as np

from reachplan.planner.bench.common import BenchError
from reachplan.rod_model.beam import PLANAR_BEAM, PlanarBeam
from reachplan.rod_model.collocation import CollocationCosserat
from reachplan.rod_model.cosserat import COSSERAT_ROD, TWO_TUBE_COSSERAT, CosseratRod, TwoTubeCosserat
from reachplan.rod_model.design import PRESET_NAMES, Loads, RodDesign, gravity_load, preset
from reachplan.rod_model.friction import loop_width_mm, solve_sweep
from reachplan.rod_model.kinematic import CONSTANT_CURVATURE, ConstantCurvature
from reachplan.rod_model.protocol import RodModel
from reachplan.rod_model.result import FailedSolve, RodPath

FRICTION_MODEL = "two_tube_cosserat+friction"


STEPS_PER_MM = (0.02, 0.05, 0.1, 0.25, 0.5, 1.0, 2.0)


REFERENCE = TwoTubeCosserat(steps_per_mm=8.0, tol=1e-12)


@dataclass(frozen=True)
class Row:
    """One point of the speed/accuracy chart.

    Parameters
    ----------
    model, resolution : str
        Model label and its resolution (steps/mm, nodes, or ``default``).
    median_ms : float, ms
        Median time per solve.
    max_tip_error_mm, median_tip_error_mm : float, mm
        Worst and median tip distance from the reference.
    success_rate : float
        Fraction of the grid solved.
    batched_solves_per_s : float or None, 1/s
        Throughput of the batched run (None when not run).
    batched_peak_mb : float or None, MB
        Its peak traced memory.
    """

    model: str
    resolution: str
    median_ms: float
    max_tip_error_mm: float
    median_tip_error_mm: float
    success_rate: float
    batched_solves_per_s: float | None = None
    batched_peak_mb: float | None = None


@dataclass(frozen=True)
class ModelSettings:
    """What the rod-model benchmark measures.

    Parameters
    ----------
    presets : tuple of str
        Stylet presets of the free-space grid.
    tensions_n : tuple of float, N
        Tendon tensions of the grid.
    stability_tensions_n : tuple of float, N
        Tensions of the stability map.
    stability_placements : tuple of str
        Joint placements of the stability map (``tip``, ``mid``, ``base``).
    batch, planar_batch : int
        Batch sizes of the throughput runs (two-tube, planar beam).
    interpreted : bool
        Also time the uncompiled kernel (a child process without numba).
    friction_presets : tuple of str
        Presets whose friction hysteresis loop is measured.
    tissue_moduli_pa : tuple of float, Pa
        Tissue moduli of the in-tissue chart.
    tissue_depths_mm : tuple of float, mm
        Its insertion depths.
    tissue_onsets_mm : tuple of float, mm
        Its ramp onsets.
    """

    presets: tuple[str, ...] = PRESET_NAMES
    tensions_n: tuple[float, ...] = tuple(float(t) for t in range(16))
    stability_tensions_n: tuple[float, ...] = (0.0, 5.0, 10.0, 15.0)
    stability_placements: tuple[str, ...] = ("tip", "mid", "base")
    batch: int = 10_000
    planar_batch: int = 100_000
    interpreted: bool = True
    friction_presets: tuple[str, ...] = PRESET_NAMES
    tissue_moduli_pa: tuple[float, ...] = (1e3, 1e4, 3e4, 1e5, 1.9e5, 5e5, 1e6, 3e6, 1e7)
    tissue_depths_mm: tuple[float, ...] = (60.0, 90.0, 120.0, 150.0)
    tissue_onsets_mm: tuple[float, ...] = (0.0, 20.0, 40.0, 60.0)


QUICK = ModelSettings(presets=("15ga-20j-tip", "15ga-20j-base", "13ga-20j-tip"), tensions_n=(0.0, 5.0, 10.0, 15.0),
                      stability_tensions_n=(7.5,),
                      stability_placements=("tip",), batch=200, planar_batch=2_000, interpreted=False,
                      friction_presets=("15ga-20j-tip", "15ga-20j-base"), tissue_moduli_pa=(1e3, 1.9e5, 1e6),
                      tissue_depths_mm=(40.0, 60.0), tissue_onsets_mm=(0.0,))


class _Solver(Protocol):
    """What the speed/accuracy chart times (a rod model, or the collocation cross-check)."""

    @property
    def name(self) -> str: ...

    def solve(self, design: RodDesign, loads: Loads) -> RodPath | FailedSolve: ...


def _tip(r: RodPath | FailedSolve) -> np.ndarray:
    """Tip position (3,), mm, of a converged solve; NaN for a failed one (its error is then infinite)."""
    return r.tip_position_mm if isinstance(r, RodPath) else np.full(3, np.nan)


def _time_model(model: _Solver, grid: list[tuple[RodDesign, float]],
                ref: np.ndarray) -> tuple[float, np.ndarray, float]:
    """(median ms per solve, tip error (n,) in mm against ``ref`` (n, 3) mm, inf when failed; success rate)."""
    times, errs = [], []
    ok = 0
    for (d, t), tip in zip(grid, ref, strict=True):
        t0 = time.perf_counter()
        r = model.solve(d, d.loads(t))
        times.append((time.perf_counter() - t0) * 1e3)
        if isinstance(r, RodPath):
            ok += 1
            errs.append(float(np.linalg.norm(r.tip_position_mm - tip)))
        else:
            errs.append(np.inf)
    return statistics.median(times), np.array(errs), ok / len(grid)


def _batched(model: RodModel, design: RodDesign, n: int) -> tuple[float, float]:
    """(median solves/s of ``n`` tensions in one ``solve_batch``, peak traced memory in MB of one more run)."""
    tensions = np.linspace(0.0, 15.0, n)
    model.solve_batch(design, tensions[:10])  # warm-up / compile
    rates = []
    for _ in range(3):
        t0 = time.perf_counter()
        model.solve_batch(design, tensions)
        rates.append(n / (time.perf_counter() - t0))
    tracemalloc.start()
    model.solve_batch(design, tensions)
    peak = tracemalloc.get_traced_memory()[1] / 2**20
    tracemalloc.stop()
    return statistics.median(rates), peak


_INTERPRETED = """
import json, time, numpy as np
from reachplan.rod_model.cosserat import TWO_TUBE_COSSERAT as M
from reachplan.rod_model.design import preset
d = preset('15ga-20j-tip'); M.solve(d, d.loads(1.0))
ts = []
for t in (2.0, 6.0, 10.0):
    t0 = time.perf_counter(); M.solve(d, d.loads(t)); ts.append((time.perf_counter() - t0) * 1e3)
print(json.dumps(sorted(ts)[1]))
"""


def _interpreted_ms() -> float | None:
    """Median ms of one two-tube solve with numba disabled (the same kernel run as plain Python)."""
    env = dict(os.environ, NUMBA_DISABLE_JIT="1")
    try:
        out = subprocess.run([sys.executable, "-c", _INTERPRETED], env=env, capture_output=True, text=True,
                             timeout=120, check=True)
    except (subprocess.SubprocessError, OSError):
        return None
    return float(json.loads(out.stdout.strip().splitlines()[-1]))


def speed_accuracy(s: ModelSettings, log: Callable[[str], None]) -> tuple[list[Row], dict[str, float]]:
    """Time every model and resolution on the grid against the converged two-tube reference.

    Parameters
    ----------
    s : ModelSettings
        Presets and tensions of the grid, batch sizes.
    log : callable (str) -> None
        Progress lines.

    Returns
    -------
    rows : list of Row
        The chart's points, one per model and resolution (tip errors in mm, times in ms).
    extra : dict of str to float
        Headline numbers of the reference check and the loaded and batched runs.

    Raises
    ------
    BenchError
        The reference solve did not converge.
    """
    grid = [(preset(n), t) for n in s.presets for t in s.tensions_n]
    REFERENCE.solve(*(grid[1][0], grid[1][0].loads(1.0)))  # compile
    t0 = time.perf_counter()
    refs = [REFERENCE.solve(d, d.loads(t)) for d, t in grid]
    failed = [r for r in refs if not isinstance(r, RodPath)]
    if failed:
        raise BenchError(f"the reference two-tube solve did not converge ({failed[0]}); the chart needs it")
    ref = np.array([_tip(r) for r in refs])
    check = TwoTubeCosserat(steps_per_mm=4.0, tol=1e-12)
    ref_conv = max(float(np.linalg.norm(_tip(check.solve(d, d.loads(t))) - tip))
                   for (d, t), tip in zip(grid, ref, strict=True))
    log(f"reference: {len(grid)} solves in {time.perf_counter() - t0:.1f} s; change vs 4 steps/mm {ref_conv:.1e} mm")
    rows: list[Row] = []
    configs: list[tuple[RodModel, str]] = [(ConstantCurvature(), "closed form"), (PlanarBeam(), "closed form")]
    for cls in (CosseratRod, TwoTubeCosserat):
        for spm in STEPS_PER_MM:
            configs.append((cls(steps_per_mm=spm), f"{spm:g} steps/mm"))
    defaults: dict[str, RodModel] = {CONSTANT_CURVATURE.name: CONSTANT_CURVATURE, PLANAR_BEAM.name: PLANAR_BEAM,
                                     COSSERAT_ROD.name: COSSERAT_ROD, TWO_TUBE_COSSERAT.name: TWO_TUBE_COSSERAT}
    for model, res in configs:
        model.solve(grid[0][0], grid[0][0].loads(1.0))  # warm-up
        med, errs, rate = _time_model(model, grid, ref)
        name = model.name
        bps: float | None = None
        peak: float | None = None
        if model == defaults[name]:
            bps, peak = _batched(model, preset("15ga-20j-tip"), s.batch)
            res += " (default)"
        rows.append(Row(name, res, med, float(np.max(errs)), float(np.median(errs)), rate, bps, peak))
        log(f"{name:20s} {res:24s} {med:8.3f} ms  max err {rows[-1].max_tip_error_mm:.2e} mm"
            + (f"  batched {bps:,.0f}/s  peak {peak:.0f} MB" if bps is not None and peak is not None else ""))
    # collocation on a subset (it is slow)
    sub = [grid[i] for i in range(0, len(grid), max(1, len(grid) // 6))][:6]
    sub_ref = np.array([ref[grid.index(g)] for g in sub])
    coll = CollocationCosserat(tol=1e-6)
    med, errs, rate = _time_model(coll, sub, sub_ref)
    rows.append(Row(coll.name, "tol 1e-6 (6 cases)", med, float(np.max(errs)), float(np.median(errs)), rate))
    log(f"{coll.name:20s} {'tol 1e-6':24s} {med:8.3f} ms  max err {rows[-1].max_tip_error_mm:.2e} mm")
    extra: dict[str, float] = {"reference_self_convergence_mm": ref_conv, "grid_cases": float(len(grid))}
    # the same grid with an out-of-plane tip force and the needle's weight: the boundary-value problem proper
    loaded = [(d, Loads(d.loads(t).tensions_n, tip_force_n=(0.0, 0.2, -0.2), distributed_n_per_m=gravity_load(d)))
              for d, t in grid]
    lref = [REFERENCE.solve(d, ld) for d, ld in loaded]
    for model in (COSSERAT_ROD, TWO_TUBE_COSSERAT):
        ltimes, lerrs = [], []
        for (d, ld), rr in zip(loaded, lref, strict=True):
            t1 = time.perf_counter()
            r = model.solve(d, ld)
            ltimes.append((time.perf_counter() - t1) * 1e3)
            ok = isinstance(r, RodPath) and isinstance(rr, RodPath)
            lerrs.append(float(np.linalg.norm(_tip(r) - _tip(rr))) if ok else np.inf)
        extra[f"{model.name}_loaded_median_ms"] = statistics.median(ltimes)
        extra[f"{model.name}_loaded_max_tip_error_mm"] = max(lerrs)
        log(f"{model.name:20s} loaded (tip force + weight) {statistics.median(ltimes):8.3f} ms  max err "
            f"{max(lerrs):.2e} mm")
    planar_rate, planar_peak = _batched(PLANAR_BEAM, preset("15ga-20j-tip"), s.planar_batch)
    extra.update(planar_batch=float(s.planar_batch), planar_batch_solves_per_s=planar_rate,
                 planar_batch_peak_mb=planar_peak)
    log(f"planar_beam {s.planar_batch:,} batched: {planar_rate:,.0f}/s, peak {planar_peak:.0f} MB")
    interp = _interpreted_ms() if s.interpreted else None
    if interp is not None:
        extra["two_tube_interpreted_ms"] = interp
        log(f"two_tube_cosserat without numba (NUMBA_DISABLE_JIT=1): {interp:.1f} ms per solve")
    return rows, extra


def _with_friction(d: RodDesign, mu: float) -> RodDesign:
    """Return ``d`` with tendon (capstan) and joint friction coefficients ``mu``."""
    return replace(d, stylet=replace(d.stylet, tendon_friction_coefficient=mu, joint_friction_coefficient=mu))


def friction(s: ModelSettings, log: Callable[[str], None]) -> tuple[list[Row], dict[str, float]]:
    """Time the friction model against itself at 8 steps/mm and measure its hysteresis loop per preset.

    Parameters
    ----------
    s : ModelSettings
        The grid and the friction presets.
    log : callable (str) -> None
        Progress lines.

    Returns
    -------
    rows : list of Row
        One row: the default two-tube model with friction coefficients 0.1 / 0.1 on the grid (tip errors in
        mm against the same model at 8 steps/mm, pulled from rest; cases whose reference failed are left out).
    widths : dict of str to float
        ``loop_width_mm_<preset>_mu0.1``: the loop width (mm, :func:`~reachplan.rod_model.friction.loop_width_mm`)
        of a 0-10-0 N sweep, for each of ``s.friction_presets`` whose sweep converged.

    Raises
    ------
    BenchError
        No reference solve of the grid converged.
    """
    grid = [(_with_friction(preset(n), 0.1), t) for n in s.presets for t in s.tensions_n]
    ref_model = TwoTubeCosserat(steps_per_mm=8.0, tol=1e-12)
    refs = [ref_model.solve(d, d.loads(t)) for d, t in grid]
    grid = [g for g, r in zip(grid, refs, strict=True) if isinstance(r, RodPath)]
    if not grid:
        raise BenchError("no reference solve with friction converged; the friction row needs one")
    ref = np.array([_tip(r) for r in refs if isinstance(r, RodPath)])
    TWO_TUBE_COSSERAT.solve(grid[0][0], grid[0][0].loads(1.0))  # warm-up
    med, errs, rate = _time_model(TWO_TUBE_COSSERAT, grid, ref)
    row = Row(FRICTION_MODEL, "mu 0.1/0.1 (default steps)", med, float(np.max(errs)), float(np.median(errs)), rate)
    log(f"{row.model:26s} {row.resolution:26s} {med:8.3f} ms  max err {row.max_tip_error_mm:.2e} mm")
    up_down = [0.0, 2.0, 4.0, 6.0, 8.0, 10.0, 8.0, 6.0, 4.0, 2.0, 0.0]
    widths: dict[str, float] = {}
    for name in s.friction_presets:
        res = solve_sweep(TWO_TUBE_COSSERAT, _with_friction(preset(name), 0.1), up_down)
        paths = [r for r in res if isinstance(r, RodPath)]
        if len(paths) == len(res):
            widths[f"loop_width_mm_{name}_mu0.1"] = loop_width_mm(up_down, [r.tip_deflection_mm for r in paths])
        else:
            log(f"hysteresis sweep of {name} failed: {next(r for r in res if not isinstance(r, RodPath))}")
    log("hysteresis loop width (mu 0.1/0.1, 0-10-0 N): " + ", ".join(f"{k}: {v:.2f} mm" for k, v in widths.items()))
    return [row], widths
