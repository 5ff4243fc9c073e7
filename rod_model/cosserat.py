"""Cosserat rod models with tendon routing, solved by shooting: the single rod and the two-tube model.

Equations (Rucker & Webster, IEEE T-RO 27(6), 2011; two-tube form after Kheradmand et al., OncoReach,
section 3), body frame of the stylet (tube 1), SI units:

* kinematics ``p' = R v``, ``R' = R [u]x``; needle (tube 2) ``R2 = R Rz(θ)``, ``θ' = u2z − u1z``,
  ``u2 = Rz(θ)ᵀ u1 + θ' e3``, ``v2 = β Rz(θ)ᵀ v1``;
* linear elastic law ``n_i = K_se,i (v_i − e3)``, ``m_i = K_bt,i u_i`` (straight, isotropic tubes);
* a tendon ``j`` at body offset ``r_j`` with tension ``λ_j`` runs along ``ṗ_j = R(v + u × r_j)``; its
  distributed load on the rod is Rucker & Webster's ``f_j = −λ_j [ṗ_j]² p̈_j/|ṗ_j|³ = λ_j (ṗ_j/|ṗ_j|)'`` with
  ``τ_j = r_j × f_j``, and its termination at the tip a point load ``−λ_j t_j(L)``.

Because ``f_j`` is the derivative of ``λ_j t_j``, the equilibrium ``n' + f = 0``, ``m' + p' × n + l = 0`` of
stylet + needle + tendons integrates once in closed form: with the *total* section force and moment (rods
plus tendons, world frame) ``N = n1 + n2 + Σλ_j t_j`` and ``M = m1 + m2 + Σ r_j × λ_j t_j`` the balances are
``N' = −f_ext``, ``M' = −p' × N − l_ext``, and the tendon terminations disappear from the tip conditions
(``N(L) = F_tip``, ``M(L) = L_tip``). This is the same boundary-value problem as ``A(x) x' = b(x)`` in
the reference (its summed in-plane balances and per-rod axial balances), written in first-integral form:
it needs no derivative of the strains, and a jump of the tendon's moment arm between tube and disks is exact
(the rod's moment jumps by ``λ Δr``, the point load the tendon's kink exerts). Per-rod axial balances are kept
as states: the needle's axial force ``n2z' = −GA2 β (u1 × v1)_z − (Rᵀ f_ext)_z`` (no friction between the
tubes) and its torsion ``m2z' = 0`` (isotropic tubes, no distributed torque). The strains follow from the
loads algebraically (:func:`reachplan.rod_model._kernel.closure`): bending ``u_xy = m_xy/(EI1 + EI2)``, torsion
``u1z = m1z/GJ1``, ``u2z = m2z/GJ2``, axial ``v1z = 1 + n1z/EA1``, dilation ``β = (1 + n2z/EA2)/v1z``, shear
``v_xy = n_xy/(GA1 + β GA2)``, with the tendon directions found by a fixed point (they depend on the strains
only through ``λ/GA`` and ``λ r²/EI``, both ~1e-3).

Boundary conditions: clamped base (``p = 0``, ``R = I``, ``θ = 0``); at the tip ``N = F_tip``, ``M = L_tip``
and, for the needle that carries the external loads, ``n2z = (Rᵀ F_tip)_z``, ``m2z = (Rᵀ L_tip)_z``. Unknowns
of the shooting: ``N(0), M(0), n2z(0), m2z(0)``, started from the undeformed rod's values
(:func:`linear_guess`); quasi-Newton with a finite-difference Jacobian, Broyden updates and a backtracking
line search, RK4 with fixed steps aligned to the section boundaries; when the full load fails from the
initial guess, the tensions and external loads are ramped from zero (continuation). Convergence is judged by
the tip residual (N, moments divided by the length), never by an optimiser's flag.

The single-rod model (``cosserat_rod``) is the same rod with stylet and needle welded together (no relative
twist or dilation: stiffnesses summed), the two-tube model (``two_tube_cosserat``) lets them twist and slide.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, replace
from typing import ClassVar

import numpy as np

from reachplan.rod_model import _kernel
from reachplan.rod_model.design import Loads, RodDesign
from reachplan.rod_model.protocol import Capabilities, check_loads
from reachplan.rod_model.result import FailedSolve, RodBatch, RodPath, turn_per_length


def section_table(design: RodDesign) -> np.ndarray:
    """Tabulate the sections for the compiled kernel.

    Returns
    -------
    (k, 11) float, SI
        One row per section: ``start, end`` (m), ``ei1, gj1`` (N·m²), ``ea1, ga1`` (N), ``ei2, gj2`` (N·m²),
        ``ea2, ga2`` (N), ``arm`` (m); see :class:`reachplan.rod_model.design.Section`.
    """
    return np.array([[s.start_m, s.end_m, s.ei1, s.gj1, s.ea1, s.ga1, s.ei2, s.gj2, s.ea2, s.ga2, s.arm_m]
                     for s in design.sections()])


def linear_guess(design: RodDesign, loads: Loads) -> np.ndarray:
    """Guess the shooting unknowns at the base from the undeformed rod.

    ``N(0) = F_tip + f L`` (exact: dead loads), ``M(0) = L_tip + L e3 × F_tip + L²/2 e3 × f`` (undeformed lever
    arms), needle ``n2z = F_z + f_z L``, ``m2z = L_tip,z``. Zero in free space, where it is the exact solution.

    Returns
    -------
    (8,) float, SI, base frame
        ``N(0)`` (N), ``M(0)`` (N·m), ``n2z(0)`` (N), ``m2z(0)`` (N·m).
    """
    length = design.length_mm * 1e-3
    f = np.array(loads.distributed_n_per_m)
    ftip = np.array(loads.tip_force_n)
    e3 = np.array([0.0, 0.0, 1.0])
    n0 = ftip + f * length
    m0 = np.array(loads.tip_moment_nm) + np.cross(length * e3, ftip) + np.cross(0.5 * length**2 * e3, f)
    return np.r_[n0, m0, n0[2], loads.tip_moment_nm[2]]


def _steps(sec: np.ndarray, steps_per_mm: float) -> np.ndarray:
    return np.array([max(2, math.ceil((b - a) * 1e3 * steps_per_mm)) for a, b in sec[:, :2]], dtype=np.int64)


@dataclass(frozen=True)
class _ShootingModel:
    """Shared solver of :class:`CosseratRod` and :class:`TwoTubeCosserat`.

    Parameters
    ----------
    steps_per_mm : float
        RK4 steps per millimetre of rod (at least 2 per section).
    tol : float
        Convergence threshold of the tip residual, relative to the load scale ``1 N + Σλ + |external|``.
    max_iter : int
        Newton iterations per continuation step.
    max_ramp : int
        Largest number of continuation steps tried (1, 4, 16, ... up to this).
    """

    steps_per_mm: float = 0.5
    tol: float = 1e-10
    max_iter: int = 25
    max_ramp: int = 64

    name: ClassVar[str] = ""
    coupled: ClassVar[bool] = True
    capabilities: ClassVar[Capabilities]

    def __post_init__(self) -> None:
        if not (self.steps_per_mm > 0 and self.tol > 0 and self.max_iter >= 1 and self.max_ramp >= 1):
            raise ValueError("steps_per_mm and tol must be positive, max_iter and max_ramp at least 1")

    def solve(self, design: RodDesign, loads: Loads, initial_guess: np.ndarray | None = None,
              *, continuation: bool = True) -> RodPath | FailedSolve:
        """Solve ``design`` under ``loads`` by shooting.

        Parameters
        ----------
        design : RodDesign
            The stylet in its needle.
        loads : Loads
            One tension per tendon (N), roll, and external loads in the needle's base frame.
        initial_guess : (8,) float or None
            Base unknowns ``N(0)`` (N, world), ``M(0)`` (N·m, world), ``n2z(0)`` (N), ``m2z(0)`` (N·m);
            default :func:`linear_guess` (exact in free space).
        continuation : bool
            Ramp the loads from zero when the direct solve fails.

        Returns
        -------
        RodPath or FailedSolve
            Positions in mm in the needle frame, sampled at the RK4 steps; a :class:`FailedSolve` with the
            residual reached when shooting does not converge.

        Raises
        ------
        UnsupportedLoadError
            Not one tension per tendon.
        ValueError
            An ``initial_guess`` that is not 8 finite numbers.
        """
        t0 = time.perf_counter()
        check_loads(self.name, self.capabilities, design, loads)
        sec = section_table(design)
        nsteps = _steps(sec, self.steps_per_mm)
        x = linear_guess(design, loads) if initial_guess is None else np.array(initial_guess, dtype=float)
        if x.shape != (_kernel.NX,) or not np.all(np.isfinite(x)):
            raise ValueError("initial_guess must be 8 finite numbers: N(0), M(0), n2z(0), m2z(0)")
        traj = np.empty((int(nsteps.sum()) + 1, _kernel.NSTATE))
        status, res, iters, ramp = _kernel.shoot(
            x, sec, nsteps, design.tendon_unit_offsets(loads.roll_deg), np.array(loads.tensions_n),
            np.array(loads.distributed_n_per_m), np.array(loads.tip_force_n), np.array(loads.tip_moment_nm),
            self.coupled, self.tol, self.max_iter, self.max_ramp if continuation else 1, traj)
        ms = (time.perf_counter() - t0) * 1e3
        if status != _kernel.OK:
            why = {_kernel.SINGULAR: "singular shooting Jacobian", _kernel.NON_FINITE: "non-finite state"}
            reason = (f"{why.get(status, 'shooting did not converge')}: tip residual {res:.2e} N after {iters} "
                      f"Newton iterations, continuation up to {ramp} load steps")
            return FailedSolve(self.name, reason, float(res), ms, loads.tensions_n, loads.roll_deg)
        s = np.concatenate([[0.0], np.concatenate([np.linspace(a, b, n + 1)[1:] for (a, b), n in
                                                   zip(sec[:, :2], nsteps, strict=True)])]) * 1e3
        frames = traj[:, 3:12].reshape(-1, 3, 3)
        return RodPath(self.name, s, traj[:, 0:3] * 1e3, frames, float(res), ms, int(iters), loads.tensions_n,
                       loads.roll_deg, None if self.coupled else traj[:, 18])

    def solve_batch(self, design: RodDesign, tensions_n: np.ndarray, roll_deg: float = 0.0) -> RodBatch:
        """Solve free-space pulls of tendon 0 with each of ``tensions_n`` (b,), N (compiled loop).

        Failed solves are NaN in the tip positions and curvatures and False in ``converged``.

        Raises
        ------
        ValueError
            A negative or non-finite tension.
        """
        t = np.asarray(tensions_n, dtype=float).ravel()
        if not np.all(np.isfinite(t)) or np.any(t < 0):
            raise ValueError("tensions_n must be finite and non-negative")
        sec = section_table(design)
        nsteps = _steps(sec, self.steps_per_mm)
        b, k = len(t), len(sec)
        tips = np.empty((b, 3))
        tang = np.empty((b, k + 1, 3))
        status = np.empty(b, dtype=np.int64)
        res = np.empty(b)
        _kernel.batch_free(t, sec, nsteps, design.tendon_unit_offsets(roll_deg), self.coupled, self.tol,
                           self.max_iter, self.max_ramp, tips, tang, status, res)
        ok = status == _kernel.OK
        tips[~ok] = np.nan
        curv = turn_per_length(tang, np.diff(np.r_[sec[:, 0], sec[-1, 1]]))
        curv[~ok] = np.nan
        bounds = np.r_[sec[:, 0], sec[-1, 1]] * 1e3
        joint = next(i for i, s in enumerate(design.sections()) if s.kind == "joints")
        return RodBatch(self.name, t, roll_deg, tips * 1e3, bounds, curv, joint, ok, res)


@dataclass(frozen=True)
class CosseratRod(_ShootingModel):
    """Single Cosserat rod (stylet and needle welded: summed stiffness) with tendon routing."""

    name: ClassVar[str] = "cosserat_rod"
    coupled: ClassVar[bool] = True
    capabilities: ClassVar[Capabilities] = Capabilities(
        planar_only=False, twist=False, several_tendons=True, external_load=True, large_deflection=True)


@dataclass(frozen=True)
class TwoTubeCosserat(_ShootingModel):
    """Two-tube Cosserat model (stylet and needle on one centreline, relative twist θ and dilation β)."""

    name: ClassVar[str] = "two_tube_cosserat"
    coupled: ClassVar[bool] = False
    capabilities: ClassVar[Capabilities] = replace(CosseratRod.capabilities, twist=True)


COSSERAT_ROD = CosseratRod()
TWO_TUBE_COSSERAT = TwoTubeCosserat()
