"""The one place the stages are chained: structures -> scene -> candidates -> ranking.

Stages are plain functions on plain data; the command line (``planner/commands``) only parses
arguments, calls these and writes files.
"""

from __future__ import annotations

import dataclasses
import re
import time
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from datetime import datetime
from functools import cached_property
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import trimesh
from tqdm import tqdm

from reachplan._arrays import arc_length_mm
from reachplan.imaging.types import Grid, Roi, StructureSet, Volume
from reachplan.planner.errors import PlanInputError
from reachplan.planner.geometry.collision import Organ, make_organ, with_distance_field
from reachplan.planner.geometry.organs import check_unique, has_closed, roi_points, select_oars
from reachplan.planner.geometry.template import TemplatePose, hole_frames, pose_from_obturator
from reachplan.planner.ranking import RankWeights, pareto_front, rank
from reachplan.planner.steering.candidates import Candidate, Target, mark_failed, score_path, straight_candidates
from reachplan.planner.steering.insertion import KINEMATIC, SIMUGEL_MODULUS_PA, KinematicInsertion
from reachplan.planner.steering.robustness import Perturbations, assess, with_robustness
from reachplan.planner.steering.schedule import TensionSchedule
from reachplan.planner.steering.steered import ScheduleFamily, match_targets, place, refine_with, shape_bank
from reachplan.planner.steering.tissue_rod import PLANNER_REFERENCE, TissueRodInsertion
from reachplan.plugins import registry
from reachplan.plugins.errors import PluginError
from reachplan.plugins.sources import BUILTIN, SourceData, normalise_label
from reachplan.plugins.templates import Template
from reachplan.rod_model.design import RodDesign, preset
from reachplan.rod_model.errors import RodModelError
from reachplan.rod_model.protocol import Capabilities, RodModel

if TYPE_CHECKING:
    from reachplan.planner.dose.aims import Aims
    from reachplan.planner.dose.structures import PlanningStructures, Structure
    from reachplan.planner.dose.tg43 import Tg43Kernel
    from reachplan.planner.implant.arms import ImplantArm, ImplantPlan
    from reachplan.planner.implant.candidates import Channel
    from reachplan.planner.implant.dwells import OptimisationResult
    from reachplan.planner.implant.settings import ImplantSettings
    from reachplan.plugins.exporters import ExportPlan, NeedleExport
    from reachplan.rod_model.select import ErrorRow

#: Organs at risk (and bone) a needle must not touch, by normalised ROI name.
DEFAULT_OARS: tuple[str, ...] = ("Bladder", "Rectum", "Sigmoid", "Bowel", "Bone")
#: clearances up to the ranking's clearance cap + this (mm) are FCL's; beyond, the organ distance field's
#: estimate (within its error bound, about 4 mm) is reported, and the Pareto flags use it. Scores and the
#: ranking are unchanged (the score caps clearance); re-ranking with a larger cap uses the estimates.
SCREEN_BAND_MM = 1.0

#: 15-gauge plastic ISBT needle, outer diameter 1.83 mm (reference: oncoreach.md, ASSUMED dimensions).
NEEDLE_RADIUS_15GA_MM = 1.83 / 2


@dataclass(frozen=True)
class PlanConfig:
    """Settings of a plan (all lengths in mm).

    ``reach_tolerance_mm``: a candidate reaches its target when its tip is within this distance of the
    target point. ``max_depth_mm``: free length of the needle beyond the template (reference: about 200 mm).
    ``obturator_depth_mm``: how far the obturator tip lies beyond the template plane, used to place the
    template from an ``Obturator`` ROI when no pose is given.
    ``designs``: stylet presets to steer with (empty: straight needles only; the pilot study used
    15ga-30j-tip). ``family``: the schedules screened per design. ``alternatives``: reaching schedules tried
    per hole before a steered candidate is declared colliding. ``refine_top``: feasible steered candidates
    per target re-solved with the reference insertion model (the two-tube Cosserat rod inserted in tissue,
    :mod:`~reachplan.planner.steering.tissue_rod`); the others keep the screening model's numbers, and every
    candidate names its model.
    ``robust_top``: feasible straight and steered candidates per target assessed under ``perturbations``
    (tension, roll and entry-angle errors); the ranking prefers robust ones among them.
    ``tissue_moduli_pa``: Young's modulus per organ (normalised ROI name, Pa), e.g. ``(("Uterus", 0.5e6),)``;
    tissue outside the named organs keeps the gel's 0.19 MPa (the reference's only modulus). The organ holding
    a target sets the screening and robustness models' curvature factor
    (:func:`~reachplan.planner.steering.insertion.curvature_factor`); the reference model takes the modulus
    along the path.
    ``screen_tolerance_mm``: the screening uses the cheapest rod model (by batched throughput) whose
    measured free-space tip error (the rod-model benchmark's table) is within it; ``planar_beam`` at 0.5 mm.
    """

    template: str = "needlefinder_syed_63"
    needle_radius_mm: float = NEEDLE_RADIUS_15GA_MM
    reach_tolerance_mm: float = 2.0
    max_depth_mm: float = 200.0
    oar_names: tuple[str, ...] = DEFAULT_OARS
    obturator_depth_mm: float = 60.0
    designs: tuple[str, ...] = ("15ga-30j-tip",)
    family: ScheduleFamily = field(default_factory=ScheduleFamily)
    alternatives: int = 8
    refine_top: int = 1
    weights: RankWeights = field(default_factory=RankWeights)
    robust_top: int = 2
    perturbations: Perturbations = field(default_factory=Perturbations)
    tissue_moduli_pa: tuple[tuple[str, float], ...] = ()
    screen_tolerance_mm: float = 0.5

    def __post_init__(self) -> None:
        for name in ("needle_radius_mm", "reach_tolerance_mm", "max_depth_mm", "obturator_depth_mm"):
            v = getattr(self, name)
            if not (np.isfinite(v) and v > 0):
                raise ValueError(f"{name} must be a positive number of mm, got {v}")

    @cached_property
    def rod_designs(self) -> tuple[RodDesign, ...]:
        """The stylet designs of ``designs``, resolved once from their preset names.

        The candidates carry these objects.

        Raises
        ------
        UnknownPresetError
            A name is not a preset.
        """
        return tuple(preset(name) for name in self.designs)


