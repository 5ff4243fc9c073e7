"""The settings of a plan and the insertion models it uses (all lengths in mm)."""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from functools import cached_property

import numpy as np

from reachplan.planner.case.fidelity import POLICIES, SAFETY_MARGIN_MM
from reachplan.planner.lookup import rod_model, rod_model_capabilities
from reachplan.planner.ranking import RankWeights
from reachplan.planner.steering.calibration import RATIO_RANGE
from reachplan.planner.steering.factors import TIP_FOLLOWING_MIN_PA
from reachplan.planner.steering.insertion import SIMUGEL_MODULUS_PA
from reachplan.planner.steering.kinematic import KINEMATIC, KinematicInsertion
from reachplan.planner.steering.robustness import Perturbations
from reachplan.planner.steering.steered import ScheduleFamily
from reachplan.planner.steering.tissue_band import ModulusBand
from reachplan.planner.steering.tissue_rod import PLANNER_REFERENCE, TissueRodInsertion
from reachplan.rod_model.design import RodDesign, preset

#: Organs at risk (and bone) a needle must not touch, by normalised ROI name.
DEFAULT_OARS: tuple[str, ...] = ("Bladder", "Rectum", "Sigmoid", "Bowel", "Bone")


#: clearances up to the ranking's clearance cap + this (mm) are FCL's; beyond, the organ distance field's
#: estimate (within its error bound, about 4 mm) is reported, and the Pareto flags use it. Scores and the
#: ranking are unchanged (the score caps clearance); re-ranking with a larger cap uses the estimates.
SCREEN_BAND_MM = 1.0


#: 15-gauge plastic ISBT needle, outer diameter 1.83 mm (reference: oncoreach.md, ASSUMED dimensions).
NEEDLE_RADIUS_15GA_MM = 1.83 / 2

#: ASSUMED source strength for planning: a new Ir-192 HDR source of about 10 Ci, S_K ≈ 40 700 U.
DEFAULT_AIR_KERMA_U = 40_700.0


