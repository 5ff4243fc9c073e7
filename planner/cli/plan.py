"""``reachplan plan``: plan straight and steered needles for a case's targets and export the plan."""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING

from reachplan.planner.cli.edges import (
    PROTOCOL_HELP,
    applicator_assignments,
    finite,
    finite_float,
    output_folder,
    print_json,
    seen_warnings,
    staged_folder,
)
from reachplan.planner.cli.points import check_targets_inside, parse_point
from reachplan.planner.cli.tissue import add_tissue_arguments, tissue_options
from reachplan.planner.errors import PlanInputError

if TYPE_CHECKING:  # the run-time imports are inside the functions: start-up of every command stays light
    from collections.abc import Callable

    import numpy as np

    from reachplan.imaging.names import SynonymTable
    from reachplan.imaging.types import StructureSet
    from reachplan.planner.case.config import PlanConfig
    from reachplan.planner.case.scene import Scene
    from reachplan.planner.geometry.template import TemplatePose
    from reachplan.planner.implant.settings import ImplantSettings
    from reachplan.planner.run.case import CaseConfig, CaseInput, CaseResult
    from reachplan.planner.steering.candidates import Target

NAME = "plan"
HELP = "rank template holes, stylet designs and tension schedules for targets; write plan.json, figures, exports"


def add_needles_argument(parser: argparse.ArgumentParser) -> None:
    """Add ``--needles K``: the implant's needle count, a point on each arm's Pareto curve.

    Parameters
    ----------
    parser : argparse.ArgumentParser
        The command's parser (``plan`` or ``demo``).
    """
    parser.add_argument("--needles", type=_needle_count, default=None, metavar="K",
                        help="implant needles: the point of each arm's Pareto curve with K needles (default: the "
                             "fewest that meet every aim with headroom and keep the hard limits with any needle 2 mm "
                             "off)")


