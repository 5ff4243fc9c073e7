"""The command line's edges, shared by every command: argument checks, output staging, JSON and warnings.

* Arguments are checked before any work: :func:`finite` for numbers, :func:`output_folder` /
  :func:`output_file` for where results go (not an input, not an existing file, writable).
* Outputs are staged beside their destination (:func:`staged_folder`, a hidden folder in the same parent) and
  moved into place only when the command succeeds, so a failure leaves nothing partial.
* :func:`print_json` never writes NaN or Infinity: a value that cannot be computed is ``null``, and the fields
  set to ``null`` are named on stderr.
* :func:`seen_warnings`: the named warnings a command met (``main`` records them), so they go into its JSON
  as well as to stderr.
"""

from __future__ import annotations

import json
import math
import os
import shutil
import sys
import tempfile
import warnings
from collections.abc import Iterable, Iterator, Sequence
from contextlib import contextmanager
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


def _check_writable(path: Path, option: str) -> None:
    """Check that the nearest existing ancestor of ``path`` is a writable folder."""
    probe = path.parent
    while not probe.exists():
        if probe.parent == probe:
            break
        probe = probe.parent
    if not probe.is_dir():
        raise ArgumentError(f"{option} {path}: {probe} is a file, not a folder; choose another output place")
    if not os.access(probe, os.W_OK | os.X_OK):
        raise ArgumentError(f"{option} {path}: cannot write in {probe}; choose a writable output place")


def output_folder(out: Path, inputs: Iterable[Path | None] = (), option: str = "--out") -> Path:
    """Check an output folder before any work; return it resolved.

    Not an existing file, not an input folder (nor inside one, nor holding an input file directly), and
    writable.

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
    """
    resolved = Path(out).resolve()
    if resolved.exists() and not resolved.is_dir():
        raise ArgumentError(f"{option} {out} is an existing file; give a folder (new or existing)")
    for given, folder in _input_folders(inputs):
        if resolved == folder or (_inside(resolved, folder) and given.resolve().is_dir()):
            raise ArgumentError(f"{option} {out} is the input folder of {given} or inside it; "
                                "choose an output folder outside the inputs")
    _check_writable(resolved / "x", option)
    return resolved


def output_file(out: Path, inputs: Iterable[Path | None] = (), option: str = "--out") -> Path:
    """Check an output file before any work: not an input, not a folder, and in a writable place.

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
    """
    resolved = Path(out).resolve()
    if resolved.is_dir():
        raise ArgumentError(f"{option} {out} is a folder; give the path of the file to write")
    for given in inputs:
        if given is not None and Path(given).exists() and Path(given).resolve() == resolved:
            raise ArgumentError(f"{option} {out} is one of the inputs; choose another output file")
    _check_writable(resolved, option)
    return resolved


@contextmanager
def staged_folder(out: Path) -> Iterator[Path]:
    """Give a hidden folder beside ``out`` to write into, moved into place on success.

    On success its entries move into ``out`` (created when missing, entries of the same name replaced); on any
    failure it is removed and ``out`` is left as it was.

    Parameters
    ----------
    out : Path
        The folder the results end up in.

    Yields
    ------
    Path
        The staging folder (same file system as ``out``, so every move is a rename).
    """
    out = Path(out).resolve()
    created: list[Path] = []
    parent = out.parent
    while not parent.exists():
        created.append(parent)
        parent = parent.parent
    out.parent.mkdir(parents=True, exist_ok=True)
    stage = Path(tempfile.mkdtemp(dir=out.parent, prefix=f".{out.name}.", suffix=".staging"))
    try:
        yield stage
    except BaseException:
        shutil.rmtree(stage, ignore_errors=True)
        for folder in created:  # the parents made for the stage, innermost first
            try:
                folder.rmdir()
            except OSError:
                break
        raise
    _commit(stage, out)


def _commit(stage: Path, out: Path) -> None:
    """Move the staged entries into ``out``.

    A new ``out`` is one rename; into an existing one, folders merge and files replace their namesakes one rename
    each (nothing else in ``out`` is touched).
    """
    if not out.exists():
        os.replace(stage, out)
        return
    _merge(stage, out)
    shutil.rmtree(stage, ignore_errors=True)


def _merge(src: Path, dest: Path) -> None:
    for entry in sorted(src.iterdir()):
        target = dest / entry.name
        if entry.is_dir() and not entry.is_symlink() and target.is_dir() and not target.is_symlink():
            _merge(entry, target)
        elif target.is_dir() and not target.is_symlink():
            raise ArgumentError(f"{target} is a folder in the way of an output file; move it away")
        else:
            os.replace(entry, target)


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