@dataclass(frozen=True)
class PlanConfig:
    """Settings of a plan (all lengths in mm).

    Parameters
    ----------
    template : str, entry-point name
        Name of the needle template (a plugin, :func:`reachplan.planner.lookup.load_template`).
    needle_radius_mm : float, mm
        Outer radius of the needle, for the collision checks.
    reach_tolerance_mm : float, mm
        A candidate reaches its target when its tip is within this distance of the target point.
    max_depth_mm : float, mm
        Free length of the needle beyond the template (reference: about 200 mm).
    oar_names : tuple of str
        Organs at risk (normalised ROI names) a needle must not touch.
    obturator_depth_mm : float, mm
        How far the obturator tip lies beyond the template plane, used to place the template from an ``Obturator``
        ROI when no pose is given.
    designs : tuple of str
        Stylet presets to steer with (empty: straight needles only; the pilot study used 15ga-30j-tip).
    family : ScheduleFamily
        The tension schedules screened per design.
    alternatives : int
        Reaching schedules tried per hole before a steered candidate is declared colliding.
    refine_top : int
        Feasible steered candidates per target re-solved with the reference insertion model (the two-tube
        Cosserat rod inserted in tissue, :mod:`~reachplan.planner.steering.tissue_rod`); the others keep the
        screening model's numbers, and every candidate names its model.
    weights : RankWeights
        Weights of the ranking's score.
    robust_top : int
        Feasible straight and steered candidates per target assessed under ``perturbations``; the ranking prefers
        robust ones among them.
    perturbations : Perturbations
        Tension, roll and entry-angle errors of the robustness check.
    tissue_moduli_pa : tuple of (str, float), Pa
        Young's modulus per organ (normalised ROI name), e.g. ``(("Uterus", 0.5e6),)`` (``--organ-modulus``);
        tissue outside the named organs has ``tissue_modulus_pa``. The organ holding a target sets the
        screening and robustness models' curvature factor
        (:func:`~reachplan.planner.steering.factors.curvature_factor`); the reference model takes the modulus
        along the path. Each at least :data:`~reachplan.planner.steering.factors.TIP_FOLLOWING_MIN_PA`.
    tissue_modulus_pa : float, Pa
        Young's modulus of the tissue outside the organs of ``tissue_moduli_pa`` (``--tissue-modulus``); default
        the phantom gel's 0.19 MPa (SimuGel #3, reference ``oncoreach.md``: the reference's only tissue modulus).
        At least :data:`~reachplan.planner.steering.factors.TIP_FOLLOWING_MIN_PA` (the screening model's range).
    modulus_band : ModulusBand
        The range of moduli each shown steered needle is re-inserted over (``--modulus-band``; default the plan's
        moduli x/÷ 3, ASSUMED: :mod:`~reachplan.planner.steering.tissue_band`); its worst reach and clearance are
        reported beside the needle.
    screen_tolerance_mm : float, mm
        The screening uses the cheapest rod model (by batched throughput) whose measured free-space tip error (the
        rod-model benchmark's table) is within it; ``planar_beam`` at 0.5 mm.
    applicators : tuple of (str, str)
        (ROI name, applicator kind) pairs from ``--applicator KIND=ROI``; they override the recognition of
        applicator ROIs by name (:func:`reachplan.plugins.applicators.applicators_from_structures`).
    tension_reserve : float
        Fraction of each stylet's tension limit that no planned schedule uses (``--tension-reserve``), in [0, 1):
        the screened schedules' plateaus, the reference re-solve's re-aim and every implant needle stay at or
        below ``(1 - tension_reserve) × max_tension_n`` (:func:`~reachplan.planner.steering.steered.usable_tension_n`),
        leaving room for the hand's tension error (the robustness check's ± 10 %).
    models : str
        Which insertion model each feasible steered candidate is solved with (``--models``): ``"scene"`` (default)
        the cheapest whose measured in-tissue error fits the candidate's margins, and the reference for those
        near the ranking's decision; ``"reference"`` the reference for every one
        (:mod:`~reachplan.planner.case.fidelity`). ``refine_top`` 0 re-solves none.
    safety_margin_mm : float, mm
        Clearance a candidate keeps beyond its model's in-tissue error (the scene policy's tolerance).
    curvature_scale : tuple of (str, float)
        A site's calibration (``--calibration``, :mod:`~reachplan.planner.steering.calibration`): per design name,
        the ratio of the in-tissue curvature its found needles showed to the model's. Every insertion model of the
        plan applies it (the kinematic model to its curvature factor, the in-tissue rod to its path's departure
        from the hole's axis). Empty: none.
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
    applicators: tuple[tuple[str, str], ...] = ()
    tension_reserve: float = 0.10
    tissue_modulus_pa: float = SIMUGEL_MODULUS_PA
    modulus_band: ModulusBand = field(default_factory=ModulusBand)
    models: str = "scene"
    safety_margin_mm: float = SAFETY_MARGIN_MM
    curvature_scale: tuple[tuple[str, float], ...] = ()

    def __post_init__(self) -> None:
        for name in ("needle_radius_mm", "reach_tolerance_mm", "max_depth_mm", "obturator_depth_mm"):
            v = getattr(self, name)
            if not (np.isfinite(v) and v > 0):
                raise ValueError(f"{name} must be a positive number of mm, got {v}")
        if not (np.isfinite(self.tension_reserve) and 0.0 <= self.tension_reserve < 1.0):
            raise ValueError(f"tension_reserve must be a fraction in [0, 1) of the stylet's limit, "
                             f"got {self.tension_reserve}")
        for name, value in (("the tissue", self.tissue_modulus_pa), *self.tissue_moduli_pa):
            if not (np.isfinite(value) and value >= TIP_FOLLOWING_MIN_PA):
                raise ValueError(f"the Young's modulus of {name} must be at least {TIP_FOLLOWING_MIN_PA / 1e6:g} MPa "
                                 f"(the screening model's range), got {value / 1e6:g} MPa")
        if self.models not in POLICIES:
            raise ValueError(f"models must be one of {', '.join(POLICIES)}, got {self.models!r}")
        if not (np.isfinite(self.safety_margin_mm) and self.safety_margin_mm >= 0):
            raise ValueError(f"safety_margin_mm must be a number of mm >= 0, got {self.safety_margin_mm}")
        lo, hi = RATIO_RANGE
        for design, ratio in self.curvature_scale:
            if not (np.isfinite(ratio) and lo <= ratio <= hi):
                raise ValueError(f"the curvature calibration of {design} must be a ratio in [{lo:g}, {hi:g}], got "
                                 f"{ratio}")

    @cached_property
    def rod_designs(self) -> tuple[RodDesign, ...]:
        """The stylet designs of ``designs``, resolved once from their preset names.

        The candidates carry these objects.

        Returns
        -------
        tuple of RodDesign
            One per name of ``designs``, in that order.

        Raises
        ------
        UnknownPresetError
            A name is not a preset.
        """
        return tuple(preset(name) for name in self.designs)


@dataclass(frozen=True)
class PlanModels:
    """The insertion models a plan uses, resolved once per plan.

    :meth:`for_config` looks the screening rod model up by name (:mod:`reachplan.planner.lookup`).

    Parameters
    ----------
    screening : KinematicInsertion
        Screens every schedule of the family.
    reference : TissueRodInsertion
        Re-solves the shortlist (``PlanConfig.refine_top``).
    robustness : KinematicInsertion
        Re-evaluates the shortlist under the perturbations.
    """

    screening: KinematicInsertion = KINEMATIC
    reference: TissueRodInsertion = PLANNER_REFERENCE
    robustness: KinematicInsertion = KINEMATIC

    @classmethod
    def for_config(cls, config: PlanConfig) -> PlanModels:
        """Return the default models, with the screening model of ``config`` (:func:`screening_model`).

        Every model's tissue modulus is ``config.tissue_modulus_pa`` (the organs of ``config.tissue_moduli_pa`` set
        theirs per target and along each path), and its site calibration ``config.curvature_scale``.

        Parameters
        ----------
        config : PlanConfig
            Its ``screen_tolerance_mm`` picks the screening rod model; ``tissue_modulus_pa`` (Pa).

        Returns
        -------
        PlanModels
            The reference and robustness defaults, and that screening model, in the plan's tissue.
        """
        e, scale = config.tissue_modulus_pa, config.curvature_scale
        return cls(screening=replace(screening_model(config), tissue_modulus_pa=e, curvature_scale=scale),
                   reference=replace(PLANNER_REFERENCE, tissue_modulus_pa=e, curvature_scale=scale),
                   robustness=replace(KINEMATIC, tissue_modulus_pa=e, curvature_scale=scale))


def screening_model(config: PlanConfig) -> KinematicInsertion:
    """Return the kinematic insertion model on the cheapest rod model within ``config.screen_tolerance_mm``.

    The rod model is looked up in the plugin registry.

    Parameters
    ----------
    config : PlanConfig
        The plan's settings (``screen_tolerance_mm``, mm).

    Returns
    -------
    KinematicInsertion
        The kinematic insertion on the selected rod model.
    """
    from reachplan.rod_model.select import Scene as RodScene
    from reachplan.rod_model.select import select_model

    name = select_model(config.screen_tolerance_mm, RodScene(), rod_model_capabilities(), batched=True)
    return KinematicInsertion(rod_model=rod_model(name))
