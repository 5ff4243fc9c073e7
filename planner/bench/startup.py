"""Start-up benchmark: ``reachplan --help`` and one ``reachplan rod`` solve against ``python -c pass``.

Run: ``reachplan bench startup --out DIR [--quick]``. Each command runs in a fresh interpreter, in turns (so a
burst of load on the shared machine hits all of them alike), ``--repeat`` times (7; 3 with ``--quick``); the
numba cache is warmed first (the first-run penalty is :mod:`reachplan.planner.bench.firstrun`'s). Records the
wall time and the CPU time of each run (the CPU time does not grow with the load of the machine, the wall time
does) and writes ``startup.csv`` (every run), ``startup_summary.csv`` (medians, ratio to ``python -c pass``,
limit) and ``startup.png``. Limits (issue 19, quiet machine): ``--help`` <= 0.3 s, ``rod`` <= 0.8 s.
"""

from __future__ import annotations

import argparse
import resource
import statistics
import subprocess
import sys
import time
from pathlib import Path

from reachplan.planner.bench._util import COMMAND, command_argv, load_avg, write_csv

#: (label, argv, limit in s or None): argv after the interpreter, or the installed command's when it starts with
#: :data:`~reachplan.planner.bench._util.COMMAND`
COMMANDS: tuple[tuple[str, tuple[str, ...], float | None], ...] = (
    ("python -c pass", ("-c", "pass"), None),
    ("reachplan --help", (COMMAND, "--help"), 0.3),
    ("reachplan rod", (COMMAND, "rod", "--preset", "15ga-30j-tip", "--tension", "5", "--json"), 0.8),
)


def _run_once(argv: tuple[str, ...]) -> tuple[float, float]:
    """(wall s, CPU s of the child) of one run of ``python argv`` (or of the installed command, see COMMANDS)."""
    full = command_argv(*argv[1:]) if argv[0] == COMMAND else [sys.executable, *argv]
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    subprocess.run(full, check=True, stdout=subprocess.DEVNULL)
    wall = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    return wall, cpu


def measure(repeat: int) -> tuple[list[dict[str, object]], list[dict[str, object]]]:
    """Every run and the summary rows (medians, ratio to ``python -c pass``).

    Parameters
    ----------
    repeat : int
        Runs of each command.

    Returns
    -------
    runs : list of dict of str to object
        One row per run and command (wall and CPU s).
    summary : list of dict of str to object
        One row per command: medians (s), ratio to ``python -c pass`` and the limit (s).
    """
    for _, argv, _ in COMMANDS:  # warm the OS file cache and the numba cache
        _run_once(argv)
    runs: list[dict[str, object]] = []
    for i in range(repeat):
        for label, argv, _ in COMMANDS:
            wall, cpu = _run_once(argv)
            runs.append({"command": label, "run": i, "wall_s": round(wall, 4), "cpu_s": round(cpu, 4),
                         "load_avg_1min": round(load_avg(), 2)})
    base_wall = statistics.median(float(r["wall_s"]) for r in runs if r["command"] == COMMANDS[0][0])  # type: ignore[arg-type]
    summary: list[dict[str, object]] = []
    for label, _, limit in COMMANDS:
        wall = statistics.median(float(r["wall_s"]) for r in runs if r["command"] == label)  # type: ignore[arg-type]
        cpu = statistics.median(float(r["cpu_s"]) for r in runs if r["command"] == label)  # type: ignore[arg-type]
        summary.append({"command": label, "median_wall_s": round(wall, 3), "median_cpu_s": round(cpu, 3),
                        "ratio_to_python": round(wall / base_wall, 1), "limit_s": limit if limit else "",
                        "within_limit_wall": "" if limit is None else wall <= limit,
                        "within_limit_cpu": "" if limit is None else cpu <= limit, "repeats": repeat})
    return runs, summary


def _png(summary: list[dict[str, object]], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.5, 3.2))
    y = range(len(summary))
    ax.barh([i + 0.2 for i in y], [float(s["median_wall_s"]) for s in summary], 0.4, label="wall (median)")  # type: ignore[arg-type]
    ax.barh([i - 0.2 for i in y], [float(s["median_cpu_s"]) for s in summary], 0.4, label="CPU (median)")  # type: ignore[arg-type]
    for i, s in zip(y, summary, strict=True):
        if s["limit_s"] != "":
            ax.plot([float(str(s["limit_s"]))] * 2, [i - 0.45, i + 0.45], color="red", lw=2)
    ax.set_yticks(list(y), [str(s["command"]) for s in summary])
    ax.set_xlabel("seconds (red: limit on a quiet machine)")
    ax.set_title(f"start-up, load {load_avg():.1f} on {__import__('os').cpu_count()} cores")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


#: results this target owns in a source checkout (``reachplan bench startup --install``)
INSTALLS = {name: f"docs/speed/{name}" for name in ("startup.csv", "startup.png", "startup_summary.csv")}


def run(args: argparse.Namespace) -> int:
    """Run the benchmark into ``args.out`` (CSV + PNG).

    Parameters
    ----------
    args : argparse.Namespace
        ``args.out`` receives the files; ``args.quick`` runs 3 times instead of 7.

    Returns
    -------
    int
        0 (the summary is printed).
    """
    out: Path = args.out  # made by the bench command
    runs, summary = measure(3 if args.quick else 7)
    write_csv(out / "startup.csv", runs)
    write_csv(out / "startup_summary.csv", summary)
    _png(summary, out / "startup.png")
    for s in summary:
        print(f"{s['command']:<18} wall {s['median_wall_s']:6.3f} s  CPU {s['median_cpu_s']:6.3f} s  "
              f"x{s['ratio_to_python']} python  limit {s['limit_s'] or '-'}")
    return 0
