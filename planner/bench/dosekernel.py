"""TG-43 kernel benchmark: voxel-dwell pairs per second by method and thread count, and accuracy.

Run: ``reachplan bench dosekernel --out DIR [--quick]``. One grid (about 400,000 voxels at 2.5 mm, 64,000 with
``--quick``) and 100 dwells of the GammaMed Plus HDR source; each method runs on 1 and 2 threads, ``--repeat``
times in turns (5; 2 with ``--quick``), and the median is kept. Methods: ``compiled`` (the numba kernel of
:mod:`reachplan.planner.dose._tg43_numba`, float32, one pair at a time) and ``numpy`` (the chunked float32 numpy
evaluation it replaced). Rates are given per wall second and per CPU second of the process (the CPU time does
not shrink when other jobs share the cores; on 1 thread it is the rate of one core). Accuracy: the largest
relative difference to the float64 evaluation of the consensus-table formula on voxels 2 mm or more from every
dwell (issue 19 limit 1e-3). Writes ``dosekernel.csv`` and ``dosekernel.png``; limit 100 M pairs/s on one core.
"""

from __future__ import annotations

import argparse
import statistics
import time
from pathlib import Path
from typing import Literal

import numpy as np

from reachplan.imaging.types import Grid
from reachplan.planner.bench._util import load_avg, write_csv
from reachplan.planner.dose.dwells import DwellSet, dose_on_grid, grid_points_mm, rate_matrix
from reachplan.planner.dose.tg43 import Tg43Kernel
from reachplan.plugins.sources import BUILTIN

LIMIT_MPAIRS = 100.0
METHODS: tuple[Literal["compiled", "numpy"], ...] = ("compiled", "numpy")


#: results this target owns in a source checkout (``reachplan bench dosekernel --install``)
INSTALLS = {"dosekernel.csv": "docs/speed/dosekernel.csv", "dosekernel.png": "docs/speed/dosekernel.png"}


def run(args: argparse.Namespace) -> int:
    """Run the benchmark into ``args.out`` (CSV + PNG).

    Parameters
    ----------
    args : argparse.Namespace
        Command line: ``out``, ``quick``.

    Returns
    -------
    int
        Always 0; failures raise.
    """
    out: Path = args.out  # made by the bench command
    side = 40 if args.quick else 74
    repeat = 2 if args.quick else 5
    grid = Grid((side, side, side), np.diag([2.5, 2.5, 2.5, 1.0]))
    n_vox = side**3
    extent = 2.5 * side
    rng = np.random.default_rng(0)
    n_dw = 100
    dwells = DwellSet(rng.uniform(0.3 * extent, 0.7 * extent, (n_dw, 3)), rng.normal(size=(n_dw, 3)),
                      rng.uniform(1.0, 20.0, n_dw))
    kernel = Tg43Kernel(BUILTIN["gammamed_plus_hdr"]())
    sk = 40000.0
    # reference: float64 formula on a sample of voxels >= 2 mm from every dwell
    sample = rng.choice(n_vox, size=min(n_vox, 20000), replace=False)
    pts = grid_points_mm(grid, sample)
    dist = np.min(np.linalg.norm(pts[:, None, :] - dwells.positions_mm[None], axis=2), axis=1)
    sample, pts = sample[dist >= 2.0], pts[dist >= 2.0]
    ref = rate_matrix(pts, dwells.positions_mm, dwells.directions, kernel) @ (dwells.times_s * sk / 360000.0)

    times: dict[tuple[str, int], list[tuple[float, float]]] = {}
    errors: dict[str, float] = {}
    for method in METHODS:  # compile / warm
        got = dose_on_grid(grid, dwells, kernel, sk, workers=1, method=method).ravel()
        errors[method] = float(np.max(np.abs(got[sample] / ref - 1.0)))
    for _ in range(repeat):
        for method in METHODS:
            for workers in (1, 2):
                t0, c0 = time.perf_counter(), time.process_time()
                dose_on_grid(grid, dwells, kernel, sk, workers=workers, method=method)
                times.setdefault((method, workers), []).append((time.perf_counter() - t0, time.process_time() - c0))
    pairs = n_vox * n_dw
    rows: list[dict[str, object]] = []
    for (name, workers), ts in times.items():
        wall = statistics.median(t for t, _ in ts)
        cpu = statistics.median(c for _, c in ts)
        rows.append({"method": name, "threads": workers, "voxels": n_vox, "dwells": n_dw,
                     "median_wall_s": round(wall, 4), "median_cpu_s": round(cpu, 4),
                     "mpairs_per_wall_s": round(pairs / wall / 1e6, 1),
                     "mpairs_per_cpu_s": round(pairs / cpu / 1e6, 1),
                     "max_rel_diff_beyond_2mm": f"{errors[name]:.2e}", "repeats": repeat,
                     "load_avg_1min": round(load_avg(), 2)})
    write_csv(out / "dosekernel.csv", rows)
    for r in rows:
        print(f"{r['method']:<9} {r['threads']} thread(s): {r['mpairs_per_wall_s']:7.1f} M pairs/s wall, "
              f"{r['mpairs_per_cpu_s']:7.1f} M per CPU s, max rel diff {r['max_rel_diff_beyond_2mm']}")

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.5, 3.6))
    x = np.arange(len(rows))
    ax.bar(x - 0.2, [float(r["mpairs_per_wall_s"]) for r in rows], 0.4, label="per wall second")  # type: ignore[arg-type]
    ax.bar(x + 0.2, [float(r["mpairs_per_cpu_s"]) for r in rows], 0.4, label="per CPU second")  # type: ignore[arg-type]
    ax.axhline(LIMIT_MPAIRS, color="red", ls=":", label=f"{LIMIT_MPAIRS:g} M/s on one core (goal)")
    ax.set_xticks(x, [f"{r['method']}\n{r['threads']} thr\nerr {r['max_rel_diff_beyond_2mm']}" for r in rows],
                  fontsize=8)
    ax.set_ylabel("million voxel-dwell pairs / s")
    ax.set_title(f"TG-43 grid dose, {n_vox} voxels x {n_dw} dwells (load {load_avg():.1f})")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(out / "dosekernel.png", dpi=110)
    plt.close(fig)
    return 0
