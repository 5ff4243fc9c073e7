"""First-run benchmark: the compiled kernels' one-off cost, a fresh numba cache against a warm one.

Every numba kernel of reachplan is compiled with ``cache=True``: the machine code goes to ``__pycache__`` beside
the installed module, or, where that folder is not writable (a system-wide site-packages), to the user's cache
folder (numba's ``_UserWideCacheLocator``, ``~/.cache/numba``), or to ``NUMBA_CACHE_DIR`` when that is set. The
first run after an install therefore compiles once, and every later run loads the machine code.

Run: ``reachplan bench firstrun --out DIR [--quick]``. A child interpreter with ``NUMBA_CACHE_DIR`` set to an
empty folder runs the work that touches every kernel (one two-tube rod solve, a TG-43 grid dose and an
optimisation matrix, the organ distance field and containment test, the built-in case's sweep field), then the
same with the now filled folder, ``--repeat`` times (3; 1 with ``--quick``). The penalty is the median cold time
minus the median warm time; limit 10 s (issue 19).
Writes ``firstrun.csv`` and ``firstrun.png``.
"""

from __future__ import annotations

import argparse
import os
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from reachplan.planner.bench._util import load_avg, write_csv

LIMIT_S = 10.0

#: the child's work: every compiled kernel once, on tiny inputs
WORK = """
import numpy as np
from reachplan.plugins import registry
from reachplan.rod_model.design import preset
from reachplan.imaging.types import Grid
from reachplan.planner.dose.tg43 import DwellSet, Tg43Kernel, dose_on_grid
from reachplan.plugins.sources import BUILTIN
d = preset("15ga-30j-tip")
registry.get("rod_models", "two_tube_cosserat").solve(d, d.loads(5.0))
k = Tg43Kernel(BUILTIN["gammamed_plus_hdr"]())
dw = DwellSet(np.zeros((2, 3)), np.tile([0.0, 0.0, 1.0], (2, 1)), np.ones(2))
dose_on_grid(Grid((4, 4, 4), np.diag([2.0, 2.0, 2.0, 1.0])), dw, k, 40000.0)
k.compiled_rates(np.ones((3, 3)), dw.positions_mm, dw.directions)
try:
    from reachplan.planner.geometry.distance_field import _warm_up
except ImportError:
    pass
else:
    _warm_up()
try:
    from reachplan.imaging._sweep_kernel import warm_up
except ImportError:
    pass
else:
    warm_up()
"""


def _child(cache_dir: str) -> tuple[float, float]:
    """(wall s, CPU s) of one child run with ``NUMBA_CACHE_DIR=cache_dir``."""
    env = dict(os.environ, NUMBA_CACHE_DIR=cache_dir)
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    subprocess.run([sys.executable, "-c", WORK], check=True, env=env)
    wall = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    return wall, (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)


#: results this target owns in a source checkout (``reachplan bench firstrun --install``)
INSTALLS = {"firstrun.csv": "docs/speed/firstrun.csv", "firstrun.png": "docs/speed/firstrun.png"}


def run(args: argparse.Namespace) -> int:
    """Run the benchmark into ``args.out`` (CSV + PNG); return 0."""
    out: Path = args.out
    out.mkdir(parents=True, exist_ok=True)
    rows: list[dict[str, object]] = []
    for i in range(1 if args.quick else 3):
        with tempfile.TemporaryDirectory(prefix="numba-cache-") as cache:
            cold, cold_cpu = _child(cache)
            warm, warm_cpu = _child(cache)
        rows.append({"run": i, "cold_s": round(cold, 3), "warm_s": round(warm, 3),
                     "penalty_s": round(cold - warm, 3), "cold_cpu_s": round(cold_cpu, 3),
                     "warm_cpu_s": round(warm_cpu, 3), "penalty_cpu_s": round(cold_cpu - warm_cpu, 3),
                     "load_avg_1min": round(load_avg(), 2)})

    def med(key: str) -> float:
        return statistics.median(float(r[key]) for r in rows)  # type: ignore[arg-type]

    penalty, cold, warm, penalty_cpu = med("penalty_s"), med("cold_s"), med("warm_s"), med("penalty_cpu_s")
    rows.append({"run": "median", "cold_s": round(cold, 3), "warm_s": round(warm, 3), "penalty_s": round(penalty, 3),
                 "cold_cpu_s": round(med("cold_cpu_s"), 3), "warm_cpu_s": round(med("warm_cpu_s"), 3),
                 "penalty_cpu_s": round(penalty_cpu, 3), "load_avg_1min": round(load_avg(), 2)})
    write_csv(out / "firstrun.csv", rows)

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(5.5, 3.2))
    ax.bar(["fresh cache", "warm cache"], [cold, warm], color=["tab:orange", "tab:blue"])
    ax.axhline(warm + LIMIT_S, color="red", ls=":", label=f"warm + {LIMIT_S:g} s (limit)")
    ax.set_ylabel("seconds (median)")
    ax.set_title(f"first run: penalty {penalty:.1f} s wall, {penalty_cpu:.1f} s CPU (load {load_avg():.1f})",
                 fontsize=9)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(out / "firstrun.png", dpi=110)
    plt.close(fig)
    print(f"fresh cache {cold:.2f} s, warm {warm:.2f} s: first-run penalty {penalty:.2f} s wall, "
          f"{penalty_cpu:.2f} s CPU (limit {LIMIT_S:g} s)")
    return 0
