"""The tissue band of each implant's steered needles: the path over the plan's range of tissue moduli.

After the needle check (:func:`~reachplan.planner.implant.needles.check_arm`) every steered needle of each arm's
chosen implant lies on its reference re-solved path, with its dwells on it. Each is re-inserted with its schedule in
tissue of the plan's moduli scaled over ``PlanConfig.modulus_band``
(:func:`~reachplan.planner.steering.tissue_band.assess_band`); its reach is measured from that path's own tip (where
the plan puts the dwells), its clearance against the organs at risk. The band is reported, not planned on: the
dwells and the selection are unchanged.
"""

from __future__ import annotations

import dataclasses

from reachplan.planner.case.config import PlanConfig
from reachplan.planner.case.scene import Scene
from reachplan.planner.case.search import modulus_profile
from reachplan.planner.errors import PlanInputError
from reachplan.planner.implant.arms import ImplantArm
from reachplan.planner.implant.candidates import Channel
from reachplan.planner.steering.candidates import Target, TissueBand, score_path
from reachplan.planner.steering.tissue_band import BAND_MODEL, assess_band, uniform_profile
from reachplan.rod_model.errors import RodModelError


def channel_band(channel: Channel, scene: Scene, config: PlanConfig) -> TissueBand:
    """Return a steered implant needle's tissue band (module docstring).

    Parameters
    ----------
    channel : Channel
        A steered needle with its design and schedule (path mm, LPS, hole to tip).
    scene : Scene
        Organs at risk (meshes, LPS mm), template pose and the meshes the moduli name.
    config : PlanConfig
        ``modulus_band``, ``tissue_modulus_pa``, ``tissue_moduli_pa``, the designs and the reach tolerance.

    Returns
    -------
    TissueBand
        The band (paths mm LPS, reach from the needle's tip, clearances), or one saying why it was not computed.
    """
    band = config.modulus_band
    design = next((d for d in config.rod_designs if d.name == channel.design), None)
    if design is None or channel.schedule is None:
        return TissueBand.failed(f"{channel.name} has no stylet design of the plan or no schedule", band.source)
    tip = channel.path_mm[-1]
    aim = Target(f"{channel.name} tip", (float(tip[0]), float(tip[1]), float(tip[2])))
    radius = design.needle.outer_diameter_mm / 2
    nominal = score_path(aim, channel.name, channel.hole_distance_mm, channel.path_mm, scene.organs, radius,
                         config.reach_tolerance_mm, BAND_MODEL.info, steered=True, design=design,
                         schedule=channel.schedule, depth_mm=channel.tissue_length_mm)
    profile = (modulus_profile(scene, channel.path_mm, config.tissue_moduli_pa, config.tissue_modulus_pa)
               or uniform_profile(config.tissue_modulus_pa))
    try:
        return assess_band(nominal, aim, scene.organs, scene.patient_from_template, radius, profile, band,
                           config.reach_tolerance_mm)
    except (PlanInputError, RodModelError) as exc:
        return TissueBand.failed(str(exc), band.source)


def with_tissue_bands(arms: tuple[ImplantArm, ...], scene: Scene, config: PlanConfig) -> tuple[ImplantArm, ...]:
    """Return the arms, each chosen implant's steered needles carrying their tissue band.

    A needle shared by both arms is re-inserted once.

    Parameters
    ----------
    arms : tuple of ImplantArm
        The checked arms (:func:`~reachplan.planner.implant.needles.check_arm`).
    scene : Scene
        Organs, template pose, meshes.
    config : PlanConfig
        The band and the moduli (``modulus_band.enabled`` False: the arms unchanged).

    Returns
    -------
    tuple of ImplantArm
        In the same order; plans without a steered needle unchanged.
    """
    if not config.modulus_band.enabled:
        return arms
    done: dict[int, Channel] = {}

    def banded(c: Channel) -> Channel:
        if id(c) not in done:
            done[id(c)] = dataclasses.replace(c, tissue_band=channel_band(c, scene, config))
        return done[id(c)]

    out = []
    for arm in arms:
        plan = arm.plan
        if plan is None or not any(c.steered for c in plan.channels):
            out.append(arm)
            continue
        channels = tuple(banded(c) if c.steered else c for c in plan.channels)
        out.append(dataclasses.replace(arm, plan=dataclasses.replace(plan, channels=channels)))
    return tuple(out)
