"""The HTML report of a plan, built in memory (the caller writes the files): its sections and figures.

The terminal text is :mod:`reachplan.planner.report.terminal`, the straight-versus-steered dose comparison
:mod:`reachplan.planner.report.comparison` and the options :mod:`reachplan.planner.report.options`.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from datetime import datetime
from typing import Any

import numpy as np
from tqdm import tqdm

from reachplan.imaging.types import Volume
from reachplan.planner.case.result import PlanResult, choose_needles
from reachplan.planner.case.scene import Scene
from reachplan.planner.delivery import Delivery
from reachplan.planner.implant.case import ImplantComparison
from reachplan.planner.implant.compare import Comparison
from reachplan.planner.implant.dwells import OptimizerSettings
from reachplan.planner.report import charts, figures, reformat
from reachplan.planner.report.handoff import handoff_section
from reachplan.planner.report.html import (
    Block,
    Figure,
    Interactive,
    Paragraph,
    Report,
    Section,
    Table,
    render_html,
)
from reachplan.planner.report.options import ReportOptions
from reachplan.planner.report.terminal import (
    AIMS_LEGEND,
    aims_rows,
    implant_rows,
    plain_model,
    reach_margin_mm,
    tension_reserve_n,
)
from reachplan.planner.report.tissue import band_section, tissue_bands
from reachplan.planner.report.view3d import Needle3d, scene_figure, with_tissue_bands
from reachplan.planner.steering.candidates import Candidate
from reachplan.plugins.exporters.handoff import RESEARCH_USE
from reachplan.rod_model.select import ErrorRow


def _implant_section(delivery: Delivery | None) -> Section | None:
    """Return the implant section: Pareto curves, both arms' DVHs and the side-by-side table (None without)."""
    implant = delivery.implant if delivery is not None else None
    if delivery is None or implant is None:
        return None
    aims = delivery.aims
    rows = implant_rows(implant, delivery.aims_tables)
    blocks: list[Block] = [
        Paragraph("The implant for the whole HR-CTV, planned twice on the same anatomy and template: with straight "
                  "needles only, and with straight and steered needles (the intracavitary channels are available "
                  "to both). For each number of template needles the Pareto curve gives the best HR-CTV D90 "
                  "(EQD2) with every organ's D2cm³ held within its limit; the chosen implant of each "
                  f"arm is circled. Aims ({aims.name}, EQD2): HR-CTV D90 ≥ {aims.target_d90_eqd2_gy:g} Gy; D2cm³ "
                  + ", ".join(f"{o} < {v:g} Gy" for o, v in aims.oar_d2cc_eqd2_gy) + "."),
        Table(rows[0], tuple(rows[1:]), "Implant arms side by side (EQD2 totals, Gy)",
              numeric=tuple(range(1, len(rows[0])))),
        Figure(figures.png_bytes(charts.pareto_figure(implant.arms, aims.target_d90_eqd2_gy)),
               "Pareto curves: template needles against HR-CTV D90 (EQD2) with the organ limits held; filled: every "
               "aim met, hollow: an aim not met; circled: the chosen implant; dotted red: the 85 Gy aim. Straight: "
               "dashed orange, steered: solid cyan."),
    ]
    if any(a.plan is not None and a.plan.dvhs for a in implant.arms):
        whole = delivery.whole_dvhs
        blocks.append(Figure(
            figures.png_bytes(charts.implant_dvh_figure(implant.arms, aims,
                                                        whole=None if whole is None else whole.by_plan)),
            "Both arms' cumulative DVHs per fraction (straight dashed, steered solid; HR-CTV thicker) with the "
            f"{aims.name} aim (diamond: HR-CTV D90) and organ limits (crosses: D2cm³) marked. {dvh_volumes(delivery)}"))
    blocks += [Paragraph(f"{a.name}: {a.reason}") for a in implant.arms if a.reason]
    blocks += _needle_checks(implant)
    return Section("Implant: straight against steered", "implant", tuple(blocks))


def _needle_checks(implant: ImplantComparison) -> list[Block]:
    """Each arm's chosen needles as checked (model, tension against the limit, worst case, dwell shift); re-loads."""
    rows = []
    for a in implant.arms:
        for c in a.plan.channels if a.plan is not None else ():
            k = c.check
            if k is None:
                continue
            limit = "-" if k.tension_limit_n is None else f"{k.tension_limit_n:g} (reserve {k.tension_reserve:.0%})"
            rows.append((a.name, c.name, c.kind, c.model, _f(k.peak_tension_n), limit, _f(k.reach_error_mm),
                         _f(k.worst_reach_mm), _f(k.worst_clearance_mm), k.worst_case, _f(k.dwell_shift_mm)))
    if not rows:
        return []
    notes = [f"{a.name}: the plan was re-loaded on the re-solved paths (HR-CTV D90 "
             f"{a.needle_check.get('screening_hrctv_d90_eqd2_gy')} Gy EQD2 on the screening paths)"
             for a in implant.arms if a.needle_check.get("reloaded")]
    notes += [f"{a.name}: rejected {r['hole_id']}: {r['reason']}" for a in implant.arms
              for r in a.needle_check.get("rejected", ()) if isinstance(r, dict)]  # type: ignore[attr-defined]
    return [Table(("arm", "hole", "kind", "model", "peak tension (N)", "limit (N)", "tip from planned (mm)",
                   "worst reach (mm)", "worst clearance (mm)", "worst case", "dwell shift (mm)"), tuple(rows),
                  "Implant needles as exported: steered ones re-solved with the reference model within the tension "
                  "reserve, every one's worst case under tension, roll and entry-tilt errors",
                  numeric=(4, 6, 7, 8, 10)), *(Paragraph(n) for n in notes)]


