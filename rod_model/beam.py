"""Planar beam with piecewise stiffness: closed form.

In free space a tendon that ends at the tip leaves no net force or moment on any cross-section of rod plus
tendon (Rucker & Webster, IEEE T-RO 27(6), 2011): the rod carries the tendon's compression ``λ`` and the bending
moment ``λ·r(s)``, with ``r`` the tendon's moment arm (disk arm in the joint section, tube arm in the tube).
An inextensible, unshearable Euler–Bernoulli beam therefore bends with the piecewise-constant curvature
``κ(s) = λ·r(s) / (EI_stylet(s) + EI_needle)`` into a chain of circular arcs, integrated exactly
(:func:`rod_model.kinematic.arc_path`). What it leaves out, against the Cosserat models: the axial
compression and shear of the rods and the tendon's small tilt against the centreline.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from rod_model.design import Loads, RodDesign
from rod_model.kinematic import DEFAULT_STEP_MM, _arc_batch, _arc_solution, _tensions, tendon_moment_direction
from rod_model.protocol import Capabilities, check_loads
from rod_model.result import RodBatch, RodPath


@dataclass(frozen=True)
class PlanarBeam:
    """Piecewise circular arcs with ``κ = λ·r / EI`` per section; closed form, free space only.

    Parameters
    ----------
    step_mm : float
        Spacing of the returned centreline samples, mm.
    """

    step_mm: float = DEFAULT_STEP_MM
    name: ClassVar[str] = "planar_beam"
    capabilities: ClassVar[Capabilities] = Capabilities(planar_only=True, twist=False, several_tendons=True,
                                                        external_load=False, large_deflection=True)

    def curvatures(self, design: RodDesign, moment_factor_n: np.ndarray) -> np.ndarray:
        """(b, k) float, 1/m: curvature of each section for ``|Σλ_j e_j|`` = ``moment_factor_n`` (b,), N."""
        c = np.array([s.arm_m / (s.ei1 + s.ei2) for s in design.sections()])
        return np.asarray(moment_factor_n, dtype=float)[:, None] * c[None, :]

    def solve(self, design: RodDesign, loads: Loads) -> RodPath:
        t0 = time.perf_counter()
        check_loads(self.name, self.capabilities, design, loads)
        _, mag = tendon_moment_direction(design, loads)
        return _arc_solution(self.name, design, loads, self.curvatures(design, np.array([mag]))[0], t0, self.step_mm)

    def solve_batch(self, design: RodDesign, tensions_n: np.ndarray, roll_deg: float = 0.0) -> RodBatch:
        t = _tensions(tensions_n)
        return _arc_batch(self.name, design, t, roll_deg, self.curvatures(design, t))


PLANAR_BEAM = PlanarBeam()
