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

from reachplan.rod_model import _kernel, multiple_shooting
from reachplan.rod_model.design import Loads, RodDesign, TensionHistory
from reachplan.rod_model.protocol import Capabilities, check_loads
from reachplan.rod_model.result import FailedSolve, RodBatch, RodPath, turn_per_length


def section_table(design: RodDesign, history: TensionHistory | None = None) -> np.ndarray:
    """Tabulate the sections for the compiled kernel.

    Parameters
    ----------
    design : RodDesign
        The design.
    history : TensionHistory, optional
        The tension history for the friction columns (default: a first pull from rest).

    Returns
    -------
    (k, 16) float, SI
        One row per section: ``start, end`` (m), ``ei1, gj1`` (N·m²), ``ea1, ga1`` (N), ``ei2, gj2`` (N·m²),
        ``ea2, ga2`` (N), ``arm`` (m) (see :class:`reachplan.rod_model.design.Section`), then the friction
        columns ``mu, jf, d, λr, κr`` (see :mod:`reachplan.rod_model._kernel`).
    """
    h = history or TensionHistory()
    d = 1.0 if h.increasing else -1.0
    return np.array([[s.start_m, s.end_m, s.ei1, s.gj1, s.ea1, s.ga1, s.ei2, s.gj2, s.ea2, s.ga2, s.arm_m,
                      s.capstan_mu, s.joint_friction_arm_m, d, h.reversal_tension_n,
                      h.reversal_joint_curvature_per_m if s.kind == "joints" else 0.0]
                     for s in design.sections()])


def _distal(sec: np.ndarray, length_m: float) -> np.ndarray:
    """Return the section table of the distal ``length_m`` of the rod, re-based so that it starts at 0."""
    total = sec[-1, 1]
    if not (0.0 < length_m <= total + 1e-12):
        raise ValueError(f"inserted length must be in (0, {total * 1e3:.1f}] mm, got {length_m * 1e3:g}")
    cut = total - length_m
    out = sec[sec[:, 1] > cut + 1e-12].copy()
    out[0, 0] = cut
    out[:, :2] -= cut
    return out


def linear_guess(design: RodDesign, loads: Loads, length_m: float | None = None) -> np.ndarray:
    """Guess the shooting unknowns at the base from the undeformed rod.

    ``N(0) = F_tip + f L`` (exact: dead loads), ``M(0) = L_tip + L e3 × F_tip + L²/2 e3 × f`` (undeformed lever
    arms), needle ``n2z = F_z + f_z L``, ``m2z = L_tip,z``. Zero in free space, where it is the exact solution.
    ``length_m``: the rod length (default: the design's).

    Returns
    -------
    (8,) float, SI, base frame
        ``N(0)`` (N), ``M(0)`` (N·m), ``n2z(0)`` (N), ``m2z(0)`` (N·m).
    """
    length = design.length_mm * 1e-3 if length_m is None else length_m
    f = np.array(loads.distributed_n_per_m)
    ftip = np.array(loads.tip_force_n)
    e3 = np.array([0.0, 0.0, 1.0])
    n0 = ftip + f * length
    m0 = np.array(loads.tip_moment_nm) + np.cross(length * e3, ftip) + np.cross(0.5 * length**2 * e3, f)
    return np.r_[n0, m0, n0[2], loads.tip_moment_nm[2]]


def _steps(sec: np.ndarray, steps_per_mm: float) -> np.ndarray:
    return np.array([max(2, math.ceil((b - a) * 1e3 * steps_per_mm)) for a, b in sec[:, :2]], dtype=np.int64)


#: With external loads the continuation starts with this many load steps (the direct solve from the
#: undeformed guess can converge to an unstable branch: e.g. a cantilever bent back against a lateral force).
EXTERNAL_FIRST_RAMP = 4
#: ... and refines (x4) up to this many while the equilibrium found is unstable.
EXTERNAL_MAX_RAMP = 1024
#: Rows of the shooting state holding the section loads: ``N``, ``M``, ``n2z``, ``m2z``.
_LOAD_ROWS = np.array([12, 13, 14, 15, 16, 17, 19, 20])


