"""The hand-off: the delivered implant's "insert these" list, built once (:func:`insert_list`).

From the exported plan (the channels the RT Plan carries, so the names are those of the RT Plan and plan.json), the
scene (template pose, organs) and the plan's settings, each template needle gets:

- its tension schedule in words, the bending direction in patient terms: the roll of the bending plane is in the
  template frame (0 = template +x, 90 = +y, :class:`~reachplan.planner.steering.schedule.TensionSchedule`), turned
  into the patient frame by the template pose and named by its largest components (left/right, anterior/posterior,
  superior/inferior);
- robustness **margins**: the needle's path re-evaluated under each perturbation of ``PlanConfig.perturbations``
  (the robustness room's :func:`~reachplan.planner.steering.robustness.perturbed_paths`, fast kinematic model at the
  modulus of the tissue at its tip), the largest tip displacement from the planned tip against the reach tolerance
  and the smallest clearance to an organ against the implant's clearance margin, each with the perturbation that
  causes it;
- check depths (where the pull starts, where it reaches full tension, the tip; half way for a straight needle) with
  the expected tip position there: the point of the planned path at that arc length (the shaft follows the track its
  tip cut), and its distance and direction from the hole's straight line.

The terminal, the report and the device instructions print this one record
(:class:`~reachplan.plugins.exporters.handoff.InsertList`).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping, Sequence

import numpy as np

from reachplan._arrays import arc_length_mm
from reachplan.planner.case.config import PlanConfig, PlanModels
from reachplan.planner.case.result import PlanResult, choose_needles
from reachplan.planner.case.scene import Scene
from reachplan.planner.case.search import target_modulus_pa
from reachplan.planner.delivery import Delivery
from reachplan.planner.steering.candidates import Target, score_path
from reachplan.planner.steering.insertion import STRAIGHT
from reachplan.planner.steering.robustness import perturbed_paths
from reachplan.planner.steering.schedule import TensionSchedule
from reachplan.plugins.exporters.base import ExportPlan, NeedleExport
from reachplan.plugins.exporters.handoff import (
    ApplicatorChannel,
    CheckDepth,
    InsertList,
    InsertNeedle,
    Margin,
    Scenario,
)
from reachplan.rod_model.design import RodDesign

#: Patient directions of the LPS axes (+x left, +y posterior, +z superior), negative then positive.
DIRECTIONS = (("the patient's right", "the patient's left"), ("anterior", "posterior"), ("inferior", "superior"))
#: A component counts in a direction's name when it is at least this share of the largest (cos 60 deg ~ 0.5 of it).
SECONDARY_SHARE = 0.5
#: An offset or bend smaller than this (mm, degrees) is "none".
NEGLIGIBLE = 0.5
#: An applicator channel's entry and tip directions are the chords of its first and last this many mm.
END_CHORD_MM = 2.0
#: An applicator channel's radius of curvature is the tightest over any window of this arc length.
RADIUS_WINDOW_MM = 20.0

#: How the robustness room labels an entry tilt (every other perturbation but "nominal" is a steering error).
TILT = "entry tilt"

#: Each implant arm's plan in words (as :attr:`~reachplan.planner.delivery.Delivery.kind` names the delivered one).
ARM_PLANS = {"straight": "implant, straight", "steered": "implant, straight + steered"}

#: Where the margins' perturbation sizes come from.
PERTURBATION_SOURCE = (
    "Sizes ASSUMED (PlanConfig.perturbations); for scale, handheld straight needles deviate by 3.6 ± 2.1 to "
    "7.9 ± 3.0 mm at the tip (Karius et al., Strahlenther. Onkol. 2025), and a 2 deg tilt moves a tip 100 mm deep "
    "by 3.5 mm.")


def toward(vector_lps: np.ndarray) -> str:
    """Name a direction in patient terms, e.g. ``"anterior and the patient's left"``.

    Parameters
    ----------
    vector_lps : (3,) float, LPS
        Any non-zero vector (not normalised).

    Returns
    -------
    str
        The largest component's direction, then any other of at least :data:`SECONDARY_SHARE` of it; "" for a
        zero vector.
    """
    v = np.asarray(vector_lps, dtype=float)
    mags = np.abs(v)
    if not mags.max() > 0:
        return ""
    order = [int(i) for i in np.argsort(-mags, kind="stable") if mags[i] >= SECONDARY_SHARE * mags.max()]
    return " and ".join(DIRECTIONS[i][int(v[i] > 0)] for i in order)


def bend_direction(roll_deg: float, patient_from_template: np.ndarray) -> np.ndarray:
    """Return the direction a needle bends to at a roll of its bending plane, in the patient frame.

    Parameters
    ----------
    roll_deg : float, degrees
        Roll of the bending plane, template frame (0 = template +x, 90 = template +y).
    patient_from_template : (4, 4) float
        The template pose.

    Returns
    -------
    (3,) float, unit, LPS
        The bending direction.
    """
    a = np.radians(roll_deg)
    return np.asarray(patient_from_template, float)[:3, :3] @ np.array([np.cos(a), np.sin(a), 0.0])


def schedule_words(rows: np.ndarray, patient_from_template: np.ndarray, depth_mm: float) -> str:
    """Say a tension schedule in words: where to pull, how hard, toward which side of the patient.

    Parameters
    ----------
    rows : (k, 3) float
        Breakpoints ``(depth mm, tension N, roll deg)``, piecewise linear, constant outside.
    patient_from_template : (4, 4) float
        The template pose (turns the roll into a patient direction).
    depth_mm : float, mm
        The insertion depth (the schedule's end).

    Returns
    -------
    str
        E.g. ``tendon slack from 0 to 40 mm; 40-45 mm: pull from 0.0 to 5.7 N, bending toward anterior (roll 270 deg);
        hold 5.7 N from 45 to 112 mm``.
    """
    d = np.r_[0.0, rows[:, 0], depth_mm]
    t = np.interp(d, rows[:, 0], rows[:, 1])
    r = np.interp(d, rows[:, 0], rows[:, 2])
    keep = np.r_[True, np.diff(d) > 1e-6] & (d <= depth_mm + 1e-6)
    d, t, r = d[keep], t[keep], r[keep]
    same = np.abs(np.diff(t)) < 1e-6
    same &= np.abs(np.diff(r)) < 1e-6
    inner = np.r_[False, same[:-1] & same[1:], False]  # a breakpoint inside one hold says nothing
    d, t, r = d[~inner], t[~inner], r[~inner]
    parts: list[str] = []
    for k in range(len(d) - 1):
        a, b = f"{d[k]:.0f}", f"{d[k + 1]:.0f}"
        side = (f", bending toward {toward(bend_direction(r[k + 1], patient_from_template))} "
                f"(roll {r[k + 1] % 360:.0f} deg)")
        if abs(t[k + 1] - t[k]) > 1e-6:
            verb = "pull" if t[k + 1] > t[k] else "release"
            parts.append(f"{a}-{b} mm: {verb} from {t[k]:.1f} to {t[k + 1]:.1f} N{side}")
        elif abs(r[k + 1] - r[k]) > 1e-6 and t[k] > 0:
            parts.append(f"{a}-{b} mm: roll from {r[k] % 360:.0f} to {r[k + 1] % 360:.0f} deg at {t[k]:.1f} N")
        elif t[k] > 0:
            parts.append(f"hold {t[k]:.1f} N from {a} to {b} mm")
        else:
            parts.append(f"tendon slack from {a} to {b} mm")
    return "; ".join(parts)


def _points_at(path_mm: np.ndarray, s_mm: Sequence[float] | np.ndarray) -> np.ndarray:
    """Points (mm, LPS) at arc lengths ``s_mm`` along ``path_mm``."""
    s = arc_length_mm(path_mm)
    return np.column_stack([np.interp(s_mm, s, path_mm[:, j]) for j in range(3)])


def check_depths(path_mm: np.ndarray, rows: np.ndarray | None, patient_from_template: np.ndarray,
                 min_gap_mm: float = 5.0) -> tuple[CheckDepth, ...]:
    """Return the depths to image a needle at, with the expected tip position there.

    A steered needle: where the pull starts, where it reaches its full tension, and the tip; a straight needle: half
    way and the tip. Depths closer than ``min_gap_mm`` to a deeper one are dropped.

    Parameters
    ----------
    path_mm : (n, 3) float, mm, LPS
        The planned path, hole (template plane) to tip.
    rows : (k, 3) float or None
        The schedule's breakpoints ``(depth mm, tension N, roll deg)``; None: a straight needle.
    patient_from_template : (4, 4) float
        The template pose (its z axis is the hole's straight line's direction).
    min_gap_mm : float, mm
        Smallest distance between two check depths.

    Returns
    -------
    tuple of CheckDepth
        Shallowest first, the tip last.
    """
    depth = float(arc_length_mm(path_mm)[-1])
    wanted: list[tuple[float, str]] = [(depth / 2, "half way")]
    if rows is not None and np.any(rows[:, 1] > 0):
        on = np.flatnonzero(rows[:, 1] > 0)
        start = float(rows[on[0] - 1, 0]) if on[0] > 0 else 0.0
        full = float(rows[int(np.argmax(rows[:, 1])), 0])
        wanted = [(start, "the pull starts"), (full, "full tension")]
    wanted = [(d, w) for d, w in wanted if 0 < d < depth - min_gap_mm] + [(depth, "tip")]
    kept: list[tuple[float, str]] = []
    for d, w in reversed(wanted):
        if not kept or kept[-1][0] - d >= min_gap_mm:
            kept.append((d, w))
    kept.reverse()
    axis = np.asarray(patient_from_template, float)[:3, 2]
    tips = _points_at(path_mm, [d for d, _ in kept])
    out = []
    for (d, what), tip in zip(kept, tips, strict=True):
        rel = tip - path_mm[0]
        off = rel - (rel @ axis) * axis
        size = float(np.linalg.norm(off))
        out.append(CheckDepth(d, (float(tip[0]), float(tip[1]), float(tip[2])), size,
                              toward(off) if size >= NEGLIGIBLE else "", what))
    return tuple(out)


def _margins(needle: NeedleExport, design: RodDesign | None, scene: Scene, config: PlanConfig,
             models: PlanModels, clearance_margin_mm: float) -> tuple[Margin, Margin, tuple[Scenario, ...]]:
    """Worst tip displacement and smallest clearance of one needle over the perturbations, and every scenario."""
    path, m = needle.path_mm, scene.patient_from_template
    depth, tip = needle.length_mm, needle.path_mm[-1]
    schedule = None if needle.schedule is None or design is None else TensionSchedule(
        needle.schedule[:, 0], needle.schedule[:, 1], needle.schedule[:, 2])
    radius = config.needle_radius_mm if design is None else design.needle.outer_diameter_mm / 2
    planned = Target(f"{needle.hole_id} planned tip", (float(tip[0]), float(tip[1]), float(tip[2])))
    robustness = dataclasses.replace(models.robustness, tissue_modulus_pa=target_modulus_pa(scene, planned, config))
    inv = np.linalg.inv(m)
    hole_distance = float(np.linalg.norm((inv[:3, :3] @ path[0] + inv[:3, 3])[:2]))
    tol = config.reach_tolerance_mm

    def score(label: str, p: np.ndarray) -> Scenario:
        c = score_path(planned, needle.hole_id, hole_distance, p, scene.organs, radius, tol, STRAIGHT,
                       steered=schedule is not None, depth_mm=depth)
        return Scenario(label, float(np.linalg.norm(p[-1] - tip)), 0.0 if c.collides else c.clearance_mm,
                        c.closest_organ)

    scenarios = (score("nominal", path), *(score(label, p) for label, p in perturbed_paths(
        path, depth, m, config.perturbations, robustness, design, schedule)))
    return (*_worst(scenarios, tol, clearance_margin_mm), scenarios)


def _worst(scenarios: Sequence[Scenario], tolerance_mm: float, clearance_margin_mm: float) -> tuple[Margin, Margin]:
    """Return the reach and clearance margins over ``scenarios`` (the first of equals: nominal when none is worse)."""
    reach = max(scenarios, key=lambda s: s.reach_mm)
    clear = min(scenarios, key=lambda s: s.clearance_mm)
    return (Margin(reach.reach_mm, tolerance_mm, tolerance_mm - reach.reach_mm, reach.label),
            Margin(clear.clearance_mm, clearance_margin_mm, clear.clearance_mm - clearance_margin_mm, clear.label,
                   clear.organ))


def steering_margins(scenarios: Sequence[Scenario], tolerance_mm: float,
                     clearance_margin_mm: float) -> tuple[Margin, Margin] | None:
    """Return the margins over the steering errors alone: the nominal path and the tension and roll errors.

    Parameters
    ----------
    scenarios : sequence of Scenario
        A needle's scenarios (nominal first), labelled as
        :func:`~reachplan.planner.steering.robustness.perturbed_paths` labels them (tilts start with
        :data:`TILT`).
    tolerance_mm : float, mm
        The reach tolerance.
    clearance_margin_mm : float, mm
        The clearance margin.

    Returns
    -------
    (Margin, Margin) or None
        Reach and clearance margins; None when there is no steering error (a straight needle).
    """
    steering = [s for s in scenarios if not s.label.startswith(TILT)]
    return _worst(steering, tolerance_mm, clearance_margin_mm) if len(steering) > 1 else None


def channel_geometry(needle: NeedleExport, channel: int) -> ApplicatorChannel:
    """Return an applicator channel's length and curvature.

    Parameters
    ----------
    needle : NeedleExport
        The channel (``applicator`` True), path mm LPS, base to tip.
    channel : int
        Its channel number.

    Returns
    -------
    ApplicatorChannel
        Arc length; the angle between its entry and tip directions (the chords of its first and last
        :data:`END_CHORD_MM`: on an arc of radius R that is END_CHORD_MM / R rad less than the turn); the tightest
        radius over any :data:`RADIUS_WINDOW_MM` of it (the turn between the chords at both ends of the window:
        exact on an arc); the direction it turns toward (the tip direction's part across the entry direction) in
        patient terms.
    """
    path = needle.path_mm
    length = float(arc_length_mm(path)[-1])
    n = max(10, int(np.ceil(length / END_CHORD_MM)))
    step = length / n
    pts = _points_at(path, np.linspace(0.0, length, n + 1))
    tangents = np.diff(pts, axis=0)
    tangents /= np.maximum(np.linalg.norm(tangents, axis=1, keepdims=True), 1e-12)
    bend = float(np.degrees(np.arccos(np.clip(tangents[0] @ tangents[-1], -1.0, 1.0))))
    w = max(1, min(len(tangents) - 1, round(RADIUS_WINDOW_MM / step)))
    turns = np.arccos(np.clip(np.einsum("ij,ij->i", tangents[:-w], tangents[w:]), -1.0, 1.0)) if w < len(
        tangents) else np.zeros(1)
    radius = float(w * step / turns.max()) if turns.max() > 1e-9 else float("inf")
    turn = tangents[-1] - (tangents[-1] @ tangents[0]) * tangents[0]  # the tip direction across the entry direction
    words = toward(turn) if bend >= NEGLIGIBLE else ""
    return ApplicatorChannel(channel, needle.hole_id, length, bend, radius if words else float("inf"), words)


def obstacles_line(scene: Scene) -> str:
    """Say which ROIs were taken as applicators, and which of them the needles keep off.

    Parameters
    ----------
    scene : Scene
        Its applicators (recognised by TG-263 name or ``--applicator``) and organs.

    Returns
    -------
    str
        E.g. ``applicators: Tandem (tandem; an obstacle: needles keep off it), Obturator (obturator; not an
        obstacle)``.
    """
    organs = {o.name.casefold() for o in scene.organs}
    parts = []
    for a in scene.applicators:
        name = a.roi_name or a.name
        obstacle = a.obstacle and name.casefold() in organs
        parts.append(f"{name} ({a.kind}; {'an obstacle: needles keep off it' if obstacle else 'not an obstacle'})")
    if not parts:
        return ("applicators: none recognised (name them by TG-263 name, e.g. Tandem, Ring, Ovoid, Cylinder, "
                "Obturator, or with --applicator KIND=ROI)")
    return "applicators: " + ", ".join(parts)


def _needle_words(design: RodDesign | None, radius_mm: float) -> str:
    """Return the needle type in words: gauge (when known) and outer diameter."""
    if design is not None:
        return f"{design.needle.gauge} ga plastic needle, {design.needle.outer_diameter_mm:.2f} mm OD"
    return f"plastic needle, {2 * radius_mm:.2f} mm OD"


def insert_list(export: ExportPlan, scene: Scene, config: PlanConfig, *, plan: str, clearance_margin_mm: float,
                models: PlanModels | None = None, model_of: Mapping[str, str] | None = None) -> InsertList:
    """Build the "insert these" list of an exported plan (module docstring).

    Parameters
    ----------
    export : ExportPlan
        The plan as exported: its channels (paths mm LPS, schedules, dwells), in RT Plan channel order.
    scene : Scene
        Template pose, organs at risk (meshes, LPS mm) and applicators.
    config : PlanConfig
        Stylet designs, needle radius, reach tolerance, perturbations and tissue moduli.
    plan : str
        Which plan this is (e.g. ``implant, straight + steered``).
    clearance_margin_mm : float, mm
        The clearance a needle must keep from every organ (the implant's).
    models : PlanModels or None
        Its robustness model re-inserts the perturbed schedules; :meth:`PlanModels.for_config` when None.
    model_of : mapping of str to str or None
        The model behind each needle's path, by hole id ("" when not given).

    Returns
    -------
    InsertList
        Needles in channel order, applicator channels, the perturbation model and the rules.
    """
    models = models or PlanModels.for_config(config)
    designs = {d.name: d for d in config.rod_designs}
    m = scene.patient_from_template
    needles: list[InsertNeedle] = []
    applicators: list[ApplicatorChannel] = []
    for ch, n in enumerate(export.needles, start=1):
        if n.applicator:
            applicators.append(channel_geometry(n, ch))
            continue
        rows = n.schedule  # None: a straight needle; a stylet the plan does not know gets no tension errors
        design = designs.get(n.design) if rows is not None else None
        reach, clear, scenarios = _margins(n, design, scene, config, models, clearance_margin_mm)
        words = ("straight: no tendon; insert to the depth" if rows is None
                 else schedule_words(np.asarray(rows), m, n.length_mm))
        peak = 0.0 if rows is None else float(np.max(rows[:, 1]))
        needles.append(InsertNeedle(ch, n.hole_id, "straight" if rows is None else "steered",
                                    _needle_words(design, config.needle_radius_mm), "" if rows is None else n.design,
                                    n.length_mm, words, peak, None if design is None else design.max_tension_n,
                                    reach, clear, check_depths(n.path_mm, rows, m),
                                    (model_of or {}).get(n.hole_id, ""), scenarios,
                                    steering_margins(scenarios, config.reach_tolerance_mm, clearance_margin_mm)))
    return InsertList(plan, tuple(needles), tuple(applicators), perturbation_words(config, clearance_margin_mm),
                      tension_rule(needles, config.reach_tolerance_mm), obstacles_line(scene))


def perturbation_words(config: PlanConfig, clearance_margin_mm: float) -> str:
    """State the perturbation model behind the margins, with its source.

    Parameters
    ----------
    config : PlanConfig
        Its perturbations and reach tolerance.
    clearance_margin_mm : float, mm
        The clearance margin.

    Returns
    -------
    str
        The perturbations, how a margin is read, and :data:`PERTURBATION_SOURCE`.
    """
    p = config.perturbations
    return (f"Margins (+ on the safe side, - over; the perturbation that sets each is named): reach = the "
            f"{config.reach_tolerance_mm:g} mm reach tolerance less the largest tip displacement, clearance = the "
            f"smallest clearance to an organ at risk less the {clearance_margin_mm:g} mm clearance margin, over "
            f"tension x (1 ± {p.tension_fraction:.0%}) and roll ± {p.roll_deg:g} deg (steered needles) and an "
            f"entry tilt of ± {p.tilt_deg:g} deg about both template axes (every needle), re-inserted with the fast "
            "kinematic model. "
            + PERTURBATION_SOURCE)


def tension_rule(needles: Sequence[InsertNeedle], reach_tolerance_mm: float) -> str:
    """Say what to do at the stylet's tension limit.

    Parameters
    ----------
    needles : sequence of InsertNeedle
        The needles to insert (the steered ones' limits and reserves are named).
    reach_tolerance_mm : float, mm
        How far a tip may be from its expected position at a check depth.

    Returns
    -------
    str
        The rule; "" when no needle is steered.
    """
    steered = [n for n in needles if n.tension_limit_n is not None]
    if not steered:
        return ""
    limits = ", ".join(f"{n.hole_id} {n.tension_limit_n:g} N (plan {n.peak_tension_n:.1f} N, reserve "
                       f"{n.reserve_n:.1f} N)" for n in steered if n.reserve_n is not None)
    return (f"At the tension limit: never pull a tendon past the stylet's design limit ({limits}). If a check "
            f"depth's image puts the tip more than {reach_tolerance_mm:g} mm from its expected position at the "
            "planned tension, do not pull harder: withdraw to the previous check depth and re-insert with the "
            "planned schedule; if it misses again, leave the stylet slack, finish the needle straight or remove it, "
            "and re-plan the dwell times on the needles as imaged.")


def _models_by_hole(export: ExportPlan, delivery: Delivery, result: PlanResult) -> dict[str, str]:
    """Return the model behind each exported needle's path: its implant arm's channel, else its ranked candidate."""
    names = {n.hole_id for n in export.needles}
    for arm in delivery.implant.arms if delivery.implant is not None else ():
        if arm.plan is not None and {c.name for c in arm.plan.channels} == names:
            return {c.name: c.model for c in arm.plan.channels}
    return {c.hole_id: c.model.label for c in choose_needles(result)}


def with_handoff(delivery: Delivery, scene: Scene, result: PlanResult, clearance_margin_mm: float) -> Delivery:
    """Return the delivery whose exports (the delivered plan's, each implant arm's) carry their insert lists.

    Parameters
    ----------
    delivery : Delivery
        The delivered plan and its arms' exports.
    scene : Scene
        Template pose, organs and applicators.
    result : PlanResult
        The ranked plan (its settings; the per-target needles' models).
    clearance_margin_mm : float, mm
        The implant's clearance margin.

    Returns
    -------
    Delivery
        ``export.handoff`` and every ``implant_exports[arm].handoff`` set (an arm's export that is the delivered one
        shares its list).
    """
    config = result.config
    models = PlanModels.for_config(config)
    built: dict[tuple[tuple[str, bytes], ...], InsertList] = {}

    def build(export: ExportPlan, plan: str) -> ExportPlan:
        key = tuple((n.hole_id, n.path_mm.tobytes()) for n in export.needles)  # an arm's export may be the delivered
        if key not in built:
            built[key] = insert_list(export, scene, config, plan=plan, clearance_margin_mm=clearance_margin_mm,
                                     models=models, model_of=_models_by_hole(export, delivery, result))
        return dataclasses.replace(export, handoff=built[key])

    export = build(delivery.export, delivery.kind)
    arms = {name: build(ex, ARM_PLANS.get(name, f"implant, {name}")) for name, ex in delivery.implant_exports.items()}
    return dataclasses.replace(delivery, export=export, implant_exports=arms)
