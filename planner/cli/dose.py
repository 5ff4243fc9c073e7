"""``reachplan dose``: recompute a brachy plan with TG-43 (secondary check) and write an RT Dose.

The source data set is the one named in the plan (Source Model ID, Isotope Name, manufacturer, treatment
machine) when its isotope, kind and active length agree; for an anonymised plan the only registered one of the
plan's isotope (named or told by the half-life), treatment type and active length (see
:func:`reachplan.plugins.sources.identify.identify_source`); else ``--source``. S_K is the plan's Reference Air Kerma
Rate decayed from its reference date to the treatment date: ``--treatment-date``, else the RT Plan Date (whole
days; Eclipse dates the strength to the plan day at midnight, rtplan_conventions.md §5). Dwell times follow the
Eclipse conventions (see :mod:`reachplan.imaging.rtplan`), doses are totals over fractions and pulses.
"""

from __future__ import annotations

import argparse
from datetime import datetime
from pathlib import Path
from typing import TYPE_CHECKING, Any

from reachplan.planner.cli.edges import ArgumentError, finite, finite_float, output_file, print_json, seen_warnings

if TYPE_CHECKING:
    from collections.abc import Sequence

    import numpy as np

    from reachplan.imaging.rtplan import BrachySource, RtPlan
    from reachplan.imaging.types import Grid
    from reachplan.planner.dose.plan_check import PointCheck
    from reachplan.plugins.sources.identify import SourceChoice

NAME = "dose"
HELP = "recompute a brachy RT Plan with TG-43 and write an RT Dose (secondary check of TPS point doses)"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Add the plan, structure set, grid, source, model and output options.

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
                        help="date (and time) of treatment the source strength is decayed to (default: RT Plan Date)")
    parser.add_argument("--model", choices=("line", "point"), default="line",
                        help="TG-43 line-source (default) or 1D point-source formalism")
    parser.add_argument("--bits", type=int, choices=(16, 32), default=16,
                        help="RT Dose pixel depth (default 16; dciodvfy cannot read 32-bit RT Dose)")
    parser.add_argument("--out", required=True, type=Path, help="RT Dose file to write")
    parser.add_argument("--json", action="store_true",
                        help="print JSON on stdout (with --points the points are under 'points'; warnings met are "
                             "under 'warnings')")


