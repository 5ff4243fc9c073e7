"""Implant needles checked like ranked ones: scenario paths, the reference re-solve, robustness and tension.

Two steps, placed by their cost (measured on the demo's clinical case, 82 steered candidates):

1. **Scenario paths for every steered candidate** (:func:`with_scenarios`, at candidate generation, under 1 ms a
   candidate): the robustness room's perturbed paths (:func:`~reachplan.planner.steering.robustness.perturbed_paths`:
   tension × (1 ± 10 %), roll ± 10°, entry tilt ± 2° about both template axes) fill
   :attr:`Channel.scenario_paths_mm`, so the needle selection sees where each needle may really go.
2. **The chosen needles of each arm** (:func:`check_arm`, after the selection): a reference re-solve costs about 1 s
   a solve and up to 4 solves a needle (the re-aim), and the robustness check's exact clearances about 0.1 s a needle,
   too much for every candidate. Each chosen steered needle is re-solved with the reference insertion model (the
   in-tissue rod the ranking refines with, :func:`~reachplan.planner.steering.steered.refine_with`), its schedule
   re-aimed at the planned tip within the plan's tension reserve; its dwells are put on the re-solved path at the
   same distances from the tip, its scenario paths recomputed about it, and the robustness room gives its worst-case
   reach error (from the planned tip) and clearance. A straight needle gets its robustness (entry tilts) the same way.

A steered needle is **rejected** when the reference fails or its path comes closer than the clearance margin to an
organ. A plan whose needles pass is **re-loaded** on the re-solved paths (its dwell times optimised again on its
channels, :func:`~reachplan.planner.implant.plan.plan_implant`), so its metrics, RT Plan and RT Dose are those of the
dwells exported; the needles whose dwells moved more than :attr:`NeedleCheckSettings.dwell_tolerance_mm` (the
selection saw them elsewhere) are named in the arm's ``needle_check`` record. When a needle is rejected, or the
re-loaded plan no longer meets the aims the screening plan met, the arm takes its next plan by its choice rule.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from reachplan._arrays import arc_length_mm
from reachplan.planner.case.config import PlanConfig, PlanModels
from reachplan.planner.case.scene import Scene
from reachplan.planner.case.search import modulus_profile, target_modulus_pa
from reachplan.planner.dose.aims import Aims
from reachplan.planner.dose.structures import PlanningStructures, Structure
from reachplan.planner.dose.tg43 import Tg43Kernel
from reachplan.planner.errors import PlanInputError
from reachplan.planner.implant.arms import ImplantArm, ImplantPlan
from reachplan.planner.implant.candidates import Channel, NeedleCheck
from reachplan.planner.implant.plan import load_implant
from reachplan.planner.implant.problem import PointLimit
from reachplan.planner.implant.settings import ImplantSettings
from reachplan.planner.steering.candidates import Target, score_path
from reachplan.planner.steering.insertion import STRAIGHT
from reachplan.planner.steering.kinematic import KinematicInsertion
from reachplan.planner.steering.robustness import assess, perturbed_paths
from reachplan.planner.steering.schedule import TensionSchedule
from reachplan.planner.steering.steered import place, refine_with, usable_tension_n
from reachplan.rod_model.design import RodDesign
from reachplan.rod_model.errors import RodModelError

#: plans with a steered needle re-solved per arm at most (each costs a few reference solves and a re-load)
MAX_TRIES = 3


@dataclass(frozen=True)
class NeedleCheckSettings:
    """How the chosen implant needles are checked.

    Parameters
    ----------
    dwell_tolerance_mm : float, mm
        A re-solved steered needle whose dwells move farther than this from the screening path's is named in the
        arm's record (the selection saw it elsewhere); the plan is re-loaded on the re-solved paths in any case.
    aim_tolerance_mm : float, mm
        The re-aim stops once the reference path's tip is this close to the planned tip.

    Raises
    ------
    ValueError
        A tolerance not > 0.
    """

    dwell_tolerance_mm: float = 1.0
    aim_tolerance_mm: float = 0.25

    def __post_init__(self) -> None:
        if not (self.dwell_tolerance_mm > 0 and self.aim_tolerance_mm > 0):
            raise ValueError("needle check: the dwell and aim tolerances must be > 0 mm")


@dataclass(frozen=True, eq=False)
class _Context:
    """What a needle check needs: the scene, the plan's settings and models, the implant settings."""

    scene: Scene
    config: PlanConfig
    models: PlanModels
    settings: ImplantSettings
    check: NeedleCheckSettings

    def design(self, name: str) -> RodDesign:
        """Return the plan's stylet design named ``name``.

        Parameters
        ----------
        name : str
            A preset name of ``config.designs``.

        Returns
        -------
        RodDesign
            The design the plan resolved.
        """
        return next(d for d in self.config.rod_designs if d.name == name)

    def hole_xy(self, hole_id: str) -> np.ndarray:
        """Return a hole's position on the template.

        Parameters
        ----------
        hole_id : str
            The template hole.

        Returns
        -------
        (2,) float, mm, template frame
            Its position.
        """
        return np.asarray(next(h.xy_mm for h in self.scene.template.needle_holes if h.hole_id == hole_id), float)

    def robustness_model(self, tip_mm: np.ndarray) -> KinematicInsertion:
        """Return the robustness model at the tissue modulus where the needle ends (as the ranking does per target).

        Parameters
        ----------
        tip_mm : (3,) float, mm, LPS
            The needle's tip.

        Returns
        -------
        KinematicInsertion
            ``models.robustness`` at the modulus of the organ holding the tip (:func:`target_modulus_pa`).
        """
        modulus = target_modulus_pa(self.scene, _point("tip", tip_mm), self.config)
        return dataclasses.replace(self.models.robustness, tissue_modulus_pa=modulus)


