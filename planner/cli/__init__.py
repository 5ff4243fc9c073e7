"""The ``reachplan`` command line: a thin layer over the packages.

Each command lives in its own module under :mod:`reachplan.planner.cli` and exposes ``NAME``, ``HELP``,
``add_arguments(parser)`` and ``run(args) -> int``. Expected failures (any :class:`ReachplanError`)
become one line on stderr and exit code 2, never a traceback; the line is written through ``tqdm.write``, so it
never shares a line with a progress bar. Warnings met while a command runs are recorded (commands put them into
their JSON through :func:`reachplan.planner.cli.edges.seen_warnings`) and printed on stderr, one line each. Any
other exception is a bug: the last-resort handler prints one line saying "internal error" and exits with
:data:`INTERNAL_ERROR_EXIT` (70, EX_SOFTWARE).

Every command takes ``--quiet``: nothing on stdout or stderr but errors and the JSON asked for with ``--json``
(a command that defines ``--quiet`` itself also uses it to skip its work for the screen). ``reachplan --version``
prints the version.
"""

from __future__ import annotations

import argparse
import contextlib
import importlib
import io
import os
import sys
import warnings
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
    "reachplan.planner.cli.reconstruct",
    "reachplan.planner.cli.calibrate",
)

#: Exit code of an unexpected exception (a bug): EX_SOFTWARE of sysexits.h.
INTERNAL_ERROR_EXIT = 70

#: per command, libraries imported before the command runs: they wrap their optional imports in
#: ``except BaseException`` (trimesh does), so a Ctrl-C or SIGTERM arriving while they import would be swallowed
#: and the run would go on with nothing cleaned up
GUARDED_IMPORTS: dict[str, tuple[str, ...]] = {"plan": ("trimesh",), "demo": ("trimesh",), "study": ("trimesh",)}


def build_parser() -> argparse.ArgumentParser:
    """Return the ``reachplan`` parser with one sub-command per module of :data:`COMMAND_MODULES`.

    Returns
    -------
    argparse.ArgumentParser
        ``--version`` and the sub-commands, each with ``--quiet`` where it had none.
    """
    from reachplan.planner.cli.points import NumbersParser  # reads --targets -20,0,90 as a value

    parser = NumbersParser(
        prog="reachplan",
        description="Pre-plan steered needle paths for interstitial gynecologic brachytherapy.",
    )
    parser.add_argument("--version", action=_VersionAction, nargs=0, help="print the version and exit")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for name in COMMAND_MODULES:
        module = importlib.import_module(name)
        p = sub.add_parser(module.NAME, help=module.HELP, description=module.HELP)
        module.add_arguments(p)
        if not any("--quiet" in a.option_strings for a in p._actions):
            p.add_argument("--quiet", action="store_true", help="print nothing but errors (and --json output)")
        p.set_defaults(_run=module.run)
    return parser


def _one_line(exc: BaseException, limit: int) -> str:
    """Return the message on one line, without an embedded traceback (pydicom nests them in its messages)."""
    text = " ".join(str(exc).split("Traceback (most recent call last)")[0].split())
    return text if len(text) <= limit else text[: limit - 3] + "..."


class _VersionAction(argparse.Action):
    """``--version``: the installed version, read only when asked (importlib.metadata costs start-up)."""

    def __call__(self, parser: argparse.ArgumentParser, namespace: argparse.Namespace, values: object,
                 option_string: str | None = None) -> None:
        from reachplan import __version__

        print(f"reachplan {__version__}")
        parser.exit()


def console() -> int:
    """Run :func:`main` on the process's arguments: the ``reachplan`` script and ``python -m reachplan.planner.cli``.

    One rod solve (``rod ... --tension N``, no ``--tensions`` sweep) runs the rod kernel as plain Python
    (``REACHPLAN_JIT=0``, see :mod:`reachplan.rod_model._kernel`): the solve takes about 50 ms so, while importing
    numba and loading the kernel's cached machine code take about 0.8 s. Only here, where the process is the
    command's own: a caller of :func:`main` keeps the compiled kernel.

    Returns
    -------
    int
        The exit code of :func:`main`.
    """
    argv = sys.argv[1:]
    if argv[:1] == ["rod"] and not any(a.startswith("--tensions") for a in argv):
        os.environ.setdefault("REACHPLAN_JIT", "0")
    return main(argv)


def main(argv: Sequence[str] | None = None) -> int:
    """Run the command in ``argv`` (default: the process's) and return its exit code.

    A :class:`ReachplanError` becomes one line on stderr and its ``exit_code`` (2); Ctrl-C gives 130, SIGTERM
    143 and SIGHUP 129 (each removes the staged outputs first). The output places' locks are released at the end.

    Parameters
    ----------
    argv : sequence of str or None
        The arguments after the program name; None: ``sys.argv[1:]``.

    Returns
    -------
    int
        The command's exit code; its error's ``exit_code`` (2) for a reachplan error, 128 + the signal on Ctrl-C
        (130), SIGTERM (143) or SIGHUP (129), :data:`INTERNAL_ERROR_EXIT` for a bug.
    """
    parser = build_parser()
    args = parser.parse_args(argv)
    from tqdm import tqdm

    from reachplan.imaging.places import release_places
    from reachplan.planner.cli.edges import interruptible, output_failure, warning_lines

    quiet = bool(getattr(args, "quiet", False))
    sink = io.StringIO()
    for module in GUARDED_IMPORTS.get(args.command, ()):  # before an interrupt can arrive while they import
        importlib.import_module(module)
    with contextlib.ExitStack() as stack:
        stack.callback(release_places)  # the output places' locks (taken by the output checks)
        stack.enter_context(interruptible())  # SIGTERM, SIGHUP: cleaned up as Ctrl-C
        if quiet:
            stack.enter_context(contextlib.redirect_stderr(sink))
            if not getattr(args, "json", False):
                stack.enter_context(contextlib.redirect_stdout(sink))
        caught = stack.enter_context(warnings.catch_warnings(record=True))  # the filters in force stay
        args._warnings = caught
        try:
            code = int(args._run(args))
        except ReachplanError as exc:
            code = exc.exit_code
            message = f"reachplan {args.command}: error: {_one_line(exc, 1000)}"
        except KeyboardInterrupt as exc:  # Ctrl-C, SIGTERM, SIGHUP: staged outputs are removed on the way here
            if "reachplan.planner.kernels" in sys.modules:  # as Ctrl-C stops the whole process group
                sys.modules["reachplan.planner.kernels"].stop()
            signum = int(getattr(exc, "signum", 2))
            code, message = 128 + signum, "reachplan: interrupted" + ("" if signum == 2 else f" (signal {signum})")
        except Exception as exc:  # the last resort: an exception that escapes is a bug (a full disk is not)
            placed = output_failure(args, exc)
            code = INTERNAL_ERROR_EXIT if placed is None else placed.exit_code
            message = (f"reachplan {args.command}: error: {_one_line(placed, 1000)}" if placed is not None else
                       f"reachplan {args.command}: internal error: {type(exc).__name__}: {_one_line(exc, 200)}; "
                       "this is a bug in reachplan, please report it with the command and its inputs")
        else:
            message = ""
        if not quiet:
            for line in warning_lines(caught):
                tqdm.write(f"reachplan {args.command}: warning: {line}", file=sys.stderr)
    if message:
        tqdm.write(message, file=sys.stderr)  # clears any bar left open, so the message has its own line
    return code
