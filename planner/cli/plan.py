"""``reachplan plan``: plan straight and steered needles for a case's targets and export the plan."""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING

from reachplan.planner.cli.edges import json_safe, output_folder, print_json, seen_warnings, staged_folder
from reachplan.planner.errors import PlanInputError

if TYPE_CHECKING:  # the run-time imports are inside the functions: start-up of every command stays light
    from collections.abc import Callable

    import numpy as np

    from reachplan.imaging.names import SynonymTable
    from reachplan.imaging.types import StructureSet, Volume
    from reachplan.planner.geometry.template import TemplatePose
    from reachplan.planner.pipeline import PlanConfig
    from reachplan.planner.steering.candidates import Target

NAME = "plan"
HELP = "rank template holes, stylet designs and tension schedules for targets; write plan.json, figures, exports"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Add the ``plan`` options to ``parser``."""
    parser.add_argument("--ct", type=Path, help="CT/MR series folder (optional: organs from contours suffice)")
    parser.add_argument("--rtstruct", type=Path, required=True, help="RT Structure Set file")
    parser.add_argument("--targets", nargs="+", required=True, metavar="ROI_OR_POINT",
                        help="target ROI names, or points 'x,y,z' in mm (DICOM patient coordinates, LPS); an ROI "
                             "of POINT contours is planned to its points")
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
    parser.add_argument("--oar", action="append", default=[], metavar="ORGAN=ROI_NAME",
                        help="use ROI_NAME as organ at risk ORGAN (e.g. Rectum=Rect_PRV); repeatable; an ORGAN "
                             "outside the default list (Bladder, Rectum, Sigmoid, Bowel, Bone) is added to it")
    parser.add_argument("--synonyms", type=Path, default=None,
                        help="CSV file with 'standard,synonym' rows added to the built-in ROI name table")
    parser.add_argument("--allow-no-oars", action="store_true",
                        help="plan even when no organ at risk is found (needles are then checked against nothing)")
    parser.add_argument("--design", nargs="*", default=["15ga-30j-tip"], metavar="PRESET",
                        help="stylet presets to steer with (none: straight needles only)")
    parser.add_argument("--target-roi", default="HR-CTV", help="ROI the dwell times are optimised on")
    parser.add_argument("--source", default="gammamed_plus_hdr", help="TG-43 source plugin for the dose")
    parser.add_argument("--reference-point", action="append", default=[], metavar="NAME=X,Y,Z",
                        help="a dose reference point of the exported plan (mm, LPS), with its planned dose; "
                             "repeatable (Point A and the ICRU bladder/rectum points are added when the "
                             "structures allow)")
    parser.add_argument("--no-export", action="store_true", help="rank only; skip dose optimisation and export")
    parser.add_argument("--no-implant", action="store_true",
                        help="skip implant planning (the needle set and dwell times for the whole target, straight "
                             "against steered)")
    parser.add_argument("--out", type=Path, required=True, help="output folder")
    parser.add_argument("--quiet", action="store_true", help="no progress bars or table")
    parser.add_argument("--json", action="store_true", help="print plan.json on stdout")


def _triple(spec: str, what: str) -> tuple[float, float, float]:
    """Three finite numbers 'x,y,z'."""
    parts = spec.split(",")
    try:
        values = tuple(float(p) for p in parts)
    except ValueError:
        values = ()
    if len(values) != 3 or not all(math.isfinite(v) for v in values):
        raise PlanInputError(f"{what} {spec!r}: give three finite numbers 'x,y,z' in mm")
    return values[0], values[1], values[2]


def _targets(specs: list[str]) -> tuple[list[str], list[Target]]:
    from reachplan.planner.errors import PlanInputError
    from reachplan.planner.steering.candidates import Target

    names: list[str] = []
    points: list[Target] = []
    for spec in specs:
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


def template_pose(args: argparse.Namespace, structures: StructureSet, config: PlanConfig) -> TemplatePose | None:
    """Return the pose asked for on the command line (None: fit it to the Obturator ROI)."""
    from reachplan.planner.geometry.template import TemplatePose, pose_from_axis, pose_from_rtplan

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
        for quirk in rtplan.quirks:
            print(f"reachplan: warning: RT Plan {args.rtplan.name}: {quirk}; read anyway", file=sys.stderr)
        return pose_from_rtplan(rtplan, structures, config.obturator_depth_mm)
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
    """Check what can be checked before any work: the output folder, template, designs, source and targets.

    Raises
    ------
    ReachplanError
        The first argument found wrong (one line saying what to do).
    """
    from reachplan.planner.pipeline import get_source
    from reachplan.plugins import registry
    from reachplan.rod_model.design import preset

    output_folder(args.out, inputs)
    registry.get("templates", args.template)
    for name in args.design:
        preset(name)
    if not args.no_export:
        get_source(args.source)
    _targets(args.targets)


def run(args: argparse.Namespace) -> int:
    """Plan a case from the command line; returns the exit code."""
    from reachplan.imaging.dicom_io import read_series
    from reachplan.imaging.names import rename
    from reachplan.imaging.rtstruct import read_rtstruct
    from reachplan.planner.kernels import start as start_kernels
    from reachplan.planner.pipeline import PlanConfig

    inputs = [p for p in (args.ct, args.rtstruct) if p is not None]
    check_plan_arguments(args, inputs)
    quiet = args.quiet or args.json
    start_kernels(quiet)  # before reading the series: the first run's compile overlaps it
    names, points = _targets(args.targets)
    named_points = _reference_points(args.reference_point)
    config = PlanConfig(template=args.template, designs=tuple(args.design))
    table, overrides, config = _names(args, config)
    volume = read_series(args.ct) if args.ct else None
    structures = read_rtstruct(args.rtstruct, volume, synonyms=table)
    if overrides:
        structures = rename(structures, overrides)
    for n in names:
        structures.get(n)  # a typed error naming the available ROIs
    if not args.no_export:
        structures.get(args.target_roi)  # the ROI the dwell times are optimised on, checked before planning
    pose = template_pose(args, structures, config)
    with staged_folder(args.out) as stage:  # nothing appears in --out unless the whole plan succeeds
        doc = run_plan(structures, volume, names, points, config, stage, quiet,
                       export=not args.no_export, source=args.source, target_roi=args.target_roi, inputs=inputs,
                       pose=pose, allow_no_oars=args.allow_no_oars, standard_names=table.standard_names,
                       named_points=named_points, implant=not args.no_implant, final_out=args.out,
                       complete=lambda doc: _add_warnings(doc, args))
    if args.json:
        print_json(doc, NAME)
    return 0


def _add_warnings(doc: dict[str, object], args: argparse.Namespace) -> None:
    """Add the named warnings met on the way (readers, planning) to the scene's notes in ``doc["warnings"]``."""
    notes = doc.get("warnings")
    doc["warnings"] = [*(notes if isinstance(notes, list) else []), *seen_warnings(args)]