@dataclass(frozen=True)
class PlanModels:
    """The insertion models a plan uses, resolved once per plan.

    :meth:`for_config` looks the screening rod model up in the plugin registry; nothing below the pipeline looks
    plugins up.

    ``screening`` screens every schedule of the family; ``reference`` re-solves the shortlist
    (``PlanConfig.refine_top``); ``robustness`` re-evaluates the shortlist under the perturbations.
    """

    screening: KinematicInsertion = KINEMATIC
    reference: TissueRodInsertion = PLANNER_REFERENCE
    robustness: KinematicInsertion = KINEMATIC

    @classmethod
    def for_config(cls, config: PlanConfig) -> PlanModels:
        """Return the default models, with the screening model of ``config`` (:func:`screening_model`)."""
        return cls(screening=screening_model(config))


@dataclass(frozen=True, eq=False)
class Scene:
    """What a plan needs: organs to avoid, targets, the template and its pose.

    ``meshes`` holds every meshed ROI by normalised name (for figures and exports);
    ``patient_from_template`` is (4, 4), LPS mm; ``pose`` says how it was found; ``notes`` are warnings about
    the input (organs at risk not found or skipped, targets planned to points).
    """

    organs: tuple[Organ, ...]
    targets: tuple[Target, ...]
    template: Template
    patient_from_template: np.ndarray
    meshes: dict[str, trimesh.Trimesh] = field(default_factory=dict)
    pose: TemplatePose | None = None
    notes: tuple[str, ...] = ()


@dataclass(frozen=True, eq=False)
class PlanResult:
    """All scored candidates and their ranking per target."""

    candidates: tuple[Candidate, ...]
    ranking: dict[str, tuple[Candidate, ...]]
    config: PlanConfig

    def rerank(self, weights: RankWeights) -> PlanResult:
        """Return the same candidates in the order of other weights (nothing is re-solved)."""
        return PlanResult(self.candidates, rank(self.candidates, weights), dataclasses.replace(self.config,
                                                                                              weights=weights))

    def best(self, target: str, steered: bool) -> Candidate | None:
        """Return the best-ranked feasible straight (or steered) candidate of a target, if any."""
        return next((c for c in self.ranking[target] if c.feasible and c.steered == steered), None)

    def to_json(self) -> dict[str, object]:
        """Return the configuration and, per target, the ranked candidates as JSON-ready values (mm, N, LPS)."""
        targets: dict[str, object] = {}
        for t, cands in self.ranking.items():
            front = {id(c) for c in pareto_front(cands)}
            straight, steered = self.best(t, False), self.best(t, True)
            straight_d = [c.hole_distance_mm for c in cands if c.feasible and not c.steered]
            steered_d = [c.hole_distance_mm for c in cands if c.feasible and c.steered and c.clearance_mm >= 2.0]
            targets[t] = {
                "most_medial_straight_mm": round(min(straight_d), 3) if straight_d else None,
                "most_medial_steered_mm": round(min(steered_d), 3) if steered_d else None,
                "medial_gain_mm": round(min(straight_d) - min(steered_d), 3) if straight_d and steered_d else None,
                "best_straight": None if straight is None else straight.to_json(),
                "best_steered": None if steered is None else steered.to_json(),
                "candidates": [{**c.to_json(), "pareto": id(c) in front} for c in cands],
            }
        return {"config": dataclasses.asdict(self.config), "targets": targets}


def load_template(name: str) -> Template:
    """Load a template layout from the plugin registry."""
    factory = registry.get("templates", name)
    template = factory()
    if not isinstance(template, Template):
        raise PlanInputError(f"template plugin {name!r} did not return a Template")
    return template


def mesh_structures(
    structures: StructureSet, names: Iterable[str], grid: Grid | None = None, quiet: bool = True
) -> dict[str, trimesh.Trimesh]:
    """Watertight meshes (LPS mm) of the named ROIs that exist in ``structures``, by normalised name."""
    from reachplan.imaging.meshing import roi_mesh

    wanted = [n for n in names if n.casefold() in {s.casefold() for s in structures.names}]
    out: dict[str, trimesh.Trimesh] = {}
    for name in tqdm(wanted, desc="meshing organs", unit="roi", disable=quiet, leave=False):
        roi = structures.get(name)
        if has_closed(roi):
            out[roi.normalized_name] = roi_mesh(roi, grid)
    return out