#: Captions of the overview and workspace figures in the case section.
OVERVIEW_CAPTION = ("Overview: axial slice at the targets' mean height and the mid-sagittal slice, with the top "
                    "needle of every target (solid cyan: steered, dashed orange: straight).")
WORKSPACE_CAPTION = ("Reachable workspace: where each hole's steered needle can put its tip at the targets' depth "
                     "(template frame, seen from the patient's feet like the template map), with the targets and the "
                     "organ outlines at that depth.")


def _f(v: float, digits: int = 1) -> str:
    return f"{v:.{digits}f}" if np.isfinite(v) else "-"


def models_used(result: PlanResult) -> dict[str, str]:
    """Say what each rod model did in this plan, by rod model name (from the candidates' models).

    E.g. ``{"planar_beam": "screening with kinematic (728 candidates)"}``.

    Parameters
    ----------
    result : PlanResult
        The plan.

    Returns
    -------
    dict of str to str
        Rod model name -> what it did.
    """
    from reachplan.planner.steering.tissue_rod import TISSUE_ROD

    counts: dict[tuple[str, str], int] = {}
    for c in result.candidates:
        key = (c.model.insertion, c.model.rod_model)
        counts[key] = counts.get(key, 0) + 1
    used: dict[str, list[str]] = {}
    for (insertion, rod), n in sorted(counts.items(), key=lambda kv: f"{kv[0][0]}+{kv[0][1]}"):
        if rod:
            role = "reference re-solve" if insertion == TISSUE_ROD.name else "screening"
            used.setdefault(rod, []).append(f"{role} with {insertion} ({n} candidates)")
    return {rod: "; ".join(roles) for rod, roles in used.items()}


def _case_section(scene: Scene, result: PlanResult, case: str, template_map: Figure) -> Section:
    cfg = result.config
    oars = {o.name for o in scene.organs}
    targets = {t.name for t in scene.targets}
    organ_rows = []
    for name, mesh in scene.meshes.items():
        role = "organ at risk" if name in oars else "target ROI" if name in targets else "context"
        lo, hi = mesh.bounds
        organ_rows.append((name, role, _f(abs(float(mesh.volume)) / 1000.0),
                           " .. ".join(f"({a:.0f}, {b:.0f}, {c:.0f})" for a, b, c in (lo, hi))))
    target_rows = [(t.name, *(f"{v:.1f}" for v in t.position_mm)) for t in scene.targets]
    m = scene.patient_from_template
    template = (f"Template {scene.template.name}: {len(scene.template.needle_holes)} needle holes "
                f"({len(scene.template.holes)} in all); its centre at "
                f"({m[0, 3]:.1f}, {m[1, 3]:.1f}, {m[2, 3]:.1f}) mm, "
                f"needles advance along ({m[0, 2]:.2f}, {m[1, 2]:.2f}, {m[2, 2]:.2f}) (LPS). "
                f"{scene.template.source.splitlines()[0] if scene.template.source else ''}")
    settings = (f"Needle radius {cfg.needle_radius_mm:.2f} mm; reach tolerance {cfg.reach_tolerance_mm:g} mm; "
                f"free length up to {cfg.max_depth_mm:g} mm; stylet designs {', '.join(cfg.designs) or 'none'}; "
                + ("every feasible steered candidate re-solved with the reference model (--models reference)."
                   if cfg.models == "reference" else
                   f"each feasible steered candidate solved with the cheapest model its clearance (less "
                   f"{cfg.safety_margin_mm:g} mm) and the reach tolerance allow, the top {cfg.refine_top} per "
                   "target and those near the ranking's decision with the reference (--models scene; each "
                   "candidate's model_reason in ranking.json)."))
    return Section("Case", "case", (
        Paragraph(f"{case}. Coordinates are DICOM patient coordinates (LPS: +x patient left, +y posterior, "
                  "+z superior), in mm."),
        Table(("organ", "role", "volume (cm³)", "extent min .. max (mm)"), tuple(organ_rows), "Organs",
              numeric=(2,)),
        Table(("target", "x (mm)", "y (mm)", "z (mm)"), tuple(target_rows), "Targets (ROI centroids or points)",
              numeric=(1, 2, 3)),
        Paragraph(template),
        Paragraph(settings),
        template_map,
    ))


def _cand_cells(c: Candidate | None, steered: bool) -> tuple[str, ...]:
    if c is None:
        return ("none feasible", "", "", "") if steered else ("none feasible", "", "")
    geometry = (f"{c.hole_distance_mm:.1f} / {c.reach_error_mm:.1f} / {_f(c.clearance_mm)} ({c.closest_organ})")
    model = c.model.label
    return (c.hole_id, geometry, _f(c.peak_tension_n), model) if steered else (c.hole_id, geometry, model)