def run_plan(structures: StructureSet, volume: Volume | None, names: list[str], points: list[Target],
             config: PlanConfig, out: Path, quiet: bool, *, export: bool = True, source: str = "gammamed_plus_hdr",
             target_roi: str = "HR-CTV", inputs: list[Path] | None = None,
             extra: dict[str, object] | None = None, pose: TemplatePose | None = None, allow_no_oars: bool = False,
             standard_names: Sequence[str] | None = None,
             named_points: Sequence[tuple[str, tuple[float, float, float]]] = (),
             implant: bool = True, final_out: Path | None = None,
             complete: Callable[[dict[str, object]], None] | None = None) -> dict[str, object]:
    """Scene → plan → files (plan.json, overview.png, workspace.png, exports, report.html); returns the plan document.

    ``final_out``: where the files will be once the staging folder ``out`` is moved into place (default ``out``):
    every path printed, returned or written inside a file is there. ``complete``: called with the document just
    before plan.json is written (once), to add what the caller knows (warnings met, a table of its own).

    ``named_points``: dose reference points (name, (x, y, z) mm LPS) the exported plan carries with their doses.

    ``pose``: the template pose (None: fitted to the Obturator ROI). The pose and how it was found, and the
    warnings about the input (organs at risk not found, targets planned to points), are printed and saved in
    plan.json (``template_pose``, ``warnings``). ``implant``: also plan the implant for the whole target
    volume, straight only and straight + steered (plan.json ``implant``, printed side by side).
    """
    import numpy as np
    from tqdm import tqdm

    from reachplan.imaging.files import atomic_write_bytes, atomic_write_json
    from reachplan.planner.geometry.organs import has_closed
    from reachplan.planner.pipeline import build_scene, plan, plan_delivery
    from reachplan.planner.report import figures
    from reachplan.planner.report.build import (
        format_implant,
        format_summary,
        report_html,
        straight_vs_steered,
        top_candidates,
    )
    from reachplan.planner.report.workspace import workspace_figure
    from reachplan.plugins import registry
    from reachplan.plugins.exporters import ExportOptions

    if export:  # the dose target is checked before any work
        roi = structures.get(target_roi)
        if not has_closed(roi):
            raise PlanInputError(f"the dose target ROI {roi.name!r} has no closed contours; name another with "
                                 "--target-roi or plan with --no-export")
    final = out if final_out is None else Path(final_out)
    timings: dict[str, float] = {}
    from reachplan.planner.kernels import start

    start(quiet)  # first run after an install: the rod and dose kernels compile on the other core meanwhile
    t = time.perf_counter()
    grid = volume.grid if volume is not None else None
    scene = build_scene(structures, names, points, grid=grid, patient_from_template=pose, config=config,
                        quiet=quiet, allow_no_oars=allow_no_oars, standard_names=standard_names)
    timings["scene_s"] = time.perf_counter() - t
    config = dataclasses.replace(config, oar_names=tuple(o.name for o in scene.organs))
    for note in scene.notes:
        tqdm.write(f"reachplan: warning: {note}", file=sys.stderr)
    if scene.pose is not None and not quiet:
        m = scene.pose.patient_from_template
        print(f"template pose: {scene.pose.method}; centre {np.round(m[:3, 3], 2).tolist()} mm, axis "
              f"{np.round(m[:3, 2], 4).tolist()} (LPS)")
    t = time.perf_counter()
    result = plan(scene, config, quiet=quiet)
    timings["plan_s"] = time.perf_counter() - t
    doc: dict[str, object] = {**(extra or {}), **result.to_json()}
    if scene.pose is not None:
        doc["template_pose"] = scene.pose.to_json()
    doc["warnings"] = list(scene.notes)
    overview_png = figures.overview(scene, top_candidates(result), volume)
    workspace_png = workspace_figure(scene, config)
    atomic_write_bytes(out / "overview.png", overview_png)
    atomic_write_bytes(out / "workspace.png", workspace_png)
    delivery = None
    comparison, comparison_note = straight_vs_steered(result, structures, None)  # no dose: the note says so
    files: list[str] = []
    if export:
        t = time.perf_counter()
        bar = tqdm(total=4, desc="delivery", unit="step", disable=quiet, leave=False)
        bar.set_postfix_str("dwell times (TG-43, LP)")
        delivery = plan_delivery(result, structures, grid, source_name=source, target_roi=target_roi,
                                 volume=volume, input_paths=inputs or [], named_points=named_points,
                                 scene=scene if implant else None)
        bar.update()
        for name in ("dicom_rt", "device_json", "device_csv"):
            bar.set_postfix_str(f"export {name}")
            exporter = registry.get("exporters", name)
            written = exporter.export(delivery.export, out / "export", ExportOptions(overwrite=True))
            files += [str(final / Path(f.path).relative_to(out)) for f in written.files]
            bar.update()
        for arm_name, arm_export in delivery.implant_exports.items():  # loaded needles only
            for name in ("device_json", "device_csv"):
                written = registry.get("exporters", name).export(arm_export, out / "export" / f"implant_{arm_name}",
                                                                 ExportOptions(overwrite=True))
                files += [str(final / Path(f.path).relative_to(out)) for f in written.files]
        bar.close()
        opt = delivery.optimisation
        ex = delivery.export
        doc["delivery"] = {
            "plan": delivery.kind,
            "needles": [n.hole_id for n in ex.needles],
            "roles": list(delivery.roles),
            "prescription": {"target": ex.target_name, "dose_per_fraction_gy": ex.prescription_dose_gy,
                             "fractions": ex.fractions_planned},
            "reference_points": [{"name": p.name, "position_mm": [round(float(x), 2) for x in p.position_mm]}
                                 for p in ex.reference_points],
            "optimisation": {"success": opt.success, "reason": opt.reason, "aim_met": opt.aim_met,
                             "hrctv_d90_gy": round(float(opt.target.d90_gy), 3) if opt.success else None},
            "files": files,
        }
        if delivery.implant is not None:
            doc["implant"] = delivery.implant.to_json()
        comparison, comparison_note = straight_vs_steered(result, structures, delivery, grid, target_roi,
                                                          quiet=quiet)
        timings["delivery_s"] = time.perf_counter() - t
    from reachplan.planner.pipeline import rod_model_errors

    t = time.perf_counter()
    case = str((extra or {}).get("case") or (inputs[-1].name if inputs else "case"))
    html = report_html(scene, result, volume=volume, delivery=delivery, comparison=comparison,
                       comparison_note=comparison_note, case=case, timings=timings, source_name=source, quiet=quiet,
                       overview_png=overview_png, workspace_png=workspace_png, model_errors=rod_model_errors())
    atomic_write_bytes(out / "report.html", html.encode("utf-8"))
    doc["report"] = str(final / "report.html")
    timings["report_s"] = time.perf_counter() - t
    doc["timings"] = timings
    if complete is not None:
        complete(doc)
    atomic_write_json(out / "plan.json", json_safe(doc))
    if not quiet:
        written = [("report", str(final / "report.html")), ("plan", str(final / "plan.json"))]
        written += [("device instructions", f) for f in files if "device" in Path(f).name and f.endswith(".json")]
        print(format_summary(result, targets=[t.name for t in scene.targets], delivery=delivery,
                             comparison=comparison, files=written))
        if delivery is not None and delivery.implant is not None:
            print("\n" + format_implant(delivery.implant))
    return doc
