"""Benchmark of the rod models: time per solve against tip error, batched throughput, and a stability map.

Run through ``reachplan bench models --out DIR`` (add ``--install`` to refresh the package's error table
``rod_model/model_errors.json`` and the figures ``docs/rod_models_pareto.png``, ``docs/rod_models_stability.png``).

Speed vs accuracy
    Grid: every preset of :data:`reachplan.rod_model.design.PRESET_NAMES` × tensions 0-15 N (1 N steps), free space.
    Reference: the two-tube Cosserat model at 8 RK4 steps/mm, residual tolerance 1e-12 (its own convergence
    against 4 steps/mm is reported). For every model and resolution: median wall time of one ``solve`` and the
    largest / median tip error against the reference. Batched throughput of each registered configuration: 10,000
    tensions in one ``solve_batch`` (and the peak memory, by ``tracemalloc``).
Friction
    The two-tube model with capstan and joint friction (coefficients 0.1 / 0.1) against the same model at
    8 steps/mm (its own numerical error, pulled from rest), and the width of the hysteresis loop of a
    0-10-0 N sweep per preset.
Honesty
    The load cases a reviewer found wrong: a 2 N lateral tip force on 15ga-20j-base (used to converge 67 mm on
    the wrong side), a dead axial load at 0.9 / 1.1 / 1.5 of the Euler load (straight and imperfect), 5000 N of
    tension (used to blow up to 7e18 mm "converged"): what the solver returns now, with its reason.
In tissue
    The in-tissue Cosserat insertion (:mod:`reachplan.planner.steering.tissue_rod`) of 15ga-20j-tip at its
    maximum tension from the template, tip deflection against the tissue modulus (1 kPa - 10 MPa) and depth,
    beside the kinematic model; the kinematic model's curvature factor fitted per modulus (least squares on
    the lateral tip over the depths), ``rod_models_tissue.csv`` / ``.png``.
Stability map
    Each solver (shooting without continuation, shooting with continuation, collocation) on tension ×
    placement × initial guess (zero, small, large), with an out-of-plane tip force so that the boundary-value
    problem is not trivial; success, residual and the failure reason per case.
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import os
import statistics
import subprocess
import sys
import tempfile
import time
import tracemalloc
import warnings
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from reachplan.rod_model.beam import PLANAR_BEAM, PlanarBeam
from reachplan.rod_model.collocation import NS, CollocationCosserat
from reachplan.rod_model.cosserat import COSSERAT_ROD, TWO_TUBE_COSSERAT, CosseratRod, TwoTubeCosserat
from reachplan.rod_model.design import PRESET_NAMES, Loads, RodDesign, gravity_load, preset
from reachplan.rod_model.errors import TensionAboveLimitWarning
from reachplan.rod_model.friction import loop_width_mm, solve_sweep
from reachplan.rod_model.kinematic import CONSTANT_CURVATURE, ConstantCurvature
from reachplan.rod_model.result import RodPath

REPO = Path(__file__).resolve().parents[1]
STEPS_PER_MM = (0.02, 0.05, 0.1, 0.25, 0.5, 1.0, 2.0)
REFERENCE = TwoTubeCosserat(steps_per_mm=8.0, tol=1e-12)
BATCH = 10_000


@dataclass(frozen=True)
class Row:
    """One point of the speed/accuracy chart."""

    model: str
    resolution: str
    median_ms: float
    max_tip_error_mm: float
    median_tip_error_mm: float
    success_rate: float
    batched_solves_per_s: float | None = None
    batched_peak_mb: float | None = None


def _atomic_write(path: Path, write: Callable[[Path], None]) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=path.suffix)
    os.close(fd)
    try:
        write(Path(tmp))
        os.chmod(tmp, 0o644)  # mkstemp creates 0600; these are committed/package files
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def _write_text(path: Path, text: str) -> None:
    def w(p: Path) -> None:
        p.write_text(text, encoding="utf-8")
    _atomic_write(path, w)


def _write_csv(path: Path, header: Sequence[str], rows: Sequence[Sequence[object]]) -> None:
    def w(p: Path) -> None:
        with p.open("w", newline="", encoding="utf-8") as fh:
            out = csv.writer(fh)
            out.writerow(header)
            out.writerows(rows)
    _atomic_write(path, w)


def _grid(quick: bool) -> list[tuple[RodDesign, float]]:
    names = ("15ga-20j-tip", "15ga-20j-base", "13ga-20j-tip") if quick else PRESET_NAMES
    tensions = (0.0, 5.0, 10.0, 15.0) if quick else tuple(float(t) for t in range(16))
    return [(preset(n), t) for n in names for t in tensions]


def _time_model(model: object, grid: list[tuple[RodDesign, float]], ref: np.ndarray) -> tuple[float, np.ndarray, float]:
    times, errs = [], []
    ok = 0
    for (d, t), tip in zip(grid, ref, strict=True):
        t0 = time.perf_counter()
        r = model.solve(d, d.loads(t))  # type: ignore[attr-defined]
        times.append((time.perf_counter() - t0) * 1e3)
        if isinstance(r, RodPath):
            ok += 1
            errs.append(float(np.linalg.norm(r.tip_position_mm - tip)))
        else:
            errs.append(np.inf)
    return statistics.median(times), np.array(errs), ok / len(grid)


def _batched(model: object, design: RodDesign, n: int) -> tuple[float, float]:
    tensions = np.linspace(0.0, 15.0, n)
    model.solve_batch(design, tensions[:10])  # type: ignore[attr-defined]  # warm-up / compile
    rates = []
    for _ in range(3):
        t0 = time.perf_counter()
        model.solve_batch(design, tensions)  # type: ignore[attr-defined]
        rates.append(n / (time.perf_counter() - t0))
    tracemalloc.start()
    model.solve_batch(design, tensions)  # type: ignore[attr-defined]
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
                             timeout=120, check=True, cwd=REPO)
    except (subprocess.SubprocessError, OSError):
        return None
    return float(json.loads(out.stdout.strip().splitlines()[-1]))


def speed_accuracy(quick: bool, log: Callable[[str], None]) -> tuple[list[Row], dict[str, float]]:
    grid = _grid(quick)
    REFERENCE.solve(*(grid[1][0], grid[1][0].loads(1.0)))  # compile
    t0 = time.perf_counter()
    refs = [REFERENCE.solve(d, d.loads(t)) for d, t in grid]
    if not all(isinstance(r, RodPath) for r in refs):
        raise RuntimeError("reference solve failed")
    ref = np.array([r.tip_position_mm for r in refs])  # type: ignore[union-attr]
    check = TwoTubeCosserat(steps_per_mm=4.0, tol=1e-12)
    ref_conv = max(float(np.linalg.norm(check.solve(d, d.loads(t)).tip_position_mm - tip))  # type: ignore[union-attr]
                   for (d, t), tip in zip(grid, ref, strict=True))
    log(f"reference: {len(grid)} solves in {time.perf_counter() - t0:.1f} s; change vs 4 steps/mm {ref_conv:.1e} mm")
    rows: list[Row] = []
    configs: list[tuple[object, str]] = [(ConstantCurvature(), "closed form"), (PlanarBeam(), "closed form")]
    for cls in (CosseratRod, TwoTubeCosserat):
        for spm in STEPS_PER_MM:
            configs.append((cls(steps_per_mm=spm), f"{spm:g} steps/mm"))
    defaults = {CONSTANT_CURVATURE.name: CONSTANT_CURVATURE, PLANAR_BEAM.name: PLANAR_BEAM,
                COSSERAT_ROD.name: COSSERAT_ROD, TWO_TUBE_COSSERAT.name: TWO_TUBE_COSSERAT}
    for model, res in configs:
        model.solve(grid[0][0], grid[0][0].loads(1.0))  # type: ignore[attr-defined]  # warm-up
        med, errs, rate = _time_model(model, grid, ref)
        name = model.name  # type: ignore[attr-defined]
        is_default = model == defaults[name]
        bps = peak = None
        if is_default:
            bps, peak = _batched(model, preset("15ga-20j-tip"), BATCH)
            res += " (default)"
        rows.append(Row(name, res, med, float(np.max(errs)), float(np.median(errs)), rate, bps, peak))
        log(f"{name:20s} {res:24s} {med:8.3f} ms  max err {rows[-1].max_tip_error_mm:.2e} mm"
            + (f"  batched {bps:,.0f}/s  peak {peak:.0f} MB" if bps else ""))
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
            lerrs.append(float(np.linalg.norm(r.tip_position_mm - rr.tip_position_mm)) if ok else np.inf)  # type: ignore[union-attr]
        extra[f"{model.name}_loaded_median_ms"] = statistics.median(ltimes)
        extra[f"{model.name}_loaded_max_tip_error_mm"] = max(lerrs)
        log(f"{model.name:20s} loaded (tip force + weight) {statistics.median(ltimes):8.3f} ms  max err "
            f"{max(lerrs):.2e} mm")
    planar_rate, planar_peak = _batched(PLANAR_BEAM, preset("15ga-20j-tip"), 100_000)
    extra.update(planar_100k_solves_per_s=planar_rate, planar_100k_peak_mb=planar_peak)
    log(f"planar_beam 100k batched: {planar_rate:,.0f}/s, peak {planar_peak:.0f} MB")
    interp = _interpreted_ms()
    if interp is not None:
        extra["two_tube_interpreted_ms"] = interp
        log(f"two_tube_cosserat without numba (NUMBA_DISABLE_JIT=1): {interp:.1f} ms per solve")
    return rows, extra


@dataclass(frozen=True)
class StabilityCase:
    """One case of the stability map."""

    solver: str
    placement: str
    tension_n: float
    guess: str
    success: bool
    residual: float
    ms: float
    reason: str


def stability(quick: bool, log: Callable[[str], None]) -> list[StabilityCase]:
    tensions = (0.0, 7.5, 15.0) if quick else (0.0, 5.0, 10.0, 15.0)
    rng = np.random.default_rng(7)
    out: list[StabilityCase] = []
    collocation = CollocationCosserat(tol=1e-6, nodes_per_section=11, max_nodes=300, max_ramp=2)
    solvers: dict[str, tuple[Any, bool]] = {"shooting": (TWO_TUBE_COSSERAT, False),
                                            "shooting+continuation": (TWO_TUBE_COSSERAT, True),
                                            "collocation": (collocation, True)}
    for placement in ("tip", "mid", "base"):
        d = preset(f"15ga-20j-{placement}")
        for t in tensions:
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
                    reason = "" if ok else r.reason  # type: ignore[union-attr]
                    out.append(StabilityCase(label, placement, t, guess, ok, float(r.residual),
                                             float(r.solve_ms), reason))
    for label in solvers:
        cases = [c for c in out if c.solver == label]
        log(f"stability {label:22s}: {sum(c.success for c in cases)}/{len(cases)} converged")
    return out


def _with_friction(d: RodDesign, mu: float) -> RodDesign:
    return replace(d, stylet=replace(d.stylet, tendon_friction_coefficient=mu, joint_friction_coefficient=mu))


def friction(quick: bool, log: Callable[[str], None]) -> tuple[list[Row], dict[str, float]]:
    """Speed/accuracy of the friction model (against itself at 8 steps/mm) and loop widths per preset."""
    grid = [(_with_friction(d, 0.1), t) for d, t in _grid(quick)]
    ref_model = TwoTubeCosserat(steps_per_mm=8.0, tol=1e-12)
    refs = [ref_model.solve(d, d.loads(t)) for d, t in grid]
    ok = [isinstance(r, RodPath) for r in refs]
    grid = [g for g, good in zip(grid, ok, strict=True) if good]
    ref = np.array([r.tip_position_mm for r in refs if isinstance(r, RodPath)])
    TWO_TUBE_COSSERAT.solve(grid[0][0], grid[0][0].loads(1.0))
    med, errs, rate = _time_model(TWO_TUBE_COSSERAT, grid, ref)
    row = Row("two_tube_cosserat+friction", "mu 0.1/0.1 (default steps)", med, float(np.max(errs)),
              float(np.median(errs)), rate)
    log(f"{row.model:26s} {row.resolution:26s} {med:8.3f} ms  max err {row.max_tip_error_mm:.2e} mm")
    up_down = [0.0, 2.0, 4.0, 6.0, 8.0, 10.0, 8.0, 6.0, 4.0, 2.0, 0.0]
    widths: dict[str, float] = {}
    for name in ("15ga-20j-tip", "15ga-20j-base") if quick else PRESET_NAMES:
        res = solve_sweep(TWO_TUBE_COSSERAT, _with_friction(preset(name), 0.1), up_down)
        if all(isinstance(r, RodPath) for r in res):
            widths[f"loop_width_mm_{name}_mu0.1"] = loop_width_mm(up_down, [r.tip_deflection_mm for r in res])  # type: ignore[union-attr]
    log("hysteresis loop width (mu 0.1/0.1, 0-10-0 N): " + ", ".join(f"{k}: {v:.2f} mm" for k, v in widths.items()))
    return [row], widths


@dataclass(frozen=True)
class HonestyCase:
    """One load case of the honesty table."""

    case: str
    converged: bool
    tip_mm: tuple[float, float, float] | None
    ms: float
    reason: str


def honesty(log: Callable[[str], None]) -> list[HonestyCase]:
    """The reviewer's wrong-branch and blow-up cases through the checked solver."""
    base, tip = preset("15ga-20j-base"), preset("15ga-20j-tip")
    sec = tip.sections()[0]
    p_cr = math.pi**2 * (sec.ei1 + sec.ei2) / (4 * (tip.length_mm * 1e-3) ** 2)  # tube + needle column
    cases: list[tuple[str, RodDesign, Loads, bool]] = [
        ("15ga-20j-base, 2 N lateral tip force (+y)", base, Loads((0.0,) * 4, tip_force_n=(0.0, 2.0, 0.0)), True),
        ("same, direct solve (no continuation)", base, Loads((0.0,) * 4, tip_force_n=(0.0, 2.0, 0.0)), False),
        ("15ga-20j-base, 9.9 N + 2 N lateral (+y)", base, Loads((9.9, 0, 0, 0), tip_force_n=(0.0, 2.0, 0.0)), True),
        ("same, direct solve (no continuation)", base, Loads((9.9, 0, 0, 0), tip_force_n=(0.0, 2.0, 0.0)), False),
        ("15ga-20j-tip, axial 0.9 P_euler(tube)", tip, Loads((0.0,) * 4, tip_force_n=(0.0, 0.0, -0.9 * p_cr)), True),
        ("15ga-20j-tip, axial 1.1 P_euler(tube)", tip, Loads((0.0,) * 4, tip_force_n=(0.0, 0.0, -1.1 * p_cr)), True),
        ("15ga-20j-tip, 1.5 P_euler + 1 % lateral", tip,
         Loads((0.0,) * 4, tip_force_n=(0.015 * p_cr, 0.0, -1.5 * p_cr)), True),
        ("15ga-20j-tip, 5000 N tension", tip, tip.loads(5000.0), True),
    ]
    out = []
    for label, d, loads, cont in cases:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", TensionAboveLimitWarning)
            r = TWO_TUBE_COSSERAT.solve(d, loads, continuation=cont)
        if isinstance(r, RodPath):
            x, y, z = (float(v) for v in r.tip_position_mm)
            out.append(HonestyCase(label, True, (x, y, z), r.solve_ms, ""))
        else:
            out.append(HonestyCase(label, False, None, r.solve_ms, r.reason))
        c = out[-1]
        log(f"honesty: {label:44s} " + (f"tip {np.round(c.tip_mm, 2)} mm" if c.converged else f"FAILED: {c.reason}"))
    return out


