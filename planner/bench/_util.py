"""Small helpers shared by the speed benchmarks (startup, firstrun, dosekernel, distance, demo): CSV, load, command."""

from __future__ import annotations

import csv
import io
import os
import sys
from collections.abc import Sequence
from importlib.metadata import entry_points
from pathlib import Path

from reachplan.imaging.files import atomic_write_bytes


def write_csv(path: Path, rows: Sequence[dict[str, object]]) -> None:
    """Write ``rows`` (dicts with the same keys) as CSV, atomically.

    Parameters
    ----------
    path : Path
        The file to write.
    rows : sequence of dict of str to object
        At least one row; the first row's keys are the columns.
    """
    buf = io.StringIO()
    writer = csv.DictWriter(buf, fieldnames=list(rows[0]))
    writer.writeheader()
    writer.writerows(rows)
    atomic_write_bytes(path, buf.getvalue().encode())


def load_avg() -> float:
    """1-minute load average (NaN where unknown): these machines are shared, so every CSV records it.

    Returns
    -------
    float
        Runnable processes averaged over the last minute.
    """
    try:
        return os.getloadavg()[0]
    except OSError:  # pragma: no cover - not on Linux
        return float("nan")


#: the console script the benchmarks time (``[project.scripts]`` of ``pyproject.toml``)
COMMAND = "reachplan"


def command_module() -> str:
    """Return the package that runs the installed ``reachplan`` command as ``python -m PACKAGE``.

    The package of the function the distribution's console script calls, read from the installed metadata: the
    benchmarks time the command as it is installed, without naming (or importing) the command line, a room above
    them.

    Returns
    -------
    str
        A dotted module name (its ``__main__`` runs the command).

    Raises
    ------
    LookupError
        No ``reachplan`` console script is installed.
    """
    for ep in entry_points(group="console_scripts", name=COMMAND):
        return ep.module
    raise LookupError(f"no {COMMAND!r} console script installed: pip install the package first")


def command_argv(*args: str) -> list[str]:
    """Return the argv of ``reachplan ARGS...`` in this interpreter: ``python -m`` :func:`command_module`.

    Parameters
    ----------
    *args : str
        The command's arguments.

    Returns
    -------
    list of str
        ``[sys.executable, "-m", module, *args]``.
    """
    return [sys.executable, "-m", command_module(), *args]
