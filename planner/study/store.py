"""The study's results on disk: one Parquet part file per finished task (the ledger), consolidated at the end.

A part file ``parts/<task key>.parquet`` is written atomically (temporary file, then ``os.replace``) when its
task finishes, so a study killed at any moment leaves only whole part files; a task is done exactly when its
part file exists. Consolidation reads every part into ``study.parquet`` (again atomically) and checks that no
(case, design, target) appears twice.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING

from reachplan.imaging.files import atomic_write_bytes
from reachplan.planner.errors import StudyError
from reachplan.planner.study.tasks import StudyRow

if TYPE_CHECKING:
    import pyarrow as pa

PARTS = "parts"
RESULTS = "study.parquet"
_ARROW_TYPES = {"str": "string", "bool": "bool_", "int": "int64", "float": "float64"}


def require_pyarrow() -> None:
    """Check that pyarrow can be imported; raise :class:`StudyError` saying how to install it if not."""
    try:
        import pyarrow  # noqa: F401
    except ModuleNotFoundError:
        raise StudyError("pyarrow is not installed; install it (pip install pyarrow) to run studies") from None


def schema() -> pa.Schema:
    """Return the Arrow schema of :class:`StudyRow` (``X | None`` fields are nullable, the others not).

    Returns
    -------
    pyarrow.Schema
        One field per :class:`StudyRow` field, in order.
    """
    import pyarrow as pa

    fields = []
    for f in dataclasses.fields(StudyRow):
        base, _, rest = str(f.type).partition(" | ")
        fields.append(pa.field(f.name, getattr(pa, _ARROW_TYPES[base])(), nullable=rest == "None"))
    return pa.schema(fields)


def to_table(rows: Sequence[StudyRow]) -> pa.Table:
    """Return ``rows`` as an Arrow table of :func:`schema`, one row each, in order.

    Parameters
    ----------
    rows : sequence of StudyRow
        The rows, in table order.

    Returns
    -------
    pyarrow.Table
        Of :func:`schema`.
    """
    import pyarrow as pa

    names = [f.name for f in dataclasses.fields(StudyRow)]
    return pa.Table.from_pydict({n: [getattr(r, n) for r in rows] for n in names}, schema=schema())


def _write_table(table: pa.Table, path: Path) -> None:
    import pyarrow as pa
    import pyarrow.parquet as pq

    sink = pa.BufferOutputStream()
    pq.write_table(table, sink)
    atomic_write_bytes(path, sink.getvalue().to_pybytes())


def part_path(out: Path, key: str) -> Path:
    """Return the part file of task ``key`` in the study folder ``out`` (``parts/<key>.parquet``).

    Parameters
    ----------
    out : Path
        The study folder (holding ``parts/``).
    key : str
        The task's key.

    Returns
    -------
    Path
        ``out/parts/<key>.parquet``.
    """
    return Path(out) / PARTS / f"{key}.parquet"


def write_part(out: Path, key: str, rows: Sequence[StudyRow]) -> Path:
    """Record a finished task: its rows in ``parts/<key>.parquet``, atomically.

    Parameters
    ----------
    out : Path
        Folder of the study.
    key : str
        Key of the finished task.
    rows : sequence of StudyRow
        The task's rows (all of task ``key``).

    Returns
    -------
    Path
        The part file written.

    Raises
    ------
    ValueError
        A row of another task.
    """
    if any(r.task != key for r in rows):
        raise ValueError(f"rows of another task than {key!r}")
    path = part_path(out, key)
    _write_table(to_table(rows), path)
    return path


def finished(out: Path) -> dict[str, Path]:
    """Task key -> part file of every finished task (stray temporary files are ignored).

    Parameters
    ----------
    out : Path
        The study's folder.

    Returns
    -------
    dict of str to Path
        Sorted by file name; empty when there is no ``parts`` folder.
    """
    folder = Path(out) / PARTS
    if not folder.is_dir():
        return {}
    return {p.name[: -len(".parquet")]: p for p in sorted(folder.glob("*.parquet")) if not p.name.startswith(".")}


def read_parts(paths: Iterable[Path]) -> pa.Table:
    """Read part files into one Arrow table of :func:`schema` (empty when there are none).

    Parameters
    ----------
    paths : iterable of Path
        Part files.

    Returns
    -------
    pyarrow.Table
        Their rows, in order.
    """
    import pyarrow as pa
    import pyarrow.parquet as pq

    tables = [pq.read_table(p, schema=schema()) for p in paths]
    return pa.concat_tables(tables) if tables else schema().empty_table()


def failed_keys(out: Path) -> set[str]:
    """Keys of finished tasks whose rows say ``failed``.

    Parameters
    ----------
    out : Path
        Folder of the study whose part files are read.

    Returns
    -------
    set of str
        Task keys.
    """
    import pyarrow.compute as pc

    done = finished(out)
    table = read_parts(done.values())
    return set(pc.unique(table.filter(pc.equal(table["status"], "failed"))["task"]).to_pylist())


def consolidate(out: Path, keys: Iterable[str]) -> pa.Table:
    """Merge the part files of ``keys`` into ``study.parquet`` (sorted by case, design, target) and return it.

    Parameters
    ----------
    out : Path
        The study's folder.
    keys : iterable of str
        Keys of every task of the study.

    Returns
    -------
    pyarrow.Table
        The consolidated rows, also written to ``out/study.parquet``.

    Raises
    ------
    StudyError
        A part file is missing, or a (case, design, target) appears twice.
    """
    done = finished(out)
    keys = sorted(keys)
    missing = [k for k in keys if k not in done]
    if missing:
        raise StudyError(f"{len(missing)} tasks have no result yet (first: {missing[0]}); run the study again")
    table = read_parts(done[k] for k in keys)
    table = table.sort_by([("case", "ascending"), ("design", "ascending"), ("target", "ascending")])
    ids = list(zip(table["case"].to_pylist(), table["design"].to_pylist(), table["target"].to_pylist(),
                   strict=True))
    if len(set(ids)) != len(ids):
        dup = next(i for i in ids if ids.count(i) > 1)
        raise StudyError(f"row {dup} appears twice in {Path(out) / PARTS}; remove its part files and resume")
    _write_table(table, Path(out) / RESULTS)
    return table
