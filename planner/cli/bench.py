"""``reachplan bench <target>``: run a benchmark of :mod:`reachplan.planner.bench` (CSV + PNG).

Each target is a module ``reachplan.planner.bench.<module>`` exposing ``run(args) -> int`` and ``INSTALLS``
(see :mod:`reachplan.planner.bench.common`); every target takes the common options ``--out DIR`` (results
folder), ``--quick`` (small grid: a smoke run of seconds), ``--install`` and ``--repo DIR`` (refresh the package
data and docs/ files the benchmark owns in the source checkout ``DIR``, default the current folder). The
module is imported only when its target runs.
"""

from __future__ import annotations

import argparse
import importlib
from dataclasses import dataclass
from pathlib import Path
from types import ModuleType

NAME = "bench"
HELP = ("Run a benchmark (rod models, curvature factors, planning, dose, imaging, study, implant, report) and "
        "write CSV + PNG.")


@dataclass(frozen=True)
class Option:
    """A target's own option (default ``None``: the target's full or quick setting).

    Added to the target's sub-command; a value given on the command line overrides both settings.

    Parameters
    ----------
    flag : str
        Long option, e.g. ``"--voxels"``.
    type : type
        Converts the argument (``int``, ``float``, ``Path``).
    help : str
        One line, with the full and quick defaults in parentheses.
    """

    flag: str
    type: type
    help: str


@dataclass(frozen=True)
class Target:
    """A ``reachplan bench`` sub-command and the module under :mod:`reachplan.planner.bench` that runs it.

    One entry of :data:`TARGETS`.

    Parameters
    ----------
    name : str
        The sub-command's name.
    module : str
        The module's name under :mod:`reachplan.planner.bench` (it has ``run(args)`` and ``INSTALLS``).
    help : str
        One line for ``--help``.
    options : tuple of Option
        The target's own options.
    """

    name: str
    module: str
    help: str
    options: tuple[Option, ...] = ()


TARGETS: tuple[Target, ...] = (
    Target("models", "models", "rod models: time per solve vs tip error (Pareto chart), batched speed, stability"),
    Target("planning", "planning",
           "whole phantom plan (paths/s, FCL queries/s, re-rank) and the insertion models' speed vs accuracy"),
    Target("dose", "dose", "TG-43 grid dose throughput (voxel-dwell pairs/s) by thread count and chunk size",
           (Option("--voxels", int, "approximate voxel count (400,000; quick 8,000)"),
            Option("--dwells", int, "dwell positions (100; quick 20)"),
            Option("--repeat", int, "timed runs, the best is kept (3; quick 1)"))),
    Target("imaging", "imaging_load", "loading a CT series: reachplan's reader against SimpleITK's (time, memory)",
           (Option("--slices", int, "slices of the synthetic series (300; quick 12)"),
            Option("--size", int, "rows = columns per slice (512; quick 64)"),
            Option("--repeat", int, "alternating runs per reader (5; quick 1)"),
            Option("--workdir", Path, "where to write the series (default: a temporary folder)"))),
    Target("study", "study", "design study on a Dask LocalCluster: 2 workers against 1, and a cohort estimate",
           (Option("--cases", int, "phantom cases (4; quick 2)"),
            Option("--targets", int, "targets per case (4; quick 1)"),
            Option("--designs", int, "stylet designs (3; quick 1)"),
            Option("--repeat", int, "alternating 1- and 2-worker runs, the best is kept (2; quick 1)"),
            Option("--est-cases", int, "patients of the estimated study (100)"),
            Option("--est-designs", int, "designs of the estimated study (7)"),
            Option("--est-targets", int, "targets per patient of the estimated study (10)"),
            Option("--est-workers", int, "workers of the estimated study (32)"))),
    Target("studycost", "study_cost", "implant study: CPU per case (both arms) by stage on one-thread Dask workers",
           (Option("--cases", int, "clinical cases (30; quick 1, reduced planning)"),
            Option("--seed", int, "first seed (0)"), Option("--workers", int, "worker processes (2; quick 1)"))),
    Target("startup", "startup", "start-up of reachplan --help and one reachplan rod solve against python -c pass"),
    Target("firstrun", "firstrun", "first-run penalty: reachplan demo and the kernels alone, fresh numba cache "
           "against a warm one", (Option("--repeat", int, "cold + warm pairs, medians reported (3; quick 1)"),)),
    Target("distance", "distance", "organ distance fields: screen vs FCL alone (rates, largest difference, ranking)"),
    Target("dosekernel", "dosekernel", "TG-43 grid dose: voxel-dwell pairs/s by method and threads, accuracy"),
    Target("implant", "implant", "implant planning: both arms with their Pareto curves on the phantom (time, D90)",
           (Option("--repeat", int, "timed runs, the fastest is reported (3; quick 1)"),)),
    Target("report", "report", "report.html of the demo: seconds to build it from the plan in memory, bytes by part",
           (Option("--repeat", int, "timed renderings, the median is reported (5; quick 1)"),)),
    Target("factors", "factors", "kinematic curvature factor per stylet design against the tissue modulus, "
           "fitted to the in-tissue rod (the planner's package table)"),
    Target("joints", "joints", "discrete joint-section model: every published free-space row (calibration or "
           "validation), the joint-count trend, convergence"),
    Target("fidelity", "fidelity", "planning time against ranking fidelity: fixed insertion models and the scene "
           "policy against the reference on the clinical case, and the ladder's in-tissue errors (package table)",
           (Option("--cases", int, "clinical seeds 0 .. N-1 (5; quick 1)"),
            Option("--table", int, "1: also measure the in-tissue error table of every preset (1; quick 0)"),
            Option("--workers", int, "processes measuring the table (2)"))),
    Target("demo", "demo", "reachplan demo on the clinical case: the median time of each stage against the 30 s limit",
           (Option("--repeat", int, "demo runs, the medians are reported (3; quick 1 of the pilot phantom)"),)),
    Target("band", "band", "the tissue band's rod model against the reference rod: tip change over the modulus band, "
           "CPU per solve"),
    Target("reconstruct", "reconstruct", "needles found in post-insertion CT/MR of the demo's implants against the "
           "truth: tip error, shaft distance, found and false (issue #32)",
           (Option("--cases", int, "clinical seeds 0 .. N-1 (5; quick 1)"),
            Option("--modality", str, "CT, MR or both (both; quick CT)"),
            Option("--draws", int, "deviations drawn per case, draw seeds 0 .. N-1 (1)"),
            Option("--content", str, "what fills the needles: metal, air or fluid (metal)"),
            Option("--plans", Path, "folder holding demo<seed>/plan.json (default: run the demo per seed into "
                   "--out)"))),
)