def target_order(scene: Scene, result: PlanResult) -> list[str]:
    """Return the ranked targets in the scene's order (the order the user gave them), then any others.

    Parameters
    ----------
    scene : Scene
        The scene (its targets in the user's order).
    result : PlanResult
        The ranked plan.

    Returns
    -------
    list of str
        Target names.
    """
    named = [t.name for t in scene.targets if t.name in result.ranking]
    return named + [t for t in result.ranking if t not in named]


def _ranking_section(result: PlanResult, order: Sequence[str]) -> Section:
    rows = []
    for target in order:
        cands = result.ranking[target]
        top = cands[0] if cands else None
        first = "none" if top is None or not top.feasible else "steered" if top.steered else "straight"
        rows.append((target, first, *_cand_cells(result.best(target, False), False),
                     *_cand_cells(result.best(target, True), True)))
    geometry = "from centre / reach error / clearance (closest organ), mm"
    head = ("target", "top ranked", "straight: hole", f"straight: {geometry}", "straight: model", "steered: hole",
            f"steered: {geometry}", "steered: peak tension (N)", "steered: model")
    main = Table(head, tuple(rows), "Best straight next to best steered needle per target", numeric=(7,))
    weights = result.config.weights
    detail_rows = []
    for target in order:
        for i, c in enumerate(result.ranking[target][:5], start=1):
            detail_rows.append((target, str(i), c.hole_id, "steered" if c.steered else "straight", c.design_name or "-",
                                _f(weights.score(c)), _f(c.reach_error_mm), _f(c.clearance_mm),
                                _f(c.insertion_depth_mm), _f(c.peak_tension_n), c.model.label,
                                "yes" if c.feasible else f"no: {c.reason}"))
    detail = Table(("target", "rank", "hole", "kind", "stylet", "score", "reach error (mm)", "clearance (mm)",
                    "depth (mm)", "peak tension (N)", "model", "feasible"), tuple(detail_rows),
                   "Top 5 candidates of every target (feasible first; among them the robustness-assessed "
                   "shortlist first, then by score, lower first; infeasible ones last)", numeric=(1, 5, 6, 7, 8, 9),
                   collapsed=True)
    counts: dict[str, int] = {}
    for c in result.candidates:
        counts[c.model.label] = counts.get(c.model.label, 0) + 1
    models = "; ".join(f"{m}: {n} candidates" for m, n in sorted(counts.items()))
    return Section("Ranked candidates", "ranking", (
        Paragraph(f"{len(result.candidates)} candidates scored (hole × target × schedule). Every number comes "
                  f"from the model named in its row ({models}). Straight needles are exact lines; steered "
                  "candidates are screened with the fast model and the best re-solved with the reference model. "
                  f"Score = {weights.per_mm_from_centre:g}/mm from the template centre + {weights.per_newton:g}/N "
                  f"peak tension + {weights.per_mm_reach:g}/mm reach error − {weights.per_mm_clearance:g}/mm "
                  f"clearance (up to {weights.clearance_cap_mm:g} mm) + {weights.steering_cost:g} for steering."),
        main, detail,
    ))


