"""What every benchmark target shares: atomic CSV / PNG / JSON writers and ``--install`` into a source checkout.

A target module ``reachplan.planner.bench.<module>`` exposes ``run(args) -> int`` (writes its results into
``args.out``) and ``INSTALLS``, the results it owns in a source checkout (file name in ``args.out`` -> path
relative to the checkout). ``--install`` copies exactly those files, and only into a folder whose
``pyproject.toml`` names the ``reachplan`` project: never into site-packages.
"""

from __future__ import annotations

import argparse
import csv
import dataclasses
import io
import json
import tomllib
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any, TypeVar

from matplotlib.figure import Figure

from reachplan.imaging.files import atomic_write_bytes
from reachplan.planner.errors import PlannerError

S = TypeVar("S")


class BenchError(PlannerError):
    """A benchmark cannot run as asked (``--install`` outside a source checkout, readers that disagree...)."""


def source_checkout(repo: Path) -> Path:
    """Check that ``repo`` is a reachplan source checkout and return it resolved.

    Parameters
    ----------
    repo : Path
        The folder ``--install`` should write into (``--repo``).

    Returns
    -------
    Path
        ``repo``, resolved.

    Raises
    ------
    BenchError
        ``repo`` holds no ``pyproject.toml`` naming the ``reachplan`` project (e.g. an installed package).
    """
    pyproject = Path(repo) / "pyproject.toml"
    hint = "pass --repo DIR, the folder of a reachplan source checkout (it holds reachplan's pyproject.toml)"
    try:
        name = tomllib.loads(pyproject.read_text(encoding="utf-8")).get("project", {}).get("name")
    except FileNotFoundError:
        raise BenchError(f"--install writes into a source checkout and {Path(repo).resolve()} has no pyproject.toml; "
                         f"{hint}") from None
    except (OSError, UnicodeDecodeError, tomllib.TOMLDecodeError) as exc:
        raise BenchError(f"cannot read {pyproject} ({exc}); {hint}") from None
    if name != "reachplan":
        raise BenchError(f"{pyproject} is project {name!r}, not reachplan; {hint}")
    return Path(repo).resolve()


def check_install(repo: Path, quick: bool) -> Path:
    """Return the checkout ``--install`` will write into, before the benchmark runs.

    Parameters
    ----------
    repo : Path
        The folder given by ``--repo``.
    quick : bool
        ``--quick`` was given.

    Returns
    -------
    Path
        The checkout, resolved.

    Raises
    ------
    BenchError
        ``repo`` is not a reachplan source checkout (:func:`source_checkout`), or ``quick`` is set (a smoke
        run's numbers must not be committed).
    """
    checkout = source_checkout(repo)
    if quick:
        raise BenchError("--install refreshes the committed numbers and figures: drop --quick (run the full grid)")
    return checkout


def install(out: Path, checkout: Path, files: Mapping[str, str]) -> list[Path]:
    """Copy results from ``out`` into ``checkout``, each atomically.

    Parameters
    ----------
    out : Path
        The results folder (``--out``).
    checkout : Path
        A checked source checkout (:func:`check_install`).
    files : mapping of str to str
        File name in ``out`` -> destination relative to ``checkout`` (a target's ``INSTALLS``).

    Returns
    -------
    list of Path
        The files written.
    """
    written = []
    for name, dest in files.items():
        target = checkout / dest
        atomic_write_bytes(target, (out / name).read_bytes())
        written.append(target)
    return written


def write_csv(path: Path, header: Sequence[str], rows: Iterable[Sequence[object] | Mapping[str, object]]) -> None:
    """Write a CSV file atomically.

    Parameters
    ----------
    path : Path
        The file to write.
    header : sequence of str
        Column names.
    rows : iterable
        Each a sequence in ``header`` order or a mapping by column name (a missing column is an empty cell).
    """
    buf = io.StringIO(newline="")
    writer = csv.writer(buf)
    writer.writerow(header)
    for row in rows:
        writer.writerow([row.get(c, "") for c in header] if isinstance(row, Mapping) else row)
    atomic_write_bytes(path, buf.getvalue().encode("utf-8"))


def write_png(path: Path, fig: Figure, dpi: int = 110) -> None:
    """Render ``fig`` (a :class:`matplotlib.figure.Figure`, not attached to pyplot) to PNG at ``path``, atomically.

    Parameters
    ----------
    path : Path
        The file to write.
    fig : matplotlib.figure.Figure
        The figure.
    dpi : int
        Dots per inch.
    """
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=dpi)
    atomic_write_bytes(path, buf.getvalue())


def write_json(path: Path, obj: Any) -> None:
    """Write ``obj`` as indented JSON atomically (non-finite numbers as ``NaN``/``Infinity``: timings may be).

    Parameters
    ----------
    path : Path
        The file to create or replace (``.json``).
    obj : object
        JSON-ready value.
    """
    atomic_write_bytes(path, (json.dumps(obj, indent=1) + "\n").encode("utf-8"))


def settings(args: argparse.Namespace, full: S, quick: S) -> S:
    """Return a target's settings for the command line ``args``.

    Parameters
    ----------
    args : argparse.Namespace
        The parsed command line; ``args.quick`` picks ``quick`` over ``full``.
    full : frozen dataclass
        The target's full settings.
    quick : frozen dataclass
        Its quick settings (same type).

    Returns
    -------
    frozen dataclass
        ``quick`` or ``full`` with every field that ``args`` gives (an attribute of the same name, not
        ``None``) replaced.
    """
    base = quick if args.quick else full
    given = {f.name: getattr(args, f.name) for f in dataclasses.fields(base)  # type: ignore[arg-type]
             if getattr(args, f.name, None) is not None}
    return dataclasses.replace(base, **given)  # type: ignore[type-var]
