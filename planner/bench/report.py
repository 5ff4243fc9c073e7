"""Benchmark: building ``report.html`` of the demo from the plan in memory (time per part, file size per part).

Runs the demo's pipeline once (the built-in clinical case written as DICOM and read back, scene, plan, delivery
with both implant arms), then renders the report ``--repeat`` times as ``reachplan demo`` does
(:func:`reachplan.planner.report.build.report_html`: figures, 3-D view, HTML) and records the wall and CPU time of
each run, the time of the straight-versus-steered dose comparison the demo runs with the delivery before it
(:func:`reachplan.planner.report.comparison.straight_vs_steered`, not part of the report), and the size of the
document split into plotly.js, the embedded images, the 3-D view's data and the rest. Limit (issue 19, quiet 2-core
machine): the report of the demo in at most 3 s.

Run: ``reachplan bench report --out DIR [--quick] [--repeat N] [--install]``. Writes ``report_benchmark.csv``
(one row per run), ``report_benchmark_summary.csv`` (medians) and ``report_benchmark.png``; ``--install``
copies them to ``docs/speed/``.
"""

from __future__ import annotations

import argparse
import re
import statistics
import tempfile
import time
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

from matplotlib.figure import Figure
from matplotlib.ticker import MaxNLocator

from reachplan.planner.bench._util import load_avg, write_csv
from reachplan.planner.bench.common import settings, write_png

INSTALLS = {name: f"docs/speed/{name}" for name in
            ("report_benchmark.csv", "report_benchmark_summary.csv", "report_benchmark.png")}
#: The report of the demo, seconds on a quiet 2-core machine (issue 19).
LIMIT_S = 3.0


@dataclass(frozen=True)
class ReportBenchSettings:
    """Timed renderings of the report (the median is reported) and whether the implant arms are planned.

    The command line's ``--repeat`` overrides ``repeat``; ``--quick`` starts from :data:`QUICK`.

    Parameters
    ----------
    repeat : int
        Timed renderings.
    implant : bool
        Plan the implant arms (as the demo does) before rendering.
    """

    repeat: int = 5
    implant: bool = True


QUICK = ReportBenchSettings(repeat=1, implant=False)


def demo_inputs(folder: Path, implant: bool = True) -> dict[str, Any]:
    """Run the demo's pipeline on the built-in clinical case (seed 0, CT) written into ``folder``.

    Parameters
    ----------
    folder : Path
        Where the case is written.
    implant : bool
        Plan the implant arms too.

    Returns
    -------
    dict of str to object
        The keyword arguments of :func:`reachplan.planner.report.build.report_html` the demo passes, plus
        ``scene``, ``result`` and ``structures``.
    """
    from reachplan.imaging.clinical import clinical_case, write_clinical
    from reachplan.imaging.dicom_io import read_series
    from reachplan.imaging.rtstruct import read_rtstruct
    from reachplan.planner.case.config import PlanConfig
    from reachplan.planner.case.scene import build_scene
    from reachplan.planner.case.search import plan
    from reachplan.planner.delivery import plan_delivery
    from reachplan.planner.report import figures
    from reachplan.planner.report.terminal import top_candidates
    from reachplan.planner.report.workspace import workspace_figure
    from reachplan.planner.run.case import rod_model_errors

    case = clinical_case(0, modality="CT")
    files = write_clinical(folder, case)
    volume = read_series(files.ct_dir)
    structures = read_rtstruct(files.rtstruct_path, volume)
    targets = [n for n in structures.names if n.casefold().startswith("target")]
    config = PlanConfig()
    scene = build_scene(structures, targets, grid=volume.grid, config=config)
    config = replace(config, oar_names=tuple(o.name for o in scene.organs))
    result = plan(scene, config)
    delivery = plan_delivery(result, structures, volume.grid, volume=volume, input_paths=[files.ct_dir],
                             scene=scene if implant else None)
    return {"scene": scene, "result": result, "structures": structures, "volume": volume, "delivery": delivery,
            "case": "built-in clinical case (seed 0, CT)",
            "overview_png": figures.overview(scene, top_candidates(result), volume),
            "workspace_png": workspace_figure(scene, config), "model_errors": rod_model_errors()}


def html_parts(html: str) -> dict[str, int]:
    """Return the bytes (UTF-8) of a report by part: ``plotly_js``, ``images`` (base64), ``view_3d``, ``rest``.

    Parameters
    ----------
    html : str
        The report.

    Returns
    -------
    dict of str to int
        Bytes per part, and ``total``.
    """
    total = len(html.encode("utf-8"))
    scripts = re.findall(r"<script>(.*?)</script>", html, flags=re.S)
    js = sum(len(s.encode("utf-8")) for s in scripts if not s.startswith("Plotly.newPlot"))
    view = sum(len(s.encode("utf-8")) for s in scripts if s.startswith("Plotly.newPlot"))
    images = sum(len(m) for m in re.findall(r'src="data:image/[a-z+]+;base64,[^"]*"', html))
    return {"plotly_js": js, "images": images, "view_3d": view, "rest": total - js - images - view, "total": total}