def _dose_section(delivery: Delivery | None, comparison: Comparison | None, dvh_png: bytes | None,
                  source_name: str, note: str, settings: OptimizerSettings) -> Section:
    blocks: list[Paragraph | Table | Figure] = []
    if comparison is not None:
        rows = comparison.rows()
        organs = [n for n, _ in rows[0].oar_d2cc_eqd2_gy] if rows else []
        table_rows = tuple(
            (r.arm, str(r.n_needles), "-" if r.needles_needed is None else str(r.needles_needed), _f(r.d90_gy, 2),
             _f(r.d90_eqd2_gy), _f(r.d98_eqd2_gy), _f(r.v100_pct), *(_f(v) for _, v in r.oar_d2cc_eqd2_gy),
             "yes" if r.aim_met else "no", r.note) for r in rows)
        aims = comparison.aims
        limits = ", ".join(f"{o} < {v:g} Gy" for o, v in aims.oar_d2cc_eqd2_gy)
        blocks += [
            Paragraph("Straight versus steered: each arm gets the best feasible needle of its kind per target "
                      "(one per hole) and its dwell times are optimised the same way (TG-43 dose, source "
                      f"{source_name}; linear programme with {settings.max_target_points} target and "
                      f"{settings.max_oar_points} points per organ, fewer than the delivered plan's: on the "
                      "demo phantom, D90 moves by up to about 2 Gy EQD2 with the point sampling, so smaller "
                      "differences between the arms are not significant). 'needed' is the smallest number of "
                      "the arm's needles, in target order, that reaches the aim. Aims ({aims.name}, EQD2 with "
                      f"{aims.fractionation.ebrt_dose_gy:g} Gy / {aims.fractionation.ebrt_fractions} fx external "
                      f"beam, {aims.fractionation.n_fractions} fractions): HR-CTV D90 ≥ "
                      f"{aims.target_d90_eqd2_gy:g} Gy; D2cm³ {limits}."),
            Table(("arm", "needles", "needed", "D90 (Gy/fx)", "D90 EQD2 (Gy)", "D98 EQD2 (Gy)", "V100 (%)",
                   *(f"{o} D2cm³ EQD2 (Gy)" for o in organs), "aim met", "note"), table_rows,
                  "Coverage, straight versus steered", numeric=tuple(range(1, 7 + len(organs)))),
        ]
        if dvh_png is not None:
            blocks.append(Figure(dvh_png, "Cumulative DVHs per fraction: solid = first arm, dashed = second arm; "
                                          "grey line = prescription."))
    elif note:
        blocks.append(Paragraph(note))
    if delivery is not None:
        opt = delivery.optimisation
        vol = {} if delivery.whole_dvhs is None else delivery.whole_dvhs.volume_cc
        rows2 = [(opt.target.name, _f(vol.get(opt.target.name, opt.target.volume_cc)), _f(opt.target.d90_gy, 2),
                  _f(opt.target.d90_eqd2_gy), _f(opt.target.d98_eqd2_gy), _f(opt.target.v100_pct), "-")]
        rows2 += [(o.name, _f(vol.get(o.name, o.volume_cc)), _f(o.d90_gy, 2), _f(o.d90_eqd2_gy), _f(o.d98_eqd2_gy),
                   _f(o.v100_pct), _f(o.d2cc_eqd2_gy)) for o in opt.oars]
        status = ((f"{delivery.aims.name} aims met" if _aims_met(delivery) else f"{delivery.aims.name} aims NOT met")
                  if opt.success else f"not solved: {opt.reason}")
        blocks += [
            Paragraph(f"Delivered plan, the one exported as the RT Plan ({delivery.kind}, {delivery.n_needles} "
                      f"needles{_intracavitary(delivery)}): {status}; {opt.reason}."),
            Table(("structure", "volume (cm³)", "D90 (Gy/fx)", "D90 EQD2 (Gy)", "D98 EQD2 (Gy)", "V100 (%)",
                   "D2cm³ EQD2 (Gy)"), tuple(rows2), "Delivered plan: dose-volume metrics",
                  numeric=(1, 2, 3, 4, 5, 6)),
        ]
        whole = delivery.whole_dvhs
        dvhs = whole.by_plan.get("delivered", opt.dvhs) if whole is not None else opt.dvhs
        if opt.success and dvhs:
            png = figures.png_bytes(charts.dvh_aims_figure(dvhs, delivery.aims, opt.target.name))
            blocks.append(Figure(png, f"Delivered plan: cumulative DVHs per fraction with the {delivery.aims.name} aim "
                                      f"(diamond: HR-CTV D90) and organ limits (crosses: D2cm³) marked. "
                                      f"{dvh_volumes(delivery)}"))
    return Section("Dose and coverage", "dose", tuple(blocks))


def dvh_volumes(delivery: Delivery) -> str:
    """Say what volume each DVH covers: every structure whole on the dose grid, or which ones the grid crops.

    Parameters
    ----------
    delivery : Delivery
        The delivered plan (its :attr:`~reachplan.planner.delivery.Delivery.whole_dvhs`).

    Returns
    -------
    str
        One or two sentences for a DVH's caption.
    """
    whole = delivery.whole_dvhs
    if whole is None:
        return ("Organ curves cover only the voxels near the loaded dwells, where D2cm³ is decided (no planned dose "
                "was computed), so their volumes are not the organs' own.")
    sizes = ", ".join(f"{n} {v:.1f} cm³" for n, v in whole.volume_cc.items())
    text = (f"Each curve covers its whole structure on one dose grid, the same for every plan ({sizes}), from the "
            "planned dose at every voxel centre.")
    cropped = whole.cropped
    if cropped:
        text += " Cropped by the images: " + ", ".join(
            f"{n} {on:.1f} of its {own:.1f} cm³" for n, (on, own) in cropped.items()) + " lie on the grid."
    return text


def _aims_met(delivery: Delivery) -> bool:
    """Return the delivered plan's verdict: the protocol's (every planning aim with headroom), else the optimiser's."""
    table = delivery.aims_tables.get("delivered")
    return delivery.optimisation.aim_met if table is None else table.aims_met


def _aims_section(delivery: Delivery | None) -> Section | None:
    """Return the protocol's section: which aims, each aim against each plan (the terminal's table), warnings."""
    if delivery is None or not delivery.aims_tables:
        return None
    from reachplan.planner.dose.evaluation import DVH_METHOD

    aims = delivery.aims
    rows = aims_rows(delivery.aims_tables)
    fr = aims.fractionation
    blocks: list[Block] = [
        Paragraph(f"Protocol: {aims.name} ({aims.site}; {aims.origin}). Source: {aims.source}. Totals of "
                  f"{fr.ebrt_dose_gy:g} Gy / {fr.ebrt_fractions} fractions external beam and {fr.n_fractions} "
                  f"brachytherapy fractions in EQD2 (α/β {aims.alpha_beta_target_gy:g} Gy targets, "
                  f"{aims.alpha_beta_oar_gy:g} Gy organs). The planning aim is what a plan is made for, the hard "
                  "limit what no delivered plan may break; both are judged separately. Aims met only when every "
                  f"planning aim holds, organs and points with {aims.headroom_eqd2_gy:g} Gy headroom."),
        Table(rows[0], tuple(rows[1:]), "Each aim against each plan (Gy EQD2): " + AIMS_LEGEND.format(
            headroom=aims.headroom_eqd2_gy), numeric=tuple(range(3, len(rows[0])))),
        Paragraph(f"Dose-volume method: {DVH_METHOD}"),
    ]
    blocks += [Paragraph(f"Warning: {w}") for w in delivery.warnings]
    return Section(f"Dose aims: {aims.name}", "aims", tuple(blocks))


