"""Benchmark: each stylet design's kinematic curvature factor against the tissue modulus, fitted to the in-tissue rod.

For every design of ``--designs`` (default: every preset) and each tissue modulus of the tip-following range, the
factor that makes the kinematic model's tips best match the in-tissue Cosserat insertion
(:func:`reachplan.planner.steering.factors.fit_curvature_factor`: 20 mm ramps from 0-60 mm onsets to 60 / 100 %
of the maximum tension, tips at 60-150 mm), with the fit's RMS tip error. The fits run on every core (one process
per design and modulus, about 10 s each). A modulus held out of the table (0.5 MPa) is fitted too, and the
table's interpolation there is compared with it.

Run: ``reachplan bench factors --out DIR [--quick] [--install]``. Writes ``curvature_factors.json`` (the planner's
package data, read by :func:`reachplan.planner.steering.factors.curvature_factor`), ``curvature_factors.csv``
(one row per design and modulus) and ``curvature_factors.png``; ``--install`` copies the JSON into
``planner/steering/`` and the CSV and PNG into ``docs/``.
"""

from __future__ import annotations

import argparse
import os
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from matplotlib.figure import Figure

from reachplan.planner.bench._util import load_avg, write_csv
from reachplan.planner.bench.common import settings, write_json, write_png
from reachplan.planner.steering.factors import TIP_FOLLOWING_MIN_PA, FactorCurve, design_key
from reachplan.rod_model.design import PRESET_NAMES, preset

INSTALLS = {"curvature_factors.json": "planner/steering/curvature_factors.json",
            "curvature_factors.csv": "docs/curvature_factors.csv",
            "curvature_factors.png": "docs/curvature_factors.png"}


@dataclass(frozen=True)
class FactorSettings:
    """Which designs and moduli the curvature factor is fitted at.

    Parameters
    ----------
    designs : tuple of str
        Stylet preset names.
    moduli_pa : tuple of float, Pa
        Tissue Young's moduli tabulated in the package.
    held_out_pa : tuple of float, Pa
        Moduli fitted but not tabulated (to check the interpolation).
    """

    designs: tuple[str, ...] = PRESET_NAMES
    moduli_pa: tuple[float, ...] = (1e5, 1.9e5, 3e5, 1e6, 3e6, 1e7)
    held_out_pa: tuple[float, ...] = (5e5,)


QUICK = FactorSettings(designs=("15ga-30j-tip",), moduli_pa=(1.9e5,), held_out_pa=())


def _fit(job: tuple[str, float]) -> tuple[str, float, float, float, int, float]:
    """One fit in a worker: (design, modulus_pa, factor, rms_mm, tips, seconds)."""
    from reachplan.planner.steering.factors import fit_curvature_factor

    name, modulus = job
    t0 = time.perf_counter()
    fit = fit_curvature_factor(preset(name), modulus)
    return name, modulus, fit.factor, fit.rms_mm, fit.tips, time.perf_counter() - t0


def fit_all(s: FactorSettings) -> list[tuple[str, float, float, float, int, float]]:
    """Fit every design at every modulus (tabulated and held out), on every core; rows in job order.

    Parameters
    ----------
    s : FactorSettings
        Designs and moduli.

    Returns
    -------
    list of (str, float, float, float, int, float)
        (design, modulus Pa, factor, RMS tip distance mm, tips fitted, seconds) per fit.
    """
    jobs = [(d, e) for d in s.designs for e in (*s.moduli_pa, *s.held_out_pa)]
    if len(jobs) == 1:
        return [_fit(jobs[0])]
    with ProcessPoolExecutor(max_workers=min(len(jobs), os.cpu_count() or 1)) as pool:
        return list(pool.map(_fit, jobs))


def table(s: FactorSettings, fits: list[tuple[str, float, float, float, int, float]]) -> list[FactorCurve]:
    """Return the package table: one curve per design over the tabulated moduli.

    Parameters
    ----------
    s : FactorSettings
        Designs and moduli.
    fits : list of (str, float, float, float, int, float)
        The fits of :func:`fit_all`.

    Returns
    -------
    list of FactorCurve
        One per design, moduli increasing (Pa), with the factors and their RMS (mm).
    """
    out = []
    for name in s.designs:
        rows = sorted((f for f in fits if f[0] == name and f[1] in s.moduli_pa), key=lambda f: f[1])
        out.append(FactorCurve(name, design_key(preset(name)), tuple(f[1] for f in rows), tuple(f[2] for f in rows),
                               tuple(f[3] for f in rows)))
    return out


def _figure(curves: list[FactorCurve], fits: list[tuple[str, float, float, float, int, float]],
            s: FactorSettings) -> Figure:
    fig = Figure(figsize=(9.5, 5.2))
    ax = fig.add_subplot()
    grid = np.geomspace(TIP_FOLLOWING_MIN_PA, max(s.moduli_pa) * 3, 120)
    for i, c in enumerate(curves):
        ax.plot(grid, [c(float(e)) for e in grid], "-", color=f"C{i}", lw=1.2, label=c.design)
        ax.plot(c.moduli_pa, c.factors, "o", color=f"C{i}", ms=4)
        held = [(f[1], f[2]) for f in fits if f[0] == c.design and f[1] in s.held_out_pa]
        if held:
            ax.plot(*zip(*held, strict=True), "x", color=f"C{i}", ms=8, mew=2)
    ax.axhline(1.0, color="k", ls=":", lw=1)
    ax.set_xscale("log")
    ax.set_xlabel("tissue Young's modulus (Pa, log)")
    ax.set_ylabel("kinematic curvature factor (1: tip following)")
    ax.set_title("curvature factor per design, fitted to the in-tissue rod (dots: table, ×: held out, lines: "
                 "interpolation)", fontsize=9)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=7, ncol=2)
    fig.tight_layout()
    return fig


def run(args: argparse.Namespace) -> int:
    """Run ``reachplan bench factors`` into ``args.out``.

    Writes ``curvature_factors.json``, ``.csv`` and ``.png``; prints one line per fit.

    Parameters
    ----------
    args : argparse.Namespace
        ``out`` and ``quick`` of ``reachplan bench factors``.

    Returns
    -------
    int
        0 once the table, CSV and chart are written.
    """
    s = settings(args, FactorSettings(), QUICK)
    out: Path = args.out  # made by the bench command
    t0 = time.perf_counter()
    fits = fit_all(s)
    wall = time.perf_counter() - t0
    curves = table(s, fits)
    by_design = {c.design: c for c in curves}
    rows = []
    for name, e, factor, rms, tips, seconds in fits:
        held = e in s.held_out_pa
        rows.append({"design": name, "modulus_pa": e, "factor": round(factor, 4), "rms_mm": round(rms, 3),
                     "tips": tips, "held_out": held,
                     "interpolated": round(by_design[name](e), 4) if held else "", "seconds": round(seconds, 2)})
        print(f"{name:14s} E = {e:9.3g} Pa: factor {factor:.3f} (RMS {rms:.2f} mm over {tips} tips)"
              + (f", held out: the table gives {by_design[name](e):.3f}" if held else ""), flush=True)
    write_json(out / "curvature_factors.json",
               {"source": "reachplan bench factors: fit_curvature_factor of the in-tissue rod",
                "designs": [c.to_json() for c in curves]})
    write_csv(out / "curvature_factors.csv", rows)
    write_png(out / "curvature_factors.png", _figure(curves, fits, s))
    print(f"{len(fits)} fits in {wall:.0f} s wall (load {load_avg():.1f})")
    return 0