def measure(inputs: dict[str, Any], repeat: int) -> list[dict[str, object]]:
    """Render the report ``repeat`` times; one row per run (seconds, CPU seconds, bytes by part).

    Parameters
    ----------
    inputs : dict of str to object
        The inputs of :func:`demo_inputs`.
    repeat : int
        Renderings.

    Returns
    -------
    list of dict of str to object
        One row per run.
    """
    from reachplan.planner.report.build import report_html
    from reachplan.planner.report.comparison import straight_vs_steered

    kw = {k: v for k, v in inputs.items() if k not in ("scene", "result", "structures")}
    rows: list[dict[str, object]] = []
    for i in range(repeat):
        t = time.perf_counter()
        comparison, note = straight_vs_steered(inputs["result"], inputs["structures"], inputs["delivery"],
                                               inputs["volume"].grid)
        comparison_s = time.perf_counter() - t
        t, cpu = time.perf_counter(), time.process_time()
        html = report_html(inputs["scene"], inputs["result"], comparison=comparison, comparison_note=note, **kw)
        seconds, cpu_s = time.perf_counter() - t, time.process_time() - cpu
        rows.append({"run": i, "report_s": round(seconds, 3), "report_cpu_s": round(cpu_s, 3),
                     "comparison_s": round(comparison_s, 3),
                     **{f"bytes_{k}": v for k, v in html_parts(html).items()},
                     "load_avg_1min": round(load_avg(), 2)})
    return rows


def summarise(rows: list[dict[str, object]]) -> dict[str, object]:
    """Medians of the runs and the limit.

    Parameters
    ----------
    rows : list of dict of str to object
        One per rendering, as :func:`measure` returns them.

    Returns
    -------
    dict of str to object
        Median wall and CPU seconds (s), bytes by part, the limit (s) and the load average.
    """
    def med(key: str) -> float:
        return statistics.median(float(str(r[key])) for r in rows)

    report_s = med("report_s")
    return {"median_report_s": round(report_s, 3), "median_report_cpu_s": round(med("report_cpu_s"), 3),
            "median_comparison_s": round(med("comparison_s"), 3), "limit_s": LIMIT_S,
            "within_limit_wall": report_s <= LIMIT_S, "within_limit_cpu": med("report_cpu_s") <= LIMIT_S,
            "bytes_total": int(med("bytes_total")), "bytes_plotly_js": int(med("bytes_plotly_js")),
            "bytes_images": int(med("bytes_images")), "bytes_view_3d": int(med("bytes_view_3d")),
            "repeats": len(rows), "load_avg_1min": round(load_avg(), 2)}


def _figure(rows: list[dict[str, object]], summary: dict[str, object]) -> Figure:
    fig = Figure(figsize=(9.0, 3.6))
    ax, bx = fig.subplots(1, 2)
    runs = [int(str(r["run"])) for r in rows]
    ax.plot(runs, [float(str(r["report_s"])) for r in rows], "o-", label="wall")
    ax.plot(runs, [float(str(r["report_cpu_s"])) for r in rows], "s--", label="CPU")
    ax.axhline(LIMIT_S, color="red", lw=1, label=f"limit {LIMIT_S:g} s")
    ax.set_xlabel("run")
    ax.xaxis.set_major_locator(MaxNLocator(integer=True))
    ax.set_ylabel("seconds")
    ax.set_ylim(0, None)
    ax.set_title(f"report of the demo: median {summary['median_report_s']} s (load {summary['load_avg_1min']})",
                 fontsize=9)
    ax.legend(fontsize=8)
    parts = ("plotly_js", "images", "view_3d")
    sizes = [int(str(summary[f"bytes_{p}"])) / 1e6 for p in parts]
    rest = int(str(summary["bytes_total"])) / 1e6 - sum(sizes)
    bx.bar([*parts, "rest"], [*sizes, rest], color=["C0", "C1", "C2", "C7"])
    bx.set_ylabel("MB")
    bx.set_title(f"report.html: {int(str(summary['bytes_total'])) / 1e6:.2f} MB", fontsize=9)
    fig.tight_layout()
    return fig


def run(args: argparse.Namespace) -> int:
    """Run ``reachplan bench report`` (``--quick``, ``--repeat``) into ``args.out``.

    Parameters
    ----------
    args : argparse.Namespace
        What ``reachplan bench report`` was given (``out``, ``quick``, ``repeat``).

    Returns
    -------
    int
        0 when the report renders.
    """
    s = settings(args, ReportBenchSettings(), QUICK)
    out: Path = args.out  # made by the bench command
    with tempfile.TemporaryDirectory() as tmp:
        inputs = demo_inputs(Path(tmp), implant=s.implant)
    rows = measure(inputs, max(1, s.repeat))
    summary = summarise(rows)
    write_csv(out / "report_benchmark.csv", rows)
    write_csv(out / "report_benchmark_summary.csv", [summary])
    write_png(out / "report_benchmark.png", _figure(rows, summary))
    print(f"report of the demo: median {summary['median_report_s']} s wall, {summary['median_report_cpu_s']} s CPU "
          f"(limit {LIMIT_S:g} s; {len(rows)} runs, load {summary['load_avg_1min']}); "
          f"{int(str(summary['bytes_total'])) / 1e6:.2f} MB, plotly.js "
          f"{int(str(summary['bytes_plotly_js'])) / 1e6:.2f} MB, images {int(str(summary['bytes_images'])) / 1e6:.2f} "
          f"MB, 3-D view {int(str(summary['bytes_view_3d'])) / 1e6:.2f} MB")
    return 0
