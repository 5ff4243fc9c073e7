"""Both implant arms of a case, straight only and straight + steered, on the same anatomy and template.

The candidates for the scene's target volume (every template hole, straight and with every stylet design of the
plan) and the case's loadable applicator channels; each arm's Pareto curve and chosen implant
(:func:`reachplan.planner.implant.plan.plan_arms`).
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np

from reachplan.planner.case.config import DEFAULT_AIR_KERMA_U, PlanConfig, PlanModels
from reachplan.planner.case.scene import Scene
from reachplan.planner.dose.aims import Aims
from reachplan.planner.dose.structures import PlanningStructures, Structure
from reachplan.planner.dose.tg43 import Tg43Kernel
from reachplan.planner.implant.arms import ImplantArm, with_straight_plans
from reachplan.planner.implant.candidates import Channel, applicator_channels, needle_candidates
from reachplan.planner.implant.needles import check_arm, with_scenarios
from reachplan.planner.implant.plan import plan_arms
from reachplan.planner.implant.problem import PointLimit
from reachplan.planner.implant.settings import ImplantSettings
from reachplan.planner.implant.tissue import with_tissue_bands
from reachplan.planner.steering.steered import shape_bank
from reachplan.plugins.sources import SourceData


@dataclass(frozen=True, eq=False)
class ImplantComparison:
    """The two implant arms on the same anatomy and template.

    Straight needles only, and straight + steered (see :mod:`reachplan.planner.implant`).

    Parameters
    ----------
    straight : ImplantArm
        The arm of straight needles (and the intracavitary channels).
    steered : ImplantArm
        The arm of straight and steered needles, the straight arm's implants taken in (never worse).
    candidates : tuple of Channel
        Every candidate channel of the steered arm, paths mm, LPS (the straight arm's are its straight ones and
        the intracavitary channels).
    seconds : float, s
        Wall time of the whole (candidates and both arms).
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

        Returns
        -------
        dict
            ``straight`` and ``steered`` (:meth:`ImplantArm.to_json`), ``candidates``: the count of candidate
            channels by kind, ``seconds``: the wall time of the whole (candidates and both arms, which run at
            once), s.
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
    gtv: Structure | None = None,
    models: PlanModels | None = None,
    aims: Aims | None = None,
    points: Sequence[PointLimit] = (),
    threads: int = 2,
) -> ImplantComparison:
    """Plan both implant arms of a case: candidates for its target volume, each arm's Pareto curve and chosen plan.

    Parameters
    ----------
    scene : Scene
        Organs to avoid, template and pose, and the applicators: the loadable ones' channels (a tandem's) are
        available to both arms (:func:`~reachplan.planner.implant.candidates.applicator_channels`).
    planning : PlanningStructures
        Target and organ masks on the planning grid (:func:`reachplan.planner.dose.structures.planning_structures`).
    config : PlanConfig
        Stylet designs, schedule family, needle radius and depth; the steered arm screens every design.
    source : SourceData
        The TG-43 data set.
    air_kerma_u : float, U
        Source strength S_K.
    settings : ImplantSettings or None
        Candidate, selection and dwell settings (defaults when None).
    gtv : Structure or None
        The GTV mask on the planning grid (its D98 is then an aim).
    models : PlanModels or None
        The insertion models (the screening model builds the shape banks); :meth:`PlanModels.for_config` when None.
    aims : Aims or None
        The protocol's aims both arms are planned to; None: EMBRACE II.
    points : sequence of PointLimit
        Dose points with a planning aim and a hard limit (the ICRU recto-vaginal point:
        :func:`~reachplan.planner.implant.problem.point_limits`), held by both arms' selection and loading.
    threads : int
        Arms planned at once, each on its own thread (1: one after the other, the same result).

    Returns
    -------
    ImplantComparison
        The straight arm, the straight + steered arm (never worse: it takes in the straight arm's implants), every
        candidate channel and the wall time. Each arm's chosen implant is checked
        (:func:`~reachplan.planner.implant.needles.check_arm`): its steered needles re-solved with the reference
        model within ``config.tension_reserve``, every needle's robustness, the plan re-loaded on the re-solved paths;
        then each steered one's tissue band (:func:`~reachplan.planner.implant.tissue.with_tissue_bands`).
    """
    arms = plan_design_arms(scene, planning, config, source, air_kerma_u, settings, gtv, models, aims,
                            {"steered": config.designs}, threads, points)
    return ImplantComparison(arms.straight, arms.steered["steered"], arms.candidates, arms.seconds)


@dataclass(frozen=True, eq=False)
class DesignArms:
    """A straight arm and straight + steered arms of chosen stylet designs, on the same anatomy and template.

    Parameters
    ----------
    straight : ImplantArm
        The arm of straight needles (and the intracavitary channels), shared by every steered arm.
    steered : dict of str to ImplantArm
        Each steered arm by name: the straight candidates and those of its designs; each takes in the straight
        arm's implants (never worse).
    candidates : tuple of Channel
        Every candidate channel (paths mm, LPS): the straight ones, every design's steered ones, the intracavitary.
    seconds : float, s
        Wall time of the whole.
    cpu_s : dict of str to float
        CPU time of this process (all its threads), s, per stage: ``candidates`` (shape banks, candidates and their
        scenario paths), ``arms`` (every arm's Pareto curve), ``check`` (the chosen needles' check and re-load).
    """

    straight: ImplantArm
    steered: dict[str, ImplantArm]
    candidates: tuple[Channel, ...]
    seconds: float = 0.0
    cpu_s: dict[str, float] = field(default_factory=dict)


