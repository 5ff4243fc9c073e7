"""The steering search: every template hole x target, straight and steered, scored against the organs and ranked.

Screening with the cheap kinematic model over the shape bank, the shortlist re-solved with the in-tissue rod
(:mod:`~reachplan.planner.steering.tissue_rod`) and assessed for robustness.
"""

from __future__ import annotations

import dataclasses

import numpy as np
from tqdm import tqdm

from reachplan._arrays import arc_length_mm
from reachplan.planner.case.config import PlanConfig, PlanModels, screening_model
from reachplan.planner.case.fidelity import REFERENCE_RUNG, RUNGS, Rung, choose_rung, rung_error_mm
from reachplan.planner.case.result import PlanResult, choose_needles
from reachplan.planner.case.scene import Scene
from reachplan.planner.errors import PlanInputError
from reachplan.planner.geometry.template import hole_frames
from reachplan.planner.ranking import RankWeights, rank
from reachplan.planner.steering.candidates import (
    Candidate,
    Target,
    TissueBand,
    mark_failed,
    score_path,
    straight_candidates,
)
from reachplan.planner.steering.insertion import SIMUGEL_MODULUS_PA
from reachplan.planner.steering.kinematic import KINEMATIC, KinematicInsertion
from reachplan.planner.steering.robustness import assess, with_robustness
from reachplan.planner.steering.schedule import TensionSchedule
from reachplan.planner.steering.steered import match_targets, place, refine_with, shape_bank, usable_tension_n
from reachplan.planner.steering.tissue_band import BAND_MODEL, assess_band, uniform_profile
from reachplan.planner.steering.tissue_rod import PLANNER_REFERENCE, TissueRodInsertion
from reachplan.rod_model.design import RodDesign
from reachplan.rod_model.errors import RodModelError


def plan(scene: Scene, config: PlanConfig | None = None, quiet: bool = True,
         models: PlanModels | None = None) -> PlanResult:
    """Score every hole x target candidate, straight and steered, and rank them.

    A model that fails for one candidate (no convergence, a shape out of range) marks that candidate (``failed``,
    with the reason); the plan goes on.

    Parameters
    ----------
    scene : Scene
        Organs, targets, template and its pose.
    config : PlanConfig or None
        The plan's settings; None: the defaults.
    quiet : bool
        No progress bar.
    models : PlanModels or None
        The insertion models to use; None: :meth:`PlanModels.for_config` of ``config``.

    Returns
    -------
    PlanResult
        Every candidate and the ranking per target.
    """
    config = config or PlanConfig()
    models = models or PlanModels.for_config(config)
    holes = scene.template.needle_holes
    entry, direction = hole_frames(scene.template, scene.patient_from_template, holes)
    hole_ids = [h.hole_id for h in holes]
    dist = np.array([h.distance_mm for h in holes])
    designs = config.rod_designs
    cands: list[Candidate] = []
    for target in tqdm(scene.targets, desc="planning targets", unit="target", disable=quiet, leave=False):
        straight = straight_candidates([target], hole_ids, dist, entry, direction, scene.organs,
                                       config.needle_radius_mm, config.reach_tolerance_mm, config.max_depth_mm)
        cands += [_noted(c, float("nan"), STRAIGHT_REASON) for c in straight]
        clear = {c.hole_id for c in straight if c.feasible}  # a steered needle from these holes adds nothing
        # the tissue the target lies in (where the needle bends) sets the screening model's curvature factor
        screening = dataclasses.replace(models.screening, tissue_modulus_pa=target_modulus_pa(scene, target, config))
        known = [c for c in straight if c.feasible]  # candidates whose numbers are exact: the ranking's anchors
        for design in designs:
            steered = steered_candidates(scene, target, design, config, skip=clear, model=screening)
            bound = min((config.weights.score(c) for c in known), default=float("inf"))
            refined = refine_shortlist(scene, target, design, steered, config, models.reference, bound)
            known += [c for c in refined if c.feasible and c.model_reason.startswith(f"{REFERENCE_RUNG.name}:")]
            cands += refined
    cands = assess_shortlist(scene, cands, config, models.robustness)
    cands = band_shortlist(scene, cands, config)
    return PlanResult(tuple(cands), rank(cands, config.weights), config)


#: The model reason of a straight needle.
STRAIGHT_REASON = "straight: an exact line, no model error"


