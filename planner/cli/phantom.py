"""``reachplan phantom --out DIR``: write a built-in case as DICOM (image series + RT Structure Set)."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from reachplan.planner.cli.edges import finite_float, output_folder, print_json, writing

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
    post = parser.add_argument_group(
        "post-insertion image", "the case a plan was made on, imaged with the plan's needles in, each drawn off its "
        "plan by the planner's uncertainty model; the truth in OUT/needles_truth.json")
    post.add_argument("--implanted", type=Path, metavar="PLAN_JSON",
                      help="a plan.json of the clinical case (demo, or plan on its files): image its delivered implant")
    post.add_argument("--extra-needles", type=int, default=2, metavar="N",
                      help="straight needles added through free holes (default 2)")
    post.add_argument("--extra-steered", type=int, default=0, metavar="N",
                      help="steered needles added besides the implant: the plan's ranked steered candidates through "
                           "free holes, as a clinician inserting the report's alternatives would (default 0)")
    post.add_argument("--needle-content", choices=("metal", "air", "fluid"), default="metal",
                      help="what fills the needles: the metal obturator or stylet (default), or an empty (air) or "
                           "water-filled lumen")
    post.add_argument("--draw-seed", type=int, default=0,
                      help="seed of the needles' deviations and the image noise (default 0)")
    post.add_argument("--curvature-scale", type=finite_float, default=1.0, metavar="RATIO",
                      help="the tissue bends each steered needle RATIO times as much as the plan's model (its "
                           "departure from its hole's axis scaled; default 1): a tissue for 'reachplan calibrate'")
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
    output_folder(args.out, [args.implanted])
    if args.implanted is not None:
        return _run_implanted(args)
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


def _run_implanted(args: argparse.Namespace) -> int:
    """``--implanted``: write the post-insertion image of a plan's case and its truth; return 0."""
    from reachplan.imaging.files import json_bytes
    from reachplan.imaging.phantom import write_phantom
    from reachplan.planner.errors import PlanInputError
    from reachplan.planner.steering.calibration import RATIO_RANGE
    from reachplan.planner.verify.implant import implanted_case

    if args.case != "clinical" or min(args.extra_needles, args.extra_steered, args.draw_seed) < 0:
        raise PlanInputError("--implanted images the clinical case; --extra-needles, --extra-steered and --draw-seed "
                             "must be >= 0")
    lo, hi = RATIO_RANGE
    if not lo <= args.curvature_scale <= hi:
        raise PlanInputError(f"--curvature-scale must be a ratio in [{lo:g}, {hi:g}], got {args.curvature_scale:g}")
    post = implanted_case(args.implanted, args.modality, args.extra_needles, args.needle_content, args.draw_seed,
                          args.seed, args.curvature_scale, args.extra_steered)
    with writing(args.out):
        files = write_phantom(args.out, post.spec, beside={"needles_truth.json": json_bytes(post.truth)},
                              values=post.image)
    doc = {"ct_dir": str(files.ct_dir), "rtstruct_path": str(files.rtstruct_path),
           "truth_path": str(args.out / "needles_truth.json"), "modality": post.spec.modality,
           "needles": [d.needle.hole_id for d in post.drawn]}
    if args.json:
        print_json(doc, NAME)
    elif not args.quiet:
        print(f"wrote {post.spec.n_slices} post-insertion {post.spec.modality} slices with {len(post.drawn)} needles "
              f"({', '.join(doc['needles'])}) to {files.ct_dir}; the truth in {doc['truth_path']}")
    return 0
