"""The ``reachplan`` command line: a thin layer over the packages.

Each command lives in its own module under :mod:`reachplan.planner.cli` and exposes ``NAME``, ``HELP``,
``add_arguments(parser)`` and ``run(args) -> int``. Expected failures (any :class:`ReachplanError`)
become one line on stderr and exit code 2, never a traceback.
"""

from __future__ import annotations

import argparse
import importlib
import sys
from collections.abc import Sequence

from reachplan import ReachplanError

COMMAND_MODULES: tuple[str, ...] = (
    "reachplan.planner.cli.demo",
    "reachplan.planner.cli.phantom",
    "reachplan.planner.cli.plan",
    "reachplan.planner.cli.inspect",
    "reachplan.planner.cli.rod",
    "reachplan.planner.cli.bench",
    "reachplan.planner.cli.dose",
    "reachplan.planner.cli.plugins",
    "reachplan.planner.cli.study",
)


def build_parser() -> argparse.ArgumentParser:
    """Return the ``reachplan`` parser with one sub-command per module of :data:`COMMAND_MODULES`."""
    parser = argparse.ArgumentParser(
        prog="reachplan",
        description="Pre-plan steered needle paths for interstitial gynecologic brachytherapy.",
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for name in COMMAND_MODULES:
        module = importlib.import_module(name)
        p = sub.add_parser(module.NAME, help=module.HELP, description=module.HELP)
        module.add_arguments(p)
        p.set_defaults(_run=module.run)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Run the command in ``argv`` (default: the process's) and return its exit code.

    A :class:`ReachplanError` becomes one line on stderr and its ``exit_code`` (2); Ctrl-C gives 130.
    """
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return int(args._run(args))
    except ReachplanError as exc:
        print(f"reachplan {args.command}: error: {exc}", file=sys.stderr)
        return exc.exit_code
    except KeyboardInterrupt:
        print("reachplan: interrupted", file=sys.stderr)
        return 130

