"""``reachplan reconstruct``: find the needles in a post-insertion CT or MR, from the template's holes to their tips.

Writes ``needles.json``, ``RS_needles.dcm`` (the needles as BRACHY_CHANNEL open ROIs) and ``report.html`` into
``--out``; with ``--plan``, each needle is compared with its planned path, the plan's dose on the needles as found is
computed (:mod:`reachplan.planner.verify.delivered`), and the dwell times are optimised again on them and written to
``replanned/`` as an RT Plan, Structure Set and Dose (:mod:`reachplan.planner.verify.replan`), each against the
plan's protocol (:mod:`reachplan.planner.run.as_inserted`).
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import TYPE_CHECKING, Any

from reachplan.planner.cli.edges import output_folder, print_json, staged_folder
from reachplan.planner.cli.plan import add_pose_arguments

if TYPE_CHECKING:
    import numpy as np

    from reachplan.imaging.types import StructureSet
    from reachplan.planner.verify.compare import Matching

NAME = "reconstruct"
HELP = ("find the needles in a post-insertion CT/MR from the template's holes (none named) to their tips; write "
        "needles.json, an RT Structure Set and a report")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Add the ``reconstruct`` options.

    Parameters
    ----------
    parser : argparse.ArgumentParser
        The sub-command's parser.
    """
    parser.add_argument("--ct", type=Path, required=True, help="the post-insertion CT (or MR) series folder")
    parser.add_argument("--rtstruct", type=Path, required=True,
                        help="its RT Structure Set (the Obturator ROI places the template unless a pose is given)")
    parser.add_argument("--out", type=Path, required=True, help="output folder")
    parser.add_argument("--plan", type=Path, metavar="PLAN_JSON",
                        help="the plan.json the needles were inserted from: planned versus actual per needle, the "
                             "plan's dose on the needles found, and a plan re-optimised on them (replanned/: RT Plan, "
                             "Structure Set, Dose)")
    add_pose_arguments(parser)
    parser.add_argument("--needle-look", choices=("auto", "bright", "dark"), default="auto",
                        help="bright: a metal obturator or stylet (CT); dark: a signal void (MR) or an empty lumen; "
                             "auto: bright on CT, dark on MR")
    parser.add_argument("--json", action="store_true", help="print needles.json's summary as JSON")


def _pose(args: argparse.Namespace, structures: StructureSet) -> tuple[np.ndarray, str]:
    """Return the template pose as ``plan`` finds it: given on the command line, else fitted to the Obturator ROI."""
    from reachplan.planner.case.config import PlanConfig
    from reachplan.planner.cli.plan import template_pose
    from reachplan.planner.errors import PlanInputError
    from reachplan.planner.geometry.template import pose_from_obturator

    config = PlanConfig(template=args.template)
    given = template_pose(args, structures, config)
    if given is not None:
        return given.patient_from_template, given.method
    if "Obturator" not in structures.names:
        raise PlanInputError("no Obturator ROI to place the template on; give the pose with --template-origin "
                             "X,Y,Z --template-axis X,Y,Z, --template-pose FILE or --rtplan FILE")
    m = pose_from_obturator(structures.get("Obturator"), config.obturator_depth_mm)
    return m, f"fitted to ROI 'Obturator' (template {config.obturator_depth_mm:g} mm behind its cranial tip)"


def _versus_plan(versus: Matching) -> dict[str, object]:
    """Return the needles against the plan for needles.json: counts, means and per needle errors (mm)."""
    doc = versus.summary()
    doc["planned_not_found"] = doc.pop("missed")
    doc["found_not_planned"] = doc.pop("false")
    return {**doc, "needles": [e.to_json() for e in versus.errors]}


def _value(r: dict[str, Any]) -> str:
    """Return an aims-table row's value, Gy EQD2, or "-"."""
    v = r.get("value_eqd2_gy")
    return "-" if v is None else f"{v:.1f}"


def _met(r: dict[str, Any]) -> str:
    """Return an aims-table row's verdict: met, not met, or not met with its hard limit broken."""
    met = r.get("planning_aim_met")
    return "-" if met is None else "met" if met else ("not met" if r.get("hard_limit_met") is not False
                                                       else "not met, hard limit broken")


def _as_inserted_section(delivered: dict[str, Any]) -> Any:
    """Return the report's section of the plan's dose on the needles as found, aim by aim beside the plan's."""
    from reachplan.planner.report.html import Paragraph, Section, Table

    before = {r["aim"]: r for r in delivered["planned"]["aims"]}
    rows = tuple((r["aim"], _value(before[r["aim"]]) if r["aim"] in before else "-", _value(r),
                  str(r.get("planning_aim") or "-"), str(r.get("hard_limit") or "-"), _met(r))
                 for r in delivered["as_inserted"]["aims"])
    return Section("As inserted: the plan's times on the needles found", "as-inserted", (
        Paragraph(str(delivered["summary"]) + " Dose as 'reachplan dose' computes any plan's (TG-43 line source; "
                  f"DVH method: {delivered['dvh_method']}); each needle's dwells kept at their distance from its tip "
                  "along the needle found."),
        Table(("aim", "as planned (Gy EQD2)", "as inserted (Gy EQD2)", "planning aim", "hard limit",
               "as inserted"), rows, "The plan's dose aims, as planned and on the needles as found", numeric=(1, 2)),
    ))