def _point(name: str, xyz_mm: np.ndarray) -> Target:
    """Return a point (mm, LPS) as a steering target."""
    return Target(name, (float(xyz_mm[0]), float(xyz_mm[1]), float(xyz_mm[2])))


def with_scenarios(channels: Sequence[Channel], scene: Scene, config: PlanConfig,
                   models: PlanModels | None = None) -> tuple[Channel, ...]:
    """Return the channels, each steered one carrying its scenario paths (the robustness room's perturbed paths).

    Parameters
    ----------
    channels : sequence of Channel
        Candidate channels (paths mm, LPS); straight needles and intracavitary channels are returned unchanged.
    scene : Scene
        The template's pose and the organs the tissue modulus is looked up in.
    config : PlanConfig
        The stylet designs, the perturbations and the tissue moduli.
    models : PlanModels or None
        Its robustness model inserts the perturbed schedules; :meth:`PlanModels.for_config` when None.

    Returns
    -------
    tuple of Channel
        In the same order; steered ones with ``scenario_paths_mm`` (8 paths, mm LPS, hole to tip).
    """
    models = models or PlanModels.for_config(config)
    ctx = _Context(scene, config, models, ImplantSettings(), NeedleCheckSettings())
    return tuple(dataclasses.replace(c, scenario_paths_mm=_scenarios(c, ctx)) if c.steered else c
                 for c in channels)


def _scenarios(c: Channel, ctx: _Context, path_mm: np.ndarray | None = None,
               schedule: TensionSchedule | None = None) -> tuple[np.ndarray, ...]:
    """Perturbed paths (mm, LPS) of a steered channel, about ``path_mm`` with ``schedule`` (default its own)."""
    path = c.path_mm if path_mm is None else path_mm
    return tuple(p for _, p in perturbed_paths(path, c.tissue_length_mm, ctx.scene.patient_from_template,
                                               ctx.config.perturbations, ctx.robustness_model(path[-1]),
                                               ctx.design(c.design), c.schedule if schedule is None else schedule))