def target_modulus_pa(scene: Scene, target: Target, config: PlanConfig) -> float:
    """Return the Young's modulus (Pa) of the tissue a target lies in.

    The first organ of ``config.tissue_moduli_pa`` whose mesh contains the target, else ``config.tissue_modulus_pa``
    (default the phantom's gel, SimuGel #3, 0.19 MPa, reference ``oncoreach.md``: the only tissue modulus the
    reference gives).

    Parameters
    ----------
    scene : Scene
        Its meshes hold the named organs.
    target : Target
        The target point (LPS mm).
    config : PlanConfig
        Its ``tissue_moduli_pa`` (Pa per organ) and ``tissue_modulus_pa`` (Pa, elsewhere).

    Returns
    -------
    float, Pa
        The modulus at the target.

    Raises
    ------
    PlanInputError
        When a named organ has no mesh in the scene, or a modulus is not positive.
    """
    point = np.asarray(target.position_mm, dtype=float)[None, :]
    profile = modulus_profile(scene, point, config.tissue_moduli_pa, config.tissue_modulus_pa)
    return config.tissue_modulus_pa if profile is None else float(profile[1][0])


def modulus_profile(scene: Scene, path_mm: np.ndarray, moduli: tuple[tuple[str, float], ...],
                    default_pa: float = SIMUGEL_MODULUS_PA) -> tuple[np.ndarray, np.ndarray] | None:
    """Return the tissue modulus along a needle path, ``(depth_mm, modulus_pa)``; None when ``moduli`` is empty.

    The modulus of the organ each point lies in (the first of ``moduli`` that contains it), ``default_pa``
    elsewhere.

    Parameters
    ----------
    scene : Scene
        Its meshes hold the named organs.
    path_mm : (n, 3) float, mm, LPS
        The needle's centre line, hub first.
    moduli : tuple of (str, float), Pa
        Organ name and its Young's modulus, first match wins.
    default_pa : float, Pa
        The modulus outside the named organs.

    Returns
    -------
    depth_mm : (n,) float, mm
        Arc length along the path from its first point.
    modulus_pa : (n,) float, Pa
        The modulus at each point.

    Raises
    ------
    PlanInputError
        When a named organ has no mesh in the scene, or a modulus is not positive.
    """
    if not moduli:
        return None
    for name, value in moduli:
        if name not in scene.meshes:
            raise PlanInputError(f"tissue modulus given for {name!r}, which is not meshed in the scene "
                                 f"(meshed: {', '.join(scene.meshes)})")
        if not (np.isfinite(value) and value > 0):
            raise PlanInputError(f"tissue modulus of {name} must be > 0 Pa, got {value}")
    depth = arc_length_mm(path_mm)
    values = np.full(len(path_mm), default_pa)
    assigned = np.zeros(len(path_mm), dtype=bool)
    for name, value in moduli:
        inside = scene.meshes[name].contains(path_mm) & ~assigned
        values[inside] = value
        assigned |= inside
    return depth, values


def assess_shortlist(scene: Scene, cands: list[Candidate], config: PlanConfig,
                     model: KinematicInsertion = KINEMATIC) -> list[Candidate]:
    """Assess the robustness of the ``config.robust_top`` best feasible straight and steered candidates per target.

    With ``model``; a candidate whose assessment fails is marked failed with the reason.

    Parameters
    ----------
    scene : Scene
        Organs, targets and the template's pose.
    cands : list of Candidate
        Every candidate of the plan.
    config : PlanConfig
        ``robust_top``, ``perturbations``, ``weights`` and the tolerances.
    model : KinematicInsertion
        The insertion model of the perturbed solves (its tissue modulus set per target).

    Returns
    -------
    list of Candidate
        ``cands`` in the same order, the assessed ones carrying their robustness (or marked failed).
    """
    if config.robust_top <= 0:
        return cands
    targets = {t.name: t for t in scene.targets}
    chosen: dict[int, Candidate] = {}
    for name, ranked in rank(cands, config.weights).items():
        model = dataclasses.replace(model, tissue_modulus_pa=target_modulus_pa(scene, targets[name], config))
        for steered in (False, True):
            for c in [c for c in ranked if c.feasible and c.steered == steered][: config.robust_top]:
                radius = c.design.needle.outer_diameter_mm / 2 if c.design else config.needle_radius_mm
                try:
                    r = assess(c, targets[name], scene.organs, scene.patient_from_template, radius,
                               config.perturbations, model, reach_tolerance_mm=config.reach_tolerance_mm)
                except (PlanInputError, RodModelError) as exc:
                    chosen[id(c)] = mark_failed(c, f"robustness ({model.info.label}) failed: {exc}")
                    continue
                chosen[id(c)] = with_robustness(c, r)
    return [chosen.get(id(c), c) for c in cands]