def build_scene(
    structures: StructureSet,
    target_names: Sequence[str] | None = None,
    target_points: Sequence[Target] = (),
    grid: Grid | None = None,
    patient_from_template: np.ndarray | TemplatePose | None = None,
    config: PlanConfig | None = None,
    quiet: bool = True,
    *,
    allow_no_oars: bool = False,
    standard_names: Sequence[str] | None = None,
) -> Scene:
    """Mesh the organs at risk and the target ROIs and place the template.

    Parameters
    ----------
    target_names : ROI names whose centroids are targets; None = every ROI named ``Target*``. A target ROI made
        only of POINT contours gives one target per point (named ``ROI`` or ``ROI_k``; a note says so).
    target_points : further targets given as points.
    grid : the CT grid to rasterise contours on (None: a grid derived from the contours).
    patient_from_template : (4, 4) float, a :class:`TemplatePose`, or None = placed on the ``Obturator`` ROI.
    allow_no_oars : plan even when no organ at risk is found (otherwise a :class:`PlanInputError`).
    standard_names : the synonym table's standard names (ROIs not mapped to one are listed in the notes).

    Organs at risk that are missing or have no closed contours are named in ``Scene.notes`` (see
    :func:`reachplan.planner.geometry.organs.select_oars`); ROIs of one name twice are an error.
    """
    config = config or PlanConfig()
    if target_names is None:
        target_names = [n for n in structures.names if n.casefold().startswith("target")]
    check_unique(structures, [*target_names, *(["Obturator"] if patient_from_template is None else [])])
    selection = select_oars(structures, config.oar_names, standard_names, exclude=target_names)
    oars = list(selection.found)
    notes = list(selection.notes)
    if not oars and not allow_no_oars:
        raise PlanInputError(
            f"no organ at risk to check needles against: none of {', '.join(config.oar_names)} is in the "
            f"structure set with closed contours (ROIs: {', '.join(repr(r.name) for r in structures.rois)}); map "
            "one with --oar ORGAN=ROI_NAME or --synonyms FILE, or plan anyway with --allow-no-oars"
        )
    rois = [structures.get(n) for n in target_names]
    context = [n for n in ("HR-CTV", "Uterus", "Cervix", "Obturator") if n in structures.names]
    meshes = mesh_structures(structures, [*oars, *[r.normalized_name for r in rois if has_closed(r)], *context],
                             grid, quiet)
    targets = []
    for roi in rois:
        if has_closed(roi):
            x, y, z = (float(v) for v in meshes[roi.normalized_name].center_mass)
            targets.append(Target(roi.normalized_name, (x, y, z)))
            continue
        pts = roi_points(roi)
        notes.append(f"target ROI {roi.name!r} is made of POINT contours: planned to its {len(pts)} point(s)")
        for k, p in enumerate(pts, start=1):
            name = roi.normalized_name if len(pts) == 1 else f"{roi.normalized_name}_{k}"
            targets.append(Target(name, (float(p[0]), float(p[1]), float(p[2]))))
    targets += list(target_points)
    if not targets:
        raise PlanInputError("no targets: name target ROIs or give target points")
    if patient_from_template is None:
        if "Obturator" not in structures.names:
            raise PlanInputError("no Obturator (or vaginal cylinder) ROI to place the template on; give the pose "
                                 "with --template-origin X,Y,Z --template-axis X,Y,Z, --template-pose FILE or "
                                 "--rtplan FILE")
        obturator = structures.get("Obturator")
        pose = TemplatePose(pose_from_obturator(obturator, config.obturator_depth_mm),
                            f"fitted to ROI {obturator.name!r} (principal axis of its contours; template "
                            f"{config.obturator_depth_mm:g} mm behind its cranial tip)")
    elif isinstance(patient_from_template, TemplatePose):
        pose = patient_from_template
    else:
        pose = TemplatePose(np.asarray(patient_from_template, dtype=float), "given")
    # distance-field screen (issue 19): FCL confirms clearances up to the ranking's cap + SCREEN_BAND_MM
    confirm = config.weights.clearance_cap_mm + SCREEN_BAND_MM
    organs = tuple(with_distance_field(make_organ(n, meshes[n]), confirm) for n in oars)
    return Scene(organs, tuple(targets), load_template(config.template), pose.patient_from_template,
                 meshes, pose=pose, notes=tuple(notes))


def plan(scene: Scene, config: PlanConfig | None = None, quiet: bool = True,
         models: PlanModels | None = None) -> PlanResult:
    """Score every hole x target candidate, straight and steered, and rank them.

    ``models``: the insertion models to use (default :meth:`PlanModels.for_config`). A model that fails for
    one candidate (no convergence, a shape out of range) marks that candidate (``failed``, with the reason);
    the plan goes on.
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
    return PlanResult(tuple(cands), rank(cands, config.weights), config)


def target_modulus_pa(scene: Scene, target: Target, config: PlanConfig) -> float:
    """Return the Young's modulus (Pa) of the tissue a target lies in.

    The first organ of ``config.tissue_moduli_pa`` whose mesh contains the target, else the phantom's gel
    (SimuGel #3, 0.19 MPa, reference ``oncoreach.md``: the only tissue modulus the reference gives).

    Raises
    ------
    PlanInputError
        When a named organ has no mesh in the scene, or a modulus is not positive.
    """
    point = np.asarray(target.position_mm, dtype=float)[None, :]
    profile = modulus_profile(scene, point, config.tissue_moduli_pa, SIMUGEL_MODULUS_PA)
    return SIMUGEL_MODULUS_PA if profile is None else float(profile[1][0])


def modulus_profile(scene: Scene, path_mm: np.ndarray, moduli: tuple[tuple[str, float], ...],
                    default_pa: float = SIMUGEL_MODULUS_PA) -> tuple[np.ndarray, np.ndarray] | None:
    """Return the tissue modulus along a needle path, ``(depth_mm, modulus_pa)``; None when ``moduli`` is empty.

    The modulus of the organ each point lies in (the first of ``moduli`` that contains it), ``default_pa``
    elsewhere.

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


def _template_offsets(scene: Scene, target: Target) -> np.ndarray:
    """(H, 3) target minus each needle hole's entry, mm, in the template frame."""
    inv = np.linalg.inv(scene.patient_from_template)
    t = inv[:3, :3] @ np.asarray(target.position_mm) + inv[:3, 3]
    xy = np.array([h.xy_mm for h in scene.template.needle_holes])
    return t - np.column_stack([xy, np.zeros(len(xy))])


def screening_model(config: PlanConfig) -> KinematicInsertion:
    """Return the kinematic insertion model on the cheapest rod model within ``config.screen_tolerance_mm``.

    The rod model is looked up in the plugin registry.
    """
    from reachplan.rod_model.select import Scene as RodScene
    from reachplan.rod_model.select import select_model

    name = select_model(config.screen_tolerance_mm, RodScene(), rod_model_capabilities(), batched=True)
    return KinematicInsertion(rod_model=rod_model(name))


def steered_candidates(scene: Scene, target: Target, design: RodDesign, config: PlanConfig,
                       skip: frozenset[str] | set[str] = frozenset(),
                       model: KinematicInsertion | None = None) -> list[Candidate]:
    """Return one steered candidate per hole (holes in ``skip`` excluded), screened with ``model``.

    ``model`` defaults to :func:`screening_model` of ``config``.

    Among the bank's schedules that reach the target, the gentlest (lowest peak tension, then smallest
    reach error) that clears every organ is kept, trying at most ``config.alternatives``; when none is
    clear, the gentlest reaching one (colliding); when none reaches, the closest approach, unchecked.
    """
    model = model or screening_model(config)
    bank = shape_bank(design, config.family, min(config.max_depth_mm, design.length_mm), model)
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
                                   modulus_profile=profile)
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


