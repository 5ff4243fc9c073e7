"""Planar beam with piecewise stiffness: closed form.

In free space a tendon that ends at the tip leaves no net force or moment on any cross-section of rod plus
tendon (Rucker & Webster, IEEE T-RO 27(6), 2011): the rod carries the tendon's compression ``λ`` and the bending
moment ``λ·r(s)``, with ``r`` the tendon's moment arm (disk arm in the joint section, tube arm in the tube).
An inextensible, unshearable Euler–Bernoulli beam therefore bends with the piecewise-constant curvature
``κ(s) = λ·r(s) / (EI_stylet(s) + EI_needle)`` into a chain of circular arcs, integrated exactly
(:func:`reachplan.rod_model.kinematic.arc_path`). What it leaves out, against the Cosserat models: the axial
compression and shear of the rods and the tendon's small tilt against the centreline.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from reachplan.rod_model.design import RodDesign
from reachplan.rod_model.kinematic import ArcModel


@dataclass(frozen=True)
class PlanarBeam(ArcModel):
    """Piecewise circular arcs with ``κ = λ·r / EI`` per section; closed form, free space only."""

    name: ClassVar[str] = "planar_beam"

    def curvatures(self, design: RodDesign, moment_factor_n: np.ndarray) -> np.ndarray:
        """Return ``κ = λ·r / (EI_stylet + EI_needle)`` of every section, (b, k) 1/m, for ``moment_factor_n`` (b,) N."""
        c = np.array([s.arm_m / (s.ei1 + s.ei2) for s in design.sections()])
        return np.asarray(moment_factor_n, dtype=float)[:, None] * c[None, :]


PLANAR_BEAM = PlanarBeam()