def _intracavitary(delivery: Delivery) -> str:
    n = len(delivery.roles) - delivery.n_needles
    return f" and {n} intracavitary channel{'s' if n != 1 else ''}" if n else ""


def _runs(schedule: np.ndarray) -> list[tuple[float, float, float]]:
    """Schedule breakpoints (depth, tension, roll) without repeats of the same tension and roll."""
    out: list[tuple[float, float, float]] = []
    for d, t, r in schedule:
        if not out or abs(out[-1][1] - t) > 1e-6 or abs(out[-1][2] - r) > 1e-6:
            out.append((float(d), float(t), float(r)))
    return out


def _device_section(delivery: Delivery | None) -> Section:
    if delivery is None:
        return Section("Device instructions", "device", (
            Paragraph("No delivery: the plan was ranked only (--no-export)."),))
    rows = []
    for ch, (n, role) in enumerate(zip(delivery.export.needles, delivery.roles, strict=True), start=1):
        steps = ("applicator channel, placed by hand" if n.applicator else "straight needle, no tendon"
                 if n.schedule is None else
                 "; ".join(f"from {d:.1f} mm: {t:.2f} N, roll {r:.0f}°" for d, t, r in _runs(n.schedule)))
        active = n.dwell_times_s > 0
        rows.append((str(ch), n.hole_id, role, "-" if n.applicator else n.design or "plain needle",
                     _f(n.length_mm), steps,
                     str(int(active.sum())), _f(float(n.dwell_times_s.sum()))))
    src = delivery.export.source
    return Section("Device instructions", "device", (
        Paragraph("Per needle, in channel order: the template hole, the stylet, how deep to insert (arc length from "
                  "the template plane) and the tension schedule (tendon tension and roll of the bending plane, "
                  "template frame, 0° = template +x; held from each depth until the next). Only channels that carry "
                  "dwell time are listed: a needle the optimum leaves empty is not inserted. The exact rows are in "
                  "export/*_device.json, the printable bedside page export/*_device.html (the insert list, check "
                  "depths, every channel's dwells) and the CSVs; the afterloader plan in export/RP_*.dcm. Source: "
                  f"{src.title or src.name}, S_K {src.air_kerma_rate_u:.0f} U (ASSUMED planning strength)."),
        Table(("channel", "hole", "for", "stylet", "insertion depth (mm)", "schedule", "active dwells",
               "total dwell time (s)"), tuple(rows), "Device instructions", numeric=(0, 4, 6, 7)),
    ))


def _models_section(result: PlanResult, chart: bytes | None, rows: Sequence[Any], used: dict[str, str]) -> Section:
    if chart is None:
        return Section("Models: speed vs accuracy", "models", (
            Paragraph("The rod-model error table (rod_model/model_errors.json) is not available; run "
                      "`reachplan bench models --out DIR --install` from a source checkout."),))
    table = tuple((r.model, r.resolution, f"{r.median_ms:.3f}", f"{r.max_tip_error_mm:.2g}",
                   "-" if r.batched_solves_per_s is None else f"{r.batched_solves_per_s:,.0f}",
                   used.get(r.model, "") if r.resolution == "default" else "") for r in rows)
    return Section("Models: speed vs accuracy", "models", (
        Paragraph("Measured by benchmarks/rod_models.py (reachplan bench models) against the converged two-tube "
                  "Cosserat reference, over every stylet preset × tensions 0-15 N in free space; the numbers come "
                  "from the packaged table rod_model/model_errors.json, not from this run. Ringed: the rod models "
                  "this plan's candidates were computed with."),
        Figure(chart, "Time per solve against worst tip error of each rod model and resolution; labels say which "
                      "model produced which numbers of this plan."),
        Table(("rod model", "resolution", "median time per solve (ms)", "max tip error (mm)",
               "batched solves per s", "used in this plan"), table, "Measured error table", numeric=(2, 3, 4),
              collapsed=True),
    ))


def dose_overlay(delivery: Delivery | None) -> figures.DoseOverlay | None:
    """Isodoses and dwell positions of the delivered plan for the slices (None without a solved delivery).

    Parameters
    ----------
    delivery : Delivery or None
        The delivered plan.

    Returns
    -------
    figures.DoseOverlay or None
        Dose (Gy per fraction) at LPS mm points, the prescription and the active dwells.
    """
    if delivery is None or not delivery.optimisation.success:
        return None
    from reachplan.planner.dose.dwells import dose_at_points
    from reachplan.planner.dose.tg43 import Tg43Kernel

    dwells = delivery.optimisation.dwells
    active = dwells.select(dwells.times_s > 0)
    kernel = Tg43Kernel(delivery.source)
    sk = delivery.export.source.air_kerma_rate_u
    return figures.DoseOverlay(lambda p: dose_at_points(p, active, kernel, sk), delivery.aims.prescription_gy,
                               active.positions_mm, active.times_s)