#: words naming an applicator part (name keys): an obstacle for needles, not an organ at risk for dose
APPLICATOR_WORDS = ("tandem", "intrauterine", "ovoid", "obturator", "applicator", "cylinder")


def is_applicator(name: str) -> bool:
    """Return True when ``name`` is an applicator part (:data:`APPLICATOR_WORDS`), not tissue."""
    from reachplan.imaging.names import name_key

    key = name_key(name)
    return any(w in key for w in APPLICATOR_WORDS)


def planning_structures(structures: StructureSet, grid: Grid | None, target_roi: str,
                        oar_names: Sequence[str]) -> PlanningStructures:
    """Return the target and organs at risk (bone and applicator parts excluded) as masks for dose.

    An applicator part (:data:`APPLICATOR_WORDS` in its name: the tandem, ovoids, obturator) may be an obstacle to
    needles (an organ of the scene) but receives no dose limit and is no organ at risk for dose.

    On ``grid`` (the CT's), or without a CT on a 2 mm grid on the contours' own slices that holds the target and
    every organ.

    Raises
    ------
    PlanInputError
        ``target_roi`` is not in the structure set.
    """
    from reachplan.imaging.meshing import fit_grid, roi_mask
    from reachplan.planner.dose.structures import PlanningStructures, Structure

    if target_roi not in structures.names:
        raise PlanInputError(f"no {target_roi} ROI to compute dose on; name it with --target-roi")
    roi = structures.get(target_roi)
    oar_rois = [structures.get(n) for n in oar_names if n in structures.names and n != "Bone"
                and not is_applicator(n)]
    if grid is None:
        union = Roi(0, "planning volume", tuple(c for r in (roi, *oar_rois) for c in r.contours
                                                  if c.geometric_type == "CLOSED_PLANAR"))
        grid = fit_grid(union, None, 2.0)
    oars = tuple(Structure(r.normalized_name, roi_mask(r, grid)) for r in oar_rois)
    return PlanningStructures(grid, Structure(target_roi, roi_mask(roi, grid)), oars)


def choose_needles(result: PlanResult, targets: Sequence[str] | None = None,
                   steered: bool | None = None) -> tuple[Candidate, ...]:
    """One needle per target: its top-ranked feasible candidate whose hole no earlier target took.

    ``steered``: True takes steered candidates only, False straight ones only, None either. Targets without a
    feasible candidate (of that kind) on a free hole get none (their ranking says why).
    """
    used: set[str] = set()
    out: list[Candidate] = []
    for t in targets or list(result.ranking):
        for c in result.ranking.get(t, ()):
            if c.feasible and c.hole_id not in used and (steered is None or c.steered == steered):
                used.add(c.hole_id)
                out.append(c)
                break
    return tuple(out)


#: What a delivered channel is for when it is an applicator channel (tandem, ring, ovoid), and the delivered plan's
#: kind when every target got its own top-ranked needle (see :class:`Delivery`).
INTRACAVITARY = "intracavitary"
PER_TARGET = "one needle per target"
#: The implant arm exported as the delivered plan: straight + steered (never worse than straight only).
EXPORT_ARM = "steered"

#: ASSUMED source strength for planning: a new Ir-192 HDR source of about 10 Ci, S_K ≈ 40 700 U.
DEFAULT_AIR_KERMA_U = 40_700.0


@dataclass(frozen=True, eq=False)
class Delivery:
    """The delivered plan: loaded channels with their dwell times, ready for the exporters.

    ``export`` holds only the channels that carry dwell time (a needle the optimum leaves empty is not part of the
    implant and gets no instructions); ``roles`` says, per exported channel, what it is for (the target a
    per-target needle was chosen for, the target volume for an implant needle, ``intracavitary`` for an applicator
    channel); ``kind``: which plan is delivered (``implant, straight + steered``, ``implant, straight`` or
    ``one needle per target``). ``optimisation``: its dwell times and dose-volume metrics. ``source``: the TG-43
    data set the dwell times were optimised with. ``implant``: the two implant arms (:func:`plan_implants`) when
    asked for, and ``implant_exports`` the export of each arm's chosen implant (loaded channels only), by arm name.
    """

    optimisation: OptimisationResult
    export: ExportPlan
    planning: PlanningStructures
    source: SourceData
    roles: tuple[str, ...]
    kind: str = PER_TARGET
    implant: ImplantComparison | None = None
    implant_exports: dict[str, ExportPlan] = field(default_factory=dict)

    @property
    def n_needles(self) -> int:
        """Template needles delivered (intracavitary channels not counted)."""
        return sum(r != INTRACAVITARY for r in self.roles)


