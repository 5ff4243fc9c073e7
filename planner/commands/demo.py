"""``reachplan demo``: the main job on the built-in phantom, end to end through DICOM on disk."""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

NAME = "demo"
HELP = "write the built-in pelvic phantom as DICOM, read it back, plan needles, write ranking.json and figures"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--out", type=Path, required=True, help="output folder (created; phantom in OUT/phantom)")
    parser.add_argument("--quiet", action="store_true", help="no progress bars or table")
    parser.add_argument("--json", action="store_true", help="print the ranking as JSON on stdout")


def run(args: argparse.Namespace) -> int:
    from imaging.dicom_io import read_series
    from imaging.phantom import write_phantom
    from imaging.rtstruct import read_rtstruct
    from planner.io import atomic_write_json
    from planner.pipeline import PlanConfig, build_scene, plan
    from planner.report import format_table, overview_figure

    out: Path = args.out
    quiet = args.quiet or args.json
    timings: dict[str, float] = {}

    def log(msg: str) -> None:
        if not quiet:
            print(msg, file=sys.stderr)

    t0 = time.perf_counter()
    files = write_phantom(out / "phantom")
    timings["write_phantom_s"] = time.perf_counter() - t0
    log(f"phantom written to {files.ct_dir.parent} ({timings['write_phantom_s']:.1f} s)")

    t = time.perf_counter()
    volume = read_series(files.ct_dir)
    structures = read_rtstruct(files.rtstruct_path, volume)
    timings["read_dicom_s"] = time.perf_counter() - t
    log(f"read CT {volume.grid.shape} and {len(structures.rois)} ROIs ({timings['read_dicom_s']:.1f} s)")

    config = PlanConfig()
    t = time.perf_counter()
    scene = build_scene(structures, grid=volume.grid, config=config, quiet=quiet)
    timings["mesh_s"] = time.perf_counter() - t
    t = time.perf_counter()
    result = plan(scene, config, quiet=quiet)
    timings["plan_s"] = time.perf_counter() - t
    log(f"scored {len(result.candidates)} candidates ({timings['plan_s']:.1f} s)")

    doc = {"case": "built-in phantom", **result.to_json(), "timings": timings}
    atomic_write_json(out / "ranking.json", doc)
    overview_figure(scene, result, out / "overview.png", volume)
    timings["total_s"] = time.perf_counter() - t0
    if args.json:
        json.dump(doc, sys.stdout, indent=2)
        print()
    elif not args.quiet:
        print(format_table(result))
        print(f"\nwrote {out / 'ranking.json'} and {out / 'overview.png'} in {timings['total_s']:.1f} s")
    return 0