def plan_design_arms(
    scene: Scene,
    planning: PlanningStructures,
    config: PlanConfig,
    source: SourceData,
    air_kerma_u: float = DEFAULT_AIR_KERMA_U,
    settings: ImplantSettings | None = None,
    gtv: Structure | None = None,
    models: PlanModels | None = None,
    aims: Aims | None = None,
    steered: Mapping[str, Sequence[str]] | None = None,
    threads: int = 2,
    points: Sequence[PointLimit] = (),
    tissue_bands: bool = True,
) -> DesignArms:
    """Plan the straight arm once and a straight + steered arm per group of stylet designs (as :func:`plan_implants`).

    The candidates of every design are found once (a design's steered candidates do not depend on the others');
    each steered arm is offered the straight candidates, its designs' steered ones and the intracavitary channels.

    Parameters
    ----------
    scene : Scene
        Organs, template and pose, applicators (as :func:`plan_implants`).
    planning : PlanningStructures
        Target and organ masks on the planning grid.
    config : PlanConfig
        Schedule family, needle radius and depth, tension reserve; its ``designs`` are the default group.
    source : SourceData
        The TG-43 data set.
    air_kerma_u : float, U
        Source strength S_K.
    settings : ImplantSettings or None
        Candidate, selection and dwell settings (defaults when None).
    gtv : Structure or None
        The GTV mask on the planning grid.
    models : PlanModels or None
        The insertion models; :meth:`PlanModels.for_config` when None.
    aims : Aims or None
        The aims; None: EMBRACE II.
    steered : mapping of str to sequence of str, optional
        Arm name -> the stylet preset names it may use (none: the straight candidates alone, as with a
        configuration without designs); None: one arm ``"steered"`` of ``config.designs``.
    threads : int
        Arms planned at once, each on its own thread (1: one after the other, the same result).
    points : sequence of PointLimit
        Dose points with a planning aim and a hard limit, held by every arm (as :func:`plan_implants`).
    tissue_bands : bool
        Give the chosen steered needles their tissue band (reported, not planned on; False: none, e.g. for a
        study, which never reads them).

    Returns
    -------
    DesignArms
        The straight arm, the steered arms by name (each checked as in :func:`plan_implants`), the candidates, the
        wall time and the CPU time per stage.
    """
    t0, c0 = time.perf_counter(), time.process_time()
    groups = {k: tuple(v) for k, v in (steered or {"steered": config.designs}).items()}
    designs = tuple(dict.fromkeys(d for v in groups.values() for d in v))
    config_all = dataclasses.replace(config, designs=designs)
    settings = settings or ImplantSettings()
    models = models or PlanModels.for_config(config_all)
    intracavitary = applicator_channels(scene.applicators, planning, settings)
    holes = scene.template.needle_holes
    banks = [shape_bank(d, config.family, min(config.max_depth_mm, d.length_mm), models.screening,
                        config.tension_reserve) for d in config_all.rod_designs]
    cands = needle_candidates([h.hole_id for h in holes], np.array([h.xy_mm for h in holes]),
                              np.array([h.distance_mm for h in holes]), scene.patient_from_template, planning,
                              scene.organs, config.needle_radius_mm, settings, banks, config.max_depth_mm)
    cands = with_scenarios(cands, scene, config_all, models)  # where each steered needle may go (cheap: every one)
    kernel = Tg43Kernel(source)
    c1 = time.process_time()
    straight_cands = [c for c in cands if not c.steered]
    # the arms at once on ``threads`` cores; a steered arm's candidates include the straight ones, so the straight
    # arm's implants are its too: never worse
    planned = plan_arms([("straight", [*straight_cands, *intracavitary]),
                         *[("steered", [*straight_cands, *[c for c in cands if c.steered and c.design in group],
                                        *intracavitary]) for group in groups.values()]],
                        planning, kernel, air_kerma_u, aims=aims, settings=settings, gtv=gtv, workers=threads,
                        points=points)
    c2 = time.process_time()
    straight = planned[0]
    steered_arms = list(planned[1:])  # each with the straight arm's implants (plan_arms)
    for arm in steered_arms:  # fair arms: an implant of straight needles a steered arm's search found is the
        straight = with_straight_plans(straight, arm)  # straight arm's too
    # the chosen needles re-solved with the reference model, their robustness, the plans re-loaded on them
    cache: dict[int, Channel | str] = {}
    checked = check_arm(straight, scene, planning, config_all, kernel, air_kerma_u, settings, models=models,
                        aims=aims, gtv=gtv, cache=cache, points=points)
    arms = {name: check_arm(arm, scene, planning, config_all, kernel, air_kerma_u, settings, models=models,
                            aims=aims, gtv=gtv, extra_plans=straight.plans, cache=cache, points=points)
            for name, arm in zip(groups, steered_arms, strict=True)}
    # each chosen steered needle over the plan's range of tissue moduli (reported, not planned on)
    if tissue_bands:
        banded = with_tissue_bands((checked, *arms.values()), scene, config_all)
        checked, arms = banded[0], dict(zip(arms, banded[1:], strict=True))
    c3 = time.process_time()
    return DesignArms(checked, arms, (*cands, *intracavitary), time.perf_counter() - t0,
                      {"candidates": round(c1 - c0, 3), "arms": round(c2 - c1, 3), "check": round(c3 - c2, 3)})
