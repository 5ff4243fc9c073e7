"""``reachplan dose``: recompute a brachy plan with TG-43 (secondary check) and write an RT Dose.

The check itself is :func:`reachplan.planner.run.dose_check.check_plan_dose` (how the source is chosen and its
strength decayed is said there); this module reads the files, calls it, writes the RT Dose and prints.
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import TYPE_CHECKING

from reachplan.planner.cli.edges import (
    PROTOCOL_HELP,
    ArgumentError,
    finite,
    finite_float,
    output_file,
    print_json,
    seen_warnings,
    writing,
)

if TYPE_CHECKING:
    from reachplan.imaging.brachy_plan import RtPlan
    from reachplan.imaging.types import StructureSet
    from reachplan.planner.dose.aims import Aims
    from reachplan.planner.run.dose_check import DoseCheck

NAME = "dose"
HELP = "recompute a brachy RT Plan with TG-43 and write an RT Dose (secondary check of TPS point doses)"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Add the plan, structure set, grid, source, model and output options.

    ``--plan``, ``--structures`` and ``--out`` are required.

    Parameters
    ----------
    parser : argparse.ArgumentParser
        The parser that ``reachplan dose`` options are added to.
    """
    parser.add_argument("--plan", required=True, type=Path, help="brachy RT Plan (RP) file")
    parser.add_argument("--structures", required=True, type=Path, help="RT Structure Set with the channels")
    parser.add_argument("--points", action="store_true", help="report the dose at the plan's dose reference points")
    grid = parser.add_mutually_exclusive_group()
    grid.add_argument("--like", type=Path, help="RT Dose (RD) whose grid to use")
    grid.add_argument("--spacing", type=finite_float, metavar="MM", help="grid spacing in mm (default 2.5)")
    parser.add_argument("--margin", type=finite_float, default=30.0, metavar="MM",
                        help="with --spacing: margin around the dwell positions, mm (default 30)")
    parser.add_argument("--source", help="TG-43 data set when the plan's source is not recognised")
    parser.add_argument("--treatment-date", metavar="YYYYMMDD[HHMMSS]",
                        help="date (and time) of treatment the source strength is decayed to (default: the RT Plan "
                             "Date when it lies within --decay-half-lives after the calibration; otherwise the "
                             "strength is used as written, with a warning)")
    parser.add_argument("--decay-half-lives", type=finite_float, default=2.0, metavar="N",
                        help="decay the strength to the RT Plan Date only up to N half-lives after its reference "
                             "date (default 2; never before it)")
    parser.add_argument("--model", choices=("line", "point"), default="line",
                        help="TG-43 line-source (default) or 1D point-source formalism")
    parser.add_argument("--bits", type=int, choices=(16, 32), default=16,
                        help="RT Dose pixel depth (default 16; dciodvfy cannot read 32-bit RT Dose)")
    parser.add_argument("--protocol", metavar="FILE_OR_NAME",
                        help="also report the plan's dose against each aim of a protocol (target, organs, points; "
                             "implies --points): " + PROTOCOL_HELP.removeprefix("the dose aims: "))
    parser.add_argument("--out", required=True, type=Path, help="RT Dose file to write")
    parser.add_argument("--json", action="store_true",
                        help="print JSON on stdout (with --points the points are under 'points'; warnings met are "
                             "under 'warnings')")


