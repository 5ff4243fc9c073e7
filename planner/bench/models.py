"""Benchmark of the rod models: time per solve against tip error, batched throughput, and a stability map.

Run through ``reachplan bench models --out DIR`` (add ``--install`` to refresh the package's error table
``rod_model/model_errors.json`` and the figures ``docs/rod_models_pareto.png``, ``docs/rod_models_stability.png``
in a source checkout). ``--quick``: three presets × four tensions, small batches, no uncompiled run, two loop
widths, the in-tissue chart at three moduli and two depths.

Speed vs accuracy
    Grid: every preset of :data:`reachplan.rod_model.design.PRESET_NAMES` × tensions 0-15 N (1 N steps), free space.
    Reference: the two-tube Cosserat model at 8 RK4 steps/mm, residual tolerance 1e-12 (its own convergence
    against 4 steps/mm is reported). For every model and resolution: median wall time of one ``solve`` and the
    largest / median tip error against the reference. Batched throughput of each registered configuration: 10,000
    tensions in one ``solve_batch`` (and the peak memory, by ``tracemalloc``).
Friction
    The two-tube model with capstan and joint friction (coefficients 0.1 / 0.1) against the same model at
    8 steps/mm (its own numerical error, pulled from rest) on the same grid, and the width of the hysteresis
    loop of a 0-10-0 N sweep per preset (``rod_models_friction.csv``; the widths in ``summary.json``).
Honesty
    The load cases a reviewer found wrong: a 2 N lateral tip force on 15ga-20j-base (used to converge 67 mm on
    the wrong side), a dead axial load at 0.9 / 1.1 / 1.5 of the Euler load (straight and imperfect), 5000 N of
    tension (used to blow up to 7e18 mm "converged"): what the solver returns now, with its reason
    (``rod_models_honesty.csv``).
In tissue
    The in-tissue Cosserat insertion (:mod:`reachplan.planner.steering.tissue_rod`) of 15ga-30j-tip under the
    planner's ramps (20 mm from 0 / 20 / 40 / 60 mm onset to 60 / 100 % of the maximum tension), tip deflection
    against the tissue modulus (1 kPa - 10 MPa) and depth; the kinematic model's curvature factor fitted per
    modulus beside :func:`~reachplan.planner.steering.factors.curvature_factor`
    (``rod_models_tissue.csv`` / ``.png``); the kinematic model with that function and the rod itself enter the
    speed/accuracy chart (time per insertion; tip error against the rod, and the rod's 2 mm step against 1 mm).
Stability map
    Each solver (shooting without continuation, shooting with continuation, collocation) on tension ×
    placement × initial guess (zero, small, large), with an out-of-plane tip force so that the boundary-value
    problem is not trivial; success, residual and the failure reason per case.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import statistics
import subprocess
import sys
import time
import tracemalloc
import warnings
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, Protocol

import numpy as np
from matplotlib.figure import Figure

from reachplan.planner.bench.common import BenchError, settings, write_csv, write_json, write_png
from reachplan.planner.steering.factors import (
    FACTOR_FRACTIONS,
    TIP_FOLLOWING_MIN_PA,
    curvature_factor,
    factor_schedules,
    fit_factor,
)
from reachplan.planner.steering.kinematic import KinematicInsertion
from reachplan.planner.steering.tissue_rod import TissueRodInsertion
from reachplan.rod_model.beam import PLANAR_BEAM, PlanarBeam
from reachplan.rod_model.collocation import NS, CollocationCosserat
from reachplan.rod_model.cosserat import COSSERAT_ROD, TWO_TUBE_COSSERAT, CosseratRod, TwoTubeCosserat
from reachplan.rod_model.design import PRESET_NAMES, Loads, RodDesign, gravity_load, preset
from reachplan.rod_model.errors import TensionAboveLimitWarning
from reachplan.rod_model.friction import loop_width_mm, solve_sweep
from reachplan.rod_model.kinematic import CONSTANT_CURVATURE, ConstantCurvature
from reachplan.rod_model.protocol import RodModel
from reachplan.rod_model.result import FailedSolve, RodPath

INSTALLS = {"model_errors.json": "rod_model/model_errors.json",
            **{name: f"docs/{name}" for name in ("rod_models_pareto.png", "rod_models_stability.png", "rod_models.csv",
                                                 "rod_models_tissue.csv", "rod_models_tissue.png")}}
ROW_COLUMNS = ("model", "resolution", "median_ms", "max_tip_error_mm", "median_tip_error_mm", "success_rate",
               "batched_solves_per_s", "batched_peak_mb")
STABILITY_COLUMNS = ("solver", "placement", "tension_n", "guess", "success", "residual_n", "ms", "reason")
FRICTION_COLUMNS = ROW_COLUMNS[:6]
HONESTY_COLUMNS = ("case", "converged", "tip_x_mm", "tip_y_mm", "tip_z_mm", "ms", "reason")
TISSUE_COLUMNS = ("modulus_pa", "schedule", "depth_mm", "tissue_rod_tip_mm", "kinematic_tip_mm",
                  "tip_following_mm", "kinematic_factor_fitted", "curvature_factor", "insertion_ms", "status")
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


@dataclass(frozen=True)
class StabilityCase:
    """One case of the stability map.

    Parameters
    ----------
    solver, placement : str
        Solver and joint placement.
    tension_n : float, N
        Tendon tension.
    guess : str
        Initial guess (``zero``, ``small``, ``large``).
    success : bool
        The solve converged.
    residual : float, N
        Boundary residual.
    ms : float, ms
        Solve time.
    reason : str
        Why it failed ("" when it did not).
    """

    solver: str
    placement: str
    tension_n: float
    guess: str
    success: bool
    residual: float
    ms: float
    reason: str


def stability(s: ModelSettings, log: Callable[[str], None]) -> list[StabilityCase]:
    """Every solver on placement × tension × initial guess, with an out-of-plane tip force.

    Parameters
    ----------
    s : ModelSettings
        Tensions and placements of the map.
    log : callable (str) -> None
        Where the progress goes, line by line.

    Returns
    -------
    list of StabilityCase
        One per solver, placement, tension and guess.
    """
    rng = np.random.default_rng(7)
    out: list[StabilityCase] = []
    collocation = CollocationCosserat(tol=1e-6, nodes_per_section=11, max_nodes=300, max_ramp=2)
    solvers: dict[str, tuple[Any, bool]] = {"shooting": (TWO_TUBE_COSSERAT, False),
                                            "shooting+continuation": (TWO_TUBE_COSSERAT, True),
                                            "collocation": (collocation, True)}
    for placement in s.stability_placements:
        d = preset(f"15ga-20j-{placement}")
        for t in s.stability_tensions_n:
            loads = Loads((t, 0.0, 0.0, 0.0), tip_force_n=(0.0, 0.2, -0.2))
            scale = 1.0 + t + 0.4
            for guess, mag in (("zero", 0.0), ("small", 0.1), ("large", 10.0)):
                noise = rng.standard_normal(8)
                x0 = mag * scale * noise * np.r_[1, 1, 1, 0.01, 0.01, 0.01, 1, 0.01]  # N and N·(1 cm)
                for label, (solver, cont) in solvers.items():
                    if isinstance(solver, CollocationCosserat):
                        k = len(d.sections())
                        y0 = np.zeros((NS * k, solver.nodes_per_section))
                        tau = np.linspace(0, 1, solver.nodes_per_section)
                        for i, sec in enumerate(d.sections()):
                            b = y0[NS * i:NS * (i + 1)]
                            b[2] = (sec.start_m + tau * sec.length_m) * 1e3
                            b[3] = b[7] = b[11] = 1.0
                            b[12:15] = x0[0:3, None]
                            b[15:18] = x0[3:6, None] * 1e3
                        r = solver.solve(d, loads, initial_guess=y0, continuation=cont)
                    else:
                        r = solver.solve(d, loads, initial_guess=x0, continuation=cont)
                    ok = isinstance(r, RodPath)
                    reason = r.reason if isinstance(r, FailedSolve) else ""
                    out.append(StabilityCase(label, placement, t, guess, ok, float(r.residual),
                                             float(r.solve_ms), reason))
    for label in solvers:
        cases = [c for c in out if c.solver == label]
        log(f"stability {label:22s}: {sum(c.success for c in cases)}/{len(cases)} converged")
    return out


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


@dataclass(frozen=True)
class HonestyCase:
    """One load case of the honesty table.

    Parameters
    ----------
    case : str
        The load case in words.
    converged : bool
        The solver reports convergence.
    tip_mm : (3,) float or None, mm, rod frame
        Tip position; None when the solve failed.
    ms : float, ms
        Solve time.
    reason : str
        Why it failed.
    """

    case: str
    converged: bool
    tip_mm: tuple[float, float, float] | None
    ms: float
    reason: str


def honesty(log: Callable[[str], None]) -> list[HonestyCase]:
    """Run the reviewer's wrong-branch and blow-up cases through the checked two-tube solver.

    The Euler load is that of the tube-plus-needle column clamped at the template, free at the tip:
    ``P = π² EI / (4 L²)`` (Timoshenko & Gere, Theory of Elastic Stability, 2nd ed., 1961, §2.1).

    Parameters
    ----------
    log : callable (str) -> None
        One line per case.

    Returns
    -------
    list of HonestyCase
        One per load case.
    """
    base, tip = preset("15ga-20j-base"), preset("15ga-20j-tip")
    sec = tip.sections()[0]
    p_cr = math.pi**2 * (sec.ei1 + sec.ei2) / (4 * (tip.length_mm * 1e-3) ** 2)  # tube + needle column, N
    lateral = (0.0, 2.0, 0.0)
    cases: list[tuple[str, RodDesign, Loads, bool]] = [
        ("15ga-20j-base, 2 N lateral tip force (+y)", base, Loads((0.0,) * 4, tip_force_n=lateral), True),
        ("same, direct solve (no continuation)", base, Loads((0.0,) * 4, tip_force_n=lateral), False),
        ("15ga-20j-base, 9.9 N + 2 N lateral (+y)", base, Loads((9.9, 0, 0, 0), tip_force_n=lateral), True),
        ("same, direct solve (no continuation)", base, Loads((9.9, 0, 0, 0), tip_force_n=lateral), False),
        ("15ga-20j-tip, axial 0.9 P_euler(tube)", tip, Loads((0.0,) * 4, tip_force_n=(0.0, 0.0, -0.9 * p_cr)), True),
        ("15ga-20j-tip, axial 1.1 P_euler(tube)", tip, Loads((0.0,) * 4, tip_force_n=(0.0, 0.0, -1.1 * p_cr)), True),
        ("15ga-20j-tip, 1.5 P_euler + 1 % lateral", tip,
         Loads((0.0,) * 4, tip_force_n=(0.015 * p_cr, 0.0, -1.5 * p_cr)), True),
        ("15ga-20j-tip, 5000 N tension", tip, tip.loads(5000.0), True),
    ]
    out = []
    for label, d, loads, cont in cases:
        r = TWO_TUBE_COSSERAT.solve(d, loads, continuation=cont)
        if isinstance(r, RodPath):
            x, y, z = (float(v) for v in r.tip_position_mm)
            out.append(HonestyCase(label, True, (x, y, z), r.solve_ms, ""))
        else:
            out.append(HonestyCase(label, False, None, r.solve_ms, r.reason))
        c = out[-1]
        log(f"honesty: {label:44s} " + (f"tip {np.round(c.tip_mm, 2)} mm" if c.tip_mm else f"FAILED: {c.reason}"))
    return out


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


def pareto_figure(rows: list[Row]) -> Figure:
    """Median time per solve against the worst tip error (log-log), with the Pareto front of the frictionless rows.

    Parameters
    ----------
    rows : list of Row
        The chart's points (ms against mm).

    Returns
    -------
    matplotlib.figure.Figure
    """
    floor = 1e-10
    fig = Figure(figsize=(9, 6))
    ax = fig.subplots()
    colors = {"constant_curvature": "tab:red", "planar_beam": "tab:orange", "cosserat_rod": "tab:blue",
              "two_tube_cosserat": "tab:green", "two_tube_collocation": "tab:purple", FRICTION_MODEL: "tab:olive"}
    own = {FRICTION_MODEL: "vs itself at 8 steps/mm"}  # rows with their own reference: not on the front
    for r in rows:
        if r.model not in colors:  # in-tissue rows
            colors[r.model] = "tab:brown" if r.model.startswith("tissue_rod") else "tab:pink"
            own[r.model] = r.resolution
    for name, c in colors.items():
        pts = [r for r in rows if r.model == name]
        if not pts:
            continue
        label = f"{name} ({own[name]})" if name in own else name
        ax.plot([r.median_ms for r in pts], [max(r.max_tip_error_mm, floor) for r in pts], "o-" if len(pts) > 1
                else "o", color=c, label=label, ms=7)
        for r in pts:
            if "default" in r.resolution or len(pts) == 1:
                ax.annotate(r.resolution, (r.median_ms, max(r.max_tip_error_mm, floor)), fontsize=7,
                            xytext=(4, 4), textcoords="offset points")
    batched = [(r, r.batched_solves_per_s) for r in rows if r.batched_solves_per_s]
    ax.scatter([1e3 / bps for _, bps in batched],
               [max(r.max_tip_error_mm, floor) for r, _ in batched], marker="s", facecolors="none",
               edgecolors=[colors[r.model] for r, _ in batched], s=60, label="same model, batched (time per solve)")
    front: list[Row] = []
    for r in sorted((r for r in rows if r.model not in own), key=lambda r: r.median_ms):
        if not front or r.max_tip_error_mm < front[-1].max_tip_error_mm:
            front.append(r)
    ax.step([r.median_ms for r in front], [max(r.max_tip_error_mm, floor) for r in front], where="post",
            color="k", lw=1, ls="--", label="Pareto front")
    ax.scatter([r.median_ms for r in front], [max(r.max_tip_error_mm, floor) for r in front], s=160,
               facecolors="none", edgecolors="k")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("median time per solve (ms, log)")
    ax.set_ylabel(f"max tip error vs converged two-tube reference (mm, log; floor {floor:g})")
    ax.set_title("Rod models: speed vs accuracy (free space: presets × tensions 0-15 N; in tissue: per insertion)")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    return fig


def stability_figure(cases: list[StabilityCase]) -> Figure:
    """Converged / failed map of each solver over placement × initial guess (rows) and tension (columns).

    Parameters
    ----------
    cases : list of StabilityCase
        The map's cases.

    Returns
    -------
    matplotlib.figure.Figure
    """
    solvers = list(dict.fromkeys(c.solver for c in cases))
    tensions = sorted({c.tension_n for c in cases})
    rows = list(dict.fromkeys((c.placement, c.guess) for c in cases))
    fig = Figure(figsize=(4.2 * len(solvers), 4.8))
    axes = fig.subplots(1, len(solvers), sharey=True)
    for ax, s in zip(np.atleast_1d(axes), solvers, strict=True):
        img = np.zeros((len(rows), len(tensions)))
        for c in cases:
            if c.solver == s:
                img[rows.index((c.placement, c.guess)), tensions.index(c.tension_n)] = 1.0 if c.success else 0.0
        ax.imshow(img, cmap="RdYlGn", vmin=0, vmax=1, aspect="auto")
        for c in cases:
            if c.solver == s and not c.success:
                code = "NC" if "did not converge" in c.reason else ("SJ" if "singular" in c.reason else "NF")
                ax.text(tensions.index(c.tension_n), rows.index((c.placement, c.guess)), code, ha="center",
                        va="center", fontsize=7)
        ok = [c.success for c in cases if c.solver == s]
        ax.set_title(f"{s}\n{sum(ok)}/{len(ok)} converged", fontsize=9)
        ax.set_xticks(range(len(tensions)), [f"{t:g} N" for t in tensions])
        ax.set_yticks(range(len(rows)), [f"{p} / {g} guess" for p, g in rows], fontsize=7)
    fig.suptitle("Two-tube solver stability (tip force (0, 0.2, -0.2) N; NC: not converged, SJ: singular, "
                 "NF: non-finite)", fontsize=9)
    fig.tight_layout()
    return fig


def error_table(rows: list[Row]) -> dict[str, object]:
    """Return the package-data document read by :func:`reachplan.rod_model.select.error_table`.

    Parameters
    ----------
    rows : list of Row
        The frictionless rows.

    Returns
    -------
    dict of str to object
        JSON-ready: source and one entry per row (ms, mm).
    """
    return {
        "source": "reachplan bench models",
        "generated_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        "reference": "two_tube_cosserat, 8 RK4 steps/mm, tol 1e-12",
        "grid": f"presets {', '.join(PRESET_NAMES)} x tensions 0-15 N, free space",
        "rows": [{"model": r.model, "resolution": "default" if "default" in r.resolution else r.resolution,
                  "max_tip_error_mm": r.max_tip_error_mm, "median_ms": r.median_ms,
                  "batched_solves_per_s": r.batched_solves_per_s, "success_rate": r.success_rate}
                 for r in rows],
    }


def write_results(out: Path, rows: list[Row], cases: list[StabilityCase], friction_rows: list[Row],
                  honest: list[HonestyCase], tissue_points: list[TissuePoint], tissue_rows: Sequence[Row] = ()) -> None:
    """Write the tables, the charts and the error table under ``out``.

    ``rod_models.csv`` (:data:`ROW_COLUMNS`), ``rod_models_stability.csv`` (:data:`STABILITY_COLUMNS`), their
    charts ``rod_models_pareto.png`` (with the friction row) and ``rod_models_stability.png``,
    ``rod_models_friction.csv`` (:data:`FRICTION_COLUMNS`), ``rod_models_honesty.csv`` (:data:`HONESTY_COLUMNS`),
    ``rod_models_tissue.csv`` (:data:`TISSUE_COLUMNS`) and its chart ``rod_models_tissue.png``, and
    ``model_errors.json`` (the frictionless rows only).

    Parameters
    ----------
    out : Path
        The results folder.
    rows : list of Row
        Speed/accuracy rows.
    cases : list of StabilityCase
        Stability map.
    friction_rows : list of Row
        The friction row.
    honest : list of HonestyCase
        The honesty table.
    tissue_points : list of TissuePoint
        The in-tissue chart.
    tissue_rows : sequence of Row
        Its speed/accuracy rows.
    """
    write_csv(out / "rod_models.csv", ROW_COLUMNS,
              [[r.model, r.resolution, f"{r.median_ms:.5g}", f"{r.max_tip_error_mm:.4g}",
                f"{r.median_tip_error_mm:.4g}", r.success_rate,
                "" if r.batched_solves_per_s is None else f"{r.batched_solves_per_s:.0f}",
                "" if r.batched_peak_mb is None else f"{r.batched_peak_mb:.1f}"] for r in [*rows, *tissue_rows]])
    write_csv(out / "rod_models_stability.csv", STABILITY_COLUMNS,
              [[c.solver, c.placement, c.tension_n, c.guess, c.success, f"{c.residual:.3g}", f"{c.ms:.2f}",
                c.reason] for c in cases])
    write_csv(out / "rod_models_friction.csv", FRICTION_COLUMNS,
              [[r.model, r.resolution, f"{r.median_ms:.5g}", f"{r.max_tip_error_mm:.4g}",
                f"{r.median_tip_error_mm:.4g}", r.success_rate] for r in friction_rows])
    write_csv(out / "rod_models_honesty.csv", HONESTY_COLUMNS,
              [[c.case, c.converged, *(f"{v:.3f}" for v in (c.tip_mm or (math.nan,) * 3)), f"{c.ms:.2f}",
                c.reason] for c in honest])
    write_csv(out / "rod_models_tissue.csv", TISSUE_COLUMNS,
              [[f"{p.modulus_pa:g}", p.schedule, f"{p.depth_mm:g}", f"{p.tissue_rod_mm:.4f}",
                f"{p.kinematic_mm:.4f}", f"{p.tip_following_mm:.4f}", f"{p.factor:.4f}", f"{p.function:.4f}",
                f"{p.ms:.0f}", p.status]
               for p in tissue_points])
    write_png(out / "rod_models_tissue.png", tissue_figure(tissue_points))
    write_png(out / "rod_models_pareto.png", pareto_figure([*rows, *friction_rows, *tissue_rows]))
    write_png(out / "rod_models_stability.png", stability_figure(cases))
    write_json(out / "model_errors.json", error_table(rows))


def run_benchmark(out: Path, s: ModelSettings, log: Callable[[str], None] = print) -> dict[str, object]:
    """Run the whole benchmark and write its CSV, PNG and JSON files into ``out``.

    Parameters
    ----------
    out : Path
        The results folder.
    s : ModelSettings
        What to measure.
    log : callable (str) -> None
        Progress lines.

    Returns
    -------
    dict
        The headline numbers, also written as ``summary.json``.
    """
    t0 = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", TensionAboveLimitWarning)  # the grid goes to 15 N, honesty to 5000 N
        rows, extra = speed_accuracy(s, log)
        friction_rows, widths = friction(s, log)
        extra.update(widths)
        honest = honesty(log)
        tissue_points, tissue_rows = tissue(s, log)
        cases = stability(s, log)
    write_results(out, rows, cases, friction_rows, honest, tissue_points, tissue_rows)
    summary: dict[str, object] = {"rows": [r.__dict__ for r in rows + friction_rows + tissue_rows], **extra,
                                  "honesty": [c.__dict__ for c in honest],
                                  "stability": {v: f"{sum(c.success for c in cases if c.solver == v)}/"
                                                   f"{sum(c.solver == v for c in cases)}"
                                                for v in dict.fromkeys(c.solver for c in cases)},
                                  "wall_s": time.perf_counter() - t0}
    write_json(out / "summary.json", summary)
    log(f"benchmark done in {summary['wall_s']:.0f} s; results in {out}")
    return summary


def run(args: argparse.Namespace) -> int:
    """Run ``reachplan bench models`` (``--quick``: a smoke run) into ``args.out``; progress on stderr.

    Parameters
    ----------
    args : argparse.Namespace
        Parsed ``reachplan bench models`` options (``out``, ``quick``).

    Returns
    -------
    int
        0; progress went to stderr.
    """
    run_benchmark(args.out, settings(args, ModelSettings(), QUICK), log=lambda m: print(m, file=sys.stderr, flush=True))
    return 0
