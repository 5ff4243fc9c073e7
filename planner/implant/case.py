"""Both implant arms of a case, straight only and straight + steered, on the same anatomy and template.

The candidates for the scene's target volume (every template hole, straight and with every stylet design of the
plan) and the case's loadable applicator channels; each arm's Pareto curve and chosen implant
(:func:`reachplan.planner.implant.plan.plan_arms`).
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from reachplan.planner.case.config import DEFAULT_AIR_KERMA_U, PlanConfig, PlanModels
from reachplan.planner.case.scene import Scene
from reachplan.planner.dose.aims import Aims
from reachplan.planner.dose.structures import PlanningStructures, Structure
from reachplan.planner.dose.tg43 import Tg43Kernel
from reachplan.planner.implant.arms import ImplantArm, with_straight_plans, with_subset
from reachplan.planner.implant.candidates import Channel, applicator_channels, needle_candidates
from reachplan.planner.implant.needles import check_arm, with_scenarios
from reachplan.planner.implant.plan import plan_arms
from reachplan.planner.implant.settings import ImplantSettings
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

    Returns
    -------
    ImplantComparison
        The straight arm, the straight + steered arm (never worse: it takes in the straight arm's implants), every
        candidate channel and the wall time. Each arm's chosen implant is checked
        (:func:`~reachplan.planner.implant.needles.check_arm`): its steered needles re-solved with the reference
        model within ``config.tension_reserve``, every needle's robustness, the plan re-loaded on the re-solved paths.
    """
    t0 = time.perf_counter()
    settings = settings or ImplantSettings()
    models = models or PlanModels.for_config(config)
    intracavitary = applicator_channels(scene.applicators, planning, settings)
    holes = scene.template.needle_holes
    banks = [shape_bank(d, config.family, min(config.max_depth_mm, d.length_mm), models.screening,
                        config.tension_reserve) for d in config.rod_designs]
    cands = needle_candidates([h.hole_id for h in holes], np.array([h.xy_mm for h in holes]),
                              np.array([h.distance_mm for h in holes]), scene.patient_from_template, planning,
                              scene.organs, config.needle_radius_mm, settings, banks, config.max_depth_mm)
    cands = with_scenarios(cands, scene, config, models)  # where each steered needle may go (cheap: every one)
    kernel = Tg43Kernel(source)
    # the two arms at once, on two cores; the steered arm's candidates include the straight ones, so the straight
    # arm's implants are its too: never worse
    straight, steered = plan_arms([("straight", [*[c for c in cands if not c.steered], *intracavitary]),
                                   ("steered", [*cands, *intracavitary])], planning, kernel, air_kerma_u,
                                  aims=aims, settings=settings, gtv=gtv)
    steered = with_subset(steered, straight)
    # fair arms: an implant of straight needles the steered arm's search found is the straight arm's too
    straight = with_straight_plans(straight, steered)
    # the chosen needles re-solved with the reference model, their robustness, the plans re-loaded on them
    cache: dict[int, Channel | str] = {}
    checked_straight = check_arm(straight, scene, planning, config, kernel, air_kerma_u, settings, models=models,
                                 gtv=gtv, cache=cache)
    steered = check_arm(steered, scene, planning, config, kernel, air_kerma_u, settings, models=models, gtv=gtv,
                        extra_plans=straight.plans, cache=cache)
    straight = checked_straight
    return ImplantComparison(straight, steered, (*cands, *intracavitary), time.perf_counter() - t0)
