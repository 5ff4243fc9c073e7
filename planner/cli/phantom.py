"""``reachplan phantom --out DIR``: write the built-in pelvic phantom as DICOM (CT series + RT Structure Set)."""

from __future__ import annotations

import argparse
from pathlib import Path

from reachplan.planner.cli.edges import output_folder, print_json

NAME = "phantom"
HELP = "write the built-in pelvic phantom (CT series + RT Structure Set) as DICOM"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Add ``--out`` and ``--json``."""
    parser.add_argument("--out", type=Path, required=True,
                        help="output folder (CT in OUT/CT, structures in OUT/RS.phantom.dcm)")
    parser.add_argument("--json", action="store_true", help="print the written paths and the analytic volumes as JSON")


def run(args: argparse.Namespace) -> int:
    """Write the built-in phantom as DICOM and print what was written; return 0."""
    from reachplan.imaging.phantom import phantom_spec, write_phantom

    output_folder(args.out)
    spec = phantom_spec()
    files = write_phantom(args.out, spec)
    if args.json:
        doc = {
            "ct_dir": str(files.ct_dir),
            "rtstruct_path": str(files.rtstruct_path),
            "structures": [
                {"name": s.name, "type": s.interpreted_type, "primitive": s.primitive,
                 "analytic_volume_cc": s.analytic_volume_mm3 / 1000.0, "is_oar": s.is_oar}
                for s in spec.structures
            ],
            "patient_from_template": spec.patient_from_template.tolist(),
        }
        print_json(doc, NAME)
    else:
        print(f"wrote {spec.n_slices} CT slices to {files.ct_dir} and {len(spec.structures)} ROIs to "
              f"{files.rtstruct_path}")
    return 0