def _needle_count(text: str) -> int:
    """Return ``--needles``'s value: an integer >= 0 (an argparse type; a bad value is a usage error)."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"--needles needs a whole number of needles, not {text!r}") from None
    if value < 0:
        raise argparse.ArgumentTypeError(f"--needles must be >= 0, not {value}")
    return value


def add_pose_arguments(parser: argparse.ArgumentParser) -> None:
    """Add ``--template`` and the template pose options (shared with ``reconstruct``).

    Parameters
    ----------
    parser : argparse.ArgumentParser
        The command's parser.
    """
    parser.add_argument("--template", default="needlefinder_syed_63", help="template plugin name")
    pose = parser.add_argument_group(
        "template pose", "where the template sits; without these it is fitted to the Obturator (vaginal cylinder) "
        "ROI. Template +x is the patient's left made perpendicular to the axis (posterior when the axis is "
        "within 10 degrees of left-right)")
    pose.add_argument("--template-origin", metavar="X,Y,Z",
                      help="template centre (the obturator axis on the template plane), mm, LPS")
    pose.add_argument("--template-axis", metavar="X,Y,Z", help="insertion direction (LPS, any length)")
    pose.add_argument("--template-pose", type=Path, metavar="FILE",
                      help="rigid 4x4 patient_from_template (mm, LPS): JSON (a 4x4 list, or an object with "
                           "'patient_from_template', e.g. a previous plan.json's 'template_pose') or 4 text rows")
    pose.add_argument("--rtplan", type=Path, metavar="FILE",
                      help="brachy RT Plan of the same Frame of Reference: the template is placed on its "
                           "obturator or tandem channel")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Add the ``plan`` options to ``parser``.

    ``--rtstruct`` and ``--targets`` are required; ``--ct`` is optional (contours suffice).

    Parameters
    ----------
    parser : argparse.ArgumentParser
        The ``plan`` sub-command's parser: inputs, targets, template pose, organs, applicators, designs, dose and
        output options.
    """
    parser.add_argument("--ct", type=Path, help="CT/MR series folder (optional: organs from contours suffice)")
    parser.add_argument("--series-uid", metavar="UID",
                        help="with --ct: the SeriesInstanceUID to read when the folder holds several series")
    parser.add_argument("--rtstruct", type=Path, required=True, help="RT Structure Set file")
    parser.add_argument("--targets", "--target", nargs="+", required=True, metavar="ROI_OR_POINT",
                        help="target ROI names, or points 'x,y,z' in mm (DICOM patient coordinates, LPS; a point "
                             "may start with a minus sign: --targets -20,0,90); an ROI of POINT contours is planned "
                             "to its points; a point must lie inside the images and the body contour")
    parser.add_argument("--allow-outside-body", action="store_true",
                        help="plan target points that lie outside the image volume or the body contour")
    add_pose_arguments(parser)
    parser.add_argument("--oar", action="append", default=[], metavar="ORGAN=ROI_NAME",
                        help="use ROI_NAME as organ at risk ORGAN (e.g. Rectum=Rect_PRV); repeatable; an ORGAN "
                             "outside the default list (Bladder, Rectum, Sigmoid, Bowel, Bone) is added to it")
    parser.add_argument("--applicator", action="append", default=[], metavar="KIND=ROI_NAME",
                        help="treat ROI_NAME as an applicator of KIND (tandem, ring, ovoid, cylinder, obturator or a "
                             "plugin's), overriding recognition by name; repeatable")
    parser.add_argument("--synonyms", type=Path, default=None,
                        help="CSV file with 'standard,synonym' rows added to the built-in ROI name table")
    parser.add_argument("--allow-no-oars", action="store_true",
                        help="plan even when no organ at risk is found (needles are then checked against nothing)")
    parser.add_argument("--design", nargs="*", default=["15ga-30j-tip"], metavar="PRESET",
                        help="stylet presets to steer with (none: straight needles only)")
    add_tissue_arguments(parser)
    parser.add_argument("--target-roi", default="HR-CTV", help="ROI the dwell times are optimised on")
    parser.add_argument("--source", default="gammamed_plus_hdr", help="TG-43 source plugin for the dose")
    parser.add_argument("--protocol", metavar="FILE_OR_NAME", help=PROTOCOL_HELP)
    parser.add_argument("--reference-point", action="append", default=[], metavar="NAME=X,Y,Z",
                        help="a dose reference point of the exported plan (mm, LPS), with its planned dose; "
                             "repeatable (Point A and the ICRU bladder/rectum points are added when the "
                             "structures allow)")
    parser.add_argument("--dwell-margin", type=finite_float, default=None, metavar="MM",
                        help="dwells lie in the --target-roi grown by this margin (default 0: the target as drawn)")
    add_rtplan_style(parser)
    parser.add_argument("--no-export", action="store_true", help="rank only; skip dose optimisation and export")
    parser.add_argument("--no-implant", action="store_true",
                        help="skip implant planning (the needle set and dwell times for the whole target, straight "
                             "against steered)")
    add_implant_arguments(parser)
    parser.add_argument("--out", type=Path, required=True, help="output folder")
    parser.add_argument("--quiet", action="store_true", help="no progress bars or table")
    parser.add_argument("--json", action="store_true", help="print plan.json on stdout")


def tension_reserve(text: str) -> float:
    """Argparse ``type=`` of ``--tension-reserve``: a fraction of the stylet's tension limit, in [0, 0.9].

    Parameters
    ----------
    text : str
        The argument as given (``0.1``: 10 %).

    Returns
    -------
    float
        The fraction.
    """
    value = finite_float(text)
    if not 0.0 <= value <= 0.9:
        raise argparse.ArgumentTypeError(f"{text} is not a fraction in [0, 0.9] of the stylet's tension limit "
                                         "(0.1 keeps 10 %; 0 allows the full limit)")
    return value


def add_rtplan_style(parser: argparse.ArgumentParser) -> None:
    """Add ``--rtplan-style`` (the exported RT Plan's layout; ``plan`` and ``demo``).

    Parameters
    ----------
    parser : argparse.ArgumentParser
        The ``plan`` or ``demo`` parser.
    """
    parser.add_argument("--rtplan-style", choices=("eclipse", "vitesse"), default="eclipse",
                        help="layout of the exported RT Plan's prescription: eclipse (default; no Target "
                             "Prescription Dose, the points as COORDINATES) or vitesse (adds the target as a SITE "
                             "item with Target Prescription Dose)")


