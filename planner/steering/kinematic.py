"""The kinematic insertion model: tip following at the design's curvature factor in the tissue.

The tip advances along its tangent, which turns toward the bending direction (set by the roll) at the free-space
curvature of the stylet's distal (joint) section under the current tension, from a rod model, times the design's
curvature factor at the tissue's modulus (:func:`reachplan.planner.steering.factors.curvature_factor`, fitted per
design to the in-tissue Cosserat insertion of :mod:`reachplan.planner.steering.tissue_rod`). Cheap and vectorised
over many schedules at once (the kernel: :func:`reachplan.planner.steering.insertion.tip_following_paths`).
Template frame (entry at the origin, ``+z`` the insertion direction, roll 0 bends toward template ``+x``),
millimetres. Registered as the ``kinematic`` insertion model (:data:`KINEMATIC`).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from reachplan.planner.errors import PlanInputError
from reachplan.planner.steering.factors import check_tip_following, curvature_factor
from reachplan.planner.steering.insertion import (
    SIMUGEL_MODULUS_PA,
    FailedInsertion,
    InsertionPath,
    NamedInsertion,
    tip_following_paths,
)
from reachplan.planner.steering.schedule import TensionSchedule
from reachplan.rod_model.beam import PLANAR_BEAM
from reachplan.rod_model.design import RodDesign
from reachplan.rod_model.protocol import RodModel


@dataclass(frozen=True)
class KinematicInsertion(NamedInsertion):
    """Tip-following insertion (see the module docstring), vectorised over schedules.

    Tip following cannot fail: every schedule gives a path.

    Parameters
    ----------
    tissue_modulus_pa : float, Pa
        Young's modulus of the tissue the needle steers in (default the phantom's SimuGel, 0.19 MPa); with the
        design it sets the curvature factor by
        :func:`~reachplan.planner.steering.factors.curvature_factor` (the per-organ modulus in a plan).
    tissue_factor : float or None
        Path curvature over the joint section's free-space curvature; None (default): ``curvature_factor(
        tissue_modulus_pa, design)``, fitted per design to the in-tissue Cosserat insertion. A number overrides
        it for every design.
    rod_model : RodModel
        Rod model that gives the curvature table (default :data:`~reachplan.rod_model.beam.PLANAR_BEAM`,
        exact to 0.1 % of the two-tube model for free-space curvature; see the rod-model benchmark).
    step_mm : float
        Integration step along the insertion.
    curvature_scale : tuple of (str, float)
        A site's calibration (:mod:`reachplan.planner.steering.calibration`): per design name, the ratio of the
        curvature factor its needles showed to the model's; the factor in use is multiplied by it.

    Raises
    ------
    PlanInputError
        A modulus below :data:`~reachplan.planner.steering.factors.TIP_FOLLOWING_MIN_PA` without an explicit
        ``tissue_factor`` (the tissue does not hold the needle on its track there: tip following does not describe
        it), or a negative factor.
    """

    label: ClassVar[str] = "kinematic"
    tissue_modulus_pa: float = SIMUGEL_MODULUS_PA
    tissue_factor: float | None = None
    rod_model: RodModel = PLANAR_BEAM
    step_mm: float = 1.0
    curvature_scale: tuple[tuple[str, float], ...] = ()

    def __post_init__(self) -> None:
        if self.tissue_factor is None:
            check_tip_following(self.tissue_modulus_pa)
        elif not (np.isfinite(self.tissue_factor) and self.tissue_factor >= 0):
            raise PlanInputError(f"tissue_factor must be a finite number >= 0, got {self.tissue_factor}")

    def factor_for(self, design: RodDesign) -> float:
        """Return the curvature factor in use for ``design``: ``tissue_factor``, or the design's fitted one.

        The fitted one is :func:`curvature_factor` at ``tissue_modulus_pa``; either is multiplied by the design's
        ``curvature_scale``.

        Parameters
        ----------
        design : RodDesign
            The stylet in its needle.

        Returns
        -------
        float
            The factor (dimensionless) the free-space curvature is multiplied by.
        """
        base = curvature_factor(self.tissue_modulus_pa, design) if self.tissue_factor is None else self.tissue_factor
        return base * self.scale_for(design)

    def insert(self, design: RodDesign, schedules: Sequence[TensionSchedule],
               depth_mm: float) -> list[InsertionPath | FailedInsertion]:
        """Insert ``design`` to ``depth_mm`` once per schedule by tip following.

        Parameters
        ----------
        design : RodDesign
            The stylet in its needle; its curvature factor is :meth:`factor_for` of it.
        schedules : sequence of TensionSchedule
            Tension (N) and roll (degrees) against depth (mm).
        depth_mm : float, mm
            Inserted arc length.

        Returns
        -------
        list of InsertionPath or FailedInsertion
            One path per schedule (positions mm, template frame); tip following does not fail.
        """
        paths = self.insert_array(design, schedules, depth_mm)
        return [InsertionPath(p, depth_mm, self.info) for p in paths]

    def insert_array(self, design: RodDesign, schedules: Sequence[TensionSchedule], depth_mm: float) -> np.ndarray:
        """Return all paths at once.

        :func:`~reachplan.planner.steering.insertion.tip_following_paths` at :meth:`factor_for` ``design``.

        Parameters
        ----------
        design : RodDesign
            The stylet in its needle.
        schedules : sequence of TensionSchedule
            S schedules, tension (N) and roll (degrees) against depth (mm).
        depth_mm : float, mm
            Inserted arc length, in ``n`` steps of ``step_mm``.

        Returns
        -------
        (S, n + 1, 3) float, mm, template frame
            Row 0 of each path at the template (origin), the last the tip.
        """
        return tip_following_paths(design, schedules, depth_mm, self.factor_for(design), self.rod_model, self.step_mm)


KINEMATIC = KinematicInsertion()