TISSUE_MODULI_PA = (1e3, 1e4, 1e5, 1.9e5, 1e6, 3e6, 1e7)
TISSUE_DEPTHS_MM = (30.0, 60.0, 90.0, 120.0, 150.0)


@dataclass(frozen=True)
class TissuePoint:
    """One point of the in-tissue chart."""

    modulus_pa: float
    depth_mm: float
    tissue_rod_mm: float
    kinematic_mm: float
    factor: float
    ms: float
    status: str


def tissue(quick: bool, log: Callable[[str], None]) -> list[TissuePoint]:
    """Tip deflection of the in-tissue rod against modulus and depth, and the kinematic factor per modulus."""
    from scipy.optimize import minimize_scalar

    from reachplan.planner.steering.insertion import KinematicInsertion
    from reachplan.planner.steering.schedule import TensionSchedule
    from reachplan.planner.steering.tissue_rod import TissueRodInsertion

    design = preset("15ga-20j-tip")
    schedule = TensionSchedule.constant(design.max_tension_n)
    moduli = (1e3, 1.9e5, 1e7) if quick else TISSUE_MODULI_PA
    depths = np.array(TISSUE_DEPTHS_MM)
    out: list[TissuePoint] = []

    def kinematic(factor: float) -> np.ndarray:
        paths = KinematicInsertion(tissue_factor=factor).insert_array(design, [schedule], float(depths[-1]))[0]
        return np.hypot(paths[:, 0], paths[:, 1])[np.round(depths).astype(int)]  # 1 mm steps from 0

    kin1 = kinematic(1.0)
    for e in moduli:
        t0 = time.perf_counter()
        final, steps = TissueRodInsertion(tissue_modulus_pa=e).insert_steps(design, schedule, float(depths[-1]))
        ms = (time.perf_counter() - t0) * 1e3
        tips = {round(d): float(np.hypot(tip[0], tip[1])) for d, tip in steps}
        got = np.array([tips.get(round(d), np.nan) for d in depths])
        ok = np.isfinite(got)
        factor = math.nan
        if ok.sum() >= 2:
            def misfit(f: float, ok: np.ndarray = ok, got: np.ndarray = got) -> float:
                return float(np.sum((kinematic(f)[ok] - got[ok]) ** 2))

            factor = float(minimize_scalar(misfit, bounds=(0.0, 3.0), method="bounded", options={"xatol": 1e-4}).x)
        status = "ok" if isinstance(final, np.ndarray) else final.reason
        for d, g, k in zip(depths, got, kin1, strict=True):
            out.append(TissuePoint(e, float(d), float(g), float(k), factor, ms,
                                   status if not np.isfinite(g) else "ok"))
        tip_text = ", ".join(f"{d:.0f} mm {g:.2f}" for d, g in zip(depths, got, strict=True))
        log(f"tissue_rod E = {e:9.3g} Pa: tip at {tip_text} mm; kinematic factor {factor:.3f}; {ms:.0f} ms"
            + ("" if status == "ok" else f"; FAILED {status}"))
    return out