def band_shortlist(scene: Scene, cands: list[Candidate], config: PlanConfig) -> list[Candidate]:
    """Give the steered needles the plan shows and delivers their tissue band (``config.modulus_band``).

    Those :func:`~reachplan.planner.case.result.choose_needles` picks (steered only, and either kind): each re-inserted
    with its schedule in tissue of the plan's moduli scaled over the band
    (:func:`~reachplan.planner.steering.tissue_band.assess_band`); when the rod model fails on the band, the band
    says why (:meth:`~reachplan.planner.steering.candidates.TissueBand.failed`). The ranking does not use the band.

    Parameters
    ----------
    scene : Scene
        Organs, targets, template pose and the meshes the moduli name.
    cands : list of Candidate
        Every candidate of the plan.
    config : PlanConfig
        ``modulus_band``, the moduli, the weights and the reach tolerance.

    Returns
    -------
    list of Candidate
        ``cands`` in the same order, the banded ones carrying ``tissue_band``.
    """
    if not config.modulus_band.enabled:
        return cands
    targets = {t.name: t for t in scene.targets}
    ranked = PlanResult(tuple(cands), rank(cands, config.weights), config)
    chosen: dict[int, Candidate] = {}
    for c in (*choose_needles(ranked, steered=True), *choose_needles(ranked)):
        if not c.steered or c.design is None or id(c) in chosen:
            continue
        profile = (modulus_profile(scene, c.path_mm, config.tissue_moduli_pa, config.tissue_modulus_pa)
                   or uniform_profile(config.tissue_modulus_pa))
        try:
            band = assess_band(c, targets[c.target], scene.organs, scene.patient_from_template,
                               c.design.needle.outer_diameter_mm / 2, profile, config.modulus_band,
                               config.reach_tolerance_mm,
                               dataclasses.replace(BAND_MODEL, curvature_scale=config.curvature_scale))
        except (PlanInputError, RodModelError) as exc:
            band = TissueBand.failed(str(exc), config.modulus_band.source)
        chosen[id(c)] = dataclasses.replace(c, tissue_band=band)
    return [chosen.get(id(c), c) for c in cands]


def _template_offsets(scene: Scene, target: Target) -> np.ndarray:
    """(H, 3) target minus each needle hole's entry, mm, in the template frame."""
    inv = np.linalg.inv(scene.patient_from_template)
    t = inv[:3, :3] @ np.asarray(target.position_mm) + inv[:3, 3]
    xy = np.array([h.xy_mm for h in scene.template.needle_holes])
    return t - np.column_stack([xy, np.zeros(len(xy))])


def steered_candidates(scene: Scene, target: Target, design: RodDesign, config: PlanConfig,
                       skip: frozenset[str] | set[str] = frozenset(),
                       model: KinematicInsertion | None = None) -> list[Candidate]:
    """Return one steered candidate per hole (holes in ``skip`` excluded), screened with ``model``.

    ``model`` defaults to :func:`screening_model` of ``config``.

    Among the bank's schedules that reach the target, the gentlest (lowest peak tension, then smallest
    reach error) that clears every organ is kept, trying at most ``config.alternatives``; when none is
    clear, the gentlest reaching one (colliding); when none reaches, the closest approach, unchecked.

    Parameters
    ----------
    scene : Scene
        Organs, template and its pose.
    target : Target
        The target point.
    design : RodDesign
        The stylet.
    config : PlanConfig
        Schedule family, tolerances, depth limit and ``alternatives``.
    skip : set of str
        Hole ids left out (a straight needle from them already reaches).
    model : KinematicInsertion or None
        The screening model.

    Returns
    -------
    list of Candidate
        One per hole not skipped, in the template's hole order.
    """
    model = model or screening_model(config)
    bank = shape_bank(design, config.family, min(config.max_depth_mm, design.length_mm), model, config.tension_reserve)
    radius = design.needle.outer_diameter_mm / 2
    matches = match_targets(bank, _template_offsets(scene, target), keep=len(bank.schedules))
    out: list[Candidate] = []
    for hole, match in zip(scene.template.needle_holes, matches, strict=True):
        if hole.hole_id in skip:
            continue
        ok = np.flatnonzero(match.reach_mm <= config.reach_tolerance_mm)
        peak = np.array([bank.schedules[k].peak_tension_n for k in match.order[ok]])
        tries = ok[np.lexsort((match.reach_mm[ok], peak))][: config.alternatives] if len(ok) else np.array([0])
        chosen: Candidate | None = None
        for i in tries:
            k = int(match.order[i])
            base = bank.schedules[k]
            sch = TensionSchedule(base.depth_mm, base.tension_n, np.full(len(base.depth_mm), match.roll_deg))
            path = place(bank.shapes_mm[k], bank.step_mm, float(match.depth_mm[i]), match.roll_deg,
                         np.asarray(hole.xy_mm), scene.patient_from_template)
            reaches = bool(match.reach_mm[i] <= config.reach_tolerance_mm)
            c = score_path(target, hole.hole_id, hole.distance_mm, path, scene.organs, radius,
                           config.reach_tolerance_mm, bank.model, steered=True, peak_tension_n=sch.peak_tension_n,
                           design=design, schedule=sch, depth_mm=float(match.depth_mm[i]), check=reaches,
                           reason="" if reaches else "no screened schedule reaches it")
            chosen = chosen or c
            if c.feasible:
                chosen = c
                break
        if chosen is not None:
            out.append(chosen)
    return out