def integration_error(x: np.ndarray, traj: np.ndarray, sec: np.ndarray, nsteps: np.ndarray, rdir: np.ndarray,
                      lam: np.ndarray, fext: np.ndarray, coupled: bool) -> tuple[float, float]:
    """Error estimate of a converged integration.

    Parameters
    ----------
    x : (8,) float, the converged base unknowns; ``traj`` : (n + 1, 21) its recorded trajectory.
    sec, nsteps, rdir, lam, fext : the kernel's inputs (see :mod:`reachplan.rod_model._kernel`).

    Returns
    -------
    step_mm : float, mm
        Tip displacement when the same base values are integrated with half the step (step doubling: RK4's
        error on the coarse grid is about 16/15 of it). ``inf`` when the finer integration is not finite.
    frame_error : float
        ``max |RᵀR − I|`` along the trajectory (RK4 does not preserve orthonormality; a blown-up integration
        loses it).
    """
    fine = _kernel.integrate(x, sec, 2 * nsteps, rdir, lam, fext, coupled, traj[:1], False)
    step_mm = float(np.linalg.norm(fine[0:3] - traj[-1, 0:3])) * 1e3
    r = traj[:, 3:12].reshape(-1, 3, 3)
    with np.errstate(invalid="ignore", over="ignore"):
        frame = float(np.max(np.abs(np.einsum("nki,nkj->nij", r, r) - np.eye(3))))
    return (step_mm if np.isfinite(step_mm) else np.inf), (frame if np.isfinite(frame) else np.inf)