def _arc_on(path_mm: np.ndarray, points_mm: np.ndarray) -> np.ndarray:
    """Arc length (mm) of each point's projection on the polyline ``path_mm``."""
    a, b = path_mm[:-1], path_mm[1:]
    ab = b - a
    len2 = np.maximum(np.sum(ab * ab, axis=1), 1e-18)
    t = np.clip(np.einsum("pkj,kj->pk", points_mm[:, None, :] - a[None], ab) / len2, 0.0, 1.0)
    dist = np.linalg.norm(a[None] + t[..., None] * ab[None] - points_mm[:, None, :], axis=2)
    seg = np.argmin(dist, axis=1)
    s = arc_length_mm(path_mm)
    out: np.ndarray = s[seg] + t[np.arange(len(seg)), seg] * np.sqrt(len2[seg])
    return out


def _points_at(path_mm: np.ndarray, s_mm: np.ndarray) -> np.ndarray:
    """Points (mm, LPS) at arc lengths ``s_mm`` along ``path_mm``."""
    s = arc_length_mm(path_mm)
    return np.column_stack([np.interp(s_mm, s, path_mm[:, j]) for j in range(3)])


def check_needle(channel: Channel, ctx: _Context) -> Channel | str:
    """Check one implant needle (module docstring): the checked channel, or why a steered one is rejected.

    Parameters
    ----------
    channel : Channel
        A needle of a chosen implant (straight or steered; paths mm, LPS).
    ctx : _Context
        The scene, the plan's settings and models, the implant and check settings.

    Returns
    -------
    Channel or str
        The channel with its ``check`` (and, steered, the reference path, dwells, schedule, model and scenario
        paths); or the reason the steered needle is rejected.
    """
    m = ctx.scene.patient_from_template
    planned = _point(f"{channel.name} planned tip", channel.path_mm[-1])
    tol = ctx.config.reach_tolerance_mm
    if not channel.steered:
        cand = score_path(planned, channel.name, channel.hole_distance_mm, channel.path_mm, ctx.scene.organs,
                          ctx.config.needle_radius_mm, tol, STRAIGHT, depth_mm=channel.tissue_length_mm)
        model = ctx.robustness_model(channel.path_mm[-1])
        rob = assess(cand, planned, ctx.scene.organs, m, ctx.config.needle_radius_mm, ctx.config.perturbations,
                     model, tol)
        check = NeedleCheck(0.0, None, 0.0, 0.0, rob.worst_reach_mm, rob.worst_clearance_mm, rob.worst_case,
                            rob.model.label)
        return dataclasses.replace(channel, model=STRAIGHT.label, check=check)
    assert channel.schedule is not None
    design = ctx.design(channel.design)
    reference = ctx.models.reference
    xy = ctx.hole_xy(channel.name)
    roll = float(channel.schedule.roll_deg[0])
    sched = channel.schedule
    base = TensionSchedule(sched.depth_mm, sched.tension_n, np.zeros(len(sched.depth_mm)))
    inv = np.linalg.inv(m)
    rel = inv[:3, :3] @ channel.path_mm[-1] + inv[:3, 3] - np.array([xy[0], xy[1], 0.0])
    depth = channel.tissue_length_mm
    profile = modulus_profile(ctx.scene, channel.path_mm, ctx.config.tissue_moduli_pa, reference.tissue_modulus_pa)
    try:
        sch, res = refine_with(reference, design, base, depth, rel, modulus_profile=profile,
                               tolerance_mm=ctx.check.aim_tolerance_mm,
                               max_tension_n=usable_tension_n(design, ctx.config.tension_reserve))
    except (PlanInputError, RodModelError) as exc:
        return f"reference re-solve ({reference.info.label}) failed: {exc}"
    sch = TensionSchedule(sch.depth_mm, sch.tension_n, np.full(len(sch.depth_mm), roll))
    step = depth / (len(res.positions_mm) - 1)
    path = place(res.positions_mm, step, depth, roll, xy, m)
    fine = place(res.positions_mm, step, depth, roll, xy, m, sample_mm=step)
    dwells = _points_at(fine, _arc_on(channel.path_mm, channel.dwell_positions_mm))
    shift = float(np.max(np.linalg.norm(dwells - channel.dwell_positions_mm, axis=1)))
    radius = design.needle.outer_diameter_mm / 2
    cand = score_path(planned, channel.name, channel.hole_distance_mm, path, ctx.scene.organs, radius, tol, res.model,
                      steered=True, peak_tension_n=sch.peak_tension_n, design=design, schedule=sch, depth_mm=depth)
    margin = ctx.settings.clearance_margin_mm
    if cand.collides or cand.clearance_mm < margin:
        return (f"the reference path comes {cand.clearance_mm:.1f} mm from {cand.closest_organ} "
                f"(margin {margin:g} mm)")
    model = ctx.robustness_model(path[-1])
    rob = assess(cand, planned, ctx.scene.organs, m, radius, ctx.config.perturbations, model, tol)
    check = NeedleCheck(sch.peak_tension_n, design.max_tension_n, ctx.config.tension_reserve, cand.reach_error_mm,
                        rob.worst_reach_mm, rob.worst_clearance_mm, rob.worst_case, rob.model.label, shift)
    return dataclasses.replace(channel, path_mm=path, dwell_positions_mm=dwells, schedule=sch,
                               clearance_mm=cand.clearance_mm, model=res.model.label,
                               scenario_paths_mm=_scenarios(channel, ctx, path, sch), check=check)


