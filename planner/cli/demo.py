"""``reachplan demo``: the main job on a built-in case, end to end through DICOM on disk."""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING

from reachplan.planner.cli.edges import PROTOCOL_HELP, output_folder, print_json, staged_folder

if TYPE_CHECKING:
    from reachplan.planner.case.result import BlockedNeedle

NAME = "demo"
HELP = ("write a built-in case as DICOM (the clinical case by default), read it back, plan needles; write plan/"
        "ranking JSON, figures, exports")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Add ``--out``, the case options, the implant options (tip offset, reserve, ``--needles``), ``--quiet``...

    Parameters
    ----------
    parser : argparse.ArgumentParser
        ``reachplan demo``'s parser.
    """
    from reachplan.planner.cli.phantom import add_case_arguments
    from reachplan.planner.cli.plan import add_implant_arguments, add_rtplan_style
    from reachplan.planner.cli.tissue import add_tissue_arguments

    parser.add_argument("--out", type=Path, required=True, help="output folder (created; case in OUT/phantom)")
    add_case_arguments(parser)
    add_implant_arguments(parser)
    add_tissue_arguments(parser)
    parser.add_argument("--protocol", metavar="FILE_OR_NAME", help=PROTOCOL_HELP)
    add_rtplan_style(parser)
    parser.add_argument("--quiet", action="store_true", help="no progress bars or table")
    parser.add_argument("--json", action="store_true", help="print the ranking as JSON on stdout")


def format_blocked(rows: Sequence[BlockedNeedle]) -> str:
    """Return the terminal table of the straight needles that reach their target but collide.

    Parameters
    ----------
    rows : sequence of BlockedNeedle
        :meth:`reachplan.planner.case.result.PlanResult.blocked_straight`.

    Returns
    -------
    str
        One line per blocked needle with its steered alternative.
    """
    if not rows:
        return "no straight needle that reaches a target collides with an organ"
    head = f"{'target':<18} {'straight hole':<16} {'collides with':<24}   steered instead (clean, >= 2 mm)"
    lines = ["straight needles that reach the target but collide:", head, "-" * len(head)]
    for row in rows:
        r, alt = row.straight, row.alternative
        alt_s = "none" if alt is None else (
            f"{alt.hole_id} ({alt.hole_distance_mm:.1f} mm from centre), clearance {alt.clearance_mm:.1f} mm "
            f"({alt.closest_organ}), {alt.peak_tension_n:.1f} N")
        depth = r.contact_depth_mm if r.contact_depth_mm is not None else float("nan")
        lines.append(f"{r.target:<18} {r.hole_id:>4} ({r.hole_distance_mm:4.1f} mm) "
                     f"{r.closest_organ:<10} at {depth:5.1f} mm   {alt_s}")
    return "\n".join(lines)


def run(args: argparse.Namespace) -> int:
    """Write the phantom, read it back and plan it into ``--out``; return the exit code (0).

    Parameters
    ----------
    args : argparse.Namespace
        Parsed ``reachplan demo`` options: ``out``, the case, ``quiet`` and ``json``.

    Returns
    -------
    int
        0: nothing appears in ``--out`` unless the whole demo succeeds (a failure raises).
    """
    from reachplan.planner.dose.protocol import load_protocol

    output_folder(args.out)
    args.aims = load_protocol(args.protocol)  # a bad file or name is an error before any work
    quiet = args.quiet or args.json
    with staged_folder(args.out) as stage:  # nothing appears in --out unless the whole demo succeeds
        doc = _demo(args, stage, quiet)
    if args.json:
        print_json(doc, NAME)
    return 0


def _demo(args: argparse.Namespace, out: Path, quiet: bool) -> dict[str, object]:
    from reachplan.imaging.dicom_io import read_series
    from reachplan.imaging.files import atomic_write_json
    from reachplan.imaging.rtstruct import read_rtstruct
    from reachplan.planner.case.config import PlanConfig
    from reachplan.planner.cli.phantom import write_case
    from reachplan.planner.cli.plan import implant_settings, plan_and_write
    from reachplan.planner.cli.tissue import tissue_options
    from reachplan.planner.kernels import start as start_kernels
    from reachplan.planner.report.progress import MovingBar
    from reachplan.planner.run.case import CaseConfig, CaseInput

    settings = implant_settings(args)  # checked before any work
    t0 = time.perf_counter()
    start_kernels(quiet)  # first run after an install: the rod and dose kernels compile meanwhile, on the other core
    bar = MovingBar(total=2, desc="case: write, read back", unit="step", disable=quiet, leave=False)
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
    targets = tuple(n for n in structures.names if n.casefold().startswith("target"))
    # the clinical case's tandem (an applicator) is an obstacle: a needle must not cross it
    config = PlanConfig(tension_reserve=args.tension_reserve, models=args.models, **tissue_options(args))
    label = ("built-in phantom" if args.case == "pilot"
             else f"built-in clinical case (seed {args.seed}, {args.modality})")
    inputs = CaseInput(structures, volume, (files.ct_dir, files.rtstruct_path), label, builtin=True)
    case_config = CaseConfig(plan=config, target_names=targets, aims=args.aims, rtplan_style=args.rtplan_style,
                             implant_settings=settings)
    case, doc = plan_and_write(inputs, case_config, out, quiet, final_out=args.out,
                               extra={"case": label, "case_about": about,
                                      "phantom_s": {"write": t_write, "read": t_read}})
    atomic_write_json(out / "ranking.json", case.result.ranking_json())
    if not quiet:
        print("\n" + format_blocked(case.result.blocked_straight()))
        print(f"demo finished in {time.perf_counter() - t0:.1f} s")
    return doc