def refine_shortlist(scene: Scene, target: Target, design: RodDesign, cands: list[Candidate],
                     config: PlanConfig, reference: TissueRodInsertion = PLANNER_REFERENCE,
                     bound_score: float = float("inf")) -> list[Candidate]:
    """Give every feasible steered candidate of one target and design the model its policy asks for.

    ``config.models``: ``"reference"`` re-solves every one with ``reference``; ``"scene"`` (the default) gives
    each the cheapest model its margins allow (:func:`~reachplan.planner.case.fidelity.choose_rung`; the screening
    model's numbers are kept when they suffice), then a model within :data:`BOUNDARY_STAGE_MM` to the top
    ``refine_top`` (shown), and the reference to every candidate that could be the target's top within its model's
    error (:func:`_decision_boundary`). ``config.refine_top`` 0 re-solves none. A re-solve takes the tissue modulus
    along the candidate's path (``config.tissue_moduli_pa`` per organ, the reference's modulus elsewhere) and
    re-aims the schedule (:func:`~reachplan.planner.steering.steered.refine_with`); one the model fails to solve is
    marked failed with the reason. Every candidate carries ``model_tolerance_mm`` and ``model_reason``.

    Parameters
    ----------
    scene : Scene
        Organs, template and its pose (and the meshes the moduli name).
    target : Target
        The target whose candidates these are.
    design : RodDesign
        Their stylet.
    cands : list of Candidate
        The target's steered candidates of ``design`` from the screening.
    config : PlanConfig
        ``models``, ``refine_top``, ``robust_top``, ``weights``, ``tissue_moduli_pa``, ``safety_margin_mm`` and the
        reach tolerance.
    reference : TissueRodInsertion
        The reference insertion model (the cheaper rungs are it at coarser steps).
    bound_score : float
        The best score among the target's candidates known exactly (its straight needles, other designs'
        reference re-solves; inf: none): a candidate that cannot reach it within its model's error is not
        re-solved for the ranking's decision.

    Returns
    -------
    list of Candidate
        ``cands`` in the same order, the re-solved ones replaced.
    """
    if config.refine_top <= 0:
        return [_noted(c, float("nan"), "kinematic: no re-solve (refine_top 0)") for c in cands]
    modulus = target_modulus_pa(scene, target, config)
    current = [c if c.feasible else _noted(c, float("nan"), NOT_FEASIBLE) for c in cands]
    exact: set[int] = set()
    errors: dict[int, float] = {}
    screened: dict[int, Candidate] = {}  # a re-solved candidate's screening: the reference always starts there
    for i, c in enumerate(current):
        if not c.feasible:
            continue
        if config.models == "reference":
            current[i] = _resolve(scene, target, design, c, config, reference, float("nan"),
                                  "reference: --models reference re-solves every feasible candidate")
            exact.add(id(current[i]))
            continue
        choice = choose_rung(c.clearance_mm, design, modulus, c.insertion_depth_mm, config.reach_tolerance_mm,
                             config.safety_margin_mm)
        model = choice.rung.model(reference)
        current[i] = (_noted(c, choice.tolerance_mm, choice.reason) if model is None else
                      _resolve(scene, target, design, c, config, model, choice.tolerance_mm, choice.reason))
        errors[id(current[i])] = rung_error_mm(choice.rung.name, design, modulus, c.insertion_depth_mm)[0]
        screened[id(current[i])] = c
        if choice.rung is REFERENCE_RUNG:
            exact.add(id(current[i]))
    if config.models == "scene":
        current = _decision_boundary(scene, target, design, current, config, reference, exact, errors, screened,
                                     bound_score)
    return current


