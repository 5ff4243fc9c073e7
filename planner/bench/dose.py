"""Benchmark: TG-43 grid dose throughput (voxel-dwell pairs per second).

Compares a straightforward float64 evaluation (one dense (voxels × dwells) block, no chunking) with the
library's float32 chunked kernel on 1 and 2 threads over several chunk sizes, and records peak memory
of the Python heap in one extra run (tracemalloc traces numpy buffers; timing runs are untraced).

Run: ``reachplan bench dose --out DIR [--quick] [--voxels N] [--dwells N] [--repeat N] [--install]``. Writes
``dose_benchmark.csv`` and ``dose_benchmark.png``; ``--install`` copies both to ``docs/``.
"""

from __future__ import annotations

import argparse
import os
import time
import tracemalloc
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from matplotlib.figure import Figure

from reachplan.imaging.types import Grid
from reachplan.planner.bench.common import settings, write_csv, write_png
from reachplan.planner.dose.dwells import DwellSet, dose_on_grid, grid_points_mm, rate_matrix
from reachplan.planner.dose.tg43 import Tg43Kernel
from reachplan.planner.lookup import get_source

INSTALLS = {"dose_benchmark.csv": "docs/dose_benchmark.csv", "dose_benchmark.png": "docs/dose_benchmark.png"}
COLUMNS = ("variant", "workers", "chunk_pairs", "seconds", "mpairs_per_s", "peak_mb", "max_rel_err",
           "load_avg_1min")
#: air-kerma strength (U) of the benchmark's source; dwell times are in s
SK_U = 40000.0


@dataclass(frozen=True)
class DoseSettings:
    """What the dose benchmark computes.

    Parameters
    ----------
    voxels : int, approximate count
        Grid size (a cube of 2.5 mm voxels).
    dwells : int
        Number of random dwells.
    repeat : int
        Timed runs (the best counts).
    chunks : tuple of int
        Voxel-dwell pairs per chunk to try.
    """

    voxels: int = 400_000
    dwells: int = 100
    repeat: int = 3
    chunks: tuple[int, ...] = (1 << 14, 1 << 16, 1 << 18, 1 << 20)


QUICK = DoseSettings(voxels=8_000, dwells=20, repeat=1, chunks=(1 << 12, 1 << 14))


@dataclass(frozen=True)
class DoseRow:
    """One timed variant.

    Parameters
    ----------
    variant : str
        ``float64 dense`` or ``float32 chunked``.
    workers : int
        Threads.
    chunk_pairs : int
        Voxel-dwell pairs per chunk.
    seconds : float, s
        Best of the timed runs.
    mpairs_per_s : float, 1e6 pairs/s
        Throughput.
    peak_mb : float, MB
        Peak traced Python heap of one extra run.
    max_rel_err : float or None
        Largest relative dose difference from the float64 evaluation; None for the baseline itself.
    load_avg_1min : float
        1-minute load average when it ran.
    """

    variant: str
    workers: int
    chunk_pairs: int
    seconds: float
    mpairs_per_s: float
    peak_mb: float
    max_rel_err: float | None
    load_avg_1min: float


def _timed(fn: Callable[[], object], repeat: int) -> tuple[float, float]:
    """(best wall time in s over ``repeat`` untraced runs, peak traced memory in MB of one more run)."""
    best = np.inf
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    tracemalloc.start()
    fn()
    peak = tracemalloc.get_traced_memory()[1] / 1e6
    tracemalloc.stop()
    return float(best), peak


