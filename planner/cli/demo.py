"""``reachplan demo``: the main job on the built-in phantom, end to end through DICOM on disk."""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from reachplan.planner.cli.edges import output_folder, print_json, relocate, staged_folder

NAME = "demo"
HELP = "write the built-in phantom as DICOM, read it back, plan needles; write plan/ranking JSON, figures, exports"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Add ``--out``, ``--quiet`` and ``--json``."""
    parser.add_argument("--out", type=Path, required=True, help="output folder (created; phantom in OUT/phantom)")
    parser.add_argument("--quiet", action="store_true", help="no progress bars or table")
    parser.add_argument("--json", action="store_true", help="print the ranking as JSON on stdout")


def run(args: argparse.Namespace) -> int:
    """Write the phantom, read it back and plan it into ``--out``; return the exit code (0)."""
    output_folder(args.out)
    quiet = args.quiet or args.json
    with staged_folder(args.out) as stage:  # nothing appears in --out unless the whole demo succeeds
        doc = _demo(stage, quiet)
        doc = relocate(stage, args.out, doc)
    if args.json:
        print_json(doc, NAME)
    return 0


def _demo(out: Path, quiet: bool) -> dict[str, object]:
    from tqdm import tqdm

    from reachplan.imaging.dicom_io import read_series
    from reachplan.imaging.files import atomic_write_json
    from reachplan.imaging.phantom import write_phantom
    from reachplan.imaging.rtstruct import read_rtstruct
    from reachplan.planner.cli.plan import run_plan
    from reachplan.planner.pipeline import PlanConfig

    t0 = time.perf_counter()
    bar = tqdm(total=2, desc="phantom: write, read back", unit="step", disable=quiet, leave=False)
    files = write_phantom(out / "phantom")
    bar.update()
    t_write = time.perf_counter() - t0
    t = time.perf_counter()
    volume = read_series(files.ct_dir)  # read back from disk: the demo exercises the DICOM reader
    structures = read_rtstruct(files.rtstruct_path, volume)
    bar.update()
    bar.close()
    t_read = time.perf_counter() - t
    if not quiet:
        print(f"phantom written to {files.ct_dir.parent} ({t_write:.1f} s), read back: CT {volume.grid.shape}, "
              f"{len(structures.rois)} ROIs ({t_read:.1f} s)", file=sys.stderr)
    targets = [n for n in structures.names if n.casefold().startswith("target")]
    doc = run_plan(structures, volume, targets, [], PlanConfig(), out, quiet,
                   inputs=[files.ct_dir, files.rtstruct_path],
                   extra={"case": "built-in phantom", "phantom_s": {"write": t_write, "read": t_read}})
    targets_doc = doc["targets"]
    assert isinstance(targets_doc, dict)
    atomic_write_json(out / "ranking.json", {t: v["candidates"] for t, v in targets_doc.items()})
    if not quiet:
        print(f"demo finished in {time.perf_counter() - t0:.1f} s")
    return doc
