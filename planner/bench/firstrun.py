"""First-run benchmark: what the first ``reachplan demo`` after an install costs more than the next one.

Every numba kernel of reachplan is compiled with ``cache=True``: the machine code goes to ``__pycache__`` beside
the installed module, or, where that folder is not writable (a system-wide site-packages), to the user's cache
folder (numba's ``_UserWideCacheLocator``, ``~/.cache/numba``), or to ``NUMBA_CACHE_DIR`` when that is set. The
first run after an install therefore compiles once (:mod:`reachplan.planner.kernels` moves the rod and dose
kernels to a background process on the other core), and every later run loads the machine code.

Run: ``reachplan bench firstrun --out DIR [--quick] [--repeat N]``. Two measurements, each in child interpreters
with ``NUMBA_CACHE_DIR`` set to an empty folder (cold), then to the folder that run filled (warm), ``--repeat``
times (3; 1 with ``--quick``):

* ``demo``: ``reachplan demo --quiet`` on the clinical case (``--quick``: the pilot phantom), what a user waits
  for after ``pip install .``. The penalty is the median cold wall time minus the median warm wall time; limit
  10 s (issue 19). Beside it: CPU seconds of the command and its children (the background compile included), the
  main process's own CPU seconds and the seconds it waited for the background compile. On a shared machine the
  wall times swing with the load (recorded); the main process's CPU penalty plus its wait is what a quiet 2-core
  machine shows as wall time.
* ``kernels``: the work that touches every kernel once on tiny inputs, in one process (no background): the
  compile cost itself, which the demo hides partly behind its own work (``python -m reachplan.planner.kernels
  warm``, :func:`reachplan.planner.kernels.warm_up`).

Writes ``firstrun.csv`` and ``firstrun.png``.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from reachplan.planner import kernels
from reachplan.planner.bench._util import command_module, load_avg, write_csv

LIMIT_S = 10.0

#: the kernels-only work: every compiled kernel once, on tiny inputs, in one process (the rod and dose kernels as
#: the background process of a first run compiles them)
WORK = ("-m", kernels.__name__, "warm", *kernels.GROUPS)

#: ``reachplan demo`` as ``python -m MODULE ARGS...`` runs it (the installed command, argv[1] the module), then the
#: main process's own CPU seconds and how long it waited for the background compile, as JSON on the last line
DEMO = f"""
import json, resource, runpy, sys
from {kernels.__name__} import waited_s
sys.argv = sys.argv[1:]
try:
    runpy.run_module(sys.argv[0], run_name="__main__", alter_sys=True)
    code = 0
except SystemExit as exc:
    code = exc.code