def add_implant_arguments(parser: argparse.ArgumentParser) -> None:
    """Add the options shared with ``demo``: tip offset, tension reserve, ``--needles``, ``--models``.

    Parameters
    ----------
    parser : argparse.ArgumentParser
        The command's parser.
    """
    parser.add_argument("--applicator-tip-offset", type=finite_float, default=None, metavar="MM",
                        help="the afterloader's source-tip offset in applicator channels (tandem, ring, ovoid, "
                             "cylinder): the deepest dwell lies this far back from the channel's end (default 3.5)")
    parser.add_argument("--tension-reserve", type=tension_reserve, default=0.1, metavar="FRACTION",
                        help="fraction of each stylet's tension limit no planned needle uses, for the hand's "
                             "tension error (default 0.1: 10 %%; 0 allows the full limit)")
    add_needles_argument(parser)
    parser.add_argument("--models", choices=("scene", "reference"), default="scene",  # case.fidelity.POLICIES
                        help="insertion model per steered candidate: scene (default: the cheapest whose measured "
                             "in-tissue error its clearance and the reach tolerance allow, the reference near the "
                             "ranking's decision) or reference (every feasible candidate re-solved with the "
                             "reference in-tissue rod)")


def implant_settings(args: argparse.Namespace) -> ImplantSettings:
    """Return the implant planning settings the options ask for (defaults for the options not given).

    Parameters
    ----------
    args : argparse.Namespace
        Parsed ``plan`` or ``demo`` options (``applicator_tip_offset``, ``needles``).

    Returns
    -------
    ImplantSettings
        The settings.

    Raises
    ------
    ArgumentError
        A negative tip offset.
    """
    from reachplan.planner.implant.settings import ImplantSettings

    offset = finite(getattr(args, "applicator_tip_offset", None), "--applicator-tip-offset", lo=0.0)
    settings = ImplantSettings(needles=getattr(args, "needles", None))
    return settings if offset is None else dataclasses.replace(settings, applicator_tip_offset_mm=offset)


def _triple(spec: str, what: str) -> tuple[float, float, float]:
    """Three finite numbers 'x,y,z' (no empty item)."""
    return parse_point(spec, what)


def _targets(specs: list[str]) -> tuple[list[str], list[Target]]:
    from reachplan.planner.errors import PlanInputError
    from reachplan.planner.steering.candidates import Target

    names: list[str] = []
    points: list[Target] = []
    for spec in specs:
        if not spec.strip():
            raise PlanInputError("--targets: an empty target; give ROI names or points 'x,y,z' (mm, LPS)")
        if len(spec.split(",")) == 3:
            try:
                x, y, z = _triple(spec, "target")
            except PlanInputError:
                raise PlanInputError(f"target {spec!r}: a point is three numbers 'x,y,z' in mm, all finite (three "
                                     "finite coordinates)") from None
            if not all(abs(v) <= 1e5 for v in (x, y, z)):
                raise PlanInputError(f"target {spec!r}: a point needs three finite coordinates within 100 m, in mm")
            points.append(Target(f"point_{len(points) + 1}", (x, y, z)))
        else:
            names.append(spec)
    return names, points


def _reference_points(specs: list[str]) -> list[tuple[str, tuple[float, float, float]]]:
    out = []
    for spec in specs:
        name, sep, xyz = spec.partition("=")
        if not sep or not name.strip() or len(name.strip()) > 64:
            raise PlanInputError(f"reference point {spec!r}: give NAME=X,Y,Z (a name of 1-64 characters, mm LPS)")
        out.append((name.strip(), _triple(xyz, f"reference point {name.strip()}")))
    return out


def read_pose_file(path: Path) -> np.ndarray:
    """Read a 4x4 template pose.

    The file holds JSON (a 4x4 list, or an object holding 'patient_from_template' at any depth) or text (4 rows
    of 4 numbers separated by spaces or commas). Rigidity is checked by the caller.

    Parameters
    ----------
    path : Path
        The ``--template-pose`` file.

    Returns
    -------
    (4, 4) float, template frame -> LPS mm
        ``patient_from_template`` as written.

    Raises
    ------
    PlanInputError
        An unreadable file, or no finite 4x4 matrix in it.
    """
    import numpy as np
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as exc:
        raise PlanInputError(f"cannot read the template pose {path}: {exc.strerror}") from None
    except UnicodeDecodeError:
        raise PlanInputError(f"template pose {path} is not a text file; give a 4x4 matrix as JSON or text") from None
    value: object
    try:
        value = json.loads(text)
    except json.JSONDecodeError:
        value = [line.replace(",", " ").split() for line in text.splitlines() if line.strip()
                 and not line.lstrip().startswith("#")]
    while isinstance(value, dict):
        value = value.get("template_pose", value.get("patient_from_template"))
    try:
        m = np.array(value, dtype=float)
    except (TypeError, ValueError):
        m = np.zeros(0)
    if m.shape != (4, 4) or not np.all(np.isfinite(m)):
        raise PlanInputError(f"template pose {path} must hold a finite 4x4 matrix (JSON list of 4 rows, or 4 text "
                             f"rows of 4 numbers)")
    return m


