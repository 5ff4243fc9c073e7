"""``reachplan demo``: the main job on a built-in case, end to end through DICOM on disk."""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from reachplan.planner.cli.edges import output_folder, print_json, staged_folder

NAME = "demo"
HELP = ("write a built-in case as DICOM (the clinical case by default), read it back, plan needles; write plan/"
        "ranking JSON, figures, exports")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Add ``--out``, the case options, ``--quiet`` and ``--json``."""
    from reachplan.planner.cli.phantom import add_case_arguments

    parser.add_argument("--out", type=Path, required=True, help="output folder (created; case in OUT/phantom)")
    add_case_arguments(parser)
    parser.add_argument("--quiet", action="store_true", help="no progress bars or table")
    parser.add_argument("--json", action="store_true", help="print the ranking as JSON on stdout")


def blocked_straight(doc: dict[str, object]) -> list[dict[str, object]]:
    """List the straight candidates that reach their target but collide.

    Each with the organ and depth of first contact and the target's most medial clean steered alternative
    (``None`` when there is none).
    """
    out: list[dict[str, object]] = []
    targets = doc["targets"]
    assert isinstance(targets, dict)
    for name, t in targets.items():
        cands = t["candidates"]
        steered = [c for c in cands if c["steered"] and c["feasible"] and (c["clearance_mm"] or 0.0) >= 2.0]
        alt = min(steered, key=lambda c: c["hole_distance_mm"]) if steered else None
        for c in cands:
            if not c["steered"] and c["reaches"] and c["collides"]:
                out.append({"target": name, "hole_id": c["hole_id"], "hole_distance_mm": c["hole_distance_mm"],
                            "organ": c["closest_organ"], "contact_depth_mm": c["contact_depth_mm"],
                            "steered_alternative": None if alt is None else {
                                k: alt[k] for k in ("hole_id", "hole_distance_mm", "clearance_mm", "closest_organ",
                                                    "peak_tension_n")}})
    return out


def format_blocked(rows: list[dict[str, object]]) -> str:
    """Return the terminal table of :func:`blocked_straight`."""
    if not rows:
        return "no straight needle that reaches a target collides with an organ"
    head = f"{'target':<18} {'straight hole':<16} {'collides with':<24}   steered instead (clean, >= 2 mm)"
    lines = ["straight needles that reach the target but collide:", head, "-" * len(head)]
    for r in rows:
        alt = r["steered_alternative"]
        alt_s = "none" if not isinstance(alt, dict) else (
            f"{alt['hole_id']} ({alt['hole_distance_mm']:.1f} mm from centre), clearance {alt['clearance_mm']:.1f} mm "
            f"({alt['closest_organ']}), {alt['peak_tension_n']:.1f} N")
        lines.append(f"{r['target']:<18} {r['hole_id']:>4} ({r['hole_distance_mm']:4.1f} mm) "
                     f"{r['organ']:<10} at {r['contact_depth_mm']:5.1f} mm   {alt_s}")
    return "\n".join(lines)


def run(args: argparse.Namespace) -> int:
    """Write the phantom, read it back and plan it into ``--out``; return the exit code (0)."""
    output_folder(args.out)
    quiet = args.quiet or args.json
    with staged_folder(args.out) as stage:  # nothing appears in --out unless the whole demo succeeds
        doc = _demo(args, stage, quiet)
    if args.json:
        print_json(doc, NAME)
    return 0


def _demo(args: argparse.Namespace, out: Path, quiet: bool) -> dict[str, object]:
    from tqdm import tqdm

    from reachplan.imaging.dicom_io import read_series
    from reachplan.imaging.files import atomic_write_json
    from reachplan.imaging.rtstruct import read_rtstruct
    from reachplan.planner.cli.phantom import write_case
    from reachplan.planner.cli.plan import run_plan
    from reachplan.planner.kernels import start as start_kernels
    from reachplan.planner.pipeline import DEFAULT_OARS, PlanConfig

    t0 = time.perf_counter()
    start_kernels(quiet)  # first run after an install: the rod and dose kernels compile meanwhile, on the other core
    bar = tqdm(total=2, desc="case: write, read back", unit="step", disable=quiet, leave=False)
    files, _spec, about = write_case(args, out / "phantom")
    bar.update()
    t_write = time.perf_counter() - t0
    t = time.perf_counter()
    volume = read_series(files.ct_dir)  # read back from disk: the demo exercises the DICOM reader
    structures = read_rtstruct(files.rtstruct_path, volume)
    bar.update()
    bar.close()
    t_read = time.perf_counter() - t
    if not quiet:
        print(f"{args.case} case written to {args.out / files.ct_dir.parent.relative_to(out)} ({t_write:.1f} s), "
              "read back: "
              f"{volume.modality} {volume.grid.shape}, {len(structures.rois)} ROIs ({t_read:.1f} s)", file=sys.stderr)
    targets = [n for n in structures.names if n.casefold().startswith("target")]
    # the clinical case's tandem is in the uterine canal: a needle must not cross it
    config = PlanConfig(oar_names=(*DEFAULT_OARS, "Tandem")) if args.case == "clinical" else PlanConfig()
    label = ("built-in phantom" if args.case == "pilot"
             else f"built-in clinical case (seed {args.seed}, {args.modality})")
    doc = run_plan(structures, volume, targets, [], config, out, quiet,
                   inputs=[files.ct_dir, files.rtstruct_path],
                   extra={"case": label, "case_about": about, "phantom_s": {"write": t_write, "read": t_read}},
                   final_out=args.out, complete=lambda d: d.update(blocked_straight=blocked_straight(d)))
    blocked = doc["blocked_straight"]
    assert isinstance(blocked, list)
    targets_doc = doc["targets"]
    assert isinstance(targets_doc, dict)
    atomic_write_json(out / "ranking.json", {t: v["candidates"] for t, v in targets_doc.items()})
    if not quiet:
        print("\n" + format_blocked(blocked))
        print(f"demo finished in {time.perf_counter() - t0:.1f} s")
    return doc
