"""``reachplan plan``: plan straight and steered needles for a case's targets and export the plan."""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:  # the run-time imports are inside the functions: start-up of every command stays light
    from reachplan.imaging.types import StructureSet, Volume
    from reachplan.planner.pipeline import PlanConfig
    from reachplan.planner.steering.candidates import Target

NAME = "plan"
HELP = "rank template holes, stylet designs and tension schedules for targets; write plan.json, figures, exports"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--ct", type=Path, help="CT/MR series folder (optional: organs from contours suffice)")
    parser.add_argument("--rtstruct", type=Path, required=True, help="RT Structure Set file")
    parser.add_argument("--targets", nargs="+", required=True, metavar="ROI_OR_POINT",
                        help="target ROI names, or points 'x,y,z' in mm (DICOM patient coordinates, LPS)")
    parser.add_argument("--template", default="needlefinder_syed_63", help="template plugin name")
    parser.add_argument("--design", nargs="*", default=["15ga-30j-tip"], metavar="PRESET",
                        help="stylet presets to steer with (none: straight needles only)")
    parser.add_argument("--target-roi", default="HR-CTV", help="ROI the dwell times are optimised on")
    parser.add_argument("--source", default="gammamed_plus_hdr", help="TG-43 source plugin for the dose")
    parser.add_argument("--no-export", action="store_true", help="rank only; skip dose optimisation and export")
    parser.add_argument("--out", type=Path, required=True, help="output folder")
    parser.add_argument("--quiet", action="store_true", help="no progress bars or table")
    parser.add_argument("--json", action="store_true", help="print plan.json on stdout")


def _targets(specs: list[str]) -> tuple[list[str], list[Target]]:
    from reachplan.planner.errors import PlanInputError
    from reachplan.planner.steering.candidates import Target

    names: list[str] = []
    points: list[Target] = []
    for spec in specs:
        parts = spec.split(",")
        if len(parts) == 3:
            try:
                x, y, z = (float(p) for p in parts)
            except ValueError:
                raise PlanInputError(f"target {spec!r}: a point is three numbers 'x,y,z' in mm") from None
            points.append(Target(f"point_{len(points) + 1}", (x, y, z)))
        else:
            names.append(spec)
    return names, points


def run(args: argparse.Namespace) -> int:
    from reachplan.imaging.dicom_io import read_series
    from reachplan.imaging.rtstruct import read_rtstruct
    from reachplan.planner.pipeline import PlanConfig

    quiet = args.quiet or args.json
    volume = read_series(args.ct) if args.ct else None
    structures = read_rtstruct(args.rtstruct, volume)
    names, points = _targets(args.targets)
    for n in names:
        structures.get(n)  # a typed error naming the available ROIs
    config = PlanConfig(template=args.template, designs=tuple(args.design))
    doc = run_plan(structures, volume, names, points, config, args.out, quiet,
                   export=not args.no_export, source=args.source, target_roi=args.target_roi,
                   inputs=[p for p in (args.ct, args.rtstruct) if p is not None])
    if args.json:
        json.dump(doc, sys.stdout, indent=2)
        print()
    return 0


def kernels_not_cached() -> bool:
    """Whether the rod kernel (the largest to compile) has no machine code in numba's cache yet.

    Reads numba's cache index path (an internal of numba; any surprise there reads as "cached": the message
    this feeds is only a courtesy)."""
    import os

    try:
        from reachplan.rod_model import _kernel

        return not os.path.exists(_kernel.shoot._cache._cache_file._index_path)  # type: ignore[attr-defined]
    except Exception:  # numba internals may change: no message then
        return False


def run_plan(structures: StructureSet, volume: Volume | None, names: list[str], points: list[Target],
             config: PlanConfig, out: Path, quiet: bool, *, export: bool = True, source: str = "gammamed_plus_hdr",
             target_roi: str = "HR-CTV", inputs: list[Path] | None = None,
             extra: dict[str, object] | None = None) -> dict[str, object]:
    """Scene → plan → files (plan.json, overview.png, exports); returns the plan document."""
    from tqdm import tqdm

    from reachplan.imaging.files import atomic_write_json
    from reachplan.planner.pipeline import build_scene, plan, plan_delivery
    from reachplan.planner.report.build import format_table, overview_figure
    from reachplan.planner.report.workspace import workspace_figure
    from reachplan.plugins import registry
    from reachplan.plugins.exporters import ExportOptions

    timings: dict[str, float] = {}
    if not quiet and kernels_not_cached():
        print("reachplan: compiling the numba kernels once (first run after an install: about 10 s of CPU, "
              "longer on a busy machine); later runs load them from the cache", file=sys.stderr)
    t = time.perf_counter()
    grid = volume.grid if volume is not None else None
    scene = build_scene(structures, names, points, grid=grid, config=config, quiet=quiet)
    timings["scene_s"] = time.perf_counter() - t
    t = time.perf_counter()
    result = plan(scene, config, quiet=quiet)
    timings["plan_s"] = time.perf_counter() - t
    doc: dict[str, object] = {**(extra or {}), **result.to_json()}
    overview_figure(scene, result, out / "overview.png", volume)
    workspace_figure(scene, config, out / "workspace.png")
    delivery = None
    if export:
        t = time.perf_counter()
        bar = tqdm(total=4, desc="delivery", unit="step", disable=quiet, leave=False)
        bar.set_postfix_str("dwell times (TG-43, LP)")
        delivery = plan_delivery(result, structures, grid, source_name=source, target_roi=target_roi,
                                 volume=volume, input_paths=inputs or [])
        bar.update()
        files = []
        for name in ("dicom_rt", "device_json", "device_csv"):
            bar.set_postfix_str(f"export {name}")
            exporter = registry.get("exporters", name)
            written = exporter.export(delivery.export, out / "export", ExportOptions(overwrite=True))
            files += [str(f.path) for f in written.files]
            bar.update()
        bar.close()
        opt = delivery.optimisation
        doc["delivery"] = {
            "needles": [c.hole_id for c in delivery.needles],
            "optimisation": {"success": opt.success, "reason": opt.reason, "aim_met": opt.aim_met,
                             "hrctv_d90_gy": round(float(opt.target.d90_gy), 3) if opt.success else None},
            "files": files,
        }
        timings["delivery_s"] = time.perf_counter() - t
    # --- report.html (issue 8: planner/report.py owns the content) ---
    from reachplan.planner.pipeline import rod_model_errors
    from reachplan.planner.report.build import write_report

    t = time.perf_counter()
    case = str((extra or {}).get("case") or (inputs[-1].name if inputs else "case"))
    doc["report"] = str(write_report(out / "report.html", scene, result, structures, volume=volume,
                                     delivery=delivery, case=case, timings=timings, source_name=source,
                                     target_roi=target_roi, quiet=quiet,
                                     case_pngs=(out / "overview.png", out / "workspace.png"),
                                     model_errors=rod_model_errors()))
    timings["report_s"] = time.perf_counter() - t
    # --- end report ---
    doc["timings"] = timings
    atomic_write_json(out / "plan.json", doc)
    if not quiet:
        print(format_table(result))
        print(f"\nwrote {out / 'plan.json'}, {out / 'overview.png'} and {out / 'report.html'}")
    return doc