def plan_delivery(
    result: PlanResult,
    structures: StructureSet,
    grid: Grid | None,
    source_name: str = "gammamed_plus_hdr",
    air_kerma_u: float = DEFAULT_AIR_KERMA_U,
    target_roi: str = "HR-CTV",
    label: str = "reachplan",
    volume: Volume | None = None,
    input_paths: Sequence[Path] = (),
    named_points: Sequence[tuple[str, Sequence[float]]] = (),
    planned_dose: bool = True,
    scene: Scene | None = None,
    implant_settings: ImplantSettings | None = None,
) -> Delivery:
    """Plan the dwell times on the target and assemble the export plan (RT Plan + Structure Set + Dose + device).

    With ``scene`` the implant is planned for the whole target volume, straight only and straight + steered
    (:func:`plan_implants` with ``implant_settings``), each arm's chosen implant is exported as device instructions,
    and the straight + steered arm's chosen implant (never worse than straight only; the straight arm's when the
    other has no plan) is the delivered plan: the RT Plan a TPS imports. Without ``scene`` (or when neither arm has
    a plan) every target gets its top-ranked feasible needle and the dwell times are optimised on those.
    Dose by TG-43 against the EMBRACE II aims.

    The export carries the prescription (the per-fraction dose whose D90 meets the EMBRACE II aim, in as many
    fractions as the EQD2 figures assume), the reference points (Point A, ICRU bladder and rectum points where
    the structures allow, see :mod:`reachplan.planner.geometry.reference_points`, and ``named_points``,
    (name, (x, y, z) mm LPS)) with each dwell's dose rate there, the template's application setup type and the
    planned dose of all fractions on the target's and organs' region of the planning grid (``planned_dose``
    False: no RT Dose, for callers that only need the optimisation).

    Raises
    ------
    PlanInputError
        No feasible needle, no target structure to optimise on, or a bad named point.
    """
    from reachplan.planner.dose.aims import Aims
    from reachplan.planner.dose.tg43 import Tg43Kernel, dose_on_grid, rate_matrix
    from reachplan.planner.geometry.reference_points import place_reference_points
    from reachplan.plugins.exporters import ExportPlan, SourceSpec
    from reachplan.plugins.exporters.base import PlannedDose, ReferencePoint

    planning = planning_structures(structures, grid, target_roi, result.config.oar_names)
    source = get_source(source_name)
    kernel = Tg43Kernel(source)
    aims = Aims()
    implant = None
    if scene is not None:
        tandem = tandem_channels(structures, planning, scene.patient_from_template, implant_settings)
        implant = plan_implants(scene, planning, result.config, source, air_kerma_u, implant_settings,
                                intracavitary=tandem)
    delivered = _delivered_implant(implant, planning.target.name)
    if delivered is not None:
        arm, opt, exports, roles = delivered
        kind = "implant, straight + steered" if arm.name == EXPORT_ARM else f"implant, {arm.name}"
    else:
        opt, exports, roles = _per_target(result, planning, kernel, air_kerma_u, aims)
        kind = PER_TARGET
    active = opt.dwells.select(opt.dwells.times_s > 0)
    placed, _ = place_reference_points(structures)
    wanted = [(p.name, p.position_mm) for p in placed]
    for name, xyz in named_points:
        pos = np.asarray(xyz, dtype=float)
        if pos.shape != (3,) or not np.all(np.isfinite(pos)):
            raise PlanInputError(f"reference point {name!r}: give three finite coordinates in mm (LPS)")
        wanted.append((name, pos))
    gy_per_s = air_kerma_u / 360000.0  # rate_matrix is cGy h⁻¹ U⁻¹: × S_K / 100 / 3600 gives Gy s⁻¹
    points = []
    for name, pos in wanted:
        rate = rate_matrix(pos[None], opt.dwells.positions_mm, opt.dwells.directions, kernel)[0] * gy_per_s
        # per exported channel, in its dwell order (exported channel ch holds the dwells with channels == ch)
        rates = tuple(rate[opt.dwells.channels == ch] for ch in range(1, len(exports) + 1))
        try:
            points.append(ReferencePoint(name, pos, rates))
        except ValueError as exc:
            raise PlanInputError(str(exc)) from None
    fractions = aims.fractionation.n_fractions
    dose = None
    if planned_dose:
        dose_grid = _dose_region(planning)
        values = dose_on_grid(dose_grid, active, kernel, air_kerma_u) if len(active) else np.zeros(dose_grid.shape)
        dose = PlannedDose(values * fractions, dose_grid)
    spec = SourceSpec.from_source_data(source, air_kerma_u, datetime.now().replace(microsecond=0))
    setup = load_template(result.config.template).application_setup_type

    def export_plan(name: str, needles: Sequence[NeedleExport], points: Sequence[ReferencePoint] = (),
                    dose: PlannedDose | None = None) -> ExportPlan:
        return ExportPlan(name[:16], tuple(needles), spec, structure_set=structures, volume=volume,
                          input_paths=tuple(input_paths), fractions_planned=fractions,
                          prescription_dose_gy=aims.prescription_gy, target_name=target_roi[:64],
                          reference_points=tuple(points), application_setup_type=setup, dose=dose)

    export = export_plan(label, exports, points, dose)
    implant_exports = {a.name: export_plan(f"implant_{a.name}", implant_needles(a.plan))
                       for a in (implant.arms if implant is not None else ()) if a.plan is not None and a.plan.channels}
    return Delivery(opt, export, planning, source, roles, kind, implant, implant_exports)