def run(args: argparse.Namespace) -> int:
    """Recompute the plan's dose with TG-43, write the RT Dose and print the point checks; return 0.

    Parameters
    ----------
    args : argparse.Namespace
        Parsed options: plan and structure set files, the grid (``like`` or ``spacing`` and ``margin``), the
        source, the treatment date and the output.

    Returns
    -------
    int
        0 (an error raises).
    """
    import numpy as np

    from reachplan.imaging.rtplan import channel_paths, read_rtplan
    from reachplan.imaging.rtstruct import read_rtstruct
    from reachplan.planner.dose.dwells import dose_on_grid, plan_dwells
    from reachplan.planner.dose.plan_check import check_isotope, check_points
    from reachplan.planner.dose.tg43 import Tg43Kernel
    from reachplan.planner.errors import PlanInputError
    from reachplan.planner.lookup import get_source
    from reachplan.plugins.errors import SourceMatchError
    from reachplan.plugins.exporters.rtdose import (
        CEILING_TIMES_PRESCRIPTION,
        DoseContext,
        write_rtdose,
    )

    # --- arguments and the output place, before any work ---
    output_file(args.out, (args.plan, args.structures, args.like))
    finite(args.spacing, "--spacing", lo=0.1, hi=50.0)
    finite(args.margin, "--margin", lo=0.0, hi=500.0)
    for given, option in ((args.plan, "--plan"), (args.structures, "--structures"), (args.like, "--like")):
        if given is not None and not given.is_file():
            raise ArgumentError(f"{option} {given} is not a file; give the path of the DICOM file")
    chosen = get_source(args.source) if args.source else None  # an unknown name is an error now, not after work

    plan = read_rtplan(args.plan)
    if not plan.is_brachy or not plan.channels:
        raise PlanInputError(f"{args.plan} is not a brachytherapy plan with channels; pass a brachy RT Plan")
    structures = read_rtstruct(args.structures)
    src = plan.source(plan.channels[0].source_number)
    if src.air_kerma_rate_u <= 0:
        raise PlanInputError(f"{args.plan}: the source has no Reference Air Kerma Rate; cannot compute dose")
    try:
        choice = _choose_source(plan, src, args.source)
    except (PlanInputError, SourceMatchError) as exc:
        raise PlanInputError(f"{args.plan}: {exc}") from None
    data = chosen if chosen is not None and choice.name == args.source else get_source(choice.name)
    check_isotope(src, data, str(args.plan))
    sk_u, decay = _decayed_strength(plan, src, args.treatment_date)
    kernel = Tg43Kernel(data, args.model)
    dwells = plan_dwells(plan, channel_paths(plan, structures))
    if not len(dwells):
        raise PlanInputError(f"{args.plan}: the plan has no dwell positions; there is no dose to compute")

    grid = _dose_grid(args, dwells.positions_mm)
    for_uid = plan.frame_of_reference_uid or structures.frame_of_reference_uid
    if not for_uid:
        raise PlanInputError("neither the plan nor the structure set gives a Frame of Reference UID")
    dose = dose_on_grid(grid, dwells, kernel, sk_u)
    if not np.all(np.isfinite(dose)):
        raise PlanInputError(f"{args.plan}: the dose is not finite on the grid (a dwell time or strength out of "
                             "range); check the plan's times and source")
    checks = check_points(plan, dwells, kernel, sk_u) if args.points else ()
    context = DoseContext(
        frame_of_reference_uid=for_uid,
        patient_study=plan.patient_study,
        referenced_plan_uid=plan.sop_instance_uid,
    )
    setup = max((d for _, d in plan.setup_doses_gy), default=0.0) * plan.n_fractions * plan.n_pulses
    # the only output, written last and atomically
    write_rtdose(args.out, dose, grid, context, bits=args.bits,
                 ceiling_gy=CEILING_TIMES_PRESCRIPTION * setup if setup > 0 else None)

    _report(args, choice, decay, grid, dose, len(dwells), checks, f"{plan.n_fractions} fraction(s) x "
            f"{plan.n_pulses} pulse(s)", sk_u)
    return 0


def _dose_grid(args: argparse.Namespace, positions_mm: np.ndarray) -> Grid:
    """Return the dose grid: ``--like``'s, else ``--spacing`` around the dwells with ``--margin`` (mm, LPS)."""
    import numpy as np

    from reachplan.imaging.types import Grid
    from reachplan.planner.errors import PlanInputError
    from reachplan.plugins.exporters.rtdose import read_rtdose_grid

    if args.like is not None:
        _, grid = read_rtdose_grid(args.like)
    else:
        spacing = 2.5 if args.spacing is None else args.spacing
        lo = positions_mm.min(axis=0) - args.margin
        hi = positions_mm.max(axis=0) + args.margin
        n = np.floor((hi - lo) / spacing).astype(int) + 1
        affine = np.diag([spacing, spacing, spacing, 1.0])
        affine[:3, 3] = lo
        grid = Grid((int(n[2]), int(n[1]), int(n[0])), affine)
    if int(np.prod(grid.shape)) > 60_000_000:
        raise PlanInputError(f"the dose grid {grid.shape} is too large; use a coarser --spacing")
    grid_out: Grid = grid
    return grid_out


def _report(args: argparse.Namespace, choice: SourceChoice, decay: dict[str, Any], grid: Grid, dose: np.ndarray,
            n_dwells: int, checks: Sequence[PointCheck], fractions: str, sk_u: float) -> None:
    """Print what was computed: one JSON document (``--json``) or lines of text."""
    if args.json:
        doc: dict[str, object] = {
            "out": str(args.out),
            "source": choice.name,
            "source_choice": choice.how,
            **decay,
            "model": args.model,
            "grid_shape": list(grid.shape),
            "spacing_mm": [float(x) for x in grid.spacing_mm],
            "max_dose_gy": float(dose.max()),
            "n_dwells": n_dwells,
        }
        if args.points:
            doc["points"] = [{"name": c.name, "position_mm": [float(x) for x in c.position_mm], "dose_gy": c.dose_gy,
                              "tps_gy": c.tps_gy, "diff_percent": c.diff_percent} for c in checks]
        doc["warnings"] = seen_warnings(args)
        print_json(doc, NAME)
        return
    print(f"source {choice.how} ({args.model} model)")
    print(f"S_K {decay['air_kerma_reference_u']:.6g} U on {decay['reference_date']}, {sk_u:.6g} U on "
          f"{decay['treatment_date']} ({decay['elapsed_days']:.3f} d); {n_dwells} dwells, {fractions}")
    print(f"wrote {args.out}: grid {grid.shape} (k, j, i), max {float(dose.max()):.3f} Gy")
    for c in checks:
        tps = "-" if c.tps_gy is None else f"{c.tps_gy:.4f}"
        diff = "-" if c.diff_percent is None else f"{c.diff_percent:+.3f} %"
        print(f"  {c.name:<20} ours {c.dose_gy:.4f} Gy  planned {tps} Gy  {diff}")


