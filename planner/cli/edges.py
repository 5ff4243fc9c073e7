"""The command line's edges, shared by every command: argument checks, output staging, JSON and warnings.

* Arguments are checked before any work: :func:`finite` for numbers, :func:`output_folder` /
  :func:`output_file` for where results go (not an input, not an existing file, writable).
* Outputs are staged beside their destination (:func:`staged_folder`, a hidden folder in the same parent) and
  moved into place only when the command succeeds, so a failure leaves nothing partial; a file that reachplan did
  not write is never replaced, and one run at a time writes to a place (:mod:`reachplan.imaging.places`).
* :func:`print_json` never writes NaN or Infinity: a value that cannot be computed is ``null``, and the fields
  set to ``null`` are named on stderr.
* :func:`seen_warnings`: the named warnings a command met (``main`` records them), so they go into its JSON
  as well as to stderr.
"""

from __future__ import annotations

import json
import math
import sys
import warnings
from collections.abc import Iterable, Iterator, Sequence
from contextlib import AbstractContextManager, contextmanager
from pathlib import Path
from typing import Any

from reachplan import ReachplanError
from reachplan.imaging.files import json_safe


class ArgumentError(ReachplanError):
    """A command-line argument is invalid (not finite, out of range, unknown name, unusable output place)."""


#: ``--protocol``'s help, the same on ``plan``, ``demo`` and ``dose``.
PROTOCOL_HELP = ("the dose aims: a protocol file (TOML, format in docs/commands.md) or an installed protocol's name "
                 "(default: embrace_ii, EMBRACE II cervix; `reachplan plugins --kind protocols` lists them)")


# --- numbers ---------------------------------------------------------------------------------------------


def finite(value: float | None, option: str, *, lo: float | None = None, hi: float | None = None,
           lo_open: bool = False) -> float | None:
    """``value`` when it is a finite number within [lo, hi] (or (lo, hi] with ``lo_open``); None stays None.

    Parameters
    ----------
    value : float or None
        The option's value.
    option : str
        The option's name, for the message (e.g. ``"--margin"``).
    lo : float or None
        The lowest value allowed; None: no lower bound.
    hi : float or None
        The highest value allowed; None: no upper bound.
    lo_open : bool
        Exclude ``lo`` itself.

    Returns
    -------
    float or None
        ``value`` unchanged.

    Raises
    ------
    ArgumentError
        NaN, infinite or out of range, with the option's name and the allowed range.
    """
    if value is None:
        return None
    rng = f"{'(' if lo_open else '['}{'-inf' if lo is None else f'{lo:g}'}, {'inf' if hi is None else f'{hi:g}'}]"
    if not math.isfinite(value):
        raise ArgumentError(f"{option} must be a finite number in {rng}, got {value}")
    if (lo is not None and (value < lo or (lo_open and value == lo))) or (hi is not None and value > hi):
        raise ArgumentError(f"{option} must be in {rng}, got {value:g}")
    return value


def finite_float(text: str) -> float:
    """Argparse ``type=`` for a finite float.

    ``nan`` and ``inf`` are refused: argparse then exits with code 2.

    Parameters
    ----------
    text : str
        The argument as given.

    Returns
    -------
    float
        Its value.
    """
    import argparse

    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"{text!r} is not a finite number")
    return value


# --- applicators ------------------------------------------------------------------------------------------


def applicator_assignments(specs: Sequence[str], kinds: Iterable[str], roi_names: Iterable[str]) -> dict[str, str]:
    """Parse repeated ``--applicator KIND=ROI`` options into ROI name -> applicator kind name.

    Parameters
    ----------
    specs : sequence of str
        The option values, ``KIND=ROI`` each (spaces around ``=`` ignored; ROI names may contain ``=``).
    kinds : iterable of str
        The installed applicator kind names.
    roi_names : iterable of str
        The ROI names of the structure set (matched ignoring case).

    Returns
    -------
    dict of str to str
        ROI name as written in the structure set -> kind name.

    Raises
    ------
    ArgumentError
        A value not ``KIND=ROI``, an unknown kind, an ROI not in the structure set, or one ROI given twice.
    """
    known_kinds = list(kinds)
    rois = {n.strip().casefold(): n for n in roi_names}
    out: dict[str, str] = {}
    for spec in specs:
        kind, sep, roi = (x.strip() for x in spec.partition("="))
        if not sep or not kind or not roi:
            raise ArgumentError(f"--applicator {spec!r}: write KIND=ROI_NAME, e.g. tandem=IU_1")
        if kind not in known_kinds:
            raise ArgumentError(f"--applicator {spec!r}: unknown applicator kind {kind!r}; kinds: "
                                f"{', '.join(known_kinds) or 'none'}")
        if roi.casefold() not in rois:
            raise ArgumentError(f"--applicator {spec!r}: no ROI named {roi!r}; available: "
                                f"{', '.join(map(repr, rois.values())) or 'none'}")
        name = rois[roi.casefold()]
        if name in out:
            raise ArgumentError(f"--applicator names ROI {name!r} twice")
        out[name] = kind
    return out


