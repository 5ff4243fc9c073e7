"""``reachplan calibrate``: learn the site's in-tissue curvature from the steered needles found after insertion.

Each ``--from`` folder is a ``reachplan reconstruct`` output made with ``--plan``: its ``needles.json`` names the
plan, the template and its pose. Every delivered steered needle of that plan that was found is fitted
(:mod:`reachplan.planner.steering.calibration`), and every needle found outside the delivered implant that was one of
the plan's steered candidates (:func:`alternate`); the fits are pooled per design with those the ``--site`` file
already holds (a needle fitted again replaces its earlier fit) and the file is written atomically. ``plan
--calibration FILE`` then applies the site's ratios.
"""

from __future__ import annotations

import argparse
from collections.abc import Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any

from reachplan.planner.cli.edges import print_json

if TYPE_CHECKING:
    import numpy as np

    from reachplan.planner.steering.calibration import FoundSteered
    from reachplan.planner.verify.implant import PlannedNeedle
    from reachplan.plugins.templates import Template

NAME = "calibrate"
#: A found needle of this confidence or less was flagged by the finder (two tracks sharing their end): not fitted.
FLAGGED = 0.3
HELP = ("fit the site's in-tissue curvature per stylet design to the steered needles found by 'reachplan reconstruct "
        "--plan' and update a site calibration file ('plan --calibration')")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Add the ``calibrate`` options.

    Parameters
    ----------
    parser : argparse.ArgumentParser
        The sub-command's parser.
    """
    parser.add_argument("--from", dest="sources", type=Path, nargs="+", required=True, metavar="RECONSTRUCTION",
                        help="folders written by 'reachplan reconstruct ... --plan PLAN_JSON' (their needles.json)")
    parser.add_argument("--site", type=Path, required=True, metavar="FILE",
                        help="the site calibration file: created, or updated with these needles")
    parser.add_argument("--json", action="store_true", help="print the site's estimates as JSON")


def _read_json(path: Path, what: str) -> Any:
    import json

    from reachplan.planner.errors import PlanInputError

    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError) as exc:
        raise PlanInputError(f"cannot read {what} {path}: {exc}") from None


def found_steered(folder: Path) -> tuple[list[FoundSteered], list[str]]:
    """Return the steered needles of one reconstruction as planned and found, and the planned ones not found.

    Parameters
    ----------
    folder : Path
        A ``reachplan reconstruct --plan`` output.

    Returns
    -------
    needles : list of FoundSteered
        Planned and found centre lines in the template frame of each needle's hole.
    missing : list of str
        Why a steered needle of the plan is not among them (not found, its planned path not exported), and the
        needles the finder flagged (two tracks sharing their end: not used).

    Raises
    ------
    PlanInputError
        No needles.json, or one made without ``--plan``, or a plan without a delivered implant.
    """
    import numpy as np

    from reachplan.planner.errors import PlanInputError
    from reachplan.planner.lookup import load_template
    from reachplan.planner.steering.calibration import FoundSteered
    from reachplan.planner.steering.kinematic import KinematicInsertion
    from reachplan.planner.verify.implant import delivered_needles, plan_channel_paths
    from reachplan.rod_model.design import preset

    doc = _read_json(folder / "needles.json", "the reconstruction")
    plan_path = doc.get("plan") if isinstance(doc, Mapping) else None
    if not plan_path:
        raise PlanInputError(f"{folder / 'needles.json'} names no plan: reconstruct it with --plan PLAN_JSON")
    plan_json = Path(str(plan_path))
    plan = _read_json(plan_json, "the plan")
    m = np.asarray(doc["template_pose"]["patient_from_template"], dtype=float)
    template = load_template(str(doc["template"]))
    holes = {h.hole_id: np.array([*h.xy_mm, 0.0]) for h in template.needle_holes}
    config = plan.get("config", {}) if isinstance(plan, Mapping) else {}
    modulus = float(config.get("tissue_modulus_pa") or KinematicInsertion().tissue_modulus_pa)
    scales = dict((str(k), float(v)) for k, v in config.get("curvature_scale") or ())
    paths = plan_channel_paths(plan_json, plan)
    flagged = {str(n["hole_id"]): n.get("note") or "low confidence" for n in doc.get("needles", [])
               if float(n.get("confidence", 1.0)) <= FLAGGED}
    found = {str(n["hole_id"]): np.asarray(n["points_mm"], dtype=float) for n in doc.get("needles", [])
             if str(n["hole_id"]) not in flagged}
    missing = [f"{folder.name}: {h} flagged by the finder ({why}): not used" for h, why in flagged.items()]

    def local(points: np.ndarray, hole: str) -> np.ndarray:  # LPS mm -> the hole's template frame
        return (points - m[:3, 3]) @ m[:3, :3] - holes[hole]

    out = []
    for needle in delivered_needles(plan):
        if not needle.steered or needle.hole_id in flagged:
            continue
        if needle.hole_id not in found or needle.hole_id not in paths or needle.hole_id not in holes:
            what = "not found in the image" if needle.hole_id not in found else "its planned path was not exported"
            missing.append(f"{folder.name}: {needle.hole_id} {what}")
            continue
        factor = KinematicInsertion(tissue_modulus_pa=modulus).factor_for(preset(needle.design))
        out.append(FoundSteered(folder.name, needle.hole_id, needle.design, factor,
                                local(paths[needle.hole_id], needle.hole_id),
                                local(found[needle.hole_id], needle.hole_id), scales.get(needle.design, 1.0)))
    delivered = {n.hole_id for n in delivered_needles(plan)}
    for hole, points in found.items():
        if hole in delivered or hole not in holes:
            continue
        match = alternate(plan, hole, points, template, m)
        if match is not None:
            needle, path = match
            factor = KinematicInsertion(tissue_modulus_pa=modulus).factor_for(preset(needle.design))
            out.append(FoundSteered(folder.name, hole, needle.design, factor, local(path, hole), local(points, hole),
                                    scales.get(needle.design, 1.0)))
    return out, missing


def alternate(plan: Mapping[str, Any], hole: str, found_mm: np.ndarray, template: Template,
              patient_from_template: np.ndarray) -> tuple[PlannedNeedle, np.ndarray] | None:
    """Return the plan's steered candidate a needle found outside the delivered implant was inserted as, if any.

    The report lists each target's ranked candidates: a clinician may insert one of them instead of, or beside, the
    delivered needles. Among the plan's steered candidates through ``hole``
    (:func:`~reachplan.planner.verify.implant.plan_candidates`) the one whose planned centre line lies nearest the
    found one (mean distance) is taken when the found needle lies nearer it than half its mean distance from the
    hole's straight axis: a straight needle, or a steered one bent elsewhere, is not taken for it.

    Parameters
    ----------
    plan : mapping
        The plan's ``plan.json`` document.
    hole : str
        The hole the needle was found in.
    found_mm : (n, 3) float, mm, LPS
        The found centre line, template plane to tip.
    template : Template
        The plan's template.
    patient_from_template : (4, 4) float
        The template's pose.

    Returns
    -------
    (PlannedNeedle, (k, 3) float) or None
        The candidate and its planned centre line (mm, LPS, the kinematic model's insertion of its schedule); None
        when no candidate fits.
    """
    import numpy as np

    from reachplan.planner.verify.find import distances_to_line
    from reachplan.planner.verify.implant import plan_candidates, planned_paths

    m = np.asarray(patient_from_template, dtype=float)
    found = np.asarray(found_mm, dtype=float)
    axis = found[0] + np.outer([0.0, float(np.linalg.norm(found[-1] - found[0])) + 50.0], m[:3, 2])
    straight = float(np.mean(distances_to_line(found, axis)))
    best = None
    for c in plan_candidates(plan):
        if c.hole_id != hole:
            continue
        path = planned_paths([c], template, m)[hole]
        d = float(np.mean(distances_to_line(found, path)))
        if d < 0.5 * straight and (best is None or d < best[0]):
            best = (d, c, path)
    return None if best is None else (best[1], best[2])


def run(args: argparse.Namespace) -> int:
    """Fit the found steered needles, update the site file; return 0.

    Parameters
    ----------
    args : argparse.Namespace
        The ``calibrate`` options.

    Returns
    -------
    int
        0 once the site file is written.
    """
    from reachplan.imaging.files import atomic_write_bytes, json_bytes
    from reachplan.planner.errors import PlanInputError
    from reachplan.planner.steering.calibration import NeedleFit, fit_needle, site_document

    previous = _read_json(args.site, "the site calibration") if args.site.is_file() else None
    fits: list[NeedleFit] = []
    skipped: list[str] = []
    for folder in args.sources:
        needles, missing = found_steered(folder)
        skipped += missing
        for needle in needles:
            try:
                fits.append(fit_needle(needle))
            except PlanInputError as exc:
                skipped.append(str(exc))
    if not fits and previous is None:
        raise PlanInputError("no steered needle was found and fitted: " + ("; ".join(skipped) or
                                                                           "the plans have no steered needle"))
    doc = site_document(fits, previous)
    atomic_write_bytes(args.site, json_bytes(doc))
    designs: list[dict[str, Any]] = [{k: d[k] for k in ("design", "planned_factor", "factor", "ratio", "ci95_ratio",
                                                        "needles")} for d in doc["designs"]]  # type: ignore[attr-defined]
    summary = {"site": str(args.site), "fitted": len(fits), "skipped": skipped, "designs": designs}
    if args.json:
        print_json(summary, NAME)
    elif not args.quiet:
        for d in designs:
            lo, hi = d["ci95_ratio"]
            ci = f"95 % CI {lo:.3f}-{hi:.3f}" if lo is not None else "one needle: no interval"
            print(f"{d['design']}: in-tissue curvature x {d['ratio']:.3f} of the plan's model ({ci}; "
                  f"{d['needles']} needles): factor {d['factor']:.3f} against {d['planned_factor']:.3f}")
        for why in skipped:
            print(f"  not used: {why}")
        print(f"site calibration written: {args.site} (use it with 'reachplan plan --calibration {args.site}')")
    return 0