def _delivered_implant(
    implant: ImplantComparison | None, target_name: str,
) -> tuple[ImplantArm, OptimisationResult, tuple[NeedleExport, ...], tuple[str, ...]] | None:
    """Return the implant arm to deliver (:data:`EXPORT_ARM`, else the other) as an optimisation result, or None.

    Each channel's role is ``target_name`` for a needle, :data:`INTRACAVITARY` for an applicator channel.
    Channel ``ch`` of the exported plan is the plan's channel ``ch`` (its dwells are ``dwells.channels == ch``).
    """
    from reachplan.planner.implant.dwells import OptimisationResult

    if implant is None:
        return None
    arms = sorted(implant.arms, key=lambda a: a.name != EXPORT_ARM)
    arm = next((a for a in arms if a.plan is not None and a.plan.channels), None)
    if arm is None or arm.plan is None:
        return None
    pl = arm.plan
    gap = "" if pl.mip_gap is None else f"; gap to the LP bound {pl.mip_gap:.2f}"
    n_ic = len(pl.channels) - pl.n_needles
    reason = (f"implant ({arm.name} arm): {pl.n_needles} needle{'s' if pl.n_needles != 1 else ''} and {n_ic} "
              f"intracavitary channel"
              f"{'s' if n_ic != 1 else ''}, chosen with the dwell times (LP relaxation rounded, then a swap "
              f"search{gap})")
    opt = OptimisationResult(pl.dwells, pl.target, pl.oars, True, reason, scaled=pl.scale < 1.0, scale=pl.scale,
                             dvhs=pl.dvhs, aim_met=pl.aims_met)
    roles = tuple(target_name if c.is_needle else INTRACAVITARY for c in pl.channels)
    return arm, opt, implant_needles(pl), roles


def _per_target(
    result: PlanResult, planning: PlanningStructures, kernel: Tg43Kernel, air_kerma_u: float, aims: Aims,
) -> tuple[OptimisationResult, tuple[NeedleExport, ...], tuple[str, ...]]:
    """Every target's top-ranked feasible needle with optimised dwell times; empty needles are left out.

    The dwells are renumbered so that channel ``ch`` of the result is the ``ch``-th exported needle.
    """
    from reachplan.planner.dose.tg43 import DwellSet
    from reachplan.planner.implant.dwells import optimise_dwell_times
    from reachplan.plugins.exporters import NeedleExport

    needles = choose_needles(result)
    if not needles:
        raise PlanInputError("no feasible needle to deliver: every target is out of reach or blocked")
    opt = optimise_dwell_times([c.path_mm for c in needles], planning, kernel, air_kerma_u, aims)
    exports: list[NeedleExport] = []
    roles: list[str] = []
    kept: list[DwellSet] = []
    for ch, c in enumerate(needles, start=1):
        keep = (opt.dwells.channels == ch) & (opt.dwells.times_s > 0)
        if not keep.any():  # a needle the optimum leaves empty is not part of the implant: no instructions
            continue
        sub = opt.dwells.select(keep)
        kept.append(DwellSet(sub.positions_mm, sub.directions, sub.times_s, np.full(len(sub), len(kept) + 1)))
        roles.append(c.target)
        exports.append(NeedleExport(c.hole_id, c.path_mm, sub.positions_mm, sub.times_s, c.design_name,
                                    _schedule_rows(c.schedule)))
    if kept:
        opt = dataclasses.replace(opt, dwells=DwellSet.concatenate(kept))
    return opt, tuple(exports), tuple(roles)


def tandem_channels(structures: StructureSet, planning: PlanningStructures, patient_from_template: np.ndarray,
                    settings: ImplantSettings | None = None) -> tuple[Channel, ...]:
    """Intracavitary channels from tandem ROIs (a name containing ``tandem`` or ``intrauterine``).

    The straight line through the ROI's points along their principal axis, from the end nearer the template (ASSUMED
    straight: a curved tandem is approximated by its chord). Ring and ovoid channels are not modelled yet. Channels
    with fewer than ``settings.min_dwells`` dwells in the target region are left out.
    """
    from reachplan.imaging.names import name_key
    from reachplan.planner.implant.candidates import intracavitary_channel

    axis = np.asarray(patient_from_template, float)[:3, 2]
    out = []
    for roi in structures.rois:
        key = name_key(roi.name)
        if "tandem" not in key and "intrauterine" not in key:
            continue
        pts = np.concatenate([c.points_mm for c in roi.contours]) if roi.contours else np.zeros((0, 3))
        if len(pts) < 2:
            continue
        centre = pts.mean(axis=0)
        u = np.linalg.svd(pts - centre, full_matrices=False)[2][0]
        u = u if u @ axis >= 0 else -u
        s = (pts - centre) @ u
        channel = intracavitary_channel(roi.name, centre + np.outer([s.min(), s.max()], u), planning, settings)
        if channel is not None:
            out.append(channel)
    return tuple(out)


def _schedule_rows(schedule: TensionSchedule | None) -> np.ndarray | None:
    """(k, 3) rows (depth mm, tension N, roll deg) of a schedule, or None."""
    return None if schedule is None else np.column_stack([schedule.depth_mm, schedule.tension_n, schedule.roll_deg])


def implant_needles(plan: ImplantPlan) -> tuple[NeedleExport, ...]:
    """Return the loaded channels of an implant as exporter needles, in the plan's order.

    Every one carries time: an empty channel is not in ``plan.channels``.
    """
    from reachplan.plugins.exporters import NeedleExport

    out = []
    for ch, c in enumerate(plan.channels, start=1):
        keep = plan.dwells.channels == ch
        out.append(NeedleExport(c.name, c.path_mm, plan.dwells.positions_mm[keep], plan.dwells.times_s[keep],
                                c.design, _schedule_rows(c.schedule), applicator=not c.is_needle))
    return tuple(out)