def _replanned_section(replanned: dict[str, Any] | None) -> tuple[Any, ...]:
    """Return the report's section of the plan re-optimised on the needles found (none without a re-plan)."""
    from reachplan.planner.report.html import Paragraph, Section, Table

    if replanned is None:
        return ()
    parts: list[Any] = [Paragraph(str(replanned["summary"]))]
    if "aims" in replanned:
        rows = tuple((r["aim"], _value(r), str(r.get("planning_aim") or "-"), str(r.get("hard_limit") or "-"),
                      _met(r)) for r in replanned["aims"]["aims"])
        parts += [Paragraph("Dwell times optimised again on the needles found and the applicators of the "
                            "post-insertion structure set, as the planner loads an implant (the protocol's aims with "
                            "their headroom, hard limits with any one needle displaced); the dose of the written RT "
                            "Plan recomputed as 'reachplan dose' computes any plan's. Files for the TPS: "
                            + ", ".join(Path(f).name for f in replanned["files"]) + "."),
                  Table(("aim", "re-optimised (Gy EQD2)", "planning aim", "hard limit", "re-optimised"), rows,
                        "The protocol's aims on the re-optimised plan", numeric=(1,))]
    return (Section("Re-optimised on the needles found", "replanned", tuple(parts)),)


def run(args: argparse.Namespace) -> int:
    """Find the needles and write what was found; return 0.

    Parameters
    ----------
    args : argparse.Namespace
        The ``reconstruct`` options.

    Returns
    -------
    int
        0 once the files are written.
    """
    import json
    import sys

    import numpy as np
    from tqdm import tqdm

    from reachplan.imaging.dicom_io import read_series
    from reachplan.imaging.files import atomic_write_bytes, json_bytes
    from reachplan.imaging.rtstruct import read_rtstruct
    from reachplan.planner.errors import PlanInputError
    from reachplan.planner.lookup import load_template
    from reachplan.planner.report.html import Report, render_html
    from reachplan.planner.report.reconstruction import reconstruction_section
    from reachplan.planner.run.as_inserted import after_insertion
    from reachplan.planner.verify.compare import match
    from reachplan.planner.verify.find import FinderSettings, detect_holes, find_needles
    from reachplan.planner.verify.implant import delivered_needles, plan_channel_paths, planned_paths
    from reachplan.planner.verify.outputs import needles_document, needles_rtstruct

    output_folder(args.out, [args.ct, args.rtstruct, args.plan])
    template = load_template(args.template)
    volume = read_series(args.ct)
    structures = read_rtstruct(args.rtstruct, volume)
    pose, method = _pose(args, structures)
    settings = FinderSettings.for_image(volume, args.needle_look)
    quiet = args.quiet or args.json
    holes = detect_holes(volume, template, pose, settings)
    with tqdm(total=len(holes), desc="needles", unit="needle", disable=quiet, leave=False) as bar:
        found = find_needles(volume, template, pose, settings, progress=lambda _h: bar.update(1), detected=holes)
    for f in found:
        if f.note:
            tqdm.write(f"reachplan reconstruct: warning: needle {f.hole_id}: {f.note}", file=sys.stderr)
    with staged_folder(args.out) as stage:
        planned = versus = delivered = None
        if args.plan is not None:
            try:
                doc = json.loads(args.plan.read_text(encoding="utf-8"))
            except (OSError, ValueError) as exc:
                raise PlanInputError(f"cannot read --plan {args.plan}: {exc}") from None
            planned = planned_paths(delivered_needles(doc), template, pose, plan_channel_paths(args.plan, doc))
            versus = match(found, planned)
            delivered = after_insertion(args.plan, doc, {f.hole_id: f.points_mm for f in found}, planned,
                                        structures, volume, stage / "replanned", args.out / "replanned")
        about = (f"{volume.modality} series {args.ct.name}; template {template.name} {method}; "
                 f"{len(template.needle_holes)} holes tested, {len(found)} needles found and tracked to their tips.")
        summary = {"found": len(found), "holes": [f.hole_id for f in found],
                   "seconds_per_needle": round(float(np.mean([f.seconds for f in found])), 3) if found else None}
        doc_out = needles_document(found, {
            "image": str(args.ct), "modality": volume.modality, "template": template.name,
            "plan": None if args.plan is None else str(args.plan.resolve()),
            "template_pose": {"method": method, "patient_from_template": np.round(pose, 6).tolist()},
            "settings": {"polarity": settings.polarity, "step_mm": settings.step_mm},
            "versus_plan": None if versus is None else _versus_plan(versus),
            "as_inserted": delivered,
            "summary": summary})
        sections = [reconstruction_section(volume, found, about, planned, versus)]
        if delivered is not None and "as_inserted" in delivered:
            sections += [_as_inserted_section(delivered), *_replanned_section(delivered.get("replanned"))]
        html = render_html(Report("reachplan: needles found", about, tuple(sections)))
        atomic_write_bytes(stage / "needles.json", json_bytes(doc_out))
        if found:
            atomic_write_bytes(stage / "RS_needles.dcm", needles_rtstruct(found, volume))
        atomic_write_bytes(stage / "report.html", html.encode("utf-8"))
    if args.json:
        print_json({**summary, "versus_plan": doc_out["versus_plan"], "out": str(args.out)}, NAME)
    elif not args.quiet:
        print(f"found {len(found)} needles ({', '.join(f.hole_id for f in found)}); wrote needles.json, "
              f"RS_needles.dcm and report.html to {args.out}")
        if delivered is not None:
            print(str(delivered["summary"]))
            if isinstance(delivered.get("replanned"), dict):
                print(str(delivered["replanned"]["summary"]))
    return 0