ru = resource.getrusage(resource.RUSAGE_SELF)
print(json.dumps({{"main_cpu_s": ru.ru_utime + ru.ru_stime, "waited_s": waited_s()}}))
sys.exit(code)
"""


def _child(argv: list[str], cache_dir: str) -> dict[str, float]:
    """Run ``argv`` with ``NUMBA_CACHE_DIR=cache_dir``.

    Returns wall s, CPU s of the child and its waited-for children (the background compile included), and what the
    child printed as JSON on its last line (the demo: its own CPU s and the seconds it waited).
    """
    env = dict(os.environ, NUMBA_CACHE_DIR=cache_dir)
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    done = subprocess.run(argv, check=True, env=env, stdout=subprocess.PIPE, text=True)
    wall = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    lines = done.stdout.strip().splitlines()
    extra = json.loads(lines[-1]) if lines and lines[-1].startswith("{") else {}
    return {"wall_s": wall, "cpu_s": (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime),
            **{k: float(v) for k, v in extra.items()}}


#: results this target owns in a source checkout (``reachplan bench firstrun --install``)
INSTALLS = {"firstrun.csv": "docs/speed/firstrun.csv", "firstrun.png": "docs/speed/firstrun.png"}


def run(args: argparse.Namespace) -> int:
    """Run ``reachplan bench firstrun`` into ``args.out`` (CSV + PNG).

    Parameters
    ----------
    args : argparse.Namespace
        ``out``, ``quick`` (the pilot case, one repeat) and ``repeat``.

    Returns
    -------
    int
        0; the cold, warm and penalty seconds per measurement are in ``firstrun.csv``.
    """
    out: Path = args.out  # made by the bench command
    repeat = getattr(args, "repeat", None) or (1 if args.quick else 3)
    case = "pilot" if args.quick else "clinical"
    what = ("demo", "kernels")
    rows: list[dict[str, object]] = []
    for i in range(repeat):
        for name in what:
            with tempfile.TemporaryDirectory(prefix="numba-cache-") as cache, \
                    tempfile.TemporaryDirectory(prefix="firstrun-") as work:
                runs = [[sys.executable, "-c", DEMO, command_module(), "demo", "--quiet", "--case", case, "--out",
                         str(Path(work) / tag)] if name == "demo" else [sys.executable, *WORK]
                        for tag in ("cold", "warm")]
                cold = _child(runs[0], cache)
                warm = _child(runs[1], cache)
            row: dict[str, object] = {"what": name, "run": i}
            for key in ("wall_s", "cpu_s", "main_cpu_s"):
                c, w = cold.get(key, cold["cpu_s"]), warm.get(key, warm["cpu_s"])
                row.update({f"cold_{key}": round(c, 3), f"warm_{key}": round(w, 3), f"penalty_{key}": round(c - w, 3)})
            row.update({"cold_waited_s": round(cold.get("waited_s", 0.0), 3), "load_avg_1min": round(load_avg(), 2)})
            rows.append(row)
            print(f"{name} run {i}: cold {cold['wall_s']:.1f} s, warm {warm['wall_s']:.1f} s wall (CPU "
                  f"{cold['cpu_s']:.1f} s, {warm['cpu_s']:.1f} s; main process {row['cold_main_cpu_s']} s, "
                  f"{row['warm_main_cpu_s']} s; waited "
                  f"{row['cold_waited_s']} s; load {row['load_avg_1min']})", file=sys.stderr)

    med: dict[str, dict[str, float]] = {}
    keys = [k for k in rows[0] if k not in ("what", "run")]
    for name in what:
        mine = [r for r in rows if r["what"] == name]
        med[name] = {k: statistics.median(float(r[k]) for r in mine) for k in keys}  # type: ignore[arg-type]
        rows.append({"what": name, "run": "median", **{k: round(v, 3) for k, v in med[name].items()}})
    write_csv(out / "firstrun.csv", rows)

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(8.0, 3.4))
    titles = {"demo": f"reachplan demo ({case} case)", "kernels": "every kernel, one process, tiny inputs"}
    for ax, name in zip(axes, what, strict=True):
        m = med[name]
        ax.bar(["fresh cache", "warm cache"], [m["cold_wall_s"], m["warm_wall_s"]], color=["tab:orange", "tab:blue"])
        if name == "demo":
            ax.axhline(m["warm_wall_s"] + LIMIT_S, color="red", ls=":", label=f"warm + {LIMIT_S:g} s (limit)")
            ax.legend(fontsize=8, loc="lower right")
        ax.set_ylabel("wall seconds (median)")
        main = f" ({m['penalty_main_cpu_s']:.1f} s main process, waited {m['cold_waited_s']:.1f} s)" \
            if name == "demo" else ""
        ax.set_title(f"{titles[name]}\npenalty {m['penalty_wall_s']:.1f} s wall, {m['penalty_cpu_s']:.1f} s CPU{main}",
                     fontsize=8)
    label = f"{repeat} run{'s' if repeat > 1 else ''}, median"
    fig.suptitle(f"first run after an install ({label}; load {load_avg():.1f})", fontsize=9)
    fig.tight_layout()
    fig.savefig(out / "firstrun.png", dpi=110)
    plt.close(fig)
    d, k = med["demo"], med["kernels"]
    print(f"demo: fresh cache {d['cold_wall_s']:.2f} s, warm {d['warm_wall_s']:.2f} s: first-run penalty "
          f"{d['penalty_wall_s']:.2f} s wall (limit {LIMIT_S:g} s), {d['penalty_cpu_s']:.2f} s CPU in all, "
          f"{d['penalty_main_cpu_s']:.2f} s CPU of the main process, which waited {d['cold_waited_s']:.2f} s; "
          f"kernels alone: {k['penalty_wall_s']:.2f} s wall, {k['penalty_cpu_s']:.2f} s CPU")
    return 0
