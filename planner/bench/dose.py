"""Benchmark: TG-43 grid dose throughput (voxel-dwell pairs per second).

Compares a straightforward float64 evaluation (one dense (voxels × dwells) block, no chunking) with the
library's float32 chunked kernel on 1 and 2 threads over several chunk sizes, and records peak memory
of the Python heap in one extra run (tracemalloc traces numpy buffers; timing runs are untraced).

Usage::

    python benchmarks/dose.py --out results/dose [--voxels 400000] [--dwells 100] [--repeat 3]

Writes ``dose_benchmark.csv`` and ``dose_benchmark.png`` under ``--out``.
"""

from __future__ import annotations

import argparse
import csv
import os
import time
import tracemalloc
from collections.abc import Callable
from pathlib import Path

import numpy as np

from reachplan.imaging.types import Grid
from reachplan.planner.dose.tg43 import DwellSet, Tg43Kernel, dose_on_grid, grid_points_mm, rate_matrix
from reachplan.planner.pipeline import get_source


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
    return best, peak


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--voxels", type=int, default=400_000, help="approximate voxel count")
    ap.add_argument("--dwells", type=int, default=100)
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)

    side = round(args.voxels ** (1 / 3))
    grid = Grid((side, side, side), np.diag([2.5, 2.5, 2.5, 1.0]))
    n_vox = side**3
    rng = np.random.default_rng(0)
    extent = 2.5 * side
    dwells = DwellSet(
        rng.uniform(0.2 * extent, 0.8 * extent, (args.dwells, 3)),
        rng.normal(size=(args.dwells, 3)),
        rng.uniform(1.0, 10.0, args.dwells),
    )
    kernel = Tg43Kernel(get_source("gammamed_plus_hdr"))
    pairs = n_vox * args.dwells
    rows: list[dict[str, object]] = []

    # baseline: the straightforward float64 evaluation, one dense block (on at most 2 M pairs: it needs
    # about 100 bytes per pair), rate extrapolated per pair
    pts = grid_points_mm(grid)
    w = dwells.times_s * 40000.0 / 360000.0
    sub = pts[: max(1, min(n_vox, 2_000_000 // args.dwells))]

    def naive() -> None:
        rate_matrix(sub, dwells.positions_mm, dwells.directions, kernel, np.float64) @ w

    t, mem = _timed(naive, args.repeat)
    rows.append({"variant": "float64 dense", "workers": 1, "chunk_pairs": len(sub) * args.dwells, "seconds": t,
                 "mpairs_per_s": len(sub) * args.dwells / t / 1e6, "peak_mb": mem,
                 "load_avg_1min": round(os.getloadavg()[0], 2)})  # the machine may be shared
    reference = np.concatenate([
        rate_matrix(pts[s : s + 20000], dwells.positions_mm, dwells.directions, kernel, np.float64) @ w
        for s in range(0, n_vox, 20000)
    ])
    for workers in (1, 2):
        for chunk in (1 << 14, 1 << 16, 1 << 18, 1 << 20):
            t, mem = _timed(lambda c=chunk, wk=workers: dose_on_grid(grid, dwells, kernel, 40000.0,
                                                                     chunk_pairs=c, workers=wk), args.repeat)
            got = dose_on_grid(grid, dwells, kernel, 40000.0, chunk_pairs=chunk, workers=workers).ravel()
            err = float(np.max(np.abs(got - reference) / np.maximum(reference, 1e-12)))
            rows.append({"variant": "float32 chunked", "workers": workers, "chunk_pairs": chunk, "seconds": t,
                         "mpairs_per_s": pairs / t / 1e6, "peak_mb": mem, "max_rel_err": err,
                         "load_avg_1min": round(os.getloadavg()[0], 2)})
    load = max(float(r["load_avg_1min"]) for r in rows)
    with (args.out / "dose_benchmark.csv").open("w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=["variant", "workers", "chunk_pairs", "seconds", "mpairs_per_s",
                                               "peak_mb", "max_rel_err", "load_avg_1min"])
        writer.writeheader()
        writer.writerows(rows)
    for r in rows:
        print(f"{r['variant']:<16} workers={r['workers']} chunk={r['chunk_pairs']:>9} "
              f"{r['mpairs_per_s']:7.1f} Mpairs/s  peak {r['peak_mb']:8.1f} MB  "
              f"err {r.get('max_rel_err', 0.0):.1e}")

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.5, 4))
    for workers, marker in ((1, "o"), (2, "s")):
        sel = [r for r in rows if r["variant"] == "float32 chunked" and r["workers"] == workers]
        ax.plot([r["chunk_pairs"] for r in sel], [r["mpairs_per_s"] for r in sel], marker=marker,
                label=f"float32 chunked, {workers} thread(s)")
    ax.axhline(float(rows[0]["mpairs_per_s"]), color="grey", ls="--", label="float64 dense (baseline)")
    ax.axhline(20.0, color="red", ls=":", label="target 20 M pairs/s")
    ax.set_xscale("log", base=2)
    ax.set_xlabel("voxel-dwell pairs per chunk")
    ax.set_ylabel("million voxel-dwell pairs / s")
    ax.set_title(f"TG-43 grid dose, {n_vox} voxels x {args.dwells} dwells (max load {load:.1f})")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(args.out / "dose_benchmark.png", dpi=120)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