def template_pose(args: argparse.Namespace, structures: StructureSet, config: PlanConfig,
                  applicators: Mapping[str, str] | None = None) -> TemplatePose | None:
    """Return the pose asked for on the command line (None: fit it to the Obturator ROI).

    ``applicators``: ROI name -> applicator kind from ``--applicator`` (for an RT Plan's channels).

    Parameters
    ----------
    args : argparse.Namespace
        ``template_origin`` and ``template_axis`` (mm, LPS), ``template_pose`` or ``rtplan``: one of them at most.
    structures : StructureSet
        The case's structures (an RT Plan's channels are found in them).
    config : PlanConfig
        Its ``obturator_depth_mm`` places the template behind an RT Plan's channel.
    applicators : mapping of str to str or None
        ROI name -> applicator kind from ``--applicator`` (for an RT Plan's channels).

    Returns
    -------
    TemplatePose or None
        The pose and a line saying where it came from; None when none was given.

    Raises
    ------
    PlanInputError
        The pose given two ways, an origin without an axis (or the reverse), or a bad pose file.
    """
    from reachplan.planner.geometry.template import TemplatePose, pose_from_axis, pose_from_rtplan
    from reachplan.planner.lookup import applicator_kinds

    given = [n for n, v in (("--template-origin/--template-axis", args.template_origin or args.template_axis),
                            ("--template-pose", args.template_pose), ("--rtplan", args.rtplan)) if v]
    if len(given) > 1:
        raise PlanInputError(f"give the template pose one way, not with {' and '.join(given)}")
    if args.template_origin or args.template_axis:
        if not (args.template_origin and args.template_axis):
            raise PlanInputError("--template-origin and --template-axis go together (centre and insertion "
                                 "direction)")
        origin = _triple(args.template_origin, "--template-origin")
        axis = _triple(args.template_axis, "--template-axis")
        return TemplatePose(pose_from_axis(origin, axis),
                            f"command line: origin {','.join(f'{v:g}' for v in origin)} mm, axis "
                            f"{','.join(f'{v:g}' for v in axis)}")
    if args.template_pose:
        matrix = read_pose_file(args.template_pose)
        return TemplatePose(matrix, f"command line: --template-pose {args.template_pose.name}")
    if args.rtplan:
        import warnings

        from reachplan.imaging.rtplan import PlanQuirkWarning, read_rtplan

        with warnings.catch_warnings():
            warnings.simplefilter("ignore", PlanQuirkWarning)  # the quirks are printed below
            rtplan = read_rtplan(args.rtplan)
        from reachplan.planner.dose.plan_usable import require_usable

        require_usable(rtplan, f"--rtplan {args.rtplan}", kinds=("geometry",))  # the channels the pose comes from
        for quirk in rtplan.quirks:
            print(f"reachplan: warning: RT Plan {args.rtplan.name}: {quirk}; read anyway", file=sys.stderr)
        return pose_from_rtplan(rtplan, structures, config.obturator_depth_mm, applicator_kinds(), applicators)
    return None