def interactive_view(scene: Scene, straight: Sequence[Candidate], steered: Sequence[Candidate],
                     delivery: Delivery | None, max_faces: int) -> dict[str, Any]:
    """Return the 3-D view's plotly figure: the needles to insert, each target's best needles, the active dwells.

    Parameters
    ----------
    scene : Scene
        Organs and targets (LPS mm).
    straight : sequence of Candidate
        The chosen straight needles.
    steered : sequence of Candidate
        The chosen steered needles.
    delivery : Delivery or None
        The delivered plan (its active dwells are drawn when solved).
    max_faces : int
        Faces per organ mesh.

    Returns
    -------
    dict of str to object
        A plotly figure as a JSON-ready dict.
    """
    needles = [Needle3d.of(c) for c in (*straight, *steered)]
    handoff = delivery.export.handoff if delivery is not None else None
    if handoff is not None:  # the implant to insert first, named as in the insert list
        paths = {n.hole_id: n.path_mm for n in delivery.export.needles}  # type: ignore[union-attr]
        needles = [Needle3d(f"insert {n.hole_id} (channel {n.channel}, {n.kind})", paths[n.hole_id],
                            n.kind == "steered", implant=True) for n in handoff.needles] + needles
    elif delivery is not None:
        needles = [Needle3d(f"implant: {'steered' if n.schedule is not None else 'straight'} {n.hole_id}",
                            n.path_mm, n.schedule is not None, implant=True)
                   for n in delivery.export.needles if not n.applicator] + needles
    if delivery is None or not delivery.optimisation.success:
        return with_tissue_bands(scene_figure(scene, needles, max_faces=max_faces), tissue_bands(steered, delivery))
    dwells = delivery.optimisation.dwells
    on = dwells.times_s > 0
    holes = [n.hole_id for n in delivery.export.needles]
    labels = [f"channel {ch} ({holes[ch - 1]})" if 0 < ch <= len(holes) else f"channel {ch}"
              for ch in dwells.channels[on]]
    return with_tissue_bands(scene_figure(scene, needles, dwell_positions_mm=dwells.positions_mm[on],
                                          dwell_times_s=dwells.times_s[on], dwell_labels=labels, max_faces=max_faces),
                             tissue_bands(steered, delivery))


def _needles_section(result: PlanResult, straight: Sequence[Candidate], steered: Sequence[Candidate],
                     order: Sequence[str]) -> Section:
    """Per chosen needle: robustness, peak tension against the design limit, and the models in plain words."""
    cfg = result.config
    tol, p = cfg.reach_tolerance_mm, cfg.perturbations
    rows = []
    for c in sorted((*straight, *steered), key=lambda c: (list(order).index(c.target), c.steered)):
        limit = "-" if c.design is None else f"{c.design.max_tension_n:g}"
        margin = reach_margin_mm(c, tol)
        rows.append((c.target, "steered" if c.steered else "straight", c.hole_id, c.design_name or "-",
                     _f(c.reach_error_mm), _f(c.worst_reach_mm), "-" if not np.isfinite(margin) else f"{margin:+.1f}",
                     _f(c.clearance_mm), _f(c.worst_clearance_mm), c.worst_case or "not assessed",
                     _f(c.peak_tension_n) if c.steered else "-", limit, _f(tension_reserve_n(c)), plain_model(c)))
    infos = {c.model.label: c.model for c in (*straight, *steered)}
    settings = tuple((label, ", ".join(f"{k} = {v:g}" if isinstance(v, float) else f"{k} = {v}"
                                       for k, v in info.settings) or "-") for label, info in infos.items())
    return Section("Per needle: robustness and tension", "needles", (
        Paragraph(f"Each target's best straight and best steered needle. Robustness: the needle re-evaluated with "
                  f"the fast kinematic model under tension × (1 ± {p.tension_fraction:.0%}), roll ± {p.roll_deg:g}° "
                  f"and an entry tilt of ± {p.tilt_deg:g}° about both template axes (handheld insertions deflect "
                  "by 3.6-7.9 mm even when straight: Karius et al., Strahlenther. Onkol. 2025; the sizes are the "
                  f"planner's assumptions). Reach margin: the {tol:g} mm reach tolerance less the worst-case reach "
                  "error (+ inside, - over), with the perturbation that sets it; tension reserve: the stylet's "
                  "design limit less the peak tension. The last column says in words which model produced the "
                  "needle's numbers."),
        Table(("target", "needle", "hole", "stylet", "reach error (mm)", "worst-case miss (mm)", "reach margin (mm)",
               "clearance (mm)", "worst-case clearance (mm)", "worst case", "peak tension (N)", "design limit (N)",
               "tension reserve (N)", "model"), tuple(rows), "Robustness margins and tension per needle",
              numeric=(4, 5, 6, 7, 8, 10, 11, 12)),
        Table(("model", "settings"), settings, "Model settings (units in the names)", collapsed=True),
    ))