def conjugate_point(x: np.ndarray, sec: np.ndarray, nsteps: np.ndarray, rdir: np.ndarray, lam: np.ndarray,
                    fext: np.ndarray, coupled: bool, tol: float = 1e-6) -> float | None:
    """Arc length (mm) of the first conjugate point of an equilibrium, or None when it is stable.

    Jacobi (conjugate-point) criterion for a rod clamped at the base with dead loads (Till & Rucker, "Elastic
    stability of Cosserat rods and parallel continuum robots", IEEE T-RO 33(3), 2017; Dhanakoti, "Stability of
    cantilever-like structures", arXiv:2407.07601): the shooting matrix ``J(σ) = ∂(N, M, n2z, m2z)(σ) /
    ∂(N, M, n2z, m2z)(0)`` (base values varied, base clamped) is the identity at the base; the equilibrium is
    stable when ``J(σ)`` stays regular on ``(0, L]``. It is computed by finite differences of the trajectory
    along the whole rod; a real eigenvalue of ``J`` crossing zero (to ``-tol``) marks the conjugate point (a
    determinant test alone misses the double root of a round rod bending in two planes at once; a complex
    pair that turns real and negative without passing zero, as on an elastic foundation, is not a crossing).
    For an Euler column this is ``cos(√(P/EI) σ) ≤ 0``, i.e. the Euler load ``π² EI / (4 L²)``.

    Parameters
    ----------
    x : (8,) float, converged base unknowns; the other inputs as the kernel's (SI units).
    """
    n = 6 if coupled else _kernel.NX
    rows = int(nsteps.sum()) + 1
    length = float(sec[-1, 1])
    base = np.empty((rows, _kernel.NSTATE))
    _kernel.integrate(x, sec, nsteps, rdir, lam, fext, coupled, base, True)
    scale = np.array([1.0, 1.0, 1.0, 1 / length, 1 / length, 1 / length, 1.0, 1 / length])[:n]  # N
    fscale = 1.0 + float(np.max(np.abs(x[:3]))) + float(np.sum(lam))
    jac = np.empty((rows, n, n))
    pert = np.empty_like(base)
    for c in range(n):
        xt = x.copy()
        eps = 1e-6 * fscale / scale[c]
        xt[c] += eps
        _kernel.integrate(xt, sec, nsteps, rdir, lam, fext, coupled, pert, True)
        jac[:, :, c] = (pert[:, _LOAD_ROWS[:n]] - base[:, _LOAD_ROWS[:n]]) / eps
    jac *= scale[None, :, None] / scale[None, None, :]  # a similarity: same eigenvalues, O(1) entries
    if not np.all(np.isfinite(jac)):
        return 0.0
    ev = np.linalg.eigvals(jac)
    real = np.abs(ev.imag) <= 1e-9 + 1e-6 * np.abs(ev)
    negative = np.sum(real & (ev.real <= -tol), axis=1)
    complex_ = np.sum(~real, axis=1)
    # an eigenvalue crossing zero adds a negative real one without a complex pair turning real
    crossing = np.diff(negative) > np.maximum(np.diff(-complex_), 0)
    bad = np.nonzero(np.r_[negative[0] > 0, crossing])[0]
    if len(bad) == 0:
        return None
    s = np.concatenate([[0.0], np.cumsum(np.repeat((sec[:, 1] - sec[:, 0]) / nsteps, nsteps))])
    return float(s[bad[0]] * 1e3)


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
        Largest number of continuation steps tried in free space (1, 4, 16, ... up to this); with external
        loads at least :data:`EXTERNAL_MAX_RAMP`.
    max_step_error_mm : float
        Largest tip change allowed when the RK4 step is halved (step doubling, :func:`integration_error`), mm.
    max_frame_error : float
        Largest departure of the integrated directors from orthonormality, ``max |RᵀR − I|``.
    """

    steps_per_mm: float = 0.5
    tol: float = 1e-10
    max_iter: int = 25
    max_ramp: int = 64
    max_step_error_mm: float = 0.05
    max_frame_error: float = 1e-3

    name: ClassVar[str] = ""
    coupled: ClassVar[bool] = True
    capabilities: ClassVar[Capabilities]

    def __post_init__(self) -> None:
        if not (self.steps_per_mm > 0 and self.tol > 0 and self.max_iter >= 1 and self.max_ramp >= 1
                and self.max_step_error_mm > 0 and self.max_frame_error > 0):
            raise ValueError("steps_per_mm, tol, max_step_error_mm and max_frame_error must be positive, max_iter "
                             "and max_ramp at least 1")

    def solve(self, design: RodDesign, loads: Loads, initial_guess: np.ndarray | None = None,
              *, continuation: bool = True, inserted_mm: float | None = None) -> RodPath | FailedSolve:
        """Solve ``design`` under ``loads`` by shooting.

        Parameters
        ----------
        design, loads : RodDesign, Loads
            As in :meth:`reachplan.rod_model.protocol.RodModel.solve`.
        initial_guess : (8,) float or None
            Base unknowns ``N(0)`` (N, world), ``M(0)`` (N·m, world), ``n2z(0)`` (N), ``m2z(0)`` (N·m);
            default :func:`linear_guess` (exact in free space).
        continuation : bool
            Ramp the loads from zero (always first when external loads act; in free space when the direct
            solve fails). Without it one Newton solve from the initial guess, still checked.
        inserted_mm : float or None
            Solve only the distal ``inserted_mm`` of the rod, clamped where it enters (the template); arc
            lengths and positions are then measured from there. None: the whole rod, clamped at its base.

        Returns
        -------
        RodPath or FailedSolve
            Positions in mm in the needle frame, sampled at the RK4 steps. A converged shape is returned only
            when its integration error estimate (:func:`integration_error`) is within ``max_step_error_mm`` and
            its frames are orthonormal, and, when external loads act, when it is stable
            (:func:`conjugate_point`); otherwise a :class:`FailedSolve` says which check failed (or the
            residual reached when shooting does not converge).

        Raises
        ------
        UnsupportedLoadError
            Not one tension per tendon.
        ValueError
            An ``initial_guess`` that is not 8 finite numbers.
        """
        t0 = time.perf_counter()
        check_loads(self.name, self.capabilities, design, loads)
        sec = section_table(design, loads.history)
        if inserted_mm is not None:
            sec = _distal(sec, inserted_mm * 1e-3)
        nsteps = _steps(sec, self.steps_per_mm)
        predictor = linear_guess(design, loads, None if inserted_mm is None else inserted_mm * 1e-3)
        x0 = predictor if initial_guess is None else np.array(initial_guess, dtype=float)
        if x0.shape != (_kernel.NX,) or not np.all(np.isfinite(x0)):
            raise ValueError("initial_guess must be 8 finite numbers: N(0), M(0), n2z(0), m2z(0)")
        traj = np.empty((int(nsteps.sum()) + 1, _kernel.NSTATE))
        fext = np.array(loads.distributed_n_per_m)
        if loads.foundation is not None:
            fext = np.r_[fext, loads.foundation.packed_si()]
        args = (sec, nsteps, design.tendon_unit_offsets(loads.roll_deg), np.array(loads.tensions_n), fext,
                np.array(loads.tip_force_n), np.array(loads.tip_moment_nm))
        # With external loads the direct solve may land on any branch: follow the load from zero instead
        # (continuation), finer and finer until the equilibrium found is stable.
        cap = max(self.max_ramp, EXTERNAL_MAX_RAMP) if loads.has_external else self.max_ramp
        # a caller's initial guess (a warm start) is tried first, then continuation from zero
        first = EXTERNAL_FIRST_RAMP if loads.has_external and continuation and initial_guess is None else 1
        unstable = ""
        if loads.foundation is not None and multiple_shooting.growth(sec, fext) > multiple_shooting.SINGLE_GROWTH:
            return self._solve_multiple(design, loads, x0, sec, args, t0)
        while True:
            x = x0.copy()
            status, res, iters, ramp = _kernel.shoot(x, *args, self.coupled, self.tol, self.max_iter,
                                                     cap if continuation else 1, traj, first, predictor)
            ms = (time.perf_counter() - t0) * 1e3
            if status != _kernel.OK and loads.foundation is not None:
                return self._solve_multiple(design, loads, x0, sec, args, t0)
            if status != _kernel.OK:
                why = {_kernel.SINGULAR: "singular shooting Jacobian", _kernel.NON_FINITE: "non-finite state"}
                reason = (f"{why.get(status, 'shooting did not converge')}: tip residual {res:.2e} N after {iters} "
                          f"Newton iterations, continuation up to {ramp} load steps")
                if unstable:
                    reason = f"{unstable}; finer continuation: {reason}"
                return FailedSolve(self.name, reason, float(res), ms, loads.tensions_n, loads.roll_deg)
            step_mm, frame_err = integration_error(x, traj, *args[:5], self.coupled)
            if not (step_mm <= self.max_step_error_mm and frame_err <= self.max_frame_error):
                ms = (time.perf_counter() - t0) * 1e3
                reason = (f"integration error: tip moves {step_mm:.2e} mm when the RK4 step is halved (limit "
                          f"{self.max_step_error_mm:g} mm), frames off orthonormal by {frame_err:.1e}; the load is "
                          "beyond what this resolution integrates (raise steps_per_mm or lower the load)")
                return FailedSolve(self.name, reason, float(res), ms, loads.tensions_n, loads.roll_deg)
            if not loads.has_external:
                break  # tendons alone: N = M = 0 along the rod, the Jacobi fields never degenerate
            at_mm = conjugate_point(x, *args[:5], self.coupled)
            if at_mm is None:
                break
            unstable = (f"unstable equilibrium: conjugate point at s = {at_mm:.1f} mm (shooting Jacobian "
                        f"singular there) after continuation in {ramp} load steps")
            if not continuation or ramp * 4 > cap:
                ms = (time.perf_counter() - t0) * 1e3
                return FailedSolve(self.name, unstable + " (a load beyond a buckling or snap-through load?)",
                                   float(res), ms, loads.tensions_n, loads.roll_deg)
            first = ramp * 4
        ms = (time.perf_counter() - t0) * 1e3
        s = np.concatenate([[0.0], np.concatenate([np.linspace(a, b, n + 1)[1:] for (a, b), n in
                                                   zip(sec[:, :2], nsteps, strict=True)])]) * 1e3
        frames = traj[:, 3:12].reshape(-1, 3, 3)
        return RodPath(self.name, s, traj[:, 0:3] * 1e3, frames, float(res), ms, int(iters), loads.tensions_n,
                       loads.roll_deg, None if self.coupled else traj[:, 18], x.copy())

    def _solve_multiple(self, design: RodDesign, loads: Loads, x0: np.ndarray, sec: np.ndarray,
                        args: tuple[np.ndarray, ...], t0: float) -> RodPath | FailedSolve:
        """Solve on an elastic foundation by multiple shooting (:mod:`reachplan.rod_model.multiple_shooting`).

        The checks are those of single shooting: the residual, each leg's step-doubling error and the frames'
        orthonormality. The equilibrium is stable without a conjugate-point test when the foundation is the
        only external load: its second variation is the free rod's under tendon loads (never degenerate) plus
        the foundation's, which is non-negative; with a tip force as well the conjugate-point test runs.
        """
        ms = multiple_shooting.solve(x0, sec, self.steps_per_mm, args[2], args[3], args[4], args[5], args[6],
                                     self.coupled, self.tol)
        elapsed = (time.perf_counter() - t0) * 1e3
        if ms.status != _kernel.OK:
            return FailedSolve(self.name, f"multiple shooting ({ms.legs} legs) did not converge: residual "
                               f"{ms.residual_n:.2e} N after {ms.iterations} Newton iterations", ms.residual_n,
                               elapsed, loads.tensions_n, loads.roll_deg)
        r = ms.traj[:, 3:12].reshape(-1, 3, 3)
        frame_err = float(np.max(np.abs(np.einsum("nki,nkj->nij", r, r) - np.eye(3))))
        if not (ms.step_error_mm <= self.max_step_error_mm and frame_err <= self.max_frame_error):
            return FailedSolve(self.name, f"integration error (multiple shooting): a leg's end moves "
                               f"{ms.step_error_mm:.2e} mm when the RK4 step is halved (limit "
                               f"{self.max_step_error_mm:g} mm), frames off orthonormal by {frame_err:.1e}; "
                               "raise steps_per_mm", ms.residual_n, elapsed, loads.tensions_n, loads.roll_deg)
        if any(any(v) for v in (loads.tip_force_n, loads.tip_moment_nm)):
            nsteps = _steps(sec, self.steps_per_mm)
            at_mm = conjugate_point(ms.x, sec, nsteps, args[2], args[3], args[4], self.coupled)
            if at_mm is not None:
                return FailedSolve(self.name, f"unstable equilibrium: conjugate point at s = {at_mm:.1f} mm "
                                   "(multiple shooting)", ms.residual_n, elapsed, loads.tensions_n, loads.roll_deg)
        frames = ms.traj[:, 3:12].reshape(-1, 3, 3)
        return RodPath(self.name, (ms.s_m - sec[0, 0]) * 1e3, ms.traj[:, 0:3] * 1e3, frames, ms.residual_n,
                       (time.perf_counter() - t0) * 1e3, ms.iterations, loads.tensions_n, loads.roll_deg,
                       None if self.coupled else ms.traj[:, 18], ms.x.copy())

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
        planar_only=False, twist=False, several_tendons=True, external_load=True, large_deflection=True,
        friction=True)


@dataclass(frozen=True)
class TwoTubeCosserat(_ShootingModel):
    """Two-tube Cosserat model (stylet and needle on one centreline, relative twist θ and dilation β)."""

    name: ClassVar[str] = "two_tube_cosserat"
    coupled: ClassVar[bool] = False
    capabilities: ClassVar[Capabilities] = replace(CosseratRod.capabilities, twist=True)


COSSERAT_ROD = CosseratRod()
TWO_TUBE_COSSERAT = TwoTubeCosserat()