def _dose_region(planning: PlanningStructures, margin: int = 2) -> Grid:
    """Return the part of the planning grid around the target and the organs at risk, as a grid of its own.

    ``margin``: voxels added on every side.
    """
    mask = planning.target.mask.copy()
    for o in planning.oars:
        mask |= o.mask
    idx = np.argwhere(mask)
    lo = np.maximum(idx.min(axis=0) - margin, 0)
    hi = np.minimum(idx.max(axis=0) + margin + 1, planning.grid.shape)
    affine = planning.grid.patient_from_index.copy()
    affine[:3, 3] = affine[:3, :3] @ np.array([lo[2], lo[1], lo[0]], dtype=float) + affine[:3, 3]
    shape = (int(hi[0] - lo[0]), int(hi[1] - lo[1]), int(hi[2] - lo[2]))
    return Grid(shape, affine)


def rod_model_capabilities() -> dict[str, Capabilities]:
    """Return what every loadable rod-model plugin can represent, by name (the selector's input)."""
    return {name: registry.get("rod_models", name).capabilities for name in registry.names("rod_models")}


def rod_model(name: str) -> RodModel:
    """Return the rod-model plugin called ``name``.

    Raises
    ------
    PluginError
        Unknown or unavailable rod model.
    """
    model: RodModel = registry.get("rod_models", name)
    return model


def get_source(name: str) -> SourceData:
    """Return the TG-43 data set ``name`` through the plugin registry (built-ins as fallback).

    Raises
    ------
    PluginError
        Unknown or unavailable source (the message lists the known names).
    """
    try:
        loader = registry.get("sources", name)
    except PluginError:
        if name not in BUILTIN:
            known = sorted(set(BUILTIN) | set(registry.names("sources")))
            raise PluginError(f"no TG-43 source named {name!r}; available: {', '.join(known)}") from None
        loader = BUILTIN[name]
    data = loader()
    if not isinstance(data, SourceData):
        raise PluginError(f"sources plugin {name!r} did not return SourceData (got {type(data).__name__})")
    return data


def recognise_source(*labels: str) -> str | None:
    """Name of the source (built-in or installed plugin) whose alias occurs in one of ``labels``.

    ``labels`` are DICOM strings (Source Isotope Name, Source Model ID, Treatment Machine Name); they and
    the aliases are compared without case, spaces, dashes, underscores or dots. None when no alias matches.
    """
    norm = [normalise_label(x) for x in labels if x]
    for name in dict.fromkeys([*BUILTIN, *registry.names("sources")]):
        if any(alias in text for alias in get_source(name).aliases for text in norm):
            return name
    return None


#: Half-lives (days) used to tell the isotope of an anonymised plan (NNDC NuDat 3): Ir-192 73.829 d, Co-60
#: 5.2714 y, Cs-137 30.08 y, I-125 59.49 d, Pd-103 16.99 d, Yb-169 32.02 d, Se-75 119.78 d.
ISOTOPE_HALF_LIVES_DAYS: tuple[tuple[str, float], ...] = (
    ("Ir-192", 73.83), ("Co-60", 1925.28), ("Cs-137", 10987.0), ("I-125", 59.49), ("Pd-103", 16.99),
    ("Yb-169", 32.02), ("Se-75", 119.78),
)
_ISOTOPE_RE = re.compile(r"\b(ir|co|cs|i|pd|yb|se)[\s-]?(192|60|137|125|103|169|75)\b", re.IGNORECASE)
#: Active lengths agree when within this (mm): the DICOM values are written to 0.1 mm or better.
ACTIVE_LENGTH_TOLERANCE_MM = 0.05


@dataclass(frozen=True)
class SourceChoice:
    """The TG-43 data set chosen for a plan's source: its ``name`` and ``how`` it was chosen (one line)."""

    name: str
    how: str


def plan_isotope(isotope_name: str, half_life_days: float | None) -> str | None:
    """Return the isotope of a plan's source: from Source Isotope Name when it names one, else from the half-life.

    Returns
    -------
    str or None
        e.g. ``"Ir-192"``; None when neither tells (a half-life within 2 % of a known isotope's counts).
    """
    m = _ISOTOPE_RE.search(isotope_name or "")
    if m:
        symbol = m.group(1).capitalize() if len(m.group(1)) > 1 else m.group(1).upper()
        return f"{symbol}-{m.group(2)}"
    if half_life_days:
        for iso, t in ISOTOPE_HALF_LIVES_DAYS:
            if abs(half_life_days / t - 1.0) <= 0.02:
                return iso
    return None


def identify_source(model_id: str, isotope_name: str, manufacturer: str, treatment_type: str,
                    half_life_days: float | None, active_length_mm: float | None,
                    machine_name: str = "") -> SourceChoice:
    """Choose the registered TG-43 data set of a plan's source.

    First by name: a data set whose alias occurs in the Source Model ID, Source Isotope Name, manufacturer or
    Treatment Machine Name (:func:`recognise_source`), kept when its isotope, kind and active length agree
    with the plan's. Otherwise (an anonymised plan) by inference: the registered data sets of the plan's
    isotope (named, or told by the half-life), treatment type (HDR, PDR) and active length (within
    :data:`ACTIVE_LENGTH_TOLERANCE_MM`), narrowed by the manufacturer when it names one; chosen when exactly one
    remains.

    Raises
    ------
    PlanInputError
        The isotope has no registered TG-43 data (e.g. Cs-137), the named source contradicts the plan, or no
        or several data sets match (the message lists them; pass ``--source``).
    """
    names = list(dict.fromkeys([*BUILTIN, *registry.names("sources")]))
    data = {n: get_source(n) for n in names}
    isotope = plan_isotope(isotope_name, half_life_days)
    if isotope is not None and not any(d.isotope == isotope for d in data.values()):
        raise PlanInputError(f"no TG-43 data is registered for {isotope} (registered: "
                             f"{', '.join(sorted({d.isotope for d in data.values()}))}); this plan cannot be "
                             "checked with reachplan")

    def conflicts(d: SourceData) -> list[str]:
        out = []
        if isotope and d.isotope != isotope:
            out.append(f"isotope {isotope} vs {d.isotope}")
        if treatment_type in ("HDR", "PDR", "LDR") and d.kind != treatment_type:
            out.append(f"treatment type {treatment_type} vs {d.kind}")
        if active_length_mm and abs(active_length_mm - 10 * d.active_length_cm) > ACTIVE_LENGTH_TOLERANCE_MM:
            out.append(f"active length {active_length_mm:g} mm vs {10 * d.active_length_cm:g} mm")
        return out

    named = recognise_source(model_id, isotope_name, manufacturer, machine_name)
    if named is not None:
        bad = conflicts(data[named])
        if bad:
            raise PlanInputError(f"the plan names the source {named}, but its {'; '.join(bad)}; pass --source NAME "
                                 "for the data set that matches")
        return SourceChoice(named, f"{named}: named in the plan")
    fits = [n for n, d in data.items() if not conflicts(d)]
    maker = normalise_label(manufacturer.split()[0]) if manufacturer.strip() else ""
    by_maker = [n for n in fits if maker and len(maker) >= 3 and maker in normalise_label(data[n].title)]
    if by_maker:
        fits = by_maker
    told = ", ".join(x for x in (isotope or "", treatment_type,
                                 f"{active_length_mm:g} mm active" if active_length_mm else "",
                                 f"manufacturer {manufacturer}" if by_maker else "") if x)
    if len(fits) == 1:
        return SourceChoice(fits[0], f"{fits[0]}: inferred from {told} (the only registered source that fits)")
    if not fits:
        raise PlanInputError(f"no registered TG-43 source fits the plan's source ({told}); pass --source NAME "
                             "(see `reachplan plugins`)")
    raise PlanInputError(f"the plan's source ({told}) fits {len(fits)} registered sources ({', '.join(fits)}); "
                         "pass --source NAME")


