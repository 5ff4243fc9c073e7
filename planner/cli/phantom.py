"""``reachplan phantom --out DIR``: write a built-in case as DICOM (image series + RT Structure Set)."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from reachplan.planner.cli.edges import output_folder, print_json, writing

NAME = "phantom"
HELP = "write a built-in case (clinical by default, or the pilot phantom) as DICOM: image series + RT Structure Set"


def add_case_arguments(parser: argparse.ArgumentParser) -> None:
    """Add ``--case``, ``--seed`` and ``--modality`` (shared with ``demo``).

    Parameters
    ----------
    parser : argparse.ArgumentParser
        The ``phantom`` or ``demo`` parser.
    """
    parser.add_argument("--case", choices=("clinical", "pilot"), default="clinical",
                        help="clinical: a cervix-cancer pelvis where organs stand in the way (default); pilot: the "
                             "OncoReach pilot phantom (SimuGel, target cylinders)")
    parser.add_argument("--seed", type=int, default=0,
                        help="clinical case: anatomical variation (0 = the reference case; deterministic)")
    parser.add_argument("--modality", choices=("CT", "MR"), default="CT",
                        help="clinical case: write a CT series or a T2-weighted-like MR series")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Add ``--out`` and ``--json``.

    Parameters
    ----------
    parser : argparse.ArgumentParser
        Parser of ``reachplan phantom`` (the case options join them).
    """
    parser.add_argument("--out", type=Path, required=True,
                        help="output folder (images in OUT/CT or OUT/MR, structures in OUT/RS.phantom.dcm)")
    add_case_arguments(parser)
    parser.add_argument("--json", action="store_true", help="print the written paths and the analytic volumes as JSON")


def write_case(args: argparse.Namespace, out: Path) -> tuple[Any, Any, dict[str, object]]:
    """Write the case the arguments ask for to ``out``.

    Parameters
    ----------
    args : argparse.Namespace
        ``case`` (``clinical`` or ``pilot``), ``seed`` and ``modality``.
    out : Path
        The folder to write the image series and structure set into.

    Returns
    -------
    files : PhantomFiles
        The image series folder and the structure set file.
    spec : PhantomSpec
        The phantom written (structures, geometry in LPS mm).
    about : dict of str to object
        The case's description for JSON (the clinical case's parameters and targets).

    Raises
    ------
    PlanInputError
        ``--seed`` or ``--modality`` given for the pilot phantom, or a negative seed.
    """
    from reachplan.planner.errors import PlanInputError

    if args.case == "pilot":
        from reachplan.imaging.phantom import phantom_spec, write_phantom

        if args.seed != 0 or args.modality != "CT":
            raise PlanInputError("--seed and --modality apply to the clinical case; the pilot phantom is one CT")
        spec = phantom_spec()
        return write_phantom(out, spec), spec, {"case": "pilot"}
    from reachplan.imaging.clinical import clinical_case, write_clinical

    if args.seed < 0:
        raise PlanInputError(f"--seed must be >= 0, got {args.seed}")
    case = clinical_case(args.seed, modality=args.modality)
    return write_clinical(out, case), case.spec, case.to_json()


def run(args: argparse.Namespace) -> int:
    """Write the built-in case as DICOM and print what was written; return 0.

    Parameters
    ----------
    args : argparse.Namespace
        ``out``, the case options and ``json``.

    Returns
    -------
    int
        0 once the files are written.
    """
    output_folder(args.out)
    with writing(args.out):  # a full disk or a read-only place: a typed error; nothing new is left
        files, spec, about = write_case(args, args.out)
    if args.json:
        doc = {
            **about,
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
        print(f"wrote {spec.n_slices} {spec.modality} slices to {files.ct_dir} and {len(spec.structures)} ROIs to "
              f"{files.rtstruct_path}")
    return 0