def template_map_block(scene: Scene, delivery: Delivery | None, straight: Sequence[Candidate],
                       steered: Sequence[Candidate]) -> Figure:
    """Return the template map: the delivered implant's holes filled (else each target's best needles, said so).

    Parameters
    ----------
    scene : Scene
        The template and its pose.
    delivery : Delivery or None
        The delivered plan; its exported needles are the implant.
    straight : sequence of Candidate
        Each target's best straight needle (used without a delivered plan).
    steered : sequence of Candidate
        Each target's best steered needle (likewise).

    Returns
    -------
    Figure
        The figure block; its alt text names the filled holes (``template map: implant holes Ab, Cc``).
    """
    if delivery is not None:
        holes = figures.implant_holes(delivery.export.needles)
        what, words = "implant", "the delivered implant's needles (the RT Plan's channels)"
    else:
        holes = [(c.hole_id, c.steered) for c in (*straight, *steered)]
        what, words = "per-target best", "each target's best straight and best steered needle (no plan delivered)"
    png = figures.template_map(scene, holes, what)
    names = ", ".join(h for h, _ in holes) or "none"
    return Figure(png, f"Template holes with their names, {figures.RADIOLOGICAL} (the same orientation as the axial "
                       f"slices); filled: the holes of {words}, straight orange and steered cyan, names in bold: "
                       f"{names}.", alt=f"template map: {what} holes {names}")


def _slice_blocks(scene: Scene, result: PlanResult, volume: Volume | None, dose: figures.DoseOverlay | None,
                  slice_targets: Sequence[str], done: Callable[[], object]) -> list[Block]:
    """Return the slices section's blocks: the caption, then each target's slice views (``done`` after each)."""
    slices: list[Block] = [Paragraph(
        "Slices through each target point (organ outlines from the meshes, image underneath); the best straight "
        "(dashed orange) and best steered (solid cyan) needle of the target are projected onto each plane, drawn "
        f"faint where more than {figures.IN_PLANE_MM:g} mm from it (a needle in front of an organ does not cross "
        "it; the slice along each implant needle shows the true gaps). "
        f"Axial slices are {figures.RADIOLOGICAL}, like the template map; coronal slices are seen from the "
        "front (patient left on the right), sagittal slices from the patient's left (anterior on the left); "
        "the letters on the edges say which side is which."
        + ("" if dose is None else " Isodose lines of the delivered plan at 50, 100, 150 and 200 % of the "
           f"prescription ({dose.prescription_gy:.2f} Gy per fraction); black dots are its active dwell "
           "positions within 2.5 mm of the plane, sized by their dwell times (the times are given along each "
           "implant needle)."))]
    for t in slice_targets:
        s, st = result.best(t, False), result.best(t, True)
        desc = "; ".join(f"{k} {c.hole_id} ({c.model.label}, reach {c.reach_error_mm:.1f} mm, clearance "
                         f"{c.clearance_mm:.1f} mm to {c.closest_organ})"
                         for k, c in (("straight", s), ("steered", st)) if c is not None) or "no feasible needle"
        slices.append(Figure(figures.slice_views(scene, t, s, st, volume, dose=dose), f"{t}: {desc}"))
        done()
    return slices


