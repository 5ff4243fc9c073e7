"""Constant-curvature model, and the closed-form geometry of piecewise circular arcs.

The arc geometry is shared with :mod:`reachplan.rod_model.beam`.

Constant curvature (the classic continuum-robot assumption, Webster & Jones, IJRR 2010): only the actuated
joint section bends, with the curvature of a beam under the tendon's moment ``λ·r_disk / (EI_joints + EI_needle)``;
the tube sections stay straight. It ignores the bending of the nitinol tube by the tendon running through it,
which on this device carries most of the tip deflection: the benchmark measures how much that costs.
"""

from __future__ import annotations

import itertools
import time
from abc import ABC, abstractmethod
from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from reachplan.rod_model.design import Loads, RodDesign
from reachplan.rod_model.protocol import Capabilities, check_loads
from reachplan.rod_model.result import RodBatch, RodPath

#: Output spacing of the sampled centreline, mm.
DEFAULT_STEP_MM = 1.0


def sample_s_mm(design: RodDesign, step_mm: float = DEFAULT_STEP_MM) -> np.ndarray:
    """Sample arc lengths at about ``step_mm`` spacing, every section boundary included.

    Returns
    -------
    (n,) float, mm
        Increasing, from 0 (the base) to the design's length.
    """
    bounds = section_bounds_mm(design)
    parts = [np.linspace(a, b, max(1, int(np.ceil((b - a) / step_mm))) + 1)[:-1]
             for a, b in itertools.pairwise(bounds)]
    return np.concatenate([*parts, bounds[-1:]])


def section_bounds_mm(design: RodDesign) -> np.ndarray:
    """Return the boundaries of the design's sections as (k + 1,) float arc lengths from the base, mm."""
    secs = design.sections()
    return np.array([secs[0].start_m * 1e3] + [s.end_m * 1e3 for s in secs])


def joint_section_index(design: RodDesign) -> int:
    """Return the index of the joint section in :meth:`RodDesign.sections`."""
    return next(i for i, s in enumerate(design.sections()) if s.kind == "joints")


def tendon_moment_direction(design: RodDesign, loads: Loads) -> tuple[np.ndarray, float]:
    """Find the in-plane direction toward which the tendons bend the rod, and the tension-weighted sum.

    Returns
    -------
    direction : (3,) float, unit, needle frame
        In the x-y plane; ``+x`` for tendon 0 at roll 0 (tendon 0's direction when no tendon is pulled).
    magnitude_n : float, N
        Length of ``Σ λ_j e_j``; multiplied by a section's arm it is the bending moment.
    """
    e = design.tendon_unit_offsets(loads.roll_deg)
    v = np.asarray(loads.tensions_n) @ e
    mag = float(np.hypot(v[0], v[1]))
    if mag == 0.0:
        return e[0], 0.0
    return v / mag, mag


