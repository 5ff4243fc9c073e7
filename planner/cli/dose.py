"""``reachplan dose``: recompute a brachy plan with TG-43 (secondary check) and write an RT Dose.

The source data set is the one recognised from the plan (Source Isotope Name, treatment machine), else
``--source``. S_K is the plan's Reference Air Kerma Rate as written (no decay), dwell times follow the
Eclipse conventions (see :mod:`reachplan.imaging.rtplan`), doses are totals over fractions and pulses.
"""

from __future__ import annotations

import argparse
import json
import sys
import warnings
from pathlib import Path

NAME = "dose"
HELP = "recompute a brachy RT Plan with TG-43 and write an RT Dose (secondary check of TPS point doses)"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--plan", required=True, type=Path, help="brachy RT Plan (RP) file")
    parser.add_argument("--structures", required=True, type=Path, help="RT Structure Set with the channels")
    parser.add_argument("--points", action="store_true", help="report the dose at the plan's dose reference points")
    grid = parser.add_mutually_exclusive_group()
    grid.add_argument("--like", type=Path, help="RT Dose (RD) whose grid to use")
    grid.add_argument("--spacing", type=float, metavar="MM", help="grid spacing in mm (default 2.5)")
    parser.add_argument("--margin", type=float, default=30.0, metavar="MM",
                        help="with --spacing: margin around the dwell positions, mm (default 30)")
    parser.add_argument("--source", help="TG-43 data set when the plan's source is not recognised")
    parser.add_argument("--model", choices=("line", "point"), default="line",
                        help="TG-43 line-source (default) or 1D point-source formalism")
    parser.add_argument("--bits", type=int, choices=(16, 32), default=16,
                        help="RT Dose pixel depth (default 16; dciodvfy cannot read 32-bit RT Dose)")
    parser.add_argument("--out", required=True, type=Path, help="RT Dose file to write")
    parser.add_argument("--json", action="store_true", help="print JSON on stdout")


def run(args: argparse.Namespace) -> int:
    import numpy as np

    from reachplan.imaging.rtplan import channel_paths, read_rtplan
    from reachplan.imaging.rtstruct import read_rtstruct
    from reachplan.imaging.types import Grid
    from reachplan.planner.dose.tg43 import Tg43Kernel, check_points, dose_on_grid, plan_dwells
    from reachplan.planner.errors import PlanInputError
    from reachplan.planner.pipeline import get_source, recognise_source
    from reachplan.plugins.exporters.rtdose import DoseContext, read_rtdose_grid, write_rtdose

    out = args.out.resolve()
    for given in (args.plan, args.structures, args.like):
        if given is not None and given.exists() and given.resolve() == out:
            raise PlanInputError(f"--out {args.out} is one of the inputs; choose another output file")
    if args.spacing is not None and not (0.1 <= args.spacing <= 50.0):
        raise PlanInputError(f"--spacing must be between 0.1 and 50 mm, got {args.spacing}")
    if not (0.0 <= args.margin <= 500.0):
        raise PlanInputError(f"--margin must be between 0 and 500 mm, got {args.margin}")

    plan = read_rtplan(args.plan)
    if not plan.is_brachy or not plan.channels:
        raise PlanInputError(f"{args.plan} is not a brachytherapy plan with channels; pass a brachy RT Plan")
    structures = read_rtstruct(args.structures)
    src = plan.source(plan.channels[0].source_number)
    if src.air_kerma_rate_u <= 0:
        raise PlanInputError(f"{args.plan}: the source has no Reference Air Kerma Rate; cannot compute dose")
    recognised = recognise_source(*src.labels(), plan.machine_name)
    name = recognised or args.source
    if name is None:
        raise PlanInputError(
            f"cannot recognise the source {src.isotope_name!r} of {args.plan.name}; pass --source NAME "
            "(see `reachplan plugins`)"
        )
    if recognised and args.source and args.source != recognised:
        warnings.warn(f"the plan's source is {recognised}; --source {args.source} ignored", stacklevel=1)
    data = get_source(name)
    if src.active_length_mm and abs(src.active_length_mm - 10 * data.active_length_cm) > 0.01:
        warnings.warn(
            f"the plan's active length {src.active_length_mm} mm differs from {name}'s "
            f"{10 * data.active_length_cm} mm",
            stacklevel=1,
        )
    kernel = Tg43Kernel(data, args.model)
    dwells = plan_dwells(plan, channel_paths(plan, structures))

    if args.like is not None:
        _, grid = read_rtdose_grid(args.like)
    else:
        spacing = 2.5 if args.spacing is None else args.spacing
        lo = dwells.positions_mm.min(axis=0) - args.margin
        hi = dwells.positions_mm.max(axis=0) + args.margin
        n = np.floor((hi - lo) / spacing).astype(int) + 1
        affine = np.diag([spacing, spacing, spacing, 1.0])
        affine[:3, 3] = lo
        grid = Grid((int(n[2]), int(n[1]), int(n[0])), affine)
    if int(np.prod(grid.shape)) > 60_000_000:
        raise PlanInputError(f"the dose grid {grid.shape} is too large; use a coarser --spacing")
    dose = dose_on_grid(grid, dwells, kernel, src.air_kerma_rate_u)
    for_uid = plan.frame_of_reference_uid or structures.frame_of_reference_uid
    if not for_uid:
        raise PlanInputError("neither the plan nor the structure set gives a Frame of Reference UID")
    context = DoseContext(
        frame_of_reference_uid=for_uid,
        study_instance_uid=plan.study_instance_uid,
        patient_id=plan.patient_id,
        patient_name=plan.patient_name,
        referenced_plan_uid=plan.sop_instance_uid,
    )
    write_rtdose(args.out, dose, grid, context, bits=args.bits)

    checks = check_points(plan, dwells, kernel, src.air_kerma_rate_u) if args.points else ()
    if args.json:
        if args.points:
            doc: object = [
                {
                    "name": c.name,
                    "position_mm": [float(x) for x in c.position_mm],
                    "dose_gy": c.dose_gy,
                    "tps_gy": c.tps_gy,
                    "diff_percent": c.diff_percent,
                }
                for c in checks
            ]
        else:
            doc = {
                "out": str(args.out),
                "source": name,
                "model": args.model,
                "grid_shape": list(grid.shape),
                "spacing_mm": [float(x) for x in grid.spacing_mm],
                "max_dose_gy": float(dose.max()),
                "n_dwells": len(dwells),
            }
        json.dump(doc, sys.stdout, indent=2)
        print()
        return 0
    print(f"source {name} ({args.model}), S_K {src.air_kerma_rate_u} U, {len(dwells)} dwells, "
          f"{plan.n_fractions} fraction(s) x {plan.n_pulses} pulse(s)")
    print(f"wrote {args.out}: grid {grid.shape} (k, j, i), max {float(dose.max()):.3f} Gy")
    for c in checks:
        tps = "-" if c.tps_gy is None else f"{c.tps_gy:.4f}"
        diff = "-" if c.diff_percent is None else f"{c.diff_percent:+.3f} %"
        print(f"  {c.name:<20} ours {c.dose_gy:.4f} Gy  TPS {tps} Gy  {diff}")
    return 0