# --- where outputs go ------------------------------------------------------------------------------------


def _inside(child: Path, parent: Path) -> bool:
    try:
        child.relative_to(parent)
        return True
    except ValueError:
        return False


def _input_folders(inputs: Iterable[Path | None]) -> list[tuple[Path, Path]]:
    """(given path, resolved folder) of every input: a folder itself, a file's parent folder."""
    out = []
    for given in inputs:
        if given is None:
            continue
        p = Path(given).resolve()
        out.append((Path(given), p if p.is_dir() else p.parent))
    return out


#: the files a planned case always writes at the top of its folder (``plan`` and ``demo``): one there that reachplan
#: did not write stops the command before the work (every other file is checked before the staged files move in)
CASE_FILES = ("plan.json", "report.html", "overview.png", "workspace.png", "ranking.json")
#: free space an output folder or file needs at least, MB (a demo writes about 35 MB, a plan about 12 MB)
FOLDER_NEED_MB = 50.0
FILE_NEED_MB = 10.0


def output_folder(out: Path, inputs: Iterable[Path | None] = (), option: str = "--out") -> Path:
    """Check an output folder before any work and take its lock; return it resolved.

    Not an existing file, not an input folder (nor inside one, nor holding an input file directly), not on a
    system file system, writable, with space (:func:`reachplan.imaging.places.check_place`). The folder's lock
    (:func:`reachplan.imaging.places.lock_place`) is held until the command ends: a second run into the same folder
    fails at once.

    Parameters
    ----------
    out : Path
        The output folder (new or existing).
    inputs : iterable of Path or None
        The command's input files and folders (None entries are skipped).
    option : str
        The option's name, for the messages.

    Returns
    -------
    Path
        ``out`` resolved.

    Raises
    ------
    ArgumentError
        An existing file, or an input folder.
    OutputPlaceError
        A place that cannot hold the output, or one another run is writing to (:class:`OutputBusyError`).
    """
    from reachplan.imaging.places import check_place, lock_place

    resolved = Path(out).resolve()
    if resolved.exists() and not resolved.is_dir():
        raise ArgumentError(f"{option} {out} is an existing file; give a folder (new or existing)")
    for given, folder in _input_folders(inputs):
        if resolved == folder or (_inside(resolved, folder) and given.resolve().is_dir()):
            raise ArgumentError(f"{option} {out} is the input folder of {given} or inside it; "
                                "choose an output folder outside the inputs")
    check_place(resolved, Path(out), option, folder=True, need_mb=FOLDER_NEED_MB)
    lock_place(resolved, Path(out), option)
    return resolved


def output_file(out: Path, inputs: Iterable[Path | None] = (), option: str = "--out") -> Path:
    """Check an output file before any work and take its lock: not an input, not a folder, in a place that can hold it.

    An existing file is replaced only when reachplan wrote it (its folder's record says so). The lock is held
    until the command ends.

    Parameters
    ----------
    out : Path
        The file to write.
    inputs : iterable of Path or None
        The command's inputs, which ``out`` must not be.
    option : str
        Named in the messages.

    Returns
    -------
    Path
        ``out``, resolved.

    Raises
    ------
    ArgumentError
        A folder, or an input.
    OutputPlaceError
        A place that cannot hold the file, or one another run is writing to (:class:`OutputBusyError`).
    OutputExistsError
        A file there that reachplan did not write.
    """
    from reachplan.imaging.files import refuse_foreign
    from reachplan.imaging.places import check_place, lock_place

    resolved = Path(out).resolve()
    if resolved.is_dir():
        raise ArgumentError(f"{option} {out} is a folder; give the path of the file to write")
    if resolved.exists() and not resolved.is_file():
        raise ArgumentError(f"{option} {out} is not a regular file (a device, pipe or socket); give the path of "
                            "the file to write")
    for given in inputs:
        if given is not None and Path(given).exists() and Path(given).resolve() == resolved:
            raise ArgumentError(f"{option} {out} is one of the inputs; choose another output file")
    check_place(resolved, Path(out), option, folder=False, need_mb=FILE_NEED_MB)
    refuse_foreign([resolved], f"{option} {out}")
    lock_place(resolved, Path(out), option)
    return resolved


def staged_folder(out: Path, option: str = "--out") -> AbstractContextManager[Path]:
    """Give a hidden folder beside ``out`` to write into, moved into place on success.

    :func:`reachplan.imaging.places.staged_folder`: on success its files move into ``out`` (created when missing;
    a file of the same name is replaced only when reachplan wrote it); on any failure it is removed and ``out`` is
    left as it was; errors of the place name ``out`` as given. A file of :data:`CASE_FILES` in ``out`` that
    reachplan did not write is refused at once.

    Parameters
    ----------
    out : Path
        The folder the results end up in, as the user gave it.
    option : str
        The option that gave it.

    Returns
    -------
    context manager of Path
        Yields the staging folder (same file system as ``out``, so every move is a rename).
    """
    from reachplan.imaging.files import refuse_foreign
    from reachplan.imaging.places import staged_folder as staged

    resolved = Path(out).resolve()
    refuse_foreign([resolved / n for n in CASE_FILES], f"{option} {out}")  # the usual clash, before the work
    return staged(resolved, Path(out), option)