def _tissue_png(points: list[TissuePoint], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (a1, a2) = plt.subplots(1, 2, figsize=(12, 5), dpi=110)
    moduli = sorted({p.modulus_pa for p in points})
    for d in sorted({p.depth_mm for p in points}):
        pts = sorted((p for p in points if p.depth_mm == d), key=lambda p: p.modulus_pa)
        line = a1.plot([p.modulus_pa for p in pts], [p.tissue_rod_mm for p in pts], "o-",
                       label=f"tissue_rod {d:.0f} mm")
        a1.axhline(pts[0].kinematic_mm, color=line[0].get_color(), ls=":", lw=1)
    a1.set_xscale("log")
    a1.set_xlabel("tissue Young's modulus (Pa, log)")
    a1.set_ylabel("lateral tip deflection (mm)")
    a1.set_title("15ga-20j-tip at 10 N: in-tissue Cosserat (dots: kinematic, factor 1)", fontsize=9)
    a1.grid(True, which="both", alpha=0.3)
    a1.legend(fontsize=7)
    fac = [next(p.factor for p in points if p.modulus_pa == e) for e in moduli]
    a2.plot(moduli, fac, "s-")
    a2.set_xscale("log")
    a2.set_xlabel("tissue Young's modulus (Pa, log)")
    a2.set_ylabel("kinematic curvature factor fitted to tissue_rod")
    a2.grid(True, which="both", alpha=0.3)
    fig.tight_layout()
    _atomic_write(path, lambda p: fig.savefig(p, format="png"))
    plt.close(fig)


def _pareto_png(rows: list[Row], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    floor = 1e-10
    fig, ax = plt.subplots(figsize=(9, 6), dpi=110)
    colors = {"constant_curvature": "tab:red", "planar_beam": "tab:orange", "cosserat_rod": "tab:blue",
              "two_tube_cosserat": "tab:green", "two_tube_collocation": "tab:purple",
              "two_tube_cosserat+friction": "tab:olive"}
    for name, c in colors.items():
        pts = [r for r in rows if r.model == name]
        if not pts:
            continue
        ax.plot([r.median_ms for r in pts], [max(r.max_tip_error_mm, floor) for r in pts], "o-" if len(pts) > 1
                else "o", color=c, label=name, ms=7)
        for r in pts:
            if "default" in r.resolution or len(pts) == 1:
                ax.annotate(r.resolution, (r.median_ms, max(r.max_tip_error_mm, floor)), fontsize=7,
                            xytext=(4, 4), textcoords="offset points")
    batched = [r for r in rows if r.batched_solves_per_s]
    ax.scatter([1e3 / r.batched_solves_per_s for r in batched],  # type: ignore[operator]
               [max(r.max_tip_error_mm, floor) for r in batched], marker="s", facecolors="none",
               edgecolors=[colors[r.model] for r in batched], s=60, label="same model, batched (time per solve)")
    front: list[Row] = []
    for r in sorted(rows, key=lambda r: r.median_ms):
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
    ax.set_title("Rod models: speed vs accuracy (presets × tensions 0-15 N, free space)")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    _atomic_write(path, lambda p: fig.savefig(p, format="png"))
    plt.close(fig)


def _stability_png(cases: list[StabilityCase], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    solvers = list(dict.fromkeys(c.solver for c in cases))
    tensions = sorted({c.tension_n for c in cases})
    rows = [(p, g) for p in ("tip", "mid", "base") for g in ("zero", "small", "large")]
    fig, axes = plt.subplots(1, len(solvers), figsize=(4.2 * len(solvers), 4.8), dpi=110, sharey=True)
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
    _atomic_write(path, lambda p: fig.savefig(p, format="png"))
    plt.close(fig)


def error_table(rows: list[Row]) -> dict[str, object]:
    """The package-data document read by :func:`reachplan.rod_model.select.error_table`."""
    return {
        "source": "benchmarks/rod_models.py (reachplan bench models)",
        "generated_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        "reference": "two_tube_cosserat, 8 RK4 steps/mm, tol 1e-12",
        "grid": f"presets {', '.join(PRESET_NAMES)} x tensions 0-15 N, free space",
        "rows": [{"model": r.model, "resolution": "default" if "default" in r.resolution else r.resolution,
                  "max_tip_error_mm": r.max_tip_error_mm, "median_ms": r.median_ms,
                  "batched_solves_per_s": r.batched_solves_per_s, "success_rate": r.success_rate}
                 for r in rows],
    }


def run_benchmark(out: Path, quick: bool = False, install: bool = False,
                  log: Callable[[str], None] = print) -> dict[str, object]:
    """Run everything, write the CSV/PNG/JSON files into ``out``; with ``install`` also refresh the package's
    error table and the figures under ``docs/``. Returns the headline numbers."""
    t0 = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", TensionAboveLimitWarning)  # the grid goes to 15 N on purpose
        rows, extra = speed_accuracy(quick, log)
        frows, widths = friction(quick, log)
        extra.update(widths)
        honest = honesty(log)
        tissue_points = tissue(quick, log)
        cases = stability(quick, log)
    _write_csv(out / "rod_models.csv", ["model", "resolution", "median_ms", "max_tip_error_mm",
                                        "median_tip_error_mm", "success_rate", "batched_solves_per_s",
                                        "batched_peak_mb"],
               [[r.model, r.resolution, f"{r.median_ms:.5g}", f"{r.max_tip_error_mm:.4g}",
                 f"{r.median_tip_error_mm:.4g}", r.success_rate,
                 "" if r.batched_solves_per_s is None else f"{r.batched_solves_per_s:.0f}",
                 "" if r.batched_peak_mb is None else f"{r.batched_peak_mb:.1f}"] for r in rows])
    _write_csv(out / "rod_models_stability.csv", ["solver", "placement", "tension_n", "guess", "success",
                                                  "residual_n", "ms", "reason"],
               [[c.solver, c.placement, c.tension_n, c.guess, c.success, f"{c.residual:.3g}", f"{c.ms:.2f}",
                 c.reason] for c in cases])
    _write_csv(out / "rod_models_friction.csv", ["model", "resolution", "median_ms", "max_tip_error_mm",
                                                 "median_tip_error_mm", "success_rate"],
               [[r.model, r.resolution, f"{r.median_ms:.5g}", f"{r.max_tip_error_mm:.4g}",
                 f"{r.median_tip_error_mm:.4g}", r.success_rate] for r in frows])
    _write_csv(out / "rod_models_honesty.csv", ["case", "converged", "tip_x_mm", "tip_y_mm", "tip_z_mm", "ms",
                                                "reason"],
               [[c.case, c.converged, *(f"{v:.3f}" for v in (c.tip_mm or (math.nan,) * 3)), f"{c.ms:.2f}",
                 c.reason] for c in honest])
    _write_csv(out / "rod_models_tissue.csv", ["modulus_pa", "depth_mm", "tissue_rod_tip_mm", "kinematic_tip_mm",
                                               "kinematic_factor_fitted", "insertion_ms", "status"],
               [[f"{p.modulus_pa:g}", f"{p.depth_mm:g}", f"{p.tissue_rod_mm:.4f}", f"{p.kinematic_mm:.4f}",
                 f"{p.factor:.4f}", f"{p.ms:.0f}", p.status] for p in tissue_points])
    _tissue_png(tissue_points, out / "rod_models_tissue.png")
    _pareto_png(rows + frows, out / "rod_models_pareto.png")
    _stability_png(cases, out / "rod_models_stability.png")
    table = json.dumps(error_table(rows), indent=1) + "\n"
    _write_text(out / "model_errors.json", table)
    summary: dict[str, object] = {"rows": [r.__dict__ for r in rows + frows], **extra,
                                  "honesty": [c.__dict__ for c in honest],
                                  "stability": {s: f"{sum(c.success for c in cases if c.solver == s)}/"
                                                   f"{sum(c.solver == s for c in cases)}"
                                                for s in dict.fromkeys(c.solver for c in cases)},
                                  "wall_s": time.perf_counter() - t0}
    _write_text(out / "summary.json", json.dumps(summary, indent=1) + "\n")
    if install:
        if quick:
            raise ValueError("--install needs the full grid; drop --quick")
        _write_text(REPO / "rod_model" / "model_errors.json", table)
        _pareto_png(rows, REPO / "docs" / "rod_models_pareto.png")
        _stability_png(cases, REPO / "docs" / "rod_models_stability.png")
    log(f"benchmark done in {summary['wall_s']:.0f} s; results in {out}")
    return summary


def run(args: argparse.Namespace) -> int:
    run_benchmark(args.out, quick=args.quick, install=args.install,
                  log=lambda m: print(m, file=sys.stderr, flush=True))
    return 0


if __name__ == "__main__":  # pragma: no cover
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", required=True, type=Path, help="results folder (CSV, PNG, JSON)")
    p.add_argument("--quick", action="store_true", help="small grid (a smoke run, seconds)")
    p.add_argument("--install", action="store_true",
                   help="also refresh rod_model/model_errors.json and docs/rod_models_*.png")
    sys.exit(run(p.parse_args()))