def _plan_order(arm: ImplantArm, extra: Sequence[ImplantPlan]) -> list[ImplantPlan]:
    """Return the arm's chosen plan, then its other plans and ``extra`` by its choice rule.

    The rule: fewest needles that meet the aims, else the highest D90.
    """
    assert arm.plan is not None
    seen = {id(arm.plan)}
    rest = []
    for p in (*arm.plans, *(b.plan for b in arm.budgets if b.plan is not None), *extra):
        if id(p) not in seen:
            seen.add(id(p))
            rest.append(p)
    rest.sort(key=lambda p: (not p.aims_met, p.n_needles if p.aims_met else 0, -p.target.d90_eqd2_gy))
    return [arm.plan, *rest]


def check_arm(arm: ImplantArm, scene: Scene, planning: PlanningStructures, config: PlanConfig, kernel: Tg43Kernel,
              air_kerma_u: float, settings: ImplantSettings, *, models: PlanModels | None = None,
              aims: Aims | None = None, gtv: Structure | None = None, check: NeedleCheckSettings | None = None,
              extra_plans: Sequence[ImplantPlan] = (), cache: dict[int, Channel | str] | None = None,
              points: Sequence[PointLimit] = ()) -> ImplantArm:
    """Check every needle of the arm's chosen implant; re-load it on the re-solved paths (module docstring).

    The chosen plan is kept when its needles pass and its re-loaded plan meets the aims as the screening plan did;
    otherwise the arm's next plan by its choice rule (at most :data:`MAX_TRIES` plans with a steered needle are
    re-solved), else the best re-loaded one by HR-CTV D90.

    Parameters
    ----------
    arm : ImplantArm
        The arm as planned on the screening paths.
    scene : Scene
        Organs (meshes, LPS mm), template and pose.
    planning : PlanningStructures
        Target and organ masks of the re-load.
    config : PlanConfig
        Stylet designs, tension reserve, reach tolerance, perturbations and tissue moduli.
    kernel : Tg43Kernel
        The source's TG-43 kernel.
    air_kerma_u : float, U
        Source strength S_K.
    settings : ImplantSettings
        The arm's settings (clearance margin; the re-load's optimiser).
    models : PlanModels or None
        Reference and robustness models; :meth:`PlanModels.for_config` when None.
    aims : Aims or None
        The aims of the re-load (EMBRACE II when None).
    gtv : Structure or None
        The GTV of the re-load, as in the arm.
    check : NeedleCheckSettings or None
        Tolerances; the defaults when None.
    extra_plans : sequence of ImplantPlan
        Further plans the arm may fall back on (the straight arm's, for the straight + steered arm).
    cache : dict or None
        Checked needles by channel object, shared between arms (their plans share channels).
    points : sequence of PointLimit
        The dose points of the re-load, as in the arm.

    Returns
    -------
    ImplantArm
        With its checked (and re-loaded) plan and its ``needle_check`` record.
    """
    t0 = time.perf_counter()
    if arm.plan is None:
        return arm
    ctx = _Context(scene, config, models or PlanModels.for_config(config), settings, check or NeedleCheckSettings())
    cache = {} if cache is None else cache

    def checked(c: Channel) -> Channel | str:
        if id(c) not in cache:
            cache[id(c)] = check_needle(c, ctx)
        return cache[id(c)]

    rejected: list[dict[str, str]] = []
    kept: list[tuple[ImplantPlan, ImplantPlan, bool]] = []  # (screening plan, checked plan, re-loaded)
    tries = 0
    for candidate in _plan_order(arm, extra_plans):
        with_steered = any(c.steered for c in candidate.channels)
        if with_steered and tries >= MAX_TRIES:
            continue  # plans of straight needles only are still tried: they need no re-solve
        tries += with_steered
        channels = [checked(c) if c.is_needle else c for c in candidate.channels]
        bad = [(c.name, r) for c, r in zip(candidate.channels, channels, strict=True) if isinstance(r, str)]
        if bad:
            rejected += [row for row in ({"hole_id": n, "reason": r} for n, r in bad) if row not in rejected]
            continue
        plan, reloaded = _reload(candidate, [c for c in channels if isinstance(c, Channel)], planning,
                                 kernel, air_kerma_u, aims, settings, gtv, points)
        if plan is None:
            continue
        kept.append((candidate, plan, reloaded))
        if plan.aims_met or not candidate.aims_met:
            break
    chosen = next((k for k in kept if k[1].aims_met or not k[0].aims_met), None)
    if chosen is None and kept:
        chosen = max(kept, key=lambda k: k[1].target.d90_eqd2_gy)
    shifts = [c.check.dwell_shift_mm for c in (chosen[1].channels if chosen else ()) if c.check is not None]
    record: dict[str, object] = {
        "reference_model": ctx.models.reference.info.label, "tension_reserve": config.tension_reserve,
        "dwell_tolerance_mm": ctx.check.dwell_tolerance_mm, "reloaded": bool(chosen and chosen[2]),
        "max_dwell_shift_mm": round(max(shifts, default=0.0), 3),
        "beyond_dwell_tolerance": [c.name for c in (chosen[1].channels if chosen else ())
                                   if c.check is not None and c.check.dwell_shift_mm > ctx.check.dwell_tolerance_mm],
        "chosen_replaced": bool(chosen and chosen[0] is not arm.plan), "rejected": rejected,
        "screening_hrctv_d90_eqd2_gy": round(chosen[0].target.d90_eqd2_gy, 3) if chosen else None,
        "seconds": round(time.perf_counter() - t0, 3)}
    if chosen is None:
        return dataclasses.replace(arm, plan=None, reason="no implant of the arm passes the needle check",
                                   needle_check=record)
    return dataclasses.replace(arm, plan=chosen[1], needle_check=record)


def _reload(plan: ImplantPlan, channels: list[Channel], planning: PlanningStructures, kernel: Tg43Kernel,
            air_kerma_u: float, aims: Aims | None, settings: ImplantSettings, gtv: Structure | None,
            points: Sequence[PointLimit]) -> tuple[ImplantPlan | None, bool]:
    """Return the plan on its checked channels, and whether its times were optimised again.

    A plan without a steered needle keeps its dwells (a straight needle's path is not re-solved); otherwise exactly
    these channels are loaded again (:func:`~reachplan.planner.implant.plan.load_implant`: no new selection).
    """
    if not any(c.steered for c in channels):
        return dataclasses.replace(plan, channels=tuple(channels)), False
    return load_implant(channels, planning, kernel, air_kerma_u, aims, settings, gtv=gtv, points=points), True
