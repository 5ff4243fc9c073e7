"""Where a plan's needles really go: the planned paths from ``plan.json`` and each one drawn off its plan.

A post-insertion image for tests and demos needs needles that are not where the plan put them, as a hand inserts
them: each needle deviates as the planner's own uncertainty model says it can (``config.perturbations`` of the plan:
:class:`reachplan.planner.steering.robustness.Perturbations`), one draw per needle from a seeded generator: the entry
tilted about the hole by an angle uniform in ``[0, tilt_deg]`` toward a uniform direction of the template plane, and
for a steered needle the tension scaled by ``1 + u``, ``u`` uniform in ``±tension_fraction`` (at most the stylet's
limit), and the roll offset uniform in ``±roll_deg`` (the kinematic insertion model re-inserts it). The planned
path of a steered needle is the kinematic model's insertion of its schedule (within the model's error of the
plan's reference path); a straight one runs along the hole's axis to its depth.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from reachplan.imaging.case_spec import PhantomSpec
from reachplan.planner.errors import PlanInputError
from reachplan.plugins.templates import Template

#: Length of needle outside the template (hub side) painted into the image, mm.
OUTSIDE_MM = 40.0


@dataclass(frozen=True)
class PlannedNeedle:
    """One needle of a plan, as ``plan.json`` gives it.

    Parameters
    ----------
    hole_id : str
        The template hole.
    depth_mm : float, mm
        Inserted length beyond the template plane.
    design : str
        Stylet preset ("" for a straight needle).
    schedule : (k, 3) float or None
        Rows of depth mm, tension N, roll degrees; None for a straight needle.
    extra : bool
        A needle added to the plan's for the test image (straight, not planned).
    """

    hole_id: str
    depth_mm: float
    design: str = ""
    schedule: np.ndarray | None = None
    extra: bool = False

    @property
    def steered(self) -> bool:
        """Whether the needle carries a stylet schedule."""
        return self.schedule is not None and bool(self.design)


@dataclass(frozen=True)
class DrawnNeedle:
    """A needle as it lies after insertion, with the deviation drawn for it.

    Parameters
    ----------
    needle : PlannedNeedle
        The plan's needle.
    planned_mm : (n, 3) float, mm, LPS
        Its planned centre line, hole to tip.
    actual_mm : (n, 3) float, mm, LPS
        Where it really lies, hole to tip.
    deviation : mapping of str to float
        The draw: ``tilt_deg``, ``tilt_azimuth_deg`` (template frame), ``tension_factor``, ``roll_offset_deg``.
    """

    needle: PlannedNeedle
    planned_mm: np.ndarray
    actual_mm: np.ndarray
    deviation: Mapping[str, float]


def delivered_needles(doc: Mapping[str, object]) -> list[PlannedNeedle]:
    """Return the template needles of the delivered implant of a ``plan.json`` document.

    Parameters
    ----------
    doc : mapping
        ``plan.json`` as read: ``delivery.needles`` names the delivered channels; the implant arm holding exactly
        those gives each needle's depth, design and schedule.

    Returns
    -------
    list of PlannedNeedle
        The needles through template holes (applicator channels left out), in the plan's order.

    Raises
    ------
    PlanInputError
        A plan without a delivered implant.
    """
    delivery, implant = doc.get("delivery"), doc.get("implant")
    if not isinstance(delivery, Mapping) or not isinstance(implant, Mapping):
        raise PlanInputError("the plan has no delivered implant (plan.json without 'delivery' and 'implant'); plan "
                             "it with the implant (no --no-implant, no --no-export)")
    names = list(delivery.get("needles") or [])
    for arm in ("steered", "straight"):
        needles = implant.get(arm, {}).get("needles", []) if isinstance(implant.get(arm), Mapping) else []
        if sorted(n["hole_id"] for n in needles) == sorted(names):
            return [PlannedNeedle(n["hole_id"], float(n["tissue_length_mm"]), n.get("design") or "",
                                  None if n.get("schedule") is None else np.asarray(n["schedule"], dtype=float))
                    for n in needles if n["kind"] in ("straight", "steered")]
    raise PlanInputError(f"no implant arm of the plan holds the delivered needles {names}")


#: Needles added to a plan's for a post-insertion image go through holes at least this far (mm) from every hole used:
#: no two in adjacent holes.
HOLE_SPACING_MM = 14.0


def _spaced(xy_mm: np.ndarray, used: Sequence[np.ndarray]) -> bool:
    """Whether a hole at ``xy_mm`` (template frame, mm) lies :data:`HOLE_SPACING_MM` or more from every used one."""
    return all(float(np.hypot(*(xy_mm - u))) >= HOLE_SPACING_MM for u in used)


def extra_needles(template: Template, taken: Sequence[str], count: int, depth_mm: float,
                  seed: int, blocked: Callable[[np.ndarray], bool] | None = None) -> list[PlannedNeedle]:
    """Return ``count`` straight needles through free holes of the outer rings, chosen by ``seed``.

    Parameters
    ----------
    template : Template
        The template (its needle holes).
    taken : sequence of str
        Holes already used.
    count : int
        How many to add.
    depth_mm : float, mm
        Their depth beyond the template plane.
    seed : int
        Chooses the holes.
    blocked : callable, optional
        Whether a straight path ((n, 3) mm, template frame, hole to tip) crosses what no needle may (organs at risk,
        bone); such holes are passed over.

    Returns
    -------
    list of PlannedNeedle
        Straight needles marked ``extra``, no two in adjacent holes (at least 14 mm apart).
    """
    rng = np.random.default_rng(10_000 + seed)
    holes = [h for h in template.needle_holes if h.hole_id not in taken and 20.0 <= np.hypot(*h.xy_mm) <= 45.0]
    used = [np.asarray(h.xy_mm) for h in template.needle_holes if h.hole_id in taken]
    out: list[PlannedNeedle] = []
    for k in rng.permutation(len(holes)):
        if len(out) == count:
            break
        xy = np.asarray(holes[k].xy_mm)
        line = np.column_stack([np.full(41, xy[0]), np.full(41, xy[1]), np.linspace(0.0, depth_mm, 41)])
        if _spaced(xy, used) and not (blocked is not None and blocked(line)):
            used.append(xy)
            out.append(PlannedNeedle(holes[k].hole_id, depth_mm, extra=True))
    return out


def plan_candidates(doc: Mapping[str, object]) -> list[PlannedNeedle]:
    """Return the plan's ranked feasible steered candidates, every target's, best first, each hole's once per shape.

    The alternatives the plan's report lists: a clinician may insert one of them instead of (or beside) the delivered
    needles.

    Parameters
    ----------
    doc : mapping
        ``plan.json`` as read: ``targets.<name>.candidates`` (hole, design, schedule, insertion depth, feasible).

    Returns
    -------
    list of PlannedNeedle
        Steered needles (``extra``), ranked within each target, the targets interleaved (every target's best, then
        every target's second, ...); a hole, design and schedule repeated across targets is kept once.
    """
    targets = doc.get("targets")
    ranked = [[c for c in (t.get("candidates") or []) if c.get("steered") and c.get("feasible") and c.get("design")
               and c.get("schedule")] for t in (targets.values() if isinstance(targets, Mapping) else ())
              if isinstance(t, Mapping)]
    out: list[PlannedNeedle] = []
    seen: set[tuple[object, ...]] = set()
    for rank in range(max((len(r) for r in ranked), default=0)):
        for cands in ranked:
            if rank >= len(cands):
                continue
            c = cands[rank]
            key = (c["hole_id"], c["design"], tuple(tuple(row) for row in c["schedule"]))
            if key not in seen:
                seen.add(key)
                out.append(PlannedNeedle(str(c["hole_id"]), float(c["insertion_depth_mm"]), str(c["design"]),
                                         np.asarray(c["schedule"], dtype=float), extra=True))
    return out


def steered_alternates(candidates: Sequence[PlannedNeedle], template: Template, taken: Sequence[str],
                       count: int) -> list[PlannedNeedle]:
    """Return the first ``count`` candidates through free holes at least 14 mm from every hole already used.

    Parameters
    ----------
    candidates : sequence of PlannedNeedle
        The plan's steered candidates in order (:func:`plan_candidates`).
    template : Template
        The template (its needle holes).
    taken : sequence of str
        Holes already used.
    count : int
        How many to add.

    Returns
    -------
    list of PlannedNeedle
        At most ``count`` of them, one per hole.
    """
    xy = {h.hole_id: np.asarray(h.xy_mm, dtype=float) for h in template.needle_holes}
    used = [xy[h] for h in taken if h in xy]
    out: list[PlannedNeedle] = []
    for c in candidates:
        if len(out) == count:
            break
        if c.hole_id in xy and _spaced(xy[c.hole_id], used):
            used.append(xy[c.hole_id])
            out.append(c)
    return out


def _rotation(axis: np.ndarray, angle_rad: float) -> np.ndarray:
    """Rotation matrix about unit ``axis`` by ``angle_rad`` (Rodrigues)."""
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + np.sin(angle_rad) * k + (1 - np.cos(angle_rad)) * k @ k


def _template_path(needle: PlannedNeedle, tension_factor: float, roll_offset_deg: float) -> np.ndarray:
    """Return the needle's path in the template frame from its hole (origin), 1 mm steps: straight, or inserted."""
    if not needle.steered:
        s = np.linspace(0.0, needle.depth_mm, max(2, int(np.ceil(needle.depth_mm)) + 1))
        return np.column_stack([np.zeros_like(s), np.zeros_like(s), s])
    from reachplan.planner.steering.kinematic import KINEMATIC
    from reachplan.planner.steering.schedule import TensionSchedule
    from reachplan.rod_model.design import preset

    design = preset(needle.design)
    assert needle.schedule is not None
    sch = needle.schedule
    schedule = TensionSchedule(sch[:, 0], np.minimum(sch[:, 1] * tension_factor, design.max_tension_n),
                               sch[:, 2] + roll_offset_deg)
    return np.asarray(KINEMATIC.insert_array(design, [schedule], needle.depth_mm)[0])


def _planned(needle: PlannedNeedle, nominal: np.ndarray, hole_xy: np.ndarray, m: np.ndarray,
             given: np.ndarray | None) -> np.ndarray:
    """Return the planned centre line (mm, LPS, 1 mm steps): the plan's own, else the nominal model path at the hole."""
    if given is not None:
        return resample_mm(np.asarray(given, dtype=float), 1.0)
    return np.asarray((nominal + np.array([*hole_xy, 0.0])) @ m[:3, :3].T + m[:3, 3])


def planned_paths(needles: Sequence[PlannedNeedle], template: Template, patient_from_template: np.ndarray,
                  channel_paths: Mapping[str, np.ndarray] | None = None) -> dict[str, np.ndarray]:
    """Return the planned centre lines of needles: the plan's exported channels, else the kinematic model's insertion.

    Parameters
    ----------
    needles : sequence of PlannedNeedle
        The needles.
    template : Template
        Their template.
    patient_from_template : (4, 4) float
        Its pose.
    channel_paths : mapping of str to (n, 3) float, mm, LPS, optional
        The plan's own centre lines by hole (:func:`plan_channel_paths`).

    Returns
    -------
    dict of str to (n, 3) float, mm, LPS
        Hole to planned centre line, hole to tip, 1 mm steps.
    """
    m = np.asarray(patient_from_template, dtype=float)
    holes = {h.hole_id: np.asarray(h.xy_mm, dtype=float) for h in template.needle_holes}
    return {n.hole_id: _planned(n, _template_path(n, 1.0, 0.0), holes[n.hole_id], m,
                                (channel_paths or {}).get(n.hole_id)) for n in needles if n.hole_id in holes}


def draw_needles(needles: Sequence[PlannedNeedle], template: Template, patient_from_template: np.ndarray,
                 perturbations: Mapping[str, float], seed: int | Sequence[int],
                 planned_paths: Mapping[str, np.ndarray] | None = None,
                 curvature_scale: float = 1.0) -> list[DrawnNeedle]:
    """Draw where each needle really goes (module docstring), one seeded draw per needle.

    Parameters
    ----------
    needles : sequence of PlannedNeedle
        The needles.
    template : Template
        Their template (hole positions).
    patient_from_template : (4, 4) float
        Template frame (mm) to LPS mm.
    perturbations : mapping of str to float
        ``tension_fraction``, ``roll_deg``, ``tilt_deg`` (the plan's ``config.perturbations``).
    seed : int or sequence of int
        The generator's seed (``numpy.random.default_rng``'s: a case's seed and a draw's, for instance).
    planned_paths : mapping of str to (n, 3) float, mm, LPS, optional
        The plan's own centre lines by hole (hole to tip, e.g. its exported channels); a needle without one is
        planned by the kinematic model. The tension and roll errors are added to it as the kinematic model's
        change (the planner's robustness check does the same).
    curvature_scale : float
        The tissue bends every steered needle this many times as much as the plan's model did: its planned path's
        departure from its hole's axis (the template frame's x and y) is scaled by it before the draw (a tissue to
        learn from, ``reachplan calibrate``; 1: the plan's tissue).

    Returns
    -------
    list of DrawnNeedle
        Planned and actual centre lines (mm, LPS, hole to tip) and each draw.

    Raises
    ------
    PlanInputError
        A needle through a hole the template does not have.
    """
    from reachplan._arrays import arc_length_mm

    rng = np.random.default_rng(seed)
    m = np.asarray(patient_from_template, dtype=float)
    holes = {h.hole_id: np.asarray(h.xy_mm, dtype=float) for h in template.needle_holes}
    out = []
    for needle in needles:
        if needle.hole_id not in holes:
            raise PlanInputError(f"needle {needle.hole_id!r}: template {template.name!r} has no such hole")
        tilt = float(rng.uniform(0.0, perturbations.get("tilt_deg", 2.0)))
        azimuth = float(rng.uniform(0.0, 360.0))
        f = float(perturbations.get("tension_fraction", 0.1))
        factor = float(1.0 + rng.uniform(-f, f))
        roll = float(rng.uniform(-1.0, 1.0) * perturbations.get("roll_deg", 10.0))
        if not needle.steered:
            factor, roll = 1.0, 0.0
        nominal = _template_path(needle, 1.0, 0.0)
        planned = _planned(needle, nominal, holes[needle.hole_id], m, (planned_paths or {}).get(needle.hole_id))
        actual = planned
        if needle.steered and curvature_scale != 1.0:  # the tissue's own curvature, against the plan's model's
            local = (planned - planned[0]) @ m[:3, :3]
            actual = (local * np.array([curvature_scale, curvature_scale, 1.0])) @ m[:3, :3].T + planned[0]
        if needle.steered:
            delta = _template_path(needle, factor, roll) - nominal
            s_model = np.linspace(0.0, 1.0, len(delta))
            s_path = arc_length_mm(planned) / max(float(arc_length_mm(planned)[-1]), 1e-9)
            shift = np.column_stack([np.interp(s_path, s_model, delta[:, j]) for j in range(3)])
            actual = actual + shift @ m[:3, :3].T
        axis = m[:3, :3] @ np.array([-np.sin(np.radians(azimuth)), np.cos(np.radians(azimuth)), 0.0])
        actual = (actual - planned[0]) @ _rotation(axis, np.radians(tilt)).T + planned[0]
        out.append(DrawnNeedle(needle, planned, actual, {"tilt_deg": round(tilt, 4), "tilt_azimuth_deg":
                                                         round(azimuth, 3), "tension_factor": round(factor, 5),
                                                         "roll_offset_deg": round(roll, 4)}))
    return out


def resample_mm(path_mm: np.ndarray, step_mm: float) -> np.ndarray:
    """Return a polyline resampled at equal arc-length steps of at most ``step_mm``, both ends kept.

    Parameters
    ----------
    path_mm : (n, 3) float, mm
        The polyline, n >= 2.
    step_mm : float, mm
        The largest step.

    Returns
    -------
    (m, 3) float, mm
        The same curve, linear between the given points.
    """
    from reachplan._arrays import arc_length_mm

    s = arc_length_mm(path_mm)
    t = np.linspace(0.0, s[-1], max(2, int(np.ceil(s[-1] / step_mm)) + 1))
    return np.column_stack([np.interp(t, s, path_mm[:, j]) for j in range(3)])


def plan_export(plan_json: Path, doc: Mapping[str, object], prefix: str) -> Path | None:
    """Return the plan's exported file whose name starts with ``prefix`` (``"RP_"``, ``"RS_"``, ``"RD_"``).

    The first such file of ``delivery.files`` found where it was written or in the plan's ``export`` folder.

    Parameters
    ----------
    plan_json : Path
        The ``plan.json`` file.
    doc : mapping
        Its document.
    prefix : str
        The file name's start.

    Returns
    -------
    Path or None
        The file; None when the plan names none or none is found.
    """
    delivery = doc.get("delivery")
    files = delivery.get("files", []) if isinstance(delivery, Mapping) else []
    for name in files:
        p = Path(str(name))
        if p.name.startswith(prefix):
            for where in (p, plan_json.parent / "export" / p.name):
                if where.is_file():
                    return where
    return None


def plan_channel_paths(plan_json: Path, doc: Mapping[str, object]) -> dict[str, np.ndarray]:
    """Return the delivered needles' planned centre lines from the plan's exported RT Structure Set.

    The structure set is :func:`plan_export`'s ``RS_`` file; each ``Needle <hole>`` BRACHY_CHANNEL ROI is its
    needle's path (written tip first).

    Parameters
    ----------
    plan_json : Path
        The ``plan.json`` file.
    doc : mapping
        Its document.

    Returns
    -------
    dict of str to (n, 3) float, mm, LPS
        Hole id to centre line, hole to tip; empty when the export is not found.
    """
    from reachplan.imaging.rtstruct import read_rtstruct

    where = plan_export(plan_json, doc, "RS_")
    if where is None:
        return {}
    rs = read_rtstruct(where)
    return {r.name.split(" ", 1)[1]: r.contours[0].points_mm[::-1].copy() for r in rs.rois
            if r.name.startswith("Needle ") and r.contours}


def painted_line(drawn: DrawnNeedle) -> np.ndarray:
    """Return the centre line to paint: the needle's part outside the template (:data:`OUTSIDE_MM`) then hole to tip.

    Parameters
    ----------
    drawn : DrawnNeedle
        The needle as it lies.

    Returns
    -------
    (n + 1, 3) float, mm, LPS
        The outer end first, the tip last.
    """
    a = drawn.actual_mm
    t = a[1] - a[0]
    return np.vstack([a[0] - OUTSIDE_MM * t / np.linalg.norm(t), a])


def truth_document(drawn: Sequence[DrawnNeedle], about: Mapping[str, object]) -> dict[str, object]:
    """Return ``needles_truth.json``: per needle the hole, kind, planned and actual centre lines and tip, the draw.

    Parameters
    ----------
    drawn : sequence of DrawnNeedle
        The needles as they lie.
    about : mapping of str to object
        What else to record (case, seed, modality, appearance).

    Returns
    -------
    dict of str to object
        JSON-ready; points mm, LPS, hole to tip, 3 decimals.
    """
    return {
        **about,
        "note": "ground truth of a synthetic post-insertion image: no reconstruction reads this file",
        "needles": [{
            "hole_id": d.needle.hole_id, "kind": "steered" if d.needle.steered else "straight",
            "extra": d.needle.extra, "design": d.needle.design, "depth_mm": round(d.needle.depth_mm, 3),
            "deviation": dict(d.deviation),
            "tip_mm": np.round(d.actual_mm[-1], 3).tolist(),
            "points_mm": np.round(d.actual_mm, 3).tolist(),
            "planned_tip_mm": np.round(d.planned_mm[-1], 3).tolist(),
            "planned_points_mm": np.round(d.planned_mm, 3).tolist(),
        } for d in drawn],
    }


@dataclass(frozen=True)
class ImplantedCase:
    """A built-in case's post-insertion image with its ground truth.

    Parameters
    ----------
    spec : PhantomSpec
        The case, as a post-insertion series (its own case id, hence its own UIDs).
    image : (n_slices, matrix, matrix) int16
        The image (HU, or MR signal) with the needles in.
    truth : dict of str to object
        ``needles_truth.json`` (:func:`truth_document`).
    drawn : tuple of DrawnNeedle
        The needles as they lie.
    """

    spec: PhantomSpec
    image: np.ndarray
    truth: dict[str, object]
    drawn: tuple[DrawnNeedle, ...]


def implanted_case(plan_json: Path, modality: str | None = None, extra: int = 2, content: str = "metal",
                   draw_seed: int = 0, seed: int | None = None, curvature_scale: float = 1.0,
                   extra_steered: int = 0) -> ImplantedCase:
    """Return the built-in case a plan was made on, imaged after its implant (plus ``extra`` straight needles) is in.

    Parameters
    ----------
    plan_json : Path
        The plan (``plan.json`` of ``demo``, or of ``plan`` on a built-in case).
    modality : str or None
        ``"CT"`` or ``"MR"``; None: the plan's.
    extra : int
        Straight needles added through free holes (100 mm deep).
    content : str
        What fills the needles: ``"metal"`` (obturator or stylet), ``"air"`` or ``"fluid"``
        (:class:`reachplan.imaging.implanted.TubeLook`).
    draw_seed : int
        Seed of the needles' deviations (with the case's seed: each case's needles are drawn independently of
        another case's) and of the image noise.
    seed : int or None
        The clinical case's seed when the plan does not say it (a plan of ``plan`` on written phantom files).
    curvature_scale : float
        The tissue's in-tissue curvature over the plan's model's (:func:`draw_needles`; 1: the plan's tissue).
    extra_steered : int
        The plan's steered candidates added besides its implant (:func:`steered_alternates`), as a clinician
        inserting the report's alternatives would: more steered needles for the tissue's calibration.

    Returns
    -------
    ImplantedCase
        The post-insertion case, its image and its truth.

    Raises
    ------
    PlanInputError
        An unreadable plan, a plan of the pilot phantom or of a patient (no built-in case to image), or a plan
        without a delivered implant.
    """
    import dataclasses
    import json

    from reachplan.imaging.clinical import clinical_case
    from reachplan.imaging.implanted import TubeLook, implanted_image
    from reachplan.imaging.phantom import phantom_ct_hu
    from reachplan.planner.lookup import load_template

    try:
        doc = json.loads(Path(plan_json).read_text(encoding="utf-8"))
    except (OSError, ValueError) as exc:
        raise PlanInputError(f"cannot read the plan {plan_json}: {exc}; give a plan.json of reachplan") from None
    about = doc.get("case_about") or {}
    if about.get("case", "clinical") != "clinical" or (not about and seed is None):
        raise PlanInputError(f"{plan_json} is not a plan of the built-in clinical case (give --seed for a plan made "
                             "on its written files); the post-insertion image is drawn for that case only")
    case_seed = int(about.get("seed", seed if seed is not None else 0))
    mod = modality or str(about.get("modality", "CT"))
    case = clinical_case(case_seed, modality=mod)
    config = doc.get("config") or {}
    template = load_template(str(config.get("template", "needlefinder_syed_63")))
    pose = np.asarray((doc.get("template_pose") or {}).get("patient_from_template", np.eye(4)), dtype=float)
    needles = delivered_needles(doc)
    oars = [st for st in case.spec.structures if st.is_oar]

    def blocked(line: np.ndarray) -> bool:  # template frame -> LPS, then inside an organ at risk or bone
        pts = line @ pose[:3, :3].T + pose[:3, 3]
        return any(bool(np.any(st.contains(pts))) for st in oars)

    needles += steered_alternates(plan_candidates(doc), template, [n.hole_id for n in needles], extra_steered)
    needles += extra_needles(template, [n.hole_id for n in needles], extra, 100.0, draw_seed + case_seed, blocked)
    drawn = draw_needles(needles, template, pose, config.get("perturbations") or {}, (case_seed, draw_seed),
                         plan_channel_paths(Path(plan_json), doc), curvature_scale)
    look = TubeLook(outer_radius_mm=float(config.get("needle_radius_mm", 0.915)), content=content)
    image = implanted_image(case.spec, phantom_ct_hu(case.spec), [painted_line(d) for d in drawn], look, draw_seed)
    spec = dataclasses.replace(case.spec, case_id=f"{case.spec.case_id or 'clinical'}_post{draw_seed}"[:40],
                               description=f"{case.spec.description}, post-insertion")
    truth = truth_document(drawn, {"case": "clinical", "seed": case_seed, "modality": mod, "draw_seed": draw_seed,
                                   "curvature_scale": curvature_scale,
                                   "plan": Path(plan_json).name, "look": dataclasses.asdict(look),
                                   "patient_from_template": np.round(pose, 6).tolist()})
    return ImplantedCase(spec, image, truth, tuple(drawn))