def _names(args: argparse.Namespace, config: PlanConfig) -> tuple[SynonymTable, dict[str, str], PlanConfig]:
    """Return the synonym table, the hand mapping ROI name -> organ (``--oar``) and the config with added organs."""
    from reachplan.imaging.names import DEFAULT_SYNONYMS, SynonymTable

    table = SynonymTable.from_csv(args.synonyms) if args.synonyms else DEFAULT_SYNONYMS
    overrides: dict[str, str] = {}
    oars = list(config.oar_names)
    for spec in args.oar:
        organ, sep, roi = (x.strip() for x in spec.partition("="))
        if not sep or not organ or not roi:
            raise PlanInputError(f"--oar {spec!r}: write ORGAN=ROI_NAME, e.g. Rectum=Rect_PRV")
        organ = table.normalize(organ)
        if roi.casefold() in {k.casefold() for k in overrides}:
            raise PlanInputError(f"--oar names ROI {roi!r} twice")
        if organ.casefold() in {v.casefold() for v in overrides.values()}:
            raise PlanInputError(f"--oar maps two ROIs to {organ}; give one ROI per organ")
        overrides[roi] = organ
        if organ not in oars:
            oars.append(organ)
    return table, overrides, dataclasses.replace(config, oar_names=tuple(oars))


def check_plan_arguments(args: argparse.Namespace, inputs: list[Path]) -> None:
    """Check what can be checked before any work: the output folder, template, designs, source, protocol, targets.

    The protocol's aims are kept as ``args.aims``.

    Parameters
    ----------
    args : argparse.Namespace
        The ``plan`` options.
    inputs : list of Path
        The input files (the output folder must not be one of them, nor hold them).

    Raises
    ------
    ReachplanError
        The first argument found wrong (one line saying what to do).
    """
    from reachplan.planner.dose.protocol import load_protocol
    from reachplan.planner.lookup import get_source, load_template
    from reachplan.rod_model.design import preset

    output_folder(args.out, inputs)
    if args.series_uid is not None and args.ct is None:
        raise PlanInputError("--series-uid chooses among the series of --ct; give --ct too")
    load_template(args.template)
    for name in args.design:
        preset(name)
    if not args.no_export:
        get_source(args.source)
    args.aims = load_protocol(args.protocol)  # a bad file or name is an error before any work
    if args.dwell_margin is not None:
        finite(args.dwell_margin, "--dwell-margin", lo=0.0, hi=20.0)
    _targets(args.targets)


def case_config(args: argparse.Namespace, structures: StructureSet, config: PlanConfig,
                standard_names: Sequence[str]) -> CaseConfig:
    """Return what the command line asks to plan on ``structures``.

    Parameters
    ----------
    args : argparse.Namespace
        The parsed ``plan`` arguments, with ``aims`` (:func:`check_plan_arguments`).
    structures : StructureSet
        The case's ROIs (for the template pose from an RT Plan and the target checks).
    config : PlanConfig
        The steering search's settings (template, designs, organs at risk with ``--oar`` added).
    standard_names : sequence of str
        The synonym table's standard names.

    Returns
    -------
    CaseConfig
        The case's configuration.

    Raises
    ------
    ReachplanError
        A target or dose target ROI that is not in the structure set, or a bad template pose.
    """
    from reachplan.planner.lookup import applicator_kinds
    from reachplan.planner.run.case import CaseConfig

    names, points = _targets(args.targets)
    for n in names:
        structures.get(n)  # a typed error naming the available ROIs
    if not args.no_export:
        structures.get(args.target_roi)  # the ROI the dwell times are optimised on, checked before planning
    assign = applicator_assignments(args.applicator, applicator_kinds(), [r.name for r in structures.rois])
    return CaseConfig(plan=dataclasses.replace(config, applicators=tuple(assign.items())), target_names=tuple(names),
                      target_points=tuple(points), pose=template_pose(args, structures, config, assign),
                      allow_no_oars=args.allow_no_oars,
                      standard_names=tuple(standard_names), export=not args.no_export, implant=not args.no_implant,
                      source=args.source, target_roi=args.target_roi,
                      named_points=tuple(_reference_points(args.reference_point)), aims=args.aims,
                      dwell_margin_mm=args.dwell_margin, rtplan_style=args.rtplan_style,
                      implant_settings=implant_settings(args))


