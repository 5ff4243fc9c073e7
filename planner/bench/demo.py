"""Demo benchmark: the per-stage times of ``reachplan demo`` on the clinical case.

Issue 19 asks for the whole demo, with implant planning of both arms, in at most 30 s on a quiet 2-core machine.
Run: ``reachplan bench demo --out DIR [--quick] [--repeat N] [--install]``. Each run is a child interpreter
running ``reachplan demo --quiet`` into a temporary folder (``--repeat`` runs, 3; ``--quick``: one run of the
pilot phantom); the stages are read from its plan.json: case write, read back, scene (organ meshes, FCL models,
distance fields), planning, delivery outside the implant (RT Dose, exports), the implant (candidates, both arms),
report, and the rest of the wall time (start-up, the overview figures, file writes); and the child's CPU time
(the machines are shared: CPU time says what wall time would be on a quiet one). Writes ``demo_stages.csv``
(one row per run and stage, then the medians) and ``demo_stages.png`` (the medians stacked, against the limit);
``--install`` copies both to ``docs/``.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import statistics
import subprocess
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

from matplotlib.figure import Figure

from reachplan.planner.bench._util import command_argv
from reachplan.planner.bench.common import settings, write_csv, write_png

INSTALLS = {"demo_stages.csv": "docs/demo_stages.csv", "demo_stages.png": "docs/demo_stages.png"}
COLUMNS = ("case", "run", "stage", "seconds", "load_avg_1min")
#: the demo's limit (issue 19), s wall
LIMIT_S = 30.0
STAGES = ("case write", "read back", "scene", "planning", "delivery (no implant)", "implant", "report", "other")


@dataclass(frozen=True)
class DemoBenchSettings:
    """Which case, and how many runs (the medians are reported).

    Parameters
    ----------
    repeat : int
        Runs of ``reachplan demo``.
    case : str
        ``clinical`` or ``pilot``.
    """

    repeat: int = 3
    case: str = "clinical"


QUICK = DemoBenchSettings(repeat=1, case="pilot")


def stage_times(doc: dict[str, object], wall_s: float) -> dict[str, float]:
    """Split one demo's wall time (s) into :data:`STAGES` from its plan.json document ``doc``.

    Parameters
    ----------
    doc : dict of str to object
        The demo's plan.json (``phantom_s``, ``timings``, ``implant``).
    wall_s : float, s
        The run's wall time.

    Returns
    -------
    dict of str to float, s
        Seconds per stage; ``other`` is what the named stages leave of ``wall_s`` (start-up, figures, writes).
    """
    phantom = doc.get("phantom_s") or {}
    timings = doc.get("timings") or {}
    implant = doc.get("implant") or {}
    assert isinstance(phantom, dict) and isinstance(timings, dict) and isinstance(implant, dict)
    # the implant's wall time (candidates and both arms, which run at once); older plan.json: the arms' sum
    arms = float(implant.get("seconds") or 0.0) or sum(float(a.get("seconds") or 0.0) for a in implant.values()
                                                       if isinstance(a, dict))
    out = {"case write": float(phantom.get("write", 0.0)), "read back": float(phantom.get("read", 0.0)),
           "scene": float(timings.get("scene_s", 0.0)), "planning": float(timings.get("plan_s", 0.0)),
           "delivery (no implant)": max(float(timings.get("delivery_s", 0.0)) - arms, 0.0),
           "implant": arms, "report": float(timings.get("report_s", 0.0))}
    out["other"] = max(wall_s - sum(out.values()), 0.0)
    return out


def _one_run(case: str, folder: Path) -> tuple[float, float, dict[str, object]]:
    """(wall s, CPU s, plan.json) of one ``reachplan demo --quiet`` in a child interpreter."""
    t = time.perf_counter()
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    subprocess.run(command_argv("demo", "--quiet", "--case", case, "--out", str(folder)), check=True,
                   stdout=subprocess.DEVNULL)
    wall = time.perf_counter() - t
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    return wall, cpu, json.loads((folder / "plan.json").read_text(encoding="utf-8"))


def run(args: argparse.Namespace) -> int:
    """Run ``reachplan bench demo`` (``--quick``, ``--repeat``) into ``args.out``.

    Parameters
    ----------
    args : argparse.Namespace
        The parsed command line (``out``, ``quick``, ``repeat``).

    Returns
    -------
    int
        0 after the medians are printed and the CSV and PNG written.
    """
    s = settings(args, DemoBenchSettings(), QUICK)
    out: Path = args.out  # made by the bench command
    runs: list[dict[str, float]] = []
    loads: list[float] = []
    rows: list[dict[str, object]] = []
    with tempfile.TemporaryDirectory() as tmp:
        for k in range(max(1, s.repeat)):
            wall, cpu, doc = _one_run(s.case, Path(tmp) / f"run{k}")
            stages = {**stage_times(doc, wall), "total": wall, "total CPU": cpu}
            load = os.getloadavg()[0]
            loads.append(load)
            runs.append(stages)
            rows += [{"case": s.case, "run": k, "stage": name, "seconds": round(v, 3),
                      "load_avg_1min": round(load, 2)} for name, v in stages.items()]
            print(f"run {k}: {wall:.1f} s wall, {cpu:.1f} s CPU (load {load:.1f})")
    median = {name: statistics.median(r[name] for r in runs) for name in (*STAGES, "total", "total CPU")}
    rows += [{"case": s.case, "run": "median", "stage": name, "seconds": round(v, 3),
              "load_avg_1min": ""} for name, v in median.items()]
    write_csv(out / "demo_stages.csv", COLUMNS, rows)
    write_png(out / "demo_stages.png", _figure(median, s.case, len(runs), statistics.median(loads)))
    outside = median["total"] - median["implant"]
    for name in STAGES:
        print(f"{name:<24} {median[name]:6.2f} s")
    print(f"demo ({s.case}): {median['total']:.1f} s wall ({median['total CPU']:.1f} s CPU), {outside:.1f} s "
          "outside the implant "
          f"(median of {len(runs)}; limit {LIMIT_S:g} s)")
    return 0


def _figure(median: dict[str, float], case: str, n: int, load: float) -> Figure:
    fig = Figure(figsize=(8.5, 2.6))
    ax = fig.subplots()
    left = 0.0
    for i, name in enumerate(STAGES):
        ax.barh([0], [median[name]], left=left, color=f"C{i}", label=f"{name} {median[name]:.1f} s")
        left += median[name]
    ax.axvline(LIMIT_S, color="grey", ls="--", lw=0.8)
    ax.set_yticks([])
    ax.set_xlabel("seconds (wall)")
    ax.set_title(f"reachplan demo, {case} case: {median['total']:.1f} s wall, {median['total CPU']:.1f} s CPU "
                 f"(median of {n}, load {load:.1f}); dashed: the {LIMIT_S:g} s limit", fontsize=9)
    ax.legend(fontsize=7, ncol=4, loc="upper center", bbox_to_anchor=(0.5, -0.42))
    fig.subplots_adjust(left=0.03, right=0.97, top=0.86, bottom=0.46)
    return fig
