"""``reachplan inspect PATH [--json]``: what is in a DICOM file or folder (series, structures, plans)."""

from __future__ import annotations

import argparse
from pathlib import Path

from reachplan.planner.cli.edges import print_json

NAME = "inspect"
HELP = "list the image series, structure sets (with volumes) and brachy plans in a DICOM file or folder"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Add the path, ``--json`` and ``--synonyms``.

    Only the path is required.

    Parameters
    ----------
    parser : argparse.ArgumentParser
        Parser of the ``reachplan inspect`` sub-command.
    """
    parser.add_argument("path", type=Path, help="a DICOM file or a folder (searched recursively)")
    parser.add_argument("--json", action="store_true", help="print one JSON document on stdout")
    parser.add_argument("--synonyms", type=Path, default=None,
                        help="CSV file with 'standard,synonym' rows added to the built-in ROI name table")


def run(args: argparse.Namespace) -> int:
    """Print what the DICOM file or folder holds (text or JSON); return 0.

    Parameters
    ----------
    args : argparse.Namespace
        ``path``, ``json`` and ``synonyms`` (a CSV of extra ROI names).

    Returns
    -------
    int
        Always 0; a file that cannot be read raises.
    """
    from reachplan.imaging.inspect import inspect_path
    from reachplan.imaging.names import SynonymTable
    from reachplan.planner.dose.plan_usable import usable_problems

    synonyms = SynonymTable.from_csv(args.synonyms) if args.synonyms else None
    result = inspect_path(args.path, synonyms, plan_check=usable_problems)  # dose's and plan's check, as warnings
    if args.json:
        print_json(result.to_json(), NAME)
        return 0
    out: list[str] = []
    for s in result.series:
        nk, nj, ni = s.shape
        dx, dy, dz = s.spacing_mm
        out.append(f"series {s.modality} {ni}x{nj}x{nk} voxels, {dx:g} x {dy:g} x {dz:g} mm, {s.n_files} files, "
                   f"{s.description or '-'}  ({s.series_instance_uid})")
    for ss in result.structure_sets:
        out.append(f"structure set {ss.label or '-'} ({ss.path}), {len(ss.structures)} ROIs")
        for r in ss.structures:
            vol = f"{r.volume_cc:10.2f} cc" if r.volume_cc is not None else " " * 13
            alias = f" -> {r.normalized_name}" if r.normalized_name != r.name else ""
            out.append(f"  {r.number:4d} {r.name + alias:32s} {r.type or '-':15s} {vol}  "
                       f"{r.n_contours} contours {'/'.join(r.geometric_types)}")
    for p in result.plans:
        out.append(f"plan {p.type or '-'} {p.technique or '-'} source {p.source or '-'} ({p.path}) {p.note}")
        rx = f"{p.prescription_gy:g} Gy per fraction" if p.prescription_gy is not None else "no prescription"
        out.append(f"  machine {p.machine or '-'}; {rx}{' to ' + p.target if p.target else ''}; "
                   f"{p.fractions} fraction(s); {len(p.channels)} channels, {sum(c.n_dwells for c in p.channels)} "
                   "dwells")
        if p.strength:
            out.append(f"  {p.strength}")
        for name, dose in p.points:
            out.append(f"  point {name}: {'-' if dose is None else f'{dose:.3f} Gy'} (plan, all fractions)")
        for c in p.channels:
            out.append(f"  channel {c.channel_number:3d}: {c.n_dwells:3d} dwells, {c.total_time_s:8.1f} s, "
                       f"ROI {c.roi_number if c.roi_number is not None else '-'}")
    for o in result.others:
        out.append(f"other {o.modality or '-'} ({o.path})")
    out += [f"warning: {w}" for w in result.warnings]
    if result.n_non_dicom:
        out.append(f"{result.n_non_dicom} non-DICOM files ignored")
    print("\n".join(out))
    return 0