#: The reason a candidate not feasible on screening keeps the screening model's numbers.
NOT_FEASIBLE = "kinematic: not feasible on screening; no ranking decision rests on its numbers"
#: Newtons of plateau tension a re-aim changes per mm of tip error: 0.8-1.8 N/mm on the clinical demo's reference
#: re-solves (the kinematic tip moves about 1 mm per N at the planner's depths); with the ranking's weights it turns
#: a model error into a score band.
TENSION_PER_MM_N = 1.5
#: A candidate in the decision band whose model is off by more than this (mm) is first re-solved with the cheapest
#: rung within it (:func:`_boundary_rung`), and with the reference only if it is still in the band.
BOUNDARY_STAGE_MM = 0.5
#: At most ``refine_top`` + this many re-solves per target and design for the ranking's decision (the most
#: threatening first: lowest score less band), as the shortlist before had: a symmetric template offers dozens of
#: near-equal holes, and a re-solve that raises the top one's score hands the top to the next; the ranking's
#: fidelity with this cap is measured (``reachplan bench fidelity``).
BOUNDARY_MAX = 4


def _noted(c: Candidate, tolerance_mm: float, reason: str) -> Candidate:
    """``c`` with its model choice recorded (its numbers unchanged)."""
    return dataclasses.replace(c, model_tolerance_mm=tolerance_mm, model_reason=reason)


def _decision_boundary(scene: Scene, target: Target, design: RodDesign, current: list[Candidate],
                       config: PlanConfig, reference: TissueRodInsertion, exact: set[int],
                       errors: dict[int, float], screened: dict[int, Candidate],
                       bound_score: float = float("inf")) -> list[Candidate]:
    """Re-solve the candidates the ranking's decision could rest on, and the shown ones (``current`` updated).

    Two kinds of re-solve, the first before the second, until none is left or ``refine_top`` +
    :data:`BOUNDARY_MAX` re-solves are spent:

    shown
        The top ``refine_top`` feasible ones (the best steered needle, which the report compares with the straight
        ones) get a model within :data:`BOUNDARY_STAGE_MM` (the cheapest rung within it,
        :func:`_boundary_rung`).
    the decision
        The target's top candidate is the best-scored one of all kinds. A candidate is in the decision while its
        score less its band (:func:`_score_band`: what its model's in-tissue error ``errors`` and its reach error
        could take off its score) reaches the best score known exactly: ``bound_score`` (the target's best straight
        needle and the earlier designs' reference re-solves) or one of ``current`` solved by the reference. Those
        are re-solved lowest first: with the reference, or first with the cheapest rung within
        :data:`BOUNDARY_STAGE_MM` when their model is off by more (a narrower band, often out of the decision).

    A candidate that cannot beat an exactly known one keeps the model its margins chose (or the shown one's): no
    ranking decision rests on it. ``exact`` holds the ids of those solved by the reference; ``screened`` maps a
    re-solved candidate's id to its screened self, which every re-solve starts from (so the reference's numbers
    are those ``--models reference`` gives: a re-aim started elsewhere stops elsewhere within its 0.25 mm).
    """
    w = config.weights
    k = max(config.refine_top, 1)
    modulus = target_modulus_pa(scene, target, config)
    for spent in range(config.refine_top + BOUNDARY_MAX + 1):
        feasible = [c for c in rank(current, w).get(target.name, ()) if c.feasible]
        shown = [c for c in feasible[:k] if errors.get(id(c), 0.0) > BOUNDARY_STAGE_MM]
        best = min([bound_score, *(w.score(c) for c in feasible if id(c) in exact)])
        if shown:
            c, rung = shown[0], _boundary_rung(design, modulus, shown[0].insertion_depth_mm)
            why = (f"among the top {k} steered needles of {target.name} (shown and compared with the straight "
                   f"ones): a model within {BOUNDARY_STAGE_MM:g} mm")
        else:
            optimistic = {id(c): w.score(c) - _score_band(c, errors.get(id(c), 0.0), w) for c in feasible}
            todo = sorted((c for c in feasible if id(c) not in exact and optimistic[id(c)] <= best),
                          key=lambda c: optimistic[id(c)])
            if not np.isfinite(best):  # nothing known exactly yet: the top one first, the anchor of the rest
                todo = feasible[:1]
            if not todo:
                return current
            c = todo[0]
            rung = (_boundary_rung(design, modulus, c.insertion_depth_mm)
                    if errors.get(id(c), 0.0) > BOUNDARY_STAGE_MM else REFERENCE_RUNG)
            why = (f"its score ({{score:.1f}}) could reach the best known exactly ({best:.1f}) within its model's "
                   f"in-tissue error (the ranking's decision boundary for {target.name})" if np.isfinite(best) else
                   f"the top of {target.name}, no needle of which is known exactly yet (the ranking's decision)")
        if spent == config.refine_top + BOUNDARY_MAX:
            return current
        model = rung.model(reference) or reference
        base = screened.get(id(c), c)
        new = _resolve(scene, target, design, base, config, model, c.model_tolerance_mm,
                       f"{rung.name}: " + why.format(score=w.score(c)))
        errors[id(new)] = rung_error_mm(rung.name, design, modulus, c.insertion_depth_mm)[0]
        screened[id(new)] = base
        if rung is REFERENCE_RUNG:
            exact.add(id(new))
        current = [new if x is c else x for x in current]
    return current


