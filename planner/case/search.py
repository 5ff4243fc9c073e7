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
from reachplan.planner.case.result import PlanResult, choose_needles
from reachplan.planner.case.scene import Scene
from reachplan.planner.errors import PlanInputError
from reachplan.planner.geometry.template import hole_frames
from reachplan.planner.ranking import rank
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
from reachplan.planner.steering.tissue_band import assess_band, uniform_profile
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
        cands += straight
        clear = {c.hole_id for c in straight if c.feasible}  # a steered needle from these holes adds nothing
        # the tissue the target lies in (where the needle bends) sets the screening model's curvature factor
        screening = dataclasses.replace(models.screening, tissue_modulus_pa=target_modulus_pa(scene, target, config))
        for design in designs:
            steered = steered_candidates(scene, target, design, config, skip=clear, model=screening)
            cands += refine_shortlist(scene, target, design, steered, config, models.reference)
    cands = assess_shortlist(scene, cands, config, models.robustness)
    cands = band_shortlist(scene, cands, config)
    return PlanResult(tuple(cands), rank(cands, config.weights), config)


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
                               config.reach_tolerance_mm)
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
                     config: PlanConfig, reference: TissueRodInsertion = PLANNER_REFERENCE) -> list[Candidate]:
    """Re-solve the best feasible steered candidates with the ``reference`` model (the in-tissue Cosserat rod).

    The rod takes the tissue modulus along the candidate's path (``config.tissue_moduli_pa`` per organ, the
    reference's modulus elsewhere) and the schedule is re-aimed
    (:func:`~reachplan.planner.steering.steered.refine_with`).

    It stops when the top ``config.refine_top`` feasible ones all carry the reference's numbers (at most
    ``refine_top + 4`` solves: a refined candidate that no longer reaches, or that the reference fails to solve
    (marked failed, with the reason), drops down and the next one is refined).

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
        ``refine_top``, ``weights``, ``tissue_moduli_pa`` and the reach tolerance.
    reference : TissueRodInsertion
        The reference insertion model.

    Returns
    -------
    list of Candidate
        ``cands`` in the same order, the re-solved ones replaced by the reference's candidates.
    """
    rel_all = _template_offsets(scene, target)
    index = {h.hole_id: i for i, h in enumerate(scene.template.needle_holes)}
    holes = {h.hole_id: h for h in scene.template.needle_holes}
    radius = design.needle.outer_diameter_mm / 2
    current = list(cands)
    done: set[str] = set()
    for _ in range(config.refine_top + 4):
        ranked = rank(current, config.weights).get(target.name, ())
        top = [c for c in ranked if c.feasible][: config.refine_top]
        todo = [c for c in top if c.hole_id not in done and c.schedule is not None]
        if not todo:
            break
        c = todo[0]
        assert c.schedule is not None
        done.add(c.hole_id)
        roll = float(c.schedule.roll_deg[0])
        base = TensionSchedule(c.schedule.depth_mm, c.schedule.tension_n, np.zeros(len(c.schedule.depth_mm)))
        profile = modulus_profile(scene, c.path_mm, config.tissue_moduli_pa, reference.tissue_modulus_pa)
        try:
            sch, res = refine_with(reference, design, base, c.insertion_depth_mm, rel_all[index[c.hole_id]],
                                   modulus_profile=profile,
                                   max_tension_n=usable_tension_n(design, config.tension_reserve))
        except (PlanInputError, RodModelError) as exc:
            new = mark_failed(c, f"reference re-solve ({reference.info.label}) failed: {exc}")
        else:
            sch = TensionSchedule(sch.depth_mm, sch.tension_n, np.full(len(sch.depth_mm), roll))
            step = c.insertion_depth_mm / (len(res.positions_mm) - 1)
            path = place(res.positions_mm, step, c.insertion_depth_mm, roll,
                         np.asarray(holes[c.hole_id].xy_mm), scene.patient_from_template)
            new = score_path(target, c.hole_id, c.hole_distance_mm, path, scene.organs, radius,
                             config.reach_tolerance_mm, res.model, steered=True, peak_tension_n=sch.peak_tension_n,
                             design=design, schedule=sch, depth_mm=c.insertion_depth_mm)
        current = [new if x is c else x for x in current]
    return current