def build_report(scene: Scene, result: PlanResult, *, volume: Volume | None = None,
                 delivery: Delivery | None = None, comparison: Comparison | None = None, case: str = "case",
                 timings: Mapping[str, float] | None = None, source_name: str = "gammamed_plus_hdr",
                 comparison_note: str = "", options: ReportOptions | None = None, quiet: bool = True,
                 case_figures: Sequence[Figure] = (), model_errors: Sequence[ErrorRow] = ()) -> Report:
    """Assemble the report of a plan (figures are rendered here; nothing is solved except the drawings).

    Parameters
    ----------
    scene : Scene
        The plan's scene (:func:`reachplan.planner.case.scene.build_scene`).
    result : PlanResult
        The ranked plan (:func:`reachplan.planner.case.search.plan`).
    volume : Volume or None
        The image series, drawn under the organ outlines.
    delivery : Delivery or None
        The delivered plan (:func:`reachplan.planner.delivery.plan_delivery`), or None (ranked only).
    comparison : Comparison or None
        Straight versus steered (:func:`reachplan.planner.report.comparison.compare_chosen`), or None
        (``comparison_note`` says why).
    case : str
        One line naming the case.
    timings : mapping of str to float, s, or None
        Seconds per stage, shown at the end.
    source_name : str
        The TG-43 source's name, for the dose section.
    comparison_note : str
        Why there is no comparison.
    options : ReportOptions or None
        What to compute and draw (None: the defaults).
    quiet : bool
        No progress bar.
    case_figures : sequence of Figure
        Further figures for the case section (e.g. the overview and workspace figures).
    model_errors : sequence of ErrorRow
        The measured rod-model error table (:func:`reachplan.planner.run.case.rod_model_errors`) for the
        speed-versus-accuracy section; empty: the section says it is not available.

    Returns
    -------
    Report
        The report's sections, ready for :func:`reachplan.planner.report.html.render_html`.
    """
    options = options or ReportOptions()
    straight, steered = choose_needles(result, steered=False), choose_needles(result, steered=True)
    order = target_order(scene, result)
    slice_targets = order[: options.max_slice_targets]
    bar = tqdm(total=4 + len(slice_targets), desc="report", unit="figure", disable=quiet, leave=False)
    try:
        case_sec = _case_section(scene, result, case, template_map_block(scene, delivery, straight, steered))
        case_sec = Section(case_sec.title, case_sec.anchor, (*case_sec.blocks, *case_figures))
        bar.update()
        slices = _slice_blocks(scene, result, volume, dose_overlay(delivery), slice_targets, bar.update)
        view = interactive_view(scene, straight, steered, delivery, options.mesh_faces)
        bar.update()
        dvh = charts.dvh_png(comparison) if comparison is not None else None
        bar.update()
        rows: Sequence[ErrorRow] = tuple(model_errors)
        used = models_used(result)
        chart = charts.speed_accuracy(rows, used) if rows else None
        bar.update()
    finally:
        bar.close()
    n_reach = {k: sum(result.best(t, k) is not None for t in result.ranking) for k in (False, True)}
    subtitle = (f"{case}: {len(result.ranking)} targets; a straight needle reaches {n_reach[False]}, a steered one "
                f"{n_reach[True]}" + ("" if delivery is None else
                                      f"; delivered plan HR-CTV D90 {delivery.optimisation.target.d90_eqd2_gy:.1f} Gy "
                                      f"EQD2 ({'aims met' if _aims_met(delivery) else 'aims not met'})"))
    sections: list[Section | None] = [
        handoff_section(delivery, scene),
        case_sec,
        _ranking_section(result, order),
        Section("Slices through the targets", "slices", tuple(slices)),
        reformat.reformat_section(scene, result.config.needle_radius_mm, volume, delivery, dose_overlay(delivery)),
        Section("3-D view", "views-3d", (
            Paragraph("Organs, the target points, the template holes, the needles to insert (legend 'insert "
                      "<hole>'), each target's best straight and best steered "
                      "needle and the delivered plan's dwell positions, in an interactive view: drag to turn, scroll "
                      "to zoom, click a legend entry to hide or show it (bone and obturator start hidden); the "
                      "buttons turn it to the named views and the title says from where it is seen. It opens "
                      f"{figures.RADIOLOGICAL.removeprefix('seen ')}. Organs are decimated to about "
                      f"{options.mesh_faces} faces each for drawing only."),
            Interactive(view, "3-D view of organs, needles, dwell positions and template (mm, LPS)"),
        )),
        _needles_section(result, straight, steered, order),
        band_section(result.config, tissue_bands(steered, delivery)),
        _dose_section(delivery, comparison, dvh, source_name, comparison_note, options.comparison_settings),
        _aims_section(delivery),
        _implant_section(delivery),
        _device_section(delivery),
        _models_section(result, chart, rows, used),
    ]
    if timings:
        sections.append(Section("Run", "run", (Table(("stage", "seconds"),
                                                     tuple((k.removesuffix("_s"), f"{v:.1f}")
                                                           for k, v in timings.items()),
                                                     "Wall time per stage", numeric=(1,)),)))
    return Report(f"reachplan report: {case}", subtitle, tuple(s for s in sections if s is not None), RESEARCH_USE)


def report_html(scene: Scene, result: PlanResult, *, volume: Volume | None = None, delivery: Delivery | None = None,
                comparison: Comparison | None = None, comparison_note: str = "", case: str = "case",
                timings: Mapping[str, float] | None = None, source_name: str = "gammamed_plus_hdr",
                options: ReportOptions | None = None, quiet: bool = True, overview_png: bytes | None = None,
                workspace_png: bytes | None = None, model_errors: Sequence[ErrorRow] = ()) -> str:
    """Build the report and render it as one self-contained HTML document, returned as text for the caller to write.

    Nothing is solved here: ``comparison`` (and ``comparison_note``) come from :func:`straight_vs_steered`, the
    implant arms from ``delivery``.

    Parameters
    ----------
    scene : Scene
        The plan's scene.
    result : PlanResult
        The ranked plan.
    volume : Volume or None
        The image series, drawn under the organ outlines.
    delivery : Delivery or None
        The delivered plan, or None (ranked only).
    comparison : Comparison or None
        Straight versus steered.
    comparison_note : str
        Why there is no comparison.
    case : str
        One line naming the case.
    timings : mapping of str to float, s, or None
        Seconds per stage.
    source_name : str
        The TG-43 source's name.
    options : ReportOptions or None
        What to compute and draw.
    quiet : bool
        No progress bar.
    overview_png : bytes or None
        The overview figure (:func:`reachplan.planner.report.figures.overview`), embedded in the case section.
    workspace_png : bytes or None
        The workspace figure (:func:`reachplan.planner.report.workspace.workspace_figure`), likewise.
    model_errors : sequence of ErrorRow
        See :func:`build_report`.

    Returns
    -------
    str
        The HTML document.
    """
    from importlib.metadata import PackageNotFoundError, version

    try:
        release = version("reachplan")
    except PackageNotFoundError:
        release = "(not installed)"
    extra = tuple(Figure(png, caption) for png, caption in ((overview_png, OVERVIEW_CAPTION),
                                                             (workspace_png, WORKSPACE_CAPTION)) if png is not None)
    report = build_report(scene, result, volume=volume, delivery=delivery, comparison=comparison, case=case,
                          timings=timings, source_name=source_name, comparison_note=comparison_note, options=options,
                          quiet=quiet, case_figures=extra, model_errors=model_errors)
    footer = (f"reachplan {release}, {datetime.now().replace(microsecond=0).isoformat()}. A pre-plan for "
              "research use; not a treatment plan.")
    return render_html(report, footer)