def _load(module: str) -> ModuleType:
    return importlib.import_module(f"reachplan.planner.bench.{module}")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Add one sub-command per target, each with the common options and its own.

    Parameters
    ----------
    parser : argparse.ArgumentParser
        ``reachplan bench``'s parser: one sub-parser per target is added (``--out``, ``--quick``, ``--install``,
        ``--repo`` and its own options).
    """
    sub = parser.add_subparsers(dest="bench_target", metavar="TARGET", required=True)
    for target in TARGETS:
        p = sub.add_parser(target.name, help=target.help, description=target.help)
        p.set_defaults(_bench_module=target.module)
        p.add_argument("--out", required=True, type=Path, help="results folder (CSV, PNG, JSON)")
        p.add_argument("--quick", action="store_true", help="small grid: a smoke run of seconds")
        p.add_argument("--install", action="store_true",
                       help="also copy the results this benchmark owns (package data, docs/ figures and tables) "
                            "into the source checkout --repo")
        p.add_argument("--repo", type=Path, default=Path("."),
                       help="the reachplan source checkout --install writes into (default: the current folder)")
        for option in target.options:
            p.add_argument(option.flag, type=option.type, default=None, help=option.help)


def run(args: argparse.Namespace) -> int:
    """Check ``--install`` and the output folder first, run the target, then copy the results it owns.

    Parameters
    ----------
    args : argparse.Namespace
        The target's parsed options (``out``, ``quick``, ``install``, ``repo``, ...).

    Returns
    -------
    int
        The target's exit code (0 when it succeeded).
    """
    from reachplan.planner.cli.edges import output_folder

    output_folder(args.out)  # not a file, writable: checked before the benchmark runs
    from reachplan.planner.bench.common import check_install, install

    checkout = check_install(args.repo, args.quick) if args.install else None  # before the long run
    args.out.mkdir(parents=True, exist_ok=True)  # every target writes into it
    module = _load(args._bench_module)
    status = int(module.run(args))
    if checkout is not None and status == 0:
        for path in install(args.out, checkout, module.INSTALLS):
            print(f"installed {path}")
    return status
