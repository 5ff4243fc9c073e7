"""``reachplan bench <target>``: run a benchmark of :mod:`reachplan.planner.bench` (CSV + PNG).

Each target is a module ``reachplan.planner.bench.<module>`` exposing ``run(args) -> int``; every target takes
the common options ``--out DIR`` (results folder), ``--quick`` (smoke run) and ``--install`` (refresh the committed
package data / figures the benchmark owns). Add a target by adding a line to :data:`TARGETS` (e.g.
``planning``, ``dose``). The module is imported only when its target runs.
"""

from __future__ import annotations

import argparse
import importlib
from pathlib import Path
from types import ModuleType

NAME = "bench"
HELP = "Run a benchmark (models: rod models speed vs accuracy and stability) and write CSV + PNG."

#: (sub-command, module file under benchmarks/, help)
TARGETS: tuple[tuple[str, str, str], ...] = (
    ("models", "models", "rod models: time per solve vs tip error (Pareto chart), batched speed, stability"),
    ("planning", "planning", "whole phantom plan (paths/s, FCL queries/s, re-rank) and insertion models' chart"),
    ("startup", "startup", "start-up of reachplan --help and one reachplan rod solve against python -c pass"),
    ("firstrun", "firstrun", "first-run penalty: compiled kernels with a fresh numba cache against a warm one"),
    ("distance", "distance", "organ distance fields: screen vs FCL alone (rates, largest difference, ranking)"),
    ("dosekernel", "dosekernel", "TG-43 grid dose: voxel-dwell pairs/s by method and threads, accuracy"),
)

def _load(module: str) -> ModuleType:
    return importlib.import_module(f"reachplan.planner.bench.{module}")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    sub = parser.add_subparsers(dest="bench_target", metavar="TARGET", required=True)
    for name, module, help_ in TARGETS:
        p = sub.add_parser(name, help=help_, description=help_)
        p.set_defaults(_bench_module=module)
        p.add_argument("--out", required=True, type=Path, help="results folder (CSV, PNG, JSON)")
        p.add_argument("--quick", action="store_true", help="small grid: a smoke run")
        p.add_argument("--install", action="store_true",
                       help="also refresh the package data and docs/ figures this benchmark produces")


def run(args: argparse.Namespace) -> int:
    return int(_load(args._bench_module).run(args))
