"""The ``reachplan`` command line: a thin layer over the packages.

Each command lives in its own module under :mod:`reachplan.planner.cli` and exposes ``NAME``, ``HELP``,
``add_arguments(parser)`` and ``run(args) -> int``. Expected failures (any :class:`ReachplanError`)
become one line on stderr and exit code 2, never a traceback; the line is written through ``tqdm.write``, so it
never shares a line with a progress bar.

Every command takes ``--quiet``: nothing on stdout or stderr but errors and the JSON asked for with ``--json``
(a command that defines ``--quiet`` itself also uses it to skip its work for the screen). ``reachplan --version``
prints the version.
"""

from __future__ import annotations

import argparse
import contextlib
import importlib
import io
import sys
from collections.abc import Sequence

from reachplan import ReachplanError, __version__

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
    parser = argparse.ArgumentParser(
        prog="reachplan",
        description="Pre-plan steered needle paths for interstitial gynecologic brachytherapy.",
    )
    parser.add_argument("--version", action="version", version=f"reachplan {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for name in COMMAND_MODULES:
        module = importlib.import_module(name)
        p = sub.add_parser(module.NAME, help=module.HELP, description=module.HELP)
        module.add_arguments(p)
        if not any("--quiet" in a.option_strings for a in p._actions):
            p.add_argument("--quiet", action="store_true", help="print nothing but errors (and --json output)")
        p.set_defaults(_run=module.run)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    from tqdm import tqdm

    quiet = bool(getattr(args, "quiet", False))
    sink = io.StringIO()
    with contextlib.ExitStack() as stack:
        if quiet:
            stack.enter_context(contextlib.redirect_stderr(sink))
            if not getattr(args, "json", False):
                stack.enter_context(contextlib.redirect_stdout(sink))
        try:
            return int(args._run(args))
        except ReachplanError as exc:
            message, code = f"reachplan {args.command}: error: {exc}", exc.exit_code
        except KeyboardInterrupt:
            message, code = "reachplan: interrupted", 130
    tqdm.write(message, file=sys.stderr)  # clears any bar left open, so the message has its own line
    return code