def _choose_source(plan: RtPlan, src: BrachySource, given: str | None) -> SourceChoice:
    """Return the TG-43 data set: ``--source`` (checked against the plan's isotope) or identified from the plan."""
    from reachplan.planner.errors import PlanInputError
    from reachplan.planner.lookup import all_sources, get_source
    from reachplan.plugins.sources.identify import PlanSource, SourceChoice, identify_source, plan_isotope

    if given:
        data = get_source(given)
        isotope = plan_isotope(src.isotope_name, src.half_life_days)
        if isotope is not None and isotope != data.isotope:
            raise PlanInputError(f"--source {given} is {data.isotope} but the plan's source is {isotope}; "
                                 "choose a data set of that isotope")
        return SourceChoice(given, f"{given}: given with --source")
    return identify_source(all_sources(), PlanSource(src.model_id, src.isotope_name, src.manufacturer,
                                                     plan.treatment_type, src.half_life_days, src.active_length_mm,
                                                     plan.machine_name))


def _parse_date(text: str, what: str) -> datetime:
    from reachplan.planner.errors import PlanInputError

    digits = text.strip().split(".")[0]
    fmt = {8: "%Y%m%d", 10: "%Y%m%d%H", 12: "%Y%m%d%H%M", 14: "%Y%m%d%H%M%S"}.get(len(digits))
    if fmt is not None and digits.isdigit():
        try:
            return datetime.strptime(digits, fmt)
        except ValueError:
            pass
    raise PlanInputError(f"{what} {text!r} is not a date YYYYMMDD[HHMMSS]")


def _decayed_strength(plan: RtPlan, src: BrachySource, treatment: str | None) -> tuple[float, dict[str, Any]]:
    """Return S_K (U) at the treatment date and what was used (reference and treatment dates, elapsed days, S_K)."""
    from reachplan.planner.errors import PlanInputError
    from reachplan.plugins.sources.identify import decay_factor

    info: dict[str, Any] = {"air_kerma_reference_u": src.air_kerma_rate_u, "reference_date": src.reference_date,
                            "treatment_date": "", "elapsed_days": 0.0}
    if not src.reference_date:
        info["treatment_date"] = "unknown (no Source Strength Reference Date: not decayed)"
        info["air_kerma_treatment_u"] = src.air_kerma_rate_u
        return src.air_kerma_rate_u, info
    ref = _parse_date(src.reference_date + (src.reference_time or ""), "Source Strength Reference Date")
    if treatment:
        when = _parse_date(treatment, "--treatment-date")
        elapsed = (when - ref).total_seconds() / 86400.0
        info["treatment_date"] = treatment
    elif plan.plan_date:
        day = _parse_date(plan.plan_date, "RT Plan Date")
        elapsed = float((day.date() - ref.date()).days)
        info["treatment_date"] = f"{plan.plan_date} (RT Plan Date)"
    else:
        elapsed = 0.0
        info["treatment_date"] = f"{src.reference_date} (no RT Plan Date: not decayed)"
    if src.half_life_days is None or src.half_life_days <= 0:
        if elapsed != 0.0:
            raise PlanInputError("the plan's source has no half-life; cannot decay its strength to the treatment "
                                 "date (pass --treatment-date equal to the reference date to use it as written)")
        factor = 1.0
    else:
        factor = decay_factor(src.half_life_days, elapsed)
    info["reference_date"] = f"{src.reference_date} {src.reference_time}".strip()
    info["elapsed_days"] = elapsed
    info["air_kerma_treatment_u"] = src.air_kerma_rate_u * factor
    return src.air_kerma_rate_u * factor, info
