"""Small helpers shared by the speed benchmarks (startup, firstrun, dosekernel, distance): CSV and load."""

from __future__ import annotations

import csv
import io
import os
from collections.abc import Sequence
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