def arc_path(bounds_mm: np.ndarray, curvature_per_m: np.ndarray, s_mm: np.ndarray,
             direction: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Compute the exact centreline and frames of a rod made of circular arcs (closed form).

    Parameters
    ----------
    bounds_mm : (k + 1,) float, mm
        Section boundaries, arc length from the base.
    curvature_per_m : (..., k) float, 1/m
        Curvature of each section, bending toward ``direction``.
    s_mm : (n,) float, mm
        Arc lengths where to evaluate.
    direction : (3,) float, unit, needle frame
        The bending direction, in the x-y plane.

    Returns
    -------
    positions_mm : (..., n, 3) float, mm, needle frame
        Base at the origin, unbent axis ``+z``.
    frames : (..., n, 3, 3) float, needle frame
        Columns ``d1, d2, d3`` (``d3`` the tangent); identity at the base.
    """
    kap = np.asarray(curvature_per_m, dtype=float)[..., None, :] * 1e-3  # 1/mm, (..., 1, k)
    lengths = np.diff(bounds_mm)
    seg = np.clip(s_mm[:, None] - bounds_mm[None, :-1], 0.0, lengths[None, :])  # (n, k) arc length in section
    psi_prev = np.cumsum(kap * lengths, axis=-1) - kap * lengths  # (..., 1, k) angle at section start
    half = 0.5 * kap * seg
    chord = seg * np.sinc(half / np.pi)
    lat = np.sum(chord * np.sin(psi_prev + half), axis=-1)  # (..., n)
    ax = np.sum(chord * np.cos(psi_prev + half), axis=-1)
    psi = np.sum(kap * seg, axis=-1)
    pos = lat[..., None] * direction + ax[..., None] * np.array([0.0, 0.0, 1.0])
    return pos, bend_frames(direction, psi)


def bend_frames(direction: np.ndarray, psi: np.ndarray) -> np.ndarray:
    """Rotate the base frame by ``psi`` about ``z × direction`` (bends ``+z`` toward ``direction``): Rodrigues.

    Parameters
    ----------
    direction : (3,) float, unit, needle frame
        The bending direction, in the x-y plane.
    psi : (...) float, rad
        Angle of the tangent from ``+z`` toward ``direction``.

    Returns
    -------
    (..., 3, 3) float, needle frame
        Columns ``d1, d2, d3`` (``d3`` the tangent); identity where ``psi`` is 0.
    """
    a = np.array([-direction[1], direction[0], 0.0])  # z x direction
    k = np.array([[0.0, -a[2], a[1]], [a[2], 0.0, -a[0]], [-a[1], a[0], 0.0]])
    sp, cp = np.sin(psi)[..., None, None], np.cos(psi)[..., None, None]
    return np.eye(3) + sp * k + (1.0 - cp) * (k @ k)


def _arc_solution(model: str, design: RodDesign, loads: Loads, curv: np.ndarray, t0: float,
                  step_mm: float) -> RodPath:
    s = sample_s_mm(design, step_mm)
    d, _ = tendon_moment_direction(design, loads)
    pos, frames = arc_path(section_bounds_mm(design), curv, s, d)
    return RodPath(model, s, pos, frames, 0.0, (time.perf_counter() - t0) * 1e3, 0, loads.tensions_n,
                   loads.roll_deg)


def _arc_batch(model: str, design: RodDesign, tensions_n: np.ndarray, roll_deg: float,
               curv: np.ndarray) -> RodBatch:
    bounds = section_bounds_mm(design)
    d = design.tendon_unit_offsets(roll_deg)[0]
    pos, _ = arc_path(bounds, curv, bounds[-1:], d)
    b = len(tensions_n)
    return RodBatch(model, tensions_n, roll_deg, pos[:, 0], bounds, curv, joint_section_index(design),
                    np.ones(b, bool), np.zeros(b))


def _tensions(tensions_n: np.ndarray) -> np.ndarray:
    t = np.asarray(tensions_n, dtype=float).ravel()
    if not np.all(np.isfinite(t)) or np.any(t < 0):
        raise ValueError("tensions_n must be finite and non-negative")
    return t


@dataclass(frozen=True)
class ArcModel(ABC):
    """Closed-form models whose every section is a circular arc; subclasses give the section curvatures.

    Parameters
    ----------
    step_mm : float
        Spacing of the returned centreline samples, mm.
    """

    step_mm: float = DEFAULT_STEP_MM
    name: ClassVar[str] = ""
    capabilities: ClassVar[Capabilities] = Capabilities(planar_only=True, twist=False, several_tendons=True,
                                                        external_load=False, large_deflection=True)

    @abstractmethod
    def curvatures(self, design: RodDesign, moment_factor_n: np.ndarray) -> np.ndarray:
        """Return the curvature of each section for a tension-weighted sum ``|Σλ_j e_j|``.

        Parameters
        ----------
        design : RodDesign
            Its sections' stiffnesses and moment arms.
        moment_factor_n : (b,) float, N
            ``|Σλ_j e_j|`` of each solve (see :func:`tendon_moment_direction`).

        Returns
        -------
        (b, k) float, 1/m
        """

    def solve(self, design: RodDesign, loads: Loads) -> RodPath:
        """Solve in closed form (see :meth:`RodModel.solve`); never fails, zero residual.

        Raises
        ------
        UnsupportedLoadError
            External loads, or not one tension per tendon.
        """
        t0 = time.perf_counter()
        check_loads(self.name, self.capabilities, design, loads)
        _, mag = tendon_moment_direction(design, loads)
        return _arc_solution(self.name, design, loads, self.curvatures(design, np.array([mag]))[0], t0, self.step_mm)

    def solve_batch(self, design: RodDesign, tensions_n: np.ndarray, roll_deg: float = 0.0) -> RodBatch:
        """Solve free-space pulls of tendon 0 with each of ``tensions_n`` (b,), N, in closed form.

        Raises
        ------
        ValueError
            A negative or non-finite tension.
        """
        t = _tensions(tensions_n)
        return _arc_batch(self.name, design, t, roll_deg, self.curvatures(design, t))


@dataclass(frozen=True)
class ConstantCurvature(ArcModel):
    """Only the joint section bends, as one circular arc; closed form."""

    name: ClassVar[str] = "constant_curvature"

    def curvatures(self, design: RodDesign, moment_factor_n: np.ndarray) -> np.ndarray:
        """Return ``λ·r_disk / (EI_joints + EI_needle)`` in the joints, 0 elsewhere: (b, k) 1/m for (b,) N."""
        secs = design.sections()
        c = np.array([s.arm_m / (s.ei1 + s.ei2) if s.kind == "joints" else 0.0 for s in secs])
        return np.asarray(moment_factor_n, dtype=float)[:, None] * c[None, :]


CONSTANT_CURVATURE = ConstantCurvature()
