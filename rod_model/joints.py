"""Discrete model of the articulated joint section: each ball joint a rotational spring with Coulomb friction.

The continuum models (:mod:`~reachplan.rod_model.cosserat`, :mod:`~reachplan.rod_model.beam`) smear the joint
section into a rod of uniform stiffness. The stylet is in fact a stack of routing disks with a 0.8 mm steel ball
between each pair (Kheradmand, Yamamoto et al., OncoReach stylet paper; the project's ``reference/oncoreach.md``):
it bends only at the balls. This model (``discrete_joints``) represents that directly, as a planar chain of rigid
links (pseudo-rigid-body model, Howell, *Compliant Mechanisms*, 2001) clamped at the template:

* **Joints at their real spacing.** The section of ``n_joints`` joints (pitch ``joint_pitch_mm``, 1.65 mm: a
  20-joint section is about 33 mm, published) has one hinge per ball, at ``(i + 1/2)`` pitches from its proximal
  end. Each is a rotational spring ``k = K_bt,joints × joint_stiffness_scale / pitch`` (the measured section
  stiffness, 0.0008 N·m² on 15 ga, shared over the joints, scaled by the calibrated
  :class:`~reachplan.rod_model.design.Calibration`) in parallel with the plastic needle around it, which bends
  over the same pitch (``EI_needle / pitch``).
* **Tendon routing through the disks.** The tendon leaves the channel of one disk at offset ``r`` (the design's
  ``disk_arm_mm``) and an axial distance ``a`` (:attr:`DiscreteJoints.joint_half_gap_mm`, ASSUMED 0.4 mm, the
  ball's radius) before the ball's centre, and enters the next disk's channel ``a`` after it, running straight
  (a chord) in between. Its pull on the distal disk has the moment ``λ (r cos(θ/2) + a sin(θ/2))`` about the ball
  for a joint angle ``θ`` toward the tendon (the chord's distance from the ball's centre; checked in the tests
  against the virtual work of a tendon of constant tension, ``λ × its length``): the lever grows as the joint
  closes.
* **Coulomb friction at every ball.** A friction moment ``μ_j × ball radius × compression`` (the
  design's ``joint_friction_coefficient``; the compression of the stack is the local tendon tension) opposes
  any change of each joint's angle: a joint sticks at its angle of the last reversal until the moment on it
  has changed by the friction moment (a play operator per joint; :class:`~reachplan.rod_model.design.TensionHistory`
  gives the reversal, as for the Cosserat models).
* **Capstan friction of the tendon** (the design's ``tendon_friction_coefficient``): at each hinge the tendon
  turns by the hinge's angle, and its tension decays by ``exp(−μ φ)`` with the wrap angle ``φ`` accumulated
  from the load cell, the rule of the Cosserat kernel (:func:`routing_tensions`).
* **The nitinol tube** is the same chain at a finer step (:attr:`DiscreteJoints.tube_step_mm`, 1 mm): hinges of
  stiffness ``(EI_tube + EI_needle) / step`` at the elements' midpoints (the midpoint rule: second order in the
  step), the tendon held at the calibrated tube arm in the middle of each element.

Equilibrium: at every hinge the spring and friction moments balance the tendon's and the external loads' moment
about it (rigid links: geometrically exact). In free space the hinges are independent (each sees only the
tendon segment crossing it); with a tip force, tip moment or distributed load in the bending plane they couple,
and the hinge angles are found by a semismooth Newton method with the exact tangent (dead loads and a tendon of
constant tension are conservative: the tangent is symmetric, and an equilibrium is reported only when it is
positive definite, i.e. stable), following the external loads from zero (continuation). Convergence is judged
by the moment residual at the hinges, N·m.

What it leaves out: bending out of one plane (one pulled tendon at a time; loads in its plane), twist, axial and
shear strain, the tissue (:mod:`reachplan.planner.steering.tissue_rod` uses the Cosserat rod), and the clearance of
the disks in the needle's lumen. The limits it converges to are tested: many frictionless joints with a zero
half-gap give the continuum beam's circular arcs (:mod:`~reachplan.rod_model.beam`), a finer tube step the
same shape, and a small tip force linear beam theory.

Calibration and validation: see :data:`JOINTS_CALIBRATION` and ``docs/mechanics.md`` ("The discrete joint section").
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, replace
from functools import lru_cache
from typing import ClassVar

import numpy as np

from reachplan.rod_model.design import Calibration, Loads, RodDesign, TensionHistory
from reachplan.rod_model.errors import RodModelError, UnsupportedLoadError
from reachplan.rod_model.kinematic import bend_frames, joint_section_index
from reachplan.rod_model.protocol import Capabilities, check_loads
from reachplan.rod_model.result import FailedSolve, RodBatch, RodPath, turn_per_length

#: The two global parameters fitted for this model on the three calibration rows of the reference only
#: (:func:`reachplan.rod_model.calibrate.calibrate` with ``model=DISCRETE_JOINTS``; ``reachplan bench joints``
#: reports every published row). Pass them to :func:`reachplan.rod_model.design.preset` to solve a design
#: calibrated for this model; a design keeps the Cosserat model's calibration otherwise.
JOINTS_CALIBRATION = Calibration(joint_stiffness_scale=0.1227, tube_arm_fraction=0.6087)


@dataclass(frozen=True, eq=False)
class Chain:
    """The rod as rigid links between hinges, SI units.

    Built by :func:`build_chain`; hinge ``i`` joins link ``i`` (proximal) and link ``i + 1`` (distal); link 0
    starts at the clamp, the last link ends at the tip.

    Parameters
    ----------
    hinge_s_m : (h,) float, m
        Arc length of each hinge from the base, increasing.
    length_m : float, m
        Length of the rod.
    stiffness_nm : (h,) float, N·m/rad
        Rotational stiffness of each hinge: stylet and needle over the hinge's length.
    arm_m : (h,) float, m
        Offset of the tendon's channel from the axis on both sides of the hinge.
    half_gap_m : (h,) float, m
        Axial distance from the hinge to the tendon's channel exits on either side.
    friction_arm_m : (h,) float, m
        Coulomb coefficient × ball radius at a joint; 0 at a tube hinge.
    is_joint : (h,) bool
        Hinges of the joint section (the balls).
    pitch_m : float, m
        Spacing of the joints.
    capstan_mu : float
        The tendon's friction coefficient on its routing.
    section_bounds_m : (k + 1,) float, m
        Boundaries of the design's sections (:meth:`RodDesign.sections`).
    contact_angle_rad : (h,) float, rad
        Largest angle of each hinge: at a joint ``2 atan(a / R_disk)``, where the rims of the two disks touch
        (their faces ``a`` from the ball's centre); π at a tube hinge or with a zero half-gap (no limit).
    """

    hinge_s_m: np.ndarray
    length_m: float
    stiffness_nm: np.ndarray
    arm_m: np.ndarray
    half_gap_m: np.ndarray
    friction_arm_m: np.ndarray
    is_joint: np.ndarray
    pitch_m: float
    capstan_mu: float
    section_bounds_m: np.ndarray
    contact_angle_rad: np.ndarray

    @property
    def node_s_m(self) -> np.ndarray:
        """(h + 2,) float, m: the links' ends, base, hinges and tip."""
        return np.r_[0.0, self.hinge_s_m, self.length_m]


def build_chain(design: RodDesign, tube_step_mm: float, joint_half_gap_mm: float) -> Chain:
    """Discretise ``design`` into hinges: one per joint, and the tubes at about ``tube_step_mm``.

    Parameters
    ----------
    design : RodDesign
        The stylet in its needle (its sections' stiffnesses and arms, calibration included).
    tube_step_mm : float, mm
        Largest element length in the tube sections.
    joint_half_gap_mm : float, mm
        Axial distance of the disks' channel exits from the ball's centre.

    Returns
    -------
    Chain

    Raises
    ------
    RodModelError
        A half-gap that does not fit in half a pitch.
    """
    cols: list[list[np.ndarray]] = [[], [], [], [], [], [], []]
    rim = 0.5 * design.stylet.disk_diameter_mm * 1e-3
    pitch = design.stylet.joint_pitch_mm * 1e-3
    for sec in design.sections():
        if sec.kind == "joints":
            n = design.stylet.n_joints
            gap = joint_half_gap_mm * 1e-3
            if not 0.0 <= gap < 0.5 * sec.length_m / n:
                raise RodModelError(f"joint half-gap {joint_half_gap_mm} mm does not fit in half a joint pitch "
                                    f"({0.5e3 * sec.length_m / n:.3f} mm) of {design.name}")
        else:
            n = max(1, math.ceil(sec.length_m * 1e3 / tube_step_mm - 1e-9))
            gap = 0.5 * sec.length_m / n
        step = sec.length_m / n
        joint = sec.kind == "joints"
        limit = 2.0 * math.atan(gap / rim) if joint and gap > 0 else math.pi
        for col, value in zip(cols, (sec.start_m + (np.arange(n) + 0.5) * step, (sec.ei1 + sec.ei2) / step,
                                     sec.arm_m, gap, sec.joint_friction_arm_m if joint else 0.0, joint, limit),
                              strict=True):
            col.append(np.broadcast_to(np.asarray(value, dtype=float), (n,)))
    s, k, arm, gap_m, fr, isj, contact = (np.concatenate(c) for c in cols)
    secs = design.sections()
    bounds = np.array([secs[0].start_m] + [x.end_m for x in secs])
    isj = isj.astype(bool)
    for a in (s, k, arm, gap_m, fr, isj, bounds, contact):
        a.setflags(write=False)  # shared through the per-design cache
    return Chain(s, float(bounds[-1]), k, arm, gap_m, fr, isj, pitch, secs[0].capstan_mu, bounds, contact)


def routing_tensions(tension_n: np.ndarray, theta: np.ndarray, mu: float, history: TensionHistory,
                     extra_wrap_rad: np.ndarray | float = 0.0) -> np.ndarray:
    """Tension of the tendon in its chord across each hinge (capstan friction on its routing).

    The rule of the Cosserat kernel's ``local_tension``: with the load-cell tension ``λ0`` the local tension lies
    within ``λ0 exp(∓μ φ)``, ``φ`` the wrap angle from the load cell (the hinges' angles before the chord, half
    of its own); where the tendon sticks it keeps the profile of the last reversal, ``λr exp(±μ φ)``.

    Parameters
    ----------
    tension_n : (b,) float, N
        Load-cell tension of each solve.
    theta : (b, h) float, rad
        Hinge angles.
    mu : float
        Capstan friction coefficient.
    history : TensionHistory
        Pulling or releasing, and the tension at the last reversal.
    extra_wrap_rad : (h,) float or float, rad
        Turn of the tendon at each hinge besides the hinge's angle (in the disks' channels,
        :attr:`DiscreteJoints.disk_wrap_rad`).

    Returns
    -------
    (b, h) float, N
    """
    lam0 = np.asarray(tension_n, dtype=float)[:, None]
    if mu == 0.0:
        return np.broadcast_to(lam0, theta.shape)
    turn = np.abs(theta) + extra_wrap_rad
    wrap = np.cumsum(turn, axis=-1) - 0.5 * turn
    d = 1.0 if history.increasing else -1.0
    prev = history.reversal_tension_n * np.exp(d * mu * wrap)
    return np.clip(prev, lam0 * np.exp(-mu * wrap), lam0 * np.exp(mu * wrap))


def tendon_moment(chain: Chain, tension_n: np.ndarray, theta: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Moment of the tendon's chord about each hinge, and its derivative in the hinge's angle.

    The chord runs from the proximal channel exit ``(r, −a)`` to the distal one, ``(r, a)`` turned by ``θ``; its
    distance from the hinge is ``r cos(θ/2) + a sin(θ/2)`` (positive ``θ``: toward the tendon).

    Parameters
    ----------
    chain : Chain
        Arms and half-gaps.
    tension_n : (b, h) float, N
        Tension in each chord.
    theta : (b, h) float, rad
        Hinge angles.

    Returns
    -------
    moment_nm : (b, h) float, N·m
        Generalised moment (conjugate to ``θ``).
    d_moment_nm : (b, h) float, N·m/rad
        Its derivative in the hinge's own angle.
    """
    c, s = np.cos(0.5 * theta), np.sin(0.5 * theta)
    moment = tension_n * (chain.arm_m * c + chain.half_gap_m * s)
    return moment, 0.5 * tension_n * (chain.half_gap_m * c - chain.arm_m * s)


def node_positions(chain: Chain, theta: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Planar positions of the links' ends, and the links' angles.

    Parameters
    ----------
    chain : Chain
        The links' lengths.
    theta : (..., h) float, rad
        Hinge angles.

    Returns
    -------
    nodes_m : (..., h + 2, 2) float, m
        ``(lateral, axial)`` of the base, each hinge and the tip; lateral toward the bending direction.
    psi : (..., h + 1) float, rad
        Angle of each link from the base axis toward the bending direction.
    """
    psi = np.concatenate([np.zeros((*theta.shape[:-1], 1)), np.cumsum(theta, axis=-1)], axis=-1)
    ell = np.diff(chain.node_s_m)
    steps = np.stack([ell * np.sin(psi), ell * np.cos(psi)], axis=-1)
    zero = np.zeros((*theta.shape[:-1], 1, 2))
    return np.concatenate([zero, np.cumsum(steps, axis=-2)], axis=-2), psi


@dataclass(frozen=True)
class PlanarLoads:
    """External loads in the bending plane (dead loads), SI.

    Parameters
    ----------
    tip_force_n : (2,) float, N
        ``(lateral, axial)`` force on the tip.
    tip_moment_nm : float, N·m
        Couple on the tip, positive bending toward the lateral direction.
    distributed_n_per_m : (2,) float, N/m
        Uniform ``(lateral, axial)`` force per length.
    """

    tip_force_n: tuple[float, float]
    tip_moment_nm: float
    distributed_n_per_m: tuple[float, float]

    @property
    def scale_nm(self) -> float:
        """A moment scale of the loads for a 0.2 m rod, N·m (for the residual's tolerance)."""
        return float(np.hypot(*self.tip_force_n) * 0.2 + abs(self.tip_moment_nm)
                     + np.hypot(*self.distributed_n_per_m) * 0.02)

    def moment(self, chain: Chain, theta: np.ndarray, factor: float) -> tuple[np.ndarray, np.ndarray]:
        """Generalised moment of the loads (× ``factor``) about each hinge, and its symmetric tangent.

        Parameters
        ----------
        chain : Chain
            The links.
        theta : (h,) float, rad
            Hinge angles.
        factor : float
            Load factor of the continuation (1: the full loads).

        Returns
        -------
        moment_nm : (h,) float, N·m
        lever_nm : (h,) float, N·m/rad
            ``s_m = Σ_{p distal of hinge m} F_p · (x_p − c_m)``: the tangent is ``∂ moment_i / ∂ θ_j = −s_max(i, j)``
            (dead loads: symmetric; see :func:`max_solve`).
        """
        nodes, _ = node_positions(chain, theta)
        ell = np.diff(chain.node_s_m)
        # point loads: each link's share of the distributed load at its middle, then the tip force
        pts = np.concatenate([0.5 * (nodes[:-1] + nodes[1:]), nodes[-1:]])
        f = factor * np.concatenate([ell[:, None] * np.asarray(self.distributed_n_per_m)[None, :],
                                     np.asarray(self.tip_force_n)[None, :]])
        centres = nodes[1:-1]

        def suffix(a: np.ndarray) -> np.ndarray:  # hinge i: sum over the points distal of it (index > i)
            return np.cumsum(a[::-1], axis=0)[::-1][1:len(centres) + 1]

        fx, fz = suffix(f[:, 0]), suffix(f[:, 1])
        a = suffix(f[:, 0] * pts[:, 1] - f[:, 1] * pts[:, 0])
        b = suffix(f[:, 0] * pts[:, 0] + f[:, 1] * pts[:, 1])
        moment = a - centres[:, 1] * fx + centres[:, 0] * fz + factor * self.tip_moment_nm
        return moment, b - centres[:, 0] * fx - centres[:, 1] * fz


def _tridiagonal(diag: np.ndarray, lever: np.ndarray) -> np.ndarray:
    """Banded form (3, h) of ``U⁻¹ (D + B) U⁻ᵀ`` (see :func:`max_solve`); symmetric tridiagonal."""
    d_next = np.r_[diag[1:], 0.0]
    delta = lever - np.r_[lever[1:], 0.0]
    ab = np.zeros((3, len(diag)))
    ab[0, 1:] = -diag[1:]
    ab[1] = diag + d_next + delta
    ab[2, :-1] = -diag[1:]
    return ab


def max_solve(diag: np.ndarray, lever: np.ndarray, rhs: np.ndarray) -> np.ndarray:
    """Solve ``(diag(d) + B) x = b`` with ``B_ij = s_max(i, j)`` in O(h): the chain's tangent.

    ``B = U diag(δ) Uᵀ`` with ``U`` the upper triangle of ones and ``δ_k = s_k − s_(k+1)``; with ``y = Uᵀ x``
    (the links' angles) the system is tridiagonal, ``U⁻¹ D U⁻ᵀ y + δ y = U⁻¹ b`` (in absolute angles the dead
    loads' stiffness is diagonal and the springs' tridiagonal).

    Parameters
    ----------
    diag : (h,) float
        The diagonal ``d``.
    lever : (h,) float
        ``s`` (:meth:`PlanarLoads.moment`).
    rhs : (h,) float
        ``b``.

    Returns
    -------
    (h,) float
        ``x``.

    Raises
    ------
    numpy.linalg.LinAlgError
        A singular system.
    """
    from scipy.linalg import solve_banded  # here: importing scipy.linalg costs ~0.5 s, loading the plugin must not

    y = solve_banded((1, 1), _tridiagonal(diag, lever), rhs - np.r_[rhs[1:], 0.0])
    return np.diff(y, prepend=0.0)


def max_matvec(lever: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Return ``B v`` with ``B_ij = s_max(i, j)`` (``s`` is ``lever``), in O(h); ``v`` and the result are (h,)."""
    delta = lever - np.r_[lever[1:], 0.0]
    return np.cumsum((delta * np.cumsum(v))[::-1])[::-1]


def max_positive_definite(diag: np.ndarray, lever: np.ndarray) -> bool:
    """Tell whether ``diag(d) + B`` (see :func:`max_solve`) is positive definite: a stable equilibrium.

    Sylvester: it is congruent to the tridiagonal ``U⁻¹ (D + B) U⁻ᵀ``, tested by a banded Cholesky factorisation.

    Parameters
    ----------
    diag : (h,) float
        The diagonal.
    lever : (h,) float
        ``s``.

    Returns
    -------
    bool
    """
    from scipy.linalg import cholesky_banded  # see max_solve

    ab = _tridiagonal(diag, lever)
    try:
        cholesky_banded(ab[1:], lower=True)
    except np.linalg.LinAlgError:
        return False
    return True


def bending_direction(design: RodDesign, loads: Loads) -> np.ndarray:
    """Find the bending plane's direction: the pulled tendon's, or without tension the loads' lateral one.

    Parameters
    ----------
    design : RodDesign
        Its tendons' offsets.
    loads : Loads
        Tensions, roll and external loads (base frame).

    Returns
    -------
    (3,) float, unit, needle frame
        In the x-y plane; tendon 0's offset when nothing is pulled and no load acts sideways.
    """
    offsets = design.tendon_unit_offsets(loads.roll_deg)
    if max(loads.tensions_n) > 0.0:
        return offsets[int(np.argmax(loads.tensions_n))]
    z = np.array([0.0, 0.0, 1.0])
    for v in (np.asarray(loads.tip_force_n), np.asarray(loads.distributed_n_per_m),
              np.cross(np.asarray(loads.tip_moment_nm), z)):
        side = v - (v @ z) * z
        if np.linalg.norm(side) > 1e-12 * (1.0 + np.linalg.norm(v)):
            return side / np.linalg.norm(side)
    return offsets[0]


def planar_loads(design: RodDesign, loads: Loads, direction: np.ndarray) -> PlanarLoads | None:
    """Project the external loads on the bending plane; None without external loads.

    Parameters
    ----------
    design : RodDesign
        Its name, for the message.
    loads : Loads
        Tip force and moment, distributed force (base frame).
    direction : (3,) float, unit
        The bending direction (the pulled tendon's).

    Returns
    -------
    PlanarLoads or None

    Raises
    ------
    UnsupportedLoadError
        A foundation, or a load out of the bending plane (a force along its normal, a moment about another
        axis).
    """
    if loads.foundation is not None:
        raise UnsupportedLoadError("discrete_joints does not model tissue; use the in-tissue rod (tissue_rod) or "
                                   "two_tube_cosserat with a foundation")
    if not loads.has_external:
        return None
    z = np.array([0.0, 0.0, 1.0])
    normal = np.cross(z, direction)
    f, m, q = (np.asarray(v) for v in (loads.tip_force_n, loads.tip_moment_nm, loads.distributed_n_per_m))
    off = (abs(f @ normal) / (1 + np.linalg.norm(f)), abs(q @ normal) / (1 + np.linalg.norm(q)),
           np.hypot(m @ direction, m @ z) / (1e-3 + np.linalg.norm(m)))
    if max(off) > 1e-9:
        raise UnsupportedLoadError(f"discrete_joints is planar: the loads on {design.name} must lie in the bending "
                                   "plane of the pulled tendon (forces without a component along z × tendon, a "
                                   "moment about z × tendon only); use cosserat_rod or two_tube_cosserat")
    return PlanarLoads((float(f @ direction), float(f @ z)), float(m @ normal), (float(q @ direction), float(q @ z)))


_GEOMETRY = ("a joint turned past the angle where its disks' rims touch (or a tendon chord past its channel): the "
             "load is beyond what the joint section can take")


@dataclass(frozen=True)
class _Solution:
    theta: np.ndarray  # (b, h) rad
    residual_nm: np.ndarray  # (b,)
    iterations: int
    ok: np.ndarray  # (b,) bool
    reason: str = ""


def _play(chain: Chain, theta: np.ndarray, g: np.ndarray, tension_n: np.ndarray,
          theta_r: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Residual of the hinges' equilibrium with Coulomb friction (a play operator per joint), rad.

    ``g = k θ − (driving moment)``; a joint slides forward where ``g + F = 0``, back where ``g − F = 0`` and
    sticks at its reversal angle ``θr`` while ``|g| ≤ F`` (``F`` its friction moment): the residual is
    ``θ − clip(θr, θ − (g + F)/k, θ − (g − F)/k)``, ``g / k`` at a hinge without friction.

    Returns
    -------
    residual : (b, h) float, rad
    stuck : (b, h) bool
        Joints held by friction at ``θr``.
    """
    k = chain.stiffness_nm
    fr = chain.friction_arm_m * tension_n
    lower, upper = theta - (g + fr) / k, theta - (g - fr) / k
    stuck = (fr > 0.0) & (theta_r >= lower) & (theta_r <= upper)
    return theta - np.clip(theta_r, lower, upper), stuck


@dataclass(frozen=True)
class DiscreteJoints:
    """The articulated joint section as discrete ball joints (see the module docstring).

    Parameters
    ----------
    tube_step_mm : float, mm
        Largest element of the nitinol tube sections (1 mm: the tip moves by about 2 µm when halved).
    joint_half_gap_mm : float, mm
        ASSUMED: axial distance from a ball's centre to the tendon's channel exits of the disks on either
        side (the ball's radius, 0.4 mm; unpublished).
    tol : float
        Convergence threshold of the hinges' moment residual, relative to the load's moment scale
        ``1 mN·m + λ·r + |external|``.
    max_iter : int
        Newton iterations per load step.
    disk_wrap_rad : float, rad
        Turn of the tendon inside each disk's channel when the section is straight (channels out of line, a
        tendon pressed on a channel's edge): with the design's ``tendon_friction_coefficient`` μ every disk costs
        the tension a factor ``exp(−μ × disk_wrap_rad)`` more. 0 by default (unpublished; the straight
        routing); see ``docs/mechanics.md`` for what it does to the joint-count trend.

    Raises
    ------
    ValueError
        A non-positive step or tolerance, a negative half-gap or disk wrap, or fewer than one iteration.
    """

    tube_step_mm: float = 1.0
    joint_half_gap_mm: float = 0.4
    tol: float = 1e-11
    max_iter: int = 60
    disk_wrap_rad: float = 0.0

    name: ClassVar[str] = "discrete_joints"
    capabilities: ClassVar[Capabilities] = Capabilities(planar_only=True, twist=False, several_tendons=False,
                                                        external_load=True, large_deflection=True, friction=True)

    def __post_init__(self) -> None:
        if not (self.tube_step_mm > 0 and self.joint_half_gap_mm >= 0 and self.tol > 0 and self.max_iter >= 1
                and self.disk_wrap_rad >= 0):
            raise ValueError("tube_step_mm and tol must be positive, joint_half_gap_mm and disk_wrap_rad "
                             "non-negative, max_iter >= 1")

    def chain(self, design: RodDesign) -> Chain:
        """Return the hinges of ``design`` at this model's resolution (cached per design).

        Parameters
        ----------
        design : RodDesign
            The stylet in its needle.

        Returns
        -------
        Chain
        """
        return _cached_chain(design, self.tube_step_mm, self.joint_half_gap_mm)

    def _disk_wrap(self, chain: Chain) -> np.ndarray:
        return np.where(chain.is_joint, self.disk_wrap_rad, 0.0)

    def _tol(self, chain: Chain, tension_n: np.ndarray, ext: PlanarLoads | None) -> np.ndarray:
        return self.tol * (1e-3 + tension_n * float(np.max(chain.arm_m)) + (ext.scale_nm if ext else 0.0))

    def _free(self, chain: Chain, tension_n: np.ndarray, history: TensionHistory) -> _Solution:
        """Solve free-space pulls (b,) N: every hinge alone (Newton per hinge, vectorised).

        Without capstan friction a hinge's angle depends only on its own stiffness, arm, half-gap and friction:
        each distinct hinge (about three per design) is solved once and copied.
        """
        if chain.capstan_mu != 0.0:
            return self._free_hinges(chain, tension_n, history)
        params = np.column_stack([chain.stiffness_nm, chain.arm_m, chain.half_gap_m, chain.friction_arm_m,
                                  chain.is_joint, chain.contact_angle_rad])
        distinct, inverse = np.unique(params, axis=0, return_inverse=True)
        small = replace(chain, hinge_s_m=np.arange(len(distinct), dtype=float), stiffness_nm=distinct[:, 0],
                        arm_m=distinct[:, 1], half_gap_m=distinct[:, 2], friction_arm_m=distinct[:, 3],
                        is_joint=distinct[:, 4] > 0, contact_angle_rad=distinct[:, 5])
        sol = self._free_hinges(small, tension_n, history)
        return replace(sol, theta=sol.theta[:, inverse.ravel()])

    def _free_hinges(self, chain: Chain, tension_n: np.ndarray, history: TensionHistory) -> _Solution:
        k = chain.stiffness_nm
        theta_r = np.where(chain.is_joint, history.reversal_joint_curvature_per_m * chain.pitch_m, 0.0)
        theta = np.zeros((len(tension_n), len(k)))
        tol = self._tol(chain, tension_n, None)
        res = np.full(len(tension_n), np.inf)
        it = 0
        while it < self.max_iter:
            it += 1
            lam = routing_tensions(tension_n, theta, chain.capstan_mu, history, self._disk_wrap(chain))
            moment, d_moment = tendon_moment(chain, lam, theta)
            e, stuck = _play(chain, theta, k * theta - moment, lam, theta_r)
            res = np.max(np.abs(k * e), axis=1)
            if np.all(res <= tol) or not np.all(np.isfinite(res)):
                break
            theta = theta - e / np.where(stuck, 1.0, (k - d_moment) / k)
        geometry = self._geometry_ok(chain, theta)
        ok = (res <= tol) & geometry
        reason = ("" if np.all(ok) else _GEOMETRY if np.all(res <= tol) else
                  f"hinge equilibrium not reached: moment residual {np.max(res):.2e} N·m after {it} Newton iterations")
        return _Solution(theta, res, it, ok, reason)

    @staticmethod
    def _geometry_ok(chain: Chain, theta: np.ndarray) -> np.ndarray:
        """(b,) bool: every angle finite and within its hinge's contact angle, every chord running forward."""
        fwd = chain.half_gap_m * np.cos(0.5 * theta) - chain.arm_m * np.sin(0.5 * theta)
        return (np.all(np.isfinite(theta), axis=-1) & np.all(np.abs(theta) < chain.contact_angle_rad, axis=-1)
                & np.all((fwd > 0) | (chain.half_gap_m == 0), axis=-1))

    def _newton(self, chain: Chain, tension_n: float, history: TensionHistory, ext: PlanarLoads, factor: float,
                theta: np.ndarray, check: bool) -> tuple[np.ndarray, float, int, str]:
        """Semismooth Newton for one load step (O(h) per iteration, :func:`max_solve`).

        Returns the angles, the residual (N·m), the iterations and the status: ``"ok"``, ``"failed"`` (not
        converged) or, when ``check``, ``"unstable"`` (the tangent on the sliding hinges not positive definite).
        """
        k = chain.stiffness_nm
        theta_r = np.where(chain.is_joint, history.reversal_joint_curvature_per_m * chain.pitch_m, 0.0)
        tol = float(self._tol(chain, np.array([tension_n]), ext)[0])
        lam0 = np.array([tension_n])

        def evaluate(th: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, float]:
            lam = routing_tensions(lam0, th[None, :], chain.capstan_mu, history, self._disk_wrap(chain))[0]
            moment, d_moment = tendon_moment(chain, lam, th)
            ext_m, lever = ext.moment(chain, th, factor)
            e, stuck = _play(chain, th, k * th - moment - ext_m, lam, theta_r)
            res = float(np.max(np.abs(k * e))) if np.all(np.isfinite(e)) else math.inf
            return e, stuck, k - d_moment, lever, res

        e, stuck, diag, lever, res = evaluate(theta)
        for it in range(1, self.max_iter + 1):
            if res <= tol:
                free = ~stuck
                stable = not check or not free.any() or max_positive_definite(diag[free], lever[free])
                return theta, res, it, "ok" if stable else "unstable"
            # stuck joints move back to their reversal angle; the sliding ones solve the tangent system
            delta = np.where(stuck, -e, 0.0)
            free = ~stuck
            rhs = -(k * e) - max_matvec(lever, delta)
            try:
                delta[free] = max_solve(diag[free], lever[free], rhs[free])
            except np.linalg.LinAlgError:
                break
            for alpha in 0.5 ** np.arange(12):
                trial = theta + alpha * delta
                got = evaluate(trial)
                if got[-1] < res:
                    theta, (e, stuck, diag, lever, res) = trial, got
                    break
            else:
                break
        return theta, res, self.max_iter, "failed"

    def _loaded(self, chain: Chain, tension_n: float, history: TensionHistory, ext: PlanarLoads) -> _Solution:
        """Follow the external loads from zero in 4, 16, 64 steps until a stable equilibrium is found."""
        reason, res, its = "", math.inf, 0
        for ramp in (4, 16, 64):
            theta = np.zeros(len(chain.stiffness_nm))
            for step in range(1, ramp + 1):
                theta, res, it, status = self._newton(chain, tension_n, history, ext, step / ramp, theta,
                                                      step == ramp)
                its += it
                if status != "ok" or not self._geometry_ok(chain, theta):
                    break
            else:
                return _Solution(theta[None, :], np.array([res]), its, np.array([True]))
            reason = (_GEOMETRY if status == "ok" else
                      f"unstable equilibrium (tangent stiffness not positive definite) after {ramp} load steps"
                      if status == "unstable" else f"hinge equilibrium not reached at load step {step}/{ramp}: "
                      f"moment residual {res:.2e} N·m")
        return _Solution(theta[None, :], np.array([res]), its, np.array([False]),
                         reason + " (a load beyond a buckling or snap-through load?)")

    def solve(self, design: RodDesign, loads: Loads) -> RodPath | FailedSolve:
        """Solve ``design`` under ``loads`` (see :meth:`reachplan.rod_model.protocol.RodModel.solve`).

        Parameters
        ----------
        design : RodDesign
            The stylet in its needle.
        loads : Loads
            One pulled tendon (its direction is the bending plane; without tension the loads' lateral direction),
            roll, history, and loads in that plane.

        Returns
        -------
        RodPath or FailedSolve
            Positions in mm (needle frame) at the base, every hinge, the section boundaries and the tip; the
            frame of the link that starts there (the distal one at a hinge). Residual: the largest moment
            residual at a hinge over the rod's length, N.

        Raises
        ------
        UnsupportedLoadError
            Several pulled tendons, a foundation, or loads out of the bending plane.
        """
        t0 = time.perf_counter()
        check_loads(self.name, self.capabilities, design, loads)
        lam = np.asarray(loads.tensions_n)
        j = int(np.argmax(lam))
        direction = bending_direction(design, loads)
        ext = planar_loads(design, loads, direction)
        chain = self.chain(design)
        sol = (self._free(chain, lam[j:j + 1], loads.history) if ext is None
               else self._loaded(chain, float(lam[j]), loads.history, ext))
        ms = (time.perf_counter() - t0) * 1e3
        residual_n = float(sol.residual_nm[0]) / chain.length_m
        if not sol.ok[0]:
            return FailedSolve(self.name, sol.reason, residual_n, ms, loads.tensions_n, loads.roll_deg)
        s, pos, frames = _samples(chain, sol.theta[0], direction)
        return RodPath(self.name, s * 1e3, pos * 1e3, frames, residual_n, ms, sol.iterations, loads.tensions_n,
                       loads.roll_deg)

    def solve_batch(self, design: RodDesign, tensions_n: np.ndarray, roll_deg: float = 0.0) -> RodBatch:
        """Solve free-space pulls of tendon 0 from rest with each of ``tensions_n`` (b,), N, at once.

        Parameters
        ----------
        design : RodDesign
            The stylet in its needle.
        tensions_n : (b,) float, N
            Tension on tendon 0 of each solve.
        roll_deg : float
            Roll shared by all solves, degrees.

        Returns
        -------
        RodBatch
            Tips (mm, needle frame) and section curvatures (1/m); failed solves NaN and not ``converged``.

        Raises
        ------
        ValueError
            A negative or non-finite tension.
        """
        t = np.asarray(tensions_n, dtype=float).ravel()
        if not np.all(np.isfinite(t)) or np.any(t < 0):
            raise ValueError("tensions_n must be finite and non-negative")
        chain = self.chain(design)
        sol = self._free(chain, t, TensionHistory())
        direction = design.tendon_unit_offsets(roll_deg)[0]
        nodes, psi = node_positions(chain, sol.theta)
        tips = nodes[:, -1, 0:1] * direction + nodes[:, -1, 1:2] * np.array([0.0, 0.0, 1.0])
        at = _link_of(chain, chain.section_bounds_m)
        ang = psi[:, at]
        tangents = np.sin(ang)[..., None] * direction + np.cos(ang)[..., None] * np.array([0.0, 0.0, 1.0])
        curv = turn_per_length(tangents, np.diff(chain.section_bounds_m))
        tips[~sol.ok], curv[~sol.ok] = np.nan, np.nan
        return RodBatch(self.name, t, roll_deg, tips * 1e3, chain.section_bounds_m * 1e3, curv,
                        joint_section_index(design), sol.ok, sol.residual_nm / chain.length_m)


def _link_of(chain: Chain, s_m: np.ndarray) -> np.ndarray:
    """Index of the link holding each arc length (the distal link at a hinge)."""
    node_s = chain.node_s_m
    return np.clip(np.searchsorted(node_s[:-1], s_m, side="right") - 1, 0, len(node_s) - 2)


def _samples(chain: Chain, theta: np.ndarray, direction: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Arc lengths (m), positions (m, needle frame) and frames of the solved chain at its nodes and section bounds."""
    nodes, psi = node_positions(chain, theta)
    s = np.unique(np.r_[chain.node_s_m, chain.section_bounds_m])
    idx = _link_of(chain, s)
    along = s - chain.node_s_m[idx]
    lat = nodes[idx, 0] + along * np.sin(psi[idx])
    ax = nodes[idx, 1] + along * np.cos(psi[idx])
    pos = lat[:, None] * direction + ax[:, None] * np.array([0.0, 0.0, 1.0])
    return s, pos, bend_frames(direction, psi[idx])


_cached_chain = lru_cache(maxsize=256)(build_chain)


DISCRETE_JOINTS = DiscreteJoints()