def measure(s: DoseSettings) -> tuple[list[DoseRow], int]:
    """Time the float64 dense baseline and the float32 chunked kernel on 1 and 2 threads.

    Parameters
    ----------
    s : DoseSettings
        Grid, dwells, runs and chunk sizes.

    Returns
    -------
    rows : list of DoseRow
        The float64 dense baseline first, then one row per thread count and chunk size.
    n_vox : int
        Voxels of the cubic grid (2.5 mm voxels).
    """
    side = max(2, round(s.voxels ** (1 / 3)))
    grid = Grid((side, side, side), np.diag([2.5, 2.5, 2.5, 1.0]))
    n_vox = side**3
    rng = np.random.default_rng(0)
    extent = 2.5 * side
    dwells = DwellSet(
        rng.uniform(0.2 * extent, 0.8 * extent, (s.dwells, 3)),
        rng.normal(size=(s.dwells, 3)),
        rng.uniform(1.0, 10.0, s.dwells),
    )
    kernel = Tg43Kernel(get_source("gammamed_plus_hdr"))
    pairs = n_vox * s.dwells
    # baseline: the straightforward float64 evaluation, one dense block (on at most 2 M pairs: it needs
    # about 100 bytes per pair), rate extrapolated per pair
    pts = grid_points_mm(grid)
    w = dwells.times_s * SK_U / 360000.0
    sub = pts[: max(1, min(n_vox, 2_000_000 // s.dwells))]

    def naive() -> None:
        rate_matrix(sub, dwells.positions_mm, dwells.directions, kernel, np.float64) @ w

    t, mem = _timed(naive, s.repeat)
    rows = [DoseRow("float64 dense", 1, len(sub) * s.dwells, t, len(sub) * s.dwells / t / 1e6, mem, None,
                    round(os.getloadavg()[0], 2))]  # the machine may be shared
    reference = np.concatenate([
        rate_matrix(pts[i : i + 20000], dwells.positions_mm, dwells.directions, kernel, np.float64) @ w
        for i in range(0, n_vox, 20000)
    ])
    for workers in (1, 2):
        for chunk in s.chunks:
            def chunked(c: int = chunk, wk: int = workers) -> np.ndarray:
                return dose_on_grid(grid, dwells, kernel, SK_U, chunk_pairs=c, workers=wk)

            t, mem = _timed(chunked, s.repeat)
            got = chunked().ravel()
            err = float(np.max(np.abs(got - reference) / np.maximum(reference, 1e-12)))
            rows.append(DoseRow("float32 chunked", workers, chunk, t, pairs / t / 1e6, mem, err,
                                round(os.getloadavg()[0], 2)))
    return rows, n_vox


def write_results(out: Path, rows: list[DoseRow], n_vox: int, dwells: int) -> None:
    """``dose_benchmark.csv`` (one row per variant, :data:`COLUMNS`) and ``dose_benchmark.png`` under ``out``.

    Parameters
    ----------
    out : Path
        The results folder.
    rows : list of DoseRow
        The timed variants.
    n_vox : int
        Voxels of the grid.
    dwells : int
        Dwells of the run.
    """
    write_csv(out / "dose_benchmark.csv", COLUMNS,
              [["" if v is None else v for v in (r.variant, r.workers, r.chunk_pairs, r.seconds, r.mpairs_per_s,
                                                 r.peak_mb, r.max_rel_err, r.load_avg_1min)] for r in rows])
    load = max(r.load_avg_1min for r in rows)
    fig = Figure(figsize=(6.5, 4))
    ax = fig.subplots()
    for workers, marker in ((1, "o"), (2, "s")):
        sel = [r for r in rows if r.variant == "float32 chunked" and r.workers == workers]
        ax.plot([r.chunk_pairs for r in sel], [r.mpairs_per_s for r in sel], marker=marker,
                label=f"float32 chunked, {workers} thread(s)")
    dense = [r for r in rows if r.variant == "float64 dense"]
    if dense:
        ax.axhline(dense[0].mpairs_per_s, color="grey", ls="--", label="float64 dense (baseline)")
    ax.axhline(20.0, color="red", ls=":", label="target 20 M pairs/s")
    ax.set_xscale("log", base=2)
    ax.set_xlabel("voxel-dwell pairs per chunk")
    ax.set_ylabel("million voxel-dwell pairs / s")
    ax.set_title(f"TG-43 grid dose, {n_vox} voxels x {dwells} dwells (max load {load:.1f})")
    ax.legend(fontsize=8)
    fig.tight_layout()
    write_png(out / "dose_benchmark.png", fig, dpi=120)


def run(args: argparse.Namespace) -> int:
    """Run ``reachplan bench dose`` (``--quick``, ``--voxels``, ``--dwells``, ``--repeat``) into ``args.out``.

    Writes ``dose_benchmark.csv`` and ``dose_benchmark.png``; prints one line per variant.

    Parameters
    ----------
    args : argparse.Namespace
        ``out``, ``quick``, ``voxels``, ``dwells`` and ``repeat`` from the command line.

    Returns
    -------
    int
        0 (the table and chart are in ``args.out``).
    """
    s = settings(args, DoseSettings(), QUICK)
    rows, n_vox = measure(s)
    write_results(args.out, rows, n_vox, s.dwells)
    for r in rows:
        print(f"{r.variant:<16} workers={r.workers} chunk={r.chunk_pairs:>9} {r.mpairs_per_s:7.1f} Mpairs/s  "
              f"peak {r.peak_mb:8.1f} MB  err {r.max_rel_err or 0.0:.1e}")
    return 0
