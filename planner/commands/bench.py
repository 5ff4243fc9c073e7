"""``reachplan bench <target>``: run a benchmark from ``benchmarks/`` (needs a source checkout).

Each target is a module ``benchmarks/<module>.py`` exposing ``run(args) -> int``; every target takes the common
options ``--out DIR`` (results folder), ``--quick`` (smoke run) and ``--install`` (refresh the committed
package data / figures the benchmark owns). Add a target by adding a line to :data:`TARGETS` (e.g.
``planning``, ``dose``). The module is imported only when its target runs.
"""

from __future__ import annotations

import argparse
import importlib.util
import sys
from pathlib import Path
from types import ModuleType

from plugins.errors import ReachplanError

NAME = "bench"
HELP = "Run a benchmark (models: rod models speed vs accuracy and stability) and write CSV + PNG."

#: (sub-command, module file under benchmarks/, help)
TARGETS: tuple[tuple[str, str, str], ...] = (
    ("models", "rod_models", "rod models: time per solve vs tip error (Pareto chart), batched speed, stability"),
    ("planning", "planning", "whole phantom plan (paths/s, FCL queries/s, re-rank) and insertion models' chart"),
)

BENCH_DIR = Path(__file__).resolve().parents[2] / "benchmarks"


class BenchmarkUnavailableError(ReachplanError):
    """The benchmark sources are not available (not a source checkout)."""


def _load(module: str) -> ModuleType:
    path = BENCH_DIR / f"{module}.py"
    spec = importlib.util.spec_from_file_location(f"benchmarks.{module}", path)
    if not path.is_file() or spec is None or spec.loader is None:
        raise BenchmarkUnavailableError(f"benchmark {path} not found; run reachplan bench from a source checkout")
    mod = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = mod  # dataclasses and pickling look the module up by name
    try:
        spec.loader.exec_module(mod)
    except BaseException:
        del sys.modules[spec.name]
        raise
    return mod


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
