"""First-run benchmark: what the first ``reachplan demo`` after an install costs more than the next one.

Every numba kernel of reachplan is compiled with ``cache=True``: the machine code goes to ``__pycache__`` beside
the installed module, or, where that folder is not writable (a system-wide site-packages), to the user's cache
folder (numba's ``_UserWideCacheLocator``, ``~/.cache/numba``), or to ``NUMBA_CACHE_DIR`` when that is set. The
first run after an install therefore compiles once (:mod:`reachplan.planner.cli.kernels` moves the rod and dose
kernels to a background process on the other core), and every later run loads the machine code.

Run: ``reachplan bench firstrun --out DIR [--quick] [--repeat N]``. Two measurements, each in child interpreters
with ``NUMBA_CACHE_DIR`` set to an empty folder (cold), then to the folder that run filled (warm), ``--repeat``
times (3; 1 with ``--quick``):

* ``demo``: ``reachplan demo --quiet`` on the clinical case (``--quick``: the pilot phantom), what a user waits
  for after ``pip install .``. The penalty is the median cold wall time minus the median warm wall time; limit
  10 s (issue 19). CPU seconds (the command and its children, the background compile included) are reported
  beside it.
* ``kernels``: the work that touches every kernel once on tiny inputs, in one process (no background): the
  compile cost itself, which the demo hides partly behind its own work.

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

#: the kernels-only work: every compiled kernel once, on tiny inputs, in one process
WORK = """
import numpy as np
from reachplan.plugins import registry
from reachplan.rod_model.design import preset
from reachplan.imaging.types import Grid
from reachplan.planner.dose.tg43 import DwellSet, Tg43Kernel, dose_on_grid
from reachplan.plugins.sources import BUILTIN
from reachplan.planner.geometry.distance_field import _warm_up
from reachplan.imaging._sweep_kernel import warm_up
warm_up()
_warm_up()
d = preset("15ga-30j-tip")
m = registry.get("rod_models", "two_tube_cosserat")
m.solve(d, d.loads(5.0))
m.solve_batch(d, np.array([1.0, 2.0]))
k = Tg43Kernel(BUILTIN["gammamed_plus_hdr"]())
dw = DwellSet(np.zeros((2, 3)), np.tile([0.0, 0.0, 1.0], (2, 1)), np.ones(2))
k.compiled_rates(np.ones((3, 3)), dw.positions_mm, dw.directions)
k.compiled_dose(np.ones((3, 3)), dw.positions_mm, dw.directions, np.ones(2))
dose_on_grid(Grid((4, 4, 4), np.diag([2.0, 2.0, 2.0, 1.0])), dw, k, 40000.0)
"""


def _child(argv: list[str], cache_dir: str) -> tuple[float, float]:
    """(wall s, CPU s of the child and its waited-for children) of one run with ``NUMBA_CACHE_DIR=cache_dir``."""
    env = dict(os.environ, NUMBA_CACHE_DIR=cache_dir)
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    subprocess.run(argv, check=True, env=env, stdout=subprocess.DEVNULL)
    wall = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    return wall, (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)


#: results this target owns in a source checkout (``reachplan bench firstrun --install``)
INSTALLS = {"firstrun.csv": "docs/speed/firstrun.csv", "firstrun.png": "docs/speed/firstrun.png"}


def run(args: argparse.Namespace) -> int:
    """Run the benchmark into ``args.out`` (CSV + PNG); return 0."""
    out: Path = args.out
    out.mkdir(parents=True, exist_ok=True)
    repeat = getattr(args, "repeat", None) or (1 if args.quick else 3)
    case = "pilot" if args.quick else "clinical"
    what = ("demo", "kernels")
    rows: list[dict[str, object]] = []
    for i in range(repeat):
        for name in what:
            with tempfile.TemporaryDirectory(prefix="numba-cache-") as cache, \
                    tempfile.TemporaryDirectory(prefix="firstrun-") as work:
                runs = [[sys.executable, "-m", "reachplan.planner.cli", "demo", "--quiet", "--case", case, "--out",
                         str(Path(work) / tag)] if name == "demo" else [sys.executable, "-c", WORK]
                        for tag in ("cold", "warm")]
                cold, cold_cpu = _child(runs[0], cache)
                warm, warm_cpu = _child(runs[1], cache)
            rows.append({"what": name, "run": i, "cold_s": round(cold, 3), "warm_s": round(warm, 3),
                         "penalty_s": round(cold - warm, 3), "cold_cpu_s": round(cold_cpu, 3),
                         "warm_cpu_s": round(warm_cpu, 3), "penalty_cpu_s": round(cold_cpu - warm_cpu, 3),
                         "load_avg_1min": round(load_avg(), 2)})
            print(f"{name} run {i}: cold {cold:.1f} s, warm {warm:.1f} s wall (CPU {cold_cpu:.1f} s, "
                  f"{warm_cpu:.1f} s)", file=sys.stderr)

    med: dict[str, dict[str, float]] = {}
    for name in what:
        mine = [r for r in rows if r["what"] == name]
        med[name] = {k: statistics.median(float(r[k]) for r in mine)  # type: ignore[arg-type]
                     for k in ("cold_s", "warm_s", "penalty_s", "cold_cpu_s", "warm_cpu_s", "penalty_cpu_s")}
        rows.append({"what": name, "run": "median", **{k: round(v, 3) for k, v in med[name].items()},
                     "load_avg_1min": round(load_avg(), 2)})
    write_csv(out / "firstrun.csv", rows)

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(8.0, 3.4))
    titles = {"demo": f"reachplan demo ({case} case)", "kernels": "every kernel, one process, tiny inputs"}
    for ax, name in zip(axes, what, strict=True):
        m = med[name]
        ax.bar(["fresh cache", "warm cache"], [m["cold_s"], m["warm_s"]], color=["tab:orange", "tab:blue"])
        if name == "demo":
            ax.axhline(m["warm_s"] + LIMIT_S, color="red", ls=":", label=f"warm + {LIMIT_S:g} s (limit)")
            ax.legend(fontsize=8, loc="lower right")
        ax.set_ylabel("wall seconds (median)")
        ax.set_title(f"{titles[name]}\npenalty {m['penalty_s']:.1f} s wall, {m['penalty_cpu_s']:.1f} s CPU",
                     fontsize=9)
    fig.suptitle(f"first run after an install ({repeat} runs, load {load_avg():.1f})", fontsize=9)
    fig.tight_layout()
    fig.savefig(out / "firstrun.png", dpi=110)
    plt.close(fig)
    d, k = med["demo"], med["kernels"]
    print(f"demo: fresh cache {d['cold_s']:.2f} s, warm {d['warm_s']:.2f} s: first-run penalty {d['penalty_s']:.2f} s "
          f"wall (limit {LIMIT_S:g} s), {d['penalty_cpu_s']:.2f} s CPU; kernels alone: {k['penalty_s']:.2f} s wall, "
          f"{k['penalty_cpu_s']:.2f} s CPU")
    return 0
