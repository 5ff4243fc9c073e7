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
import math
import sys
import time
import warnings
from collections.abc import Callable, Sequence
from pathlib import Path

from matplotlib.figure import Figure

from reachplan.planner.bench.common import settings, write_csv, write_json, write_png
from reachplan.planner.bench.models_robustness import HonestyCase, StabilityCase, honesty, stability, stability_figure
from reachplan.planner.bench.models_speed import FRICTION_MODEL, QUICK, ModelSettings, Row, friction, speed_accuracy
from reachplan.planner.bench.models_tissue import TissuePoint, tissue, tissue_figure
from reachplan.rod_model.design import PRESET_NAMES
from reachplan.rod_model.errors import TensionAboveLimitWarning

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