def decay_factor(half_life_days: float, elapsed_days: float) -> float:
    """Fraction of the source strength left after ``elapsed_days`` (negative: before calibration), 2^(-t/T½)."""
    if not (np.isfinite(half_life_days) and half_life_days > 0 and np.isfinite(elapsed_days)):
        raise PlanInputError(f"cannot decay the source: half-life {half_life_days} d, elapsed {elapsed_days} d")
    return float(2.0 ** (-elapsed_days / half_life_days))


def rod_model_errors() -> tuple[ErrorRow, ...]:
    """Return the measured rod-model error table (the rod-model benchmark's, packaged); () when not available.

    For the report's speed-versus-accuracy section.
    """
    from reachplan.rod_model.select import error_table

    try:
        return error_table()
    except RodModelError:
        return ()


@dataclass(frozen=True, eq=False)
class ImplantComparison:
    """The two implant arms on the same anatomy and template.

    Straight needles only, and straight + steered (see :mod:`reachplan.planner.implant`); ``candidates`` every
    candidate channel of the steered arm (the straight arm's are its straight ones and the intracavitary channels).
    """

    straight: ImplantArm
    steered: ImplantArm
    candidates: tuple[Channel, ...]
    seconds: float = 0.0

    @property
    def arms(self) -> tuple[ImplantArm, ImplantArm]:
        """Return the straight and the steered arm."""
        return self.straight, self.steered

    def to_json(self) -> dict[str, object]:
        """Return plan.json's ``implant``.

        ``straight`` and ``steered`` (:meth:`ImplantArm.to_json`), the count of candidate channels by kind and the
        wall time of the whole (candidates and both arms, which run at once), s.
        """
        kinds: dict[str, int] = {}
        for c in self.candidates:
            kinds[c.kind] = kinds.get(c.kind, 0) + 1
        return {"straight": self.straight.to_json(), "steered": self.steered.to_json(), "candidates": kinds,
                "seconds": round(self.seconds, 3)}


def plan_implants(
    scene: Scene,
    planning: PlanningStructures,
    config: PlanConfig,
    source: SourceData,
    air_kerma_u: float = DEFAULT_AIR_KERMA_U,
    settings: ImplantSettings | None = None,
    intracavitary: Sequence[Channel] = (),
    gtv: Structure | None = None,
    models: PlanModels | None = None,
) -> ImplantComparison:
    """Candidate needles for the target volume and both implant arms (Pareto curve and chosen plan each).

    ``intracavitary``: applicator channels (tandem, ring, ovoids) available to both arms
    (:func:`reachplan.planner.implant.candidates.intracavitary_channel`). The steered arm screens every stylet design
    of ``config`` with the screening model of ``models``.
    """
    from reachplan.planner.dose.tg43 import Tg43Kernel
    from reachplan.planner.implant.arms import with_subset
    from reachplan.planner.implant.candidates import needle_candidates
    from reachplan.planner.implant.plan import plan_arms
    from reachplan.planner.implant.settings import ImplantSettings

    t0 = time.perf_counter()
    settings = settings or ImplantSettings()
    models = models or PlanModels.for_config(config)
    holes = scene.template.needle_holes
    banks = [shape_bank(d, config.family, min(config.max_depth_mm, d.length_mm), models.screening)
             for d in config.rod_designs]
    cands = needle_candidates([h.hole_id for h in holes], np.array([h.xy_mm for h in holes]),
                              np.array([h.distance_mm for h in holes]), scene.patient_from_template, planning,
                              scene.organs, config.needle_radius_mm, settings, banks, config.max_depth_mm)
    kernel = Tg43Kernel(source)
    # the two arms at once, on two cores; the steered arm's candidates include the straight ones, so the straight
    # arm's implants are its too: never worse
    straight, steered = plan_arms([("straight", [*[c for c in cands if not c.steered], *intracavitary]),
                                   ("steered", [*cands, *intracavitary])], planning, kernel, air_kerma_u,
                                  settings=settings, gtv=gtv)
    steered = with_subset(steered, straight)
    return ImplantComparison(straight, steered, (*cands, *intracavitary), time.perf_counter() - t0)