def run(args: argparse.Namespace) -> int:
    """Recompute the plan's dose with TG-43, write the RT Dose and print the point checks.

    Parameters
    ----------
    args : argparse.Namespace
        The parsed ``dose`` arguments.

    Returns
    -------
    int
        The exit status, 0.
    """
    from reachplan.imaging.rtplan import read_rtplan
    from reachplan.imaging.rtstruct import read_rtstruct
    from reachplan.imaging.source_strength import DecayWindow
    from reachplan.planner.lookup import get_source
    from reachplan.planner.run.dose_check import DoseCheckConfig, check_plan_dose
    from reachplan.plugins.exporters.rtdose import read_rtdose_grid, write_rtdose

    # --- arguments and the output place, before any work ---
    output_file(args.out, (args.plan, args.structures, args.like))
    finite(args.spacing, "--spacing", lo=0.1, hi=50.0)
    finite(args.margin, "--margin", lo=0.0, hi=500.0)
    finite(args.decay_half_lives, "--decay-half-lives", lo=0.0, hi=50.0)
    for given, option in ((args.plan, "--plan"), (args.structures, "--structures"), (args.like, "--like")):
        if given is not None and not given.is_file():
            raise ArgumentError(f"{option} {given} is not a file; give the path of the DICOM file")
    if args.source:
        get_source(args.source)  # an unknown name is an error now, not after work
    aims = None
    if args.protocol:
        from reachplan.planner.dose.protocol import load_protocol

        aims = load_protocol(args.protocol)  # a bad file or name is an error now, not after work
        args.points = True
    plan = read_rtplan(args.plan)
    structures = read_rtstruct(args.structures)
    like = read_rtdose_grid(args.like)[1] if args.like is not None else None
    config = DoseCheckConfig(args.source, args.model, 2.5 if args.spacing is None else args.spacing, args.margin,
                             like, args.treatment_date, args.points, DecayWindow(args.decay_half_lives))
    check = check_plan_dose(plan, structures, config, str(args.plan))
    # the only output, written last and atomically (and recorded as reachplan's)
    with writing(args.out, file=True):
        write_rtdose(args.out, check.dose_gy, check.grid, check.context, bits=args.bits, ceiling_gy=check.ceiling_gy)
    aims_doc, aims_text = _aims(plan, structures, check, aims) if aims is not None else (None, "")
    _report(args, check, aims_doc)
    if aims_text and not args.json:
        print(aims_text)
    return 0


def _aims(plan: RtPlan, structures: StructureSet, check: DoseCheck, aims: Aims) -> tuple[dict[str, object], str]:
    """Return ``protocol`` and ``aims`` for the JSON and the aims table as text; the warnings are issued."""
    from reachplan.planner.dose.evaluation import emit, protocol_json
    from reachplan.planner.report.terminal import AIMS_LEGEND, aims_rows, format_rows
    from reachplan.planner.run.dose_aims import plan_dose_aims

    table, notes = plan_dose_aims(plan, structures, check.grid, check.dose_gy, check.checks, aims)
    emit(notes)
    text = "\n".join([f"dose aims: {aims.name} ({aims.site}; {aims.origin}), Gy EQD2 totals with "
                      f"{aims.fractionation.n_fractions} fractions of this plan's fraction dose ({plan.n_fractions} "
                      "planned) and the protocol's external beam", format_rows(aims_rows({"delivered": table})),
                      AIMS_LEGEND.format(headroom=aims.headroom_eqd2_gy)])
    return {"protocol": protocol_json(aims), "aims": table.to_json()}, text


def _report(args: argparse.Namespace, check: DoseCheck, aims_doc: dict[str, object] | None = None) -> None:
    """Print what was computed: one JSON document (``--json``) or lines of text."""
    grid, dose, strength = check.grid, check.dose_gy, check.strength
    if args.json:
        doc: dict[str, object] = {
            "out": str(args.out),
            "source": check.choice.name,
            "source_choice": check.choice.how,
            **strength.to_json(),
            "model": args.model,
            "grid_shape": list(grid.shape),
            "spacing_mm": [float(x) for x in grid.spacing_mm],
            "max_dose_gy": float(dose.max()),
            "n_dwells": check.n_dwells,
        }
        if args.points:
            doc["points"] = [{"name": c.name, "position_mm": [float(x) for x in c.position_mm], "dose_gy": c.dose_gy,
                              "tps_gy": c.tps_gy, "diff_percent": c.diff_percent} for c in check.checks]
        doc.update(aims_doc or {})
        doc["warnings"] = seen_warnings(args)
        print_json(doc, NAME)
        return
    print(f"source {check.choice.how} ({args.model} model)")
    used = (f"{strength.treatment_u:.6g} U on {strength.treatment_date} ({strength.elapsed_days:.3f} d)"
            if strength.decayed else f"used as written (not decayed to {strength.treatment_date}: see the warning)")
    print(f"S_K {strength.reference_u:.6g} U on {strength.reference_date or 'no date'}, {used}; {check.n_dwells} "
          f"dwells, {check.fractions}")
    print(f"wrote {args.out}: grid {grid.shape} (k, j, i), max {float(dose.max()):.3f} Gy")
    for c in check.checks:
        tps = "-" if c.tps_gy is None else f"{c.tps_gy:.4f}"
        diff = "-" if c.diff_percent is None else f"{c.diff_percent:+.3f} %"
        print(f"  {c.name:<20} ours {c.dose_gy:.4f} Gy  planned {tps} Gy  {diff}")