def writing(out: Path, option: str = "--out", *, file: bool = False) -> AbstractContextManager[None]:
    """Around writing an output in place (no staging): the place's errors name ``out`` as the user gave it.

    Parameters
    ----------
    out : Path
        The output folder (or file, with ``file``), as the user gave it.
    option : str
        The option that gave it.
    file : bool
        ``out`` is the one file written in the block: it must not be a file reachplan did not write, and it is
        recorded as reachplan's (:func:`reachplan.imaging.places.written_file`).

    Returns
    -------
    context manager
        The caller writes in its block.
    """
    from reachplan.imaging.places import place_errors, written_file

    return (written_file if file else place_errors)(Path(out).resolve(), Path(out), option)


def output_failure(args: Any, exc: BaseException) -> ReachplanError | None:
    """Return the typed error for a failure of the output place that escaped a command, or None.

    The commands that write in place without staging (``study``, ``bench``) meet a full disk or a read-only place
    as an ``OSError``; it becomes an :class:`~reachplan.imaging.errors.OutputPlaceError` naming ``--out`` as given.

    Parameters
    ----------
    args : argparse.Namespace
        The command's arguments (``out``, when it has one).
    exc : BaseException
        What escaped the command.

    Returns
    -------
    ReachplanError or None
        The error to report (exit code 2); None when ``exc`` is not about the output place.
    """
    from reachplan.imaging.places import place_error

    out = getattr(args, "out", None)
    if not isinstance(exc, OSError) or out is None:
        return None
    return place_error(exc, Path(out), "--out", (Path(out).resolve(),))


# --- interruptions -----------------------------------------------------------------------------------------------


class Interrupted(KeyboardInterrupt):
    """SIGTERM or SIGHUP arrived: raised like Ctrl-C's ``KeyboardInterrupt``, so every staged output is removed.

    Parameters
    ----------
    signum : int
        The signal's number (the command exits with 128 + it).
    """

    def __init__(self, signum: int) -> None:
        super().__init__(signum)
        self.signum = signum


@contextmanager
def interruptible() -> Iterator[None]:
    """Within the block, SIGTERM and SIGHUP raise :class:`Interrupted` (as SIGINT raises ``KeyboardInterrupt``).

    Only in the main thread (elsewhere signal handlers cannot be set) and not for a signal that is ignored (under
    ``nohup``, SIGHUP); the previous handlers come back after.

    Yields
    ------
    None
        The command runs in the block.
    """
    import signal
    import threading

    wanted = [getattr(signal, n) for n in ("SIGTERM", "SIGHUP") if hasattr(signal, n)]
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def interrupt(signum: int, frame: object) -> None:
        for sig in previous:  # one clean-up: a second signal during it does not cut it short
            signal.signal(sig, signal.SIG_IGN)
        raise Interrupted(signum)

    # a signal ignored on purpose stays ignored (``nohup`` ignores SIGHUP so that the run outlives the terminal)
    previous = {sig: signal.signal(sig, interrupt) for sig in wanted if signal.getsignal(sig) != signal.SIG_IGN}
    try:
        yield
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)


# --- JSON and warnings -----------------------------------------------------------------------------------


def print_json(doc: Any, command: str = "") -> None:
    """Print ``doc`` as indented JSON on stdout, never NaN or Infinity (see :func:`json_safe`).

    When values had to be set to null, a dict document says which under ``"not_computable"`` (JSON paths), and
    stderr says so too.

    Parameters
    ----------
    doc : object
        Dicts, lists, strings, numbers (NumPy ones too), None.
    command : str
        The sub-command's name, for the warning on stderr.
    """
    nulled: list[str] = []
    safe = json_safe(doc, "", nulled)
    if nulled:
        if isinstance(safe, dict):
            safe["not_computable"] = [f"{p}: not a finite number" for p in nulled]
        print(f"reachplan {command}: warning: not computable (null in the JSON): {', '.join(nulled[:10])}",
              file=sys.stderr)
    sys.stdout.write(json.dumps(safe, indent=2, allow_nan=False) + "\n")


def warning_lines(caught: Iterable[warnings.WarningMessage]) -> list[str]:
    """``"Category: message"`` of recorded warnings, in order, without repeats (for stderr and the JSON).

    Parameters
    ----------
    caught : iterable of warnings.WarningMessage
        Warnings recorded by :func:`warnings.catch_warnings`.

    Returns
    -------
    list of str
        One line per distinct warning.
    """
    return list(dict.fromkeys(f"{w.category.__name__}: {w.message}" for w in caught))


def seen_warnings(args: Any) -> list[str]:
    """Return the warnings the running command has met so far (recorded by :func:`reachplan.planner.cli.main`).

    Parameters
    ----------
    args : argparse.Namespace
        The parsed arguments (they carry the record as ``_warnings``).

    Returns
    -------
    list of str
        ``"Category: message"`` lines (:func:`warning_lines`).
    """
    return warning_lines(getattr(args, "_warnings", []))
