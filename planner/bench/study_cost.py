"""Benchmark: the CPU cost of an implant study per case (both arms), by stage, on Dask workers of one thread each.

Runs ``reachplan study --implant CASES --seed SEED --workers WORKERS`` (a loopback LocalCluster; each worker on one
numba and one HiGHS thread, its kernels loaded before its first case: :mod:`reachplan.planner.study.workers`) into
``OUT/study`` (a study already there resumes: its cases keep their measured times), then reads every case's CPU
seconds (the planning process, all threads) and its stages (``case``: the anatomy and contours; ``scene``: meshes,
organs, template pose, planning masks; ``candidates``; ``arms``: every arm's Pareto curve; ``check``: the chosen
needles' check and re-load). Writes ``study_cost.csv`` (one row per case) and ``study_cost.png`` (stacked stages per
case, the median and the issue's 10 s aim); prints the median, the 90th percentile and each stage's median.

Run: ``reachplan bench studycost --out DIR [--cases N] [--seed S] [--workers W] [--quick] [--install]``; ``--quick``:
one case in a reduced configuration (two needles at most), a smoke run.
"""

from __future__ import annotations

import argparse
import json
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from matplotlib.figure import Figure

from reachplan.planner.bench.common import settings, write_csv, write_png

INSTALLS = {"study_cost.csv": "docs/speed/study_cost.csv", "study_cost.png": "docs/speed/study_cost.png"}
STAGES = ("case", "scene", "candidates", "arms", "check")
AIM_CPU_S = 10.0  # the aim: median CPU per case, both arms
HEADER = ("case", "seed", "status", "cpu_s", "wall_s", *(f"{s}_cpu_s" for s in STAGES), "straight_needles",
          "steered_needles", "worker", "load_avg_1min")


@dataclass(frozen=True)
class CostSettings:
    """What the benchmark plans.

    Every field has a command-line option of its name.

    Parameters
    ----------
    cases : int
        Clinical cases (seeds ``seed`` .. ``seed + cases - 1``).
    seed : int
        The first seed.
    workers : int
        Worker processes of the local cluster (one thread each).
    reduced : bool
        The quick configuration: two rolls, one steered candidate per hole and design, at most two needles per arm.
    """

    cases: int = 30
    seed: int = 0
    workers: int = 2
    reduced: bool = False


QUICK = CostSettings(cases=1, workers=1, reduced=True)


def measure(out: Path, s: CostSettings) -> list[dict[str, Any]]:
    """Run (or resume) the implant study under ``out / "study"`` and return one row per case.

    Parameters
    ----------
    out : Path
        The results folder.
    s : CostSettings
        What to plan.

    Returns
    -------
    list of dict
        :data:`HEADER` keys; times in s.
    """
    from reachplan.planner.case.config import PlanConfig
    from reachplan.planner.study.implant import ImplantStudySpec, run_implant_study, study_settings

    implant = study_settings()
    if s.reduced:
        implant = study_settings(max_needles=2, rolls=2, steered_per_hole=1, selection_target_points=150,
                                 final_target_points=400)
    spec = ImplantStudySpec(tuple(range(s.seed, s.seed + s.cases)), PlanConfig(), implant)
    run_implant_study(spec, out / "study", workers=s.workers)
    load = os.getloadavg()[0]
    rows = []
    for seed in spec.seeds:
        part = json.loads((out / "study" / "parts" / f"clinical_{seed}.json").read_text(encoding="utf-8"))
        r, stages = part["row"], part.get("cpu_s") or {}
        rows.append({"case": r["case"], "seed": seed, "status": r["status"], "cpu_s": r["cpu_seconds"],
                     "wall_s": r["seconds"], **{f"{k}_cpu_s": stages.get(k) for k in STAGES},
                     "straight_needles": r["straight_needles"], "steered_needles": r["steered_needles"],
                     "worker": r["worker"], "load_avg_1min": round(load, 2)})
    return rows


def write_results(out: Path, rows: list[dict[str, Any]]) -> dict[str, float]:
    """Write ``study_cost.csv`` and ``study_cost.png`` under ``out``; return the summary numbers.

    Parameters
    ----------
    out : Path
        The results folder.
    rows : list of dict
        :func:`measure`'s rows.

    Returns
    -------
    dict of str to float
        ``median_cpu_s``, ``p90_cpu_s`` and ``median_<stage>_cpu_s`` over the cases with a time (nan without).
    """
    write_csv(out / "study_cost.csv", HEADER, rows)
    timed = [r for r in rows if r["cpu_s"] is not None]
    cpu = np.array([float(r["cpu_s"]) for r in timed])
    summary = {"median_cpu_s": float(np.median(cpu)) if len(cpu) else float("nan"),
               "p90_cpu_s": float(np.quantile(cpu, 0.9)) if len(cpu) else float("nan")}
    fig = Figure(figsize=(max(6.0, 0.35 * len(timed) + 3.0), 4.2), layout="constrained")
    ax = fig.subplots()
    x = np.arange(len(timed))
    bottom = np.zeros(len(timed))
    for k, stage in enumerate(STAGES):
        v = np.array([float(r[f"{stage}_cpu_s"] or 0.0) for r in timed])
        summary[f"median_{stage}_cpu_s"] = float(np.median(v)) if len(v) else float("nan")
        ax.bar(x, v, bottom=bottom, color=f"C{k}", label=stage)
        bottom += v
    ax.axhline(summary["median_cpu_s"], color="k", lw=1.0, label=f"median {summary['median_cpu_s']:.1f} s")
    ax.axhline(AIM_CPU_S, color="red", lw=1.0, ls="--", label=f"aim {AIM_CPU_S:g} s")
    ax.set_xticks(x, [str(r["seed"]) for r in timed], fontsize=9)
    ax.set_xlabel("clinical case (seed)")
    ax.set_ylabel("CPU s per case (both arms)")
    ax.set_title(f"implant study: {len(timed)} cases, one thread per worker (1-min load when summarised "
                 f"{rows[0]['load_avg_1min']:g})" if rows else "implant study", fontsize=10)
    ax.legend(fontsize=9, ncols=2)
    write_png(out / "study_cost.png", fig)
    return summary


def run(args: argparse.Namespace) -> int:
    """Run ``reachplan bench studycost`` into ``args.out``; print the median and each stage's median.

    Parameters
    ----------
    args : argparse.Namespace
        ``out``, ``quick`` and the :class:`CostSettings` options.

    Returns
    -------
    int
        0.
    """
    s = settings(args, CostSettings(), QUICK)
    out: Path = args.out
    summary = write_results(out, measure(out, s))
    for k, v in summary.items():
        print(f"{k:>28}: {v:.2f} s")
    return 0