def run(args: argparse.Namespace) -> int:
    """Plan a case from the command line; returns the exit code.

    Parameters
    ----------
    args : argparse.Namespace
        The ``plan`` options.

    Returns
    -------
    int
        0; nothing appears in ``--out`` unless the whole plan succeeds (a failure raises).
    """
    from reachplan.imaging.dicom_io import read_series
    from reachplan.imaging.names import rename
    from reachplan.imaging.rtstruct import read_rtstruct
    from reachplan.planner.case.config import PlanConfig
    from reachplan.planner.kernels import start as start_kernels
    from reachplan.planner.run.case import CaseInput

    inputs = [p for p in (args.ct, args.rtstruct) if p is not None]
    check_plan_arguments(args, inputs)
    quiet = args.quiet or args.json
    start_kernels(quiet)  # before reading the series: the first run's compile overlaps it
    _reference_points(args.reference_point)  # a bad point is an error before the series is read
    config = PlanConfig(template=args.template, designs=tuple(args.design), tension_reserve=args.tension_reserve,
                        models=args.models, **tissue_options(args))
    table, overrides, config = _names(args, config)
    volume = read_series(args.ct, series_uid=args.series_uid) if args.ct else None
    structures = read_rtstruct(args.rtstruct, volume, synonyms=table)
    if overrides:
        structures = rename(structures, overrides)
    case = case_config(args, structures, config, table.standard_names)
    check_targets_inside(case.target_points, volume, structures, args.allow_outside_body)  # before any planning
    label = inputs[-1].name
    with staged_folder(args.out) as stage:  # nothing appears in --out unless the whole plan succeeds
        _, doc = plan_and_write(CaseInput(structures, volume, tuple(inputs), label), case, stage, quiet,
                                final_out=args.out, complete=lambda doc: _add_warnings(doc, args))
    if args.json:
        print_json(doc, NAME)
    return 0


def _add_warnings(doc: dict[str, object], args: argparse.Namespace) -> None:
    """Add the named warnings met on the way (readers, planning) to the scene's notes in ``doc["warnings"]``."""
    notes = doc.get("warnings")
    doc["warnings"] = list(dict.fromkeys([*(notes if isinstance(notes, list) else []), *seen_warnings(args)]))


def _print_scene(scene: Scene, quiet: bool) -> None:
    """Print the scene's warnings (stderr) and, unless ``quiet``, the template pose."""
    import numpy as np
    from tqdm import tqdm

    for note in scene.notes:
        tqdm.write(f"reachplan: warning: {note}", file=sys.stderr)
    if scene.pose is not None and not quiet:
        m = scene.pose.patient_from_template
        print(f"template pose: {scene.pose.method}; centre {np.round(m[:3, 3], 2).tolist()} mm, axis "
              f"{np.round(m[:3, 2], 4).tolist()} (LPS)")


def plan_and_write(inputs: CaseInput, config: CaseConfig, out: Path, quiet: bool, *,
                   final_out: Path | None = None, extra: dict[str, object] | None = None,
                   complete: Callable[[dict[str, object]], None] | None = None,
                   ) -> tuple[CaseResult, dict[str, object]]:
    """Plan a case (:func:`~reachplan.planner.run.case.run_case`), write its files and print the summary.

    Parameters
    ----------
    inputs : CaseInput
        The case.
    config : CaseConfig
        What to plan.
    out : Path
        The staging folder written into.
    quiet : bool
        No progress bars or tables.
    final_out : Path or None
        Where ``out`` will be moved (the paths printed and written name it).
    extra : dict or None
        Keys put first in plan.json.
    complete : callable or None
        Called with plan.json's content before it is written.

    Returns
    -------
    CaseResult
        What was computed.
    dict
        plan.json's content.
    """
    from reachplan.planner.handoff import obstacles_line
    from reachplan.planner.kernels import start
    from reachplan.planner.report.terminal import format_implant, format_summary
    from reachplan.planner.run.case import run_case
    from reachplan.planner.run.outputs import write_outputs

    start(quiet)  # first run after an install: the rod and dose kernels compile on the other core meanwhile
    case = run_case(inputs, config, quiet=quiet, on_scene=lambda scene: _print_scene(scene, quiet))
    files = write_outputs(case, out, final_out, extra=extra or {}, complete=complete, quiet=quiet)
    if not quiet:
        written = [("report", str(files.report)), ("plan", str(files.plan))]
        written += [("device instructions", str(f)) for f in files.device_instructions]
        print(format_summary(case.result, targets=[t.name for t in case.scene.targets], delivery=case.delivery,
                             comparison=case.comparison, files=written, applicators=obstacles_line(case.scene)))
        if case.delivery is not None and case.delivery.implant is not None:
            print("\n" + format_implant(case.delivery.implant, case.delivery.aims_tables))
    return case, files.doc