def _score_band(c: Candidate, error_mm: float, w: RankWeights) -> float:
    """How much a re-solve could lower ``c``'s score: its reach error (re-aimed away) and its model error's share.

    The clearance term counts while the clearance less the error is under the cap; tension moves by
    :data:`TENSION_PER_MM_N` per mm of error.
    """
    clear = w.per_mm_clearance if np.isfinite(c.clearance_mm) and c.clearance_mm - error_mm < w.clearance_cap_mm \
        else 0.0
    return w.per_mm_reach * c.reach_error_mm + (clear + w.per_newton * TENSION_PER_MM_N) * error_mm


def _boundary_rung(design: RodDesign, modulus_pa: float, depth_mm: float) -> Rung:
    """Return the cheapest in-tissue rung within :data:`BOUNDARY_STAGE_MM`; the reference when none is."""
    within = [r for r in RUNGS[1:-1] if rung_error_mm(r.name, design, modulus_pa, depth_mm)[0] <= BOUNDARY_STAGE_MM]
    return within[0] if within else REFERENCE_RUNG


def _resolve(scene: Scene, target: Target, design: RodDesign, c: Candidate, config: PlanConfig,
             model: TissueRodInsertion, tolerance_mm: float, reason: str) -> Candidate:
    """Re-solve one screened candidate with the in-tissue ``model``, re-aimed; marked failed when it fails."""
    assert c.schedule is not None
    index = {h.hole_id: i for i, h in enumerate(scene.template.needle_holes)}
    hole = scene.template.needle_holes[index[c.hole_id]]
    rel = _template_offsets(scene, target)[index[c.hole_id]]
    roll = float(c.schedule.roll_deg[0])
    base = TensionSchedule(c.schedule.depth_mm, c.schedule.tension_n, np.zeros(len(c.schedule.depth_mm)))
    profile = modulus_profile(scene, c.path_mm, config.tissue_moduli_pa, model.tissue_modulus_pa)
    name = reason.split(":", 1)[0]
    try:
        sch, res = refine_with(model, design, base, c.insertion_depth_mm, rel, modulus_profile=profile,
                               max_tension_n=usable_tension_n(design, config.tension_reserve))
    except (PlanInputError, RodModelError) as exc:
        return _noted(mark_failed(c, f"{name} re-solve ({model.info.label}) failed: {exc}"), tolerance_mm, reason)
    sch = TensionSchedule(sch.depth_mm, sch.tension_n, np.full(len(sch.depth_mm), roll))
    step = c.insertion_depth_mm / (len(res.positions_mm) - 1)
    path = place(res.positions_mm, step, c.insertion_depth_mm, roll, np.asarray(hole.xy_mm),
                 scene.patient_from_template)
    new = score_path(target, c.hole_id, c.hole_distance_mm, path, scene.organs, design.needle.outer_diameter_mm / 2,
                     config.reach_tolerance_mm, res.model, steered=True, peak_tension_n=sch.peak_tension_n,
                     design=design, schedule=sch, depth_mm=c.insertion_depth_mm)
    return _noted(new, tolerance_mm, reason)
