"""Second, independent solver of the two-tube (and single-rod) Cosserat boundary-value problem by collocation.

The solver is :func:`scipy.integrate.solve_bvp`.

Same equations as :mod:`reachplan.rod_model.cosserat` (see there), re-implemented vectorised in numpy in
millimetre / newton units, solved on the whole rod at once (4th-order Lobatto IIIA collocation with mesh
refinement, no shooting). Each section of constant properties is mapped onto ``τ ∈ [0, 1]`` as its own block of
21 states so that the jumps of stiffness and moment arm fall on block boundaries; the blocks are tied by
continuity. It exists to check the shooting solver (they must agree to ≤ 1 µm) and as a fallback; it is much slower.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import ClassVar

import numpy as np
from scipy.integrate import solve_bvp

from reachplan.rod_model.cosserat import _steps, conjugate_point, section_table
from reachplan.rod_model.design import Loads, RodDesign
from reachplan.rod_model.errors import UnsupportedLoadError
from reachplan.rod_model.protocol import Capabilities, check_loads
from reachplan.rod_model.result import FailedSolve, RodPath

NS = 21


def _strains(y: np.ndarray, sec: np.ndarray, r: np.ndarray, lam: np.ndarray,
             coupled: bool) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Return u (3, m) 1/mm, v (3, m), u2z (m,) 1/mm, beta (m,) from states y (21, m) (mm, N, N·mm units)."""
    ei1, gj1, ea1, ga1, ei2, gj2, ea2, ga2 = sec[2:10]
    rot = y[3:12].reshape(3, 3, -1)  # rot[i, j] = R_ij
    nb = np.einsum("ijm,im->jm", rot, y[12:15])
    mb = np.einsum("ijm,im->jm", rot, y[15:18])
    n2z, m2z = y[19], y[20]
    m = y.shape[1]
    u = np.zeros((3, m))
    v = np.zeros((3, m))
    v[2] = 1.0
    beta = np.ones(m)
    u2z = np.zeros(m)
    rx, ry = r[:, 0, None], r[:, 1, None]  # (k, 1); tendon offsets have no z component
    for _ in range(4):
        tx = v[0] - u[2] * ry  # tendon tangent v + u x r, (k, m)
        ty = v[1] + u[2] * rx
        tz = v[2] + u[0] * ry - u[1] * rx
        w = lam[:, None] / np.sqrt(tx * tx + ty * ty + tz * tz)
        tx, ty, tz = w * tx, w * ty, w * tz
        ft = np.stack([tx.sum(0), ty.sum(0), tz.sum(0)])
        mt = np.stack([(ry * tz).sum(0), (-rx * tz).sum(0), (rx * ty - ry * tx).sum(0)])
        nr, mr = nb - ft, mb - mt
        u[:2] = mr[:2] / (ei1 + ei2)
        if coupled:
            v[2] = 1.0 + nr[2] / (ea1 + ea2)
            v[:2] = nr[:2] / (ga1 + ga2)
            u[2] = mr[2] / (gj1 + gj2)
            u2z = u[2]
        else:
            v[2] = 1.0 + (nr[2] - n2z) / ea1
            beta = (1.0 + n2z / ea2) / v[2]
            v[:2] = nr[:2] / (ga1 + beta * ga2)
            u[2] = (mr[2] - m2z) / gj1
            u2z = m2z / gj2
    return u, v, u2z, beta


def _block_rhs(y: np.ndarray, sec: np.ndarray, r: np.ndarray, lam: np.ndarray, fext: np.ndarray,
               coupled: bool) -> np.ndarray:
    u, v, u2z, beta = _strains(y, sec, r, lam, coupled)
    rot = y[3:12].reshape(3, 3, -1)
    dy = np.zeros_like(y)
    dp = np.einsum("ijm,jm->im", rot, v)
    dy[0:3] = dp
    ux = np.zeros((3, 3, y.shape[1]))
    ux[0, 1], ux[0, 2], ux[1, 0], ux[1, 2], ux[2, 0], ux[2, 1] = -u[2], u[1], u[2], -u[0], -u[1], u[0]
    dy[3:12] = np.einsum("ijm,jkm->ikm", rot, ux).reshape(9, -1)
    dy[12:15] = -fext[:, None]
    n = y[12:15]
    dy[15] = -(dp[1] * n[2] - dp[2] * n[1])
    dy[16] = -(dp[2] * n[0] - dp[0] * n[2])
    dy[17] = -(dp[0] * n[1] - dp[1] * n[0])
    if not coupled:
        dy[18] = u2z - u[2]
        dy[19] = -sec[9] * beta * (u[0] * v[1] - u[1] * v[0]) - np.einsum("im,i->m", rot[:, 2], fext)
    return dy


@dataclass(frozen=True)
class CollocationCosserat:
    """The Cosserat BVP by collocation (``scipy.integrate.solve_bvp``).

    An independent cross-check of the shooting models (another discretisation and solver), slow.

    Parameters
    ----------
    coupled : bool
        ``False``: two-tube model; ``True``: single rod.
    tol : float
        ``solve_bvp`` collocation tolerance.
    nodes_per_section : int
        Initial mesh nodes per section.
    max_nodes : int
        Largest mesh ``solve_bvp`` may refine to.
    max_ramp : int
        Largest number of load-continuation steps.
    """

    coupled: bool = False
    tol: float = 1e-9
    nodes_per_section: int = 21
    max_nodes: int = 20000
    max_ramp: int = 8
    name: ClassVar[str] = "two_tube_collocation"
    capabilities: ClassVar[Capabilities] = Capabilities(planar_only=False, twist=True, several_tendons=True,
                                                        external_load=True, large_deflection=True)

    def solve(self, design: RodDesign, loads: Loads, initial_guess: np.ndarray | None = None,
              *, continuation: bool = True) -> RodPath | FailedSolve:
        """Solve ``design`` under ``loads`` by collocation.

        Parameters
        ----------
        design, loads : RodDesign, Loads
            As in :meth:`reachplan.rod_model.protocol.RodModel.solve`.
        initial_guess : (21 k, n_mesh) float, optional
            States of the k section blocks on a common mesh in ``τ ∈ [0, 1]`` (mm, N, N·mm); for the stability
            map only (default: the straight, unloaded rod).
        continuation : bool
            Ramp the loads from zero (2, 4, ... steps) when the direct solve fails.

        Returns
        -------
        RodPath or FailedSolve
            Positions in mm in the needle frame at the final mesh; ``iterations`` holds the continuation steps.

        Raises
        ------
        UnsupportedLoadError
            Not one tension per tendon.
        """
        t0 = time.perf_counter()
        check_loads(self.name, self.capabilities, design, loads)
        if loads.foundation is not None:
            raise UnsupportedLoadError(f"model {self.name} has no elastic foundation; use two_tube_cosserat")
        sec = section_table(design)
        sec_mm = _in_mm(sec)
        r = design.tendon_unit_offsets(loads.roll_deg)
        lam_full = np.array(loads.tensions_n)
        full = _Bvp(sec_mm, r, lam_full, np.array(loads.distributed_n_per_m) * 1e-3, np.array(loads.tip_force_n),
                    np.array(loads.tip_moment_nm) * 1e3, self.coupled)
        if initial_guess is None:
            tau = np.linspace(0.0, 1.0, self.nodes_per_section)
            y0 = _straight(sec_mm, tau)
        else:
            y0 = np.asarray(initial_guess, dtype=float)
            tau = np.linspace(0.0, 1.0, y0.shape[1])
        messages: list[str] = []
        ok, mesh, guess, res, ramp = self._continued(full, tau, y0, continuation, messages)
        ms = (time.perf_counter() - t0) * 1e3
        if not ok:
            why = messages[-1].rstrip(".") if messages else "no attempt"
            return FailedSolve(self.name, f"collocation did not converge: {why} (residual {res:.2e}, continuation "
                               f"up to {ramp // 2} load steps)", res, ms, loads.tensions_n, loads.roll_deg)
        if loads.has_external:  # the same Jacobi test as the shooting models, on the collocation's base values
            base = guess[:, 0]
            x = np.r_[base[12:15], base[15:18] * 1e-3, base[19], base[20] * 1e-3]
            at_mm = conjugate_point(x, sec, _steps(sec, 2.0), r, lam_full, np.array(loads.distributed_n_per_m),
                                    self.coupled)
            if at_mm is not None:
                return FailedSolve(self.name, f"unstable equilibrium: conjugate point at s = {at_mm:.1f} mm",
                                   res, ms, loads.tensions_n, loads.roll_deg)
        return self._path(sec_mm, mesh, guess, res, ms, ramp, loads)

    def _continued(self, full: _Bvp, tau: np.ndarray, y0: np.ndarray, continuation: bool,
                   messages: list[str]) -> tuple[bool, np.ndarray, np.ndarray, float, int]:
        """Solve at the full loads, ramping them from zero in 2, 4, ... steps while the solve fails.

        Parameters
        ----------
        full : _Bvp
            The problem at the full loads.
        tau, y0 : (n,) float and (21 k, n) float
            Initial mesh in ``τ ∈ [0, 1]`` and states on it.
        continuation : bool
            Ramp at all (else one direct attempt).
        messages : list of str
            ``solve_bvp``'s message of every attempt, appended to.

        Returns
        -------
        ok : bool
            The last ramp reached the full loads.
        mesh, states : (m,) float and (21 k, m) float
            The last solution (of the last step tried).
        residual : float
            Its residual.
        ramp : int
            Number of load steps of the last ramp tried.
        """
        ramp = 1
        res = np.inf
        ok = True
        mesh, guess = tau, y0
        while ramp <= (self.max_ramp if continuation else 1):
            mesh, guess = tau, y0
            ok = True
            for j in range(1, ramp + 1):
                ok, mesh, guess, res = self._solve_at(full.scaled(j / ramp), mesh, guess, messages)
                if not ok:
                    break
            if ok:
                break
            ramp *= 2
        return ok, mesh, guess, res, ramp

    def _solve_at(self, bvp: _Bvp, mesh: np.ndarray, guess: np.ndarray,
                  messages: list[str]) -> tuple[bool, np.ndarray, np.ndarray, float]:
        """Run ``solve_bvp`` once on ``bvp`` from ``guess``; success needs boundary and collocation residuals small.

        Returns
        -------
        ok : bool
            Converged, finite, boundary residual below 1e-8 and collocation residual below ``10 tol``.
        mesh, states : (m,) float and (21 k, m) float
            The solution ``solve_bvp`` returned.
        residual : float
            The larger of the two residuals (inf when not finite).
        """
        with np.errstate(all="ignore"):  # a diverging iterate is reported as a failure below
            sol = solve_bvp(bvp.fun, bvp.bc, mesh, guess, tol=self.tol, max_nodes=self.max_nodes, fun_jac=bvp.fun_jac)
        finite = bool(np.all(np.isfinite(sol.y)))
        with np.errstate(all="ignore"):
            bres = float(np.max(np.abs(bvp.bc(sol.y[:, 0], sol.y[:, -1])))) if finite else np.inf
        rms = float(np.max(sol.rms_residuals)) if finite and sol.rms_residuals is not None else np.inf
        res = max(bres, rms) if np.isfinite(bres) and np.isfinite(rms) else np.inf
        messages.append(str(sol.message))
        return bool(sol.success and finite and bres < 1e-8 and rms < 10 * self.tol), sol.x, sol.y, res

    def _path(self, sec_mm: np.ndarray, mesh: np.ndarray, states: np.ndarray, res: float, ms: float, ramp: int,
              loads: Loads) -> RodPath:
        """Join the section blocks of a solution into one path (positions and frames in mm, needle frame)."""
        k = len(sec_mm)
        lengths = sec_mm[:, 1] - sec_mm[:, 0]
        s = np.concatenate([sec_mm[i, 0] + mesh[(1 if i else 0):] * lengths[i] for i in range(k)])
        ys = np.concatenate([states[NS * i:NS * (i + 1), (1 if i else 0):] for i in range(k)], axis=1)
        keep = np.r_[True, np.diff(s) > 1e-12]
        frames = ys[3:12].T.reshape(-1, 3, 3)
        return RodPath(self.name, s[keep], ys[0:3].T[keep], frames[keep], res, ms, ramp, loads.tensions_n,
                       loads.roll_deg, None if self.coupled else ys[18][keep])


def _in_mm(sec: np.ndarray) -> np.ndarray:
    """Return a section table (SI, :func:`reachplan.rod_model.cosserat.section_table`) in mm and N units."""
    sec_mm = sec.copy()
    sec_mm[:, :2] *= 1e3
    sec_mm[:, 2:4] *= 1e6
    sec_mm[:, 6:8] *= 1e6
    sec_mm[:, 10] *= 1e3
    return sec_mm


def _straight(sec_mm: np.ndarray, tau: np.ndarray) -> np.ndarray:
    """Return the states (21 k, n) of the straight, unloaded rod on the mesh ``tau`` of every section block."""
    k = len(sec_mm)
    lengths = sec_mm[:, 1] - sec_mm[:, 0]
    y0 = np.zeros((NS * k, tau.size))
    for i in range(k):
        b = y0[NS * i:NS * (i + 1)]
        b[2] = sec_mm[i, 0] + tau * lengths[i]
        b[3] = b[7] = b[11] = 1.0
    return y0


@dataclass(frozen=True)
class _Bvp:
    """The rod's boundary-value problem for ``solve_bvp``: one block of 21 states per section, mm and N units.

    Parameters
    ----------
    sec_mm : (k, 11) float
        Section table in mm and N units (:func:`_in_mm`).
    r : (n_tendons, 3) float
        Tendon unit offsets (times ``sec_mm[i, 10]``, the moment arm of section ``i``, mm).
    lam : (n_tendons,) float, N
        Tendon tensions.
    fext : (3,) float, N/mm
        Distributed force.
    ftip, ltip : (3,) float, N and N·mm
        Tip force and moment.
    coupled : bool
        The tubes are bonded (no relative twist or sliding).
    """

    sec_mm: np.ndarray
    r: np.ndarray
    lam: np.ndarray
    fext: np.ndarray
    ftip: np.ndarray
    ltip: np.ndarray
    coupled: bool

    def scaled(self, f: float) -> _Bvp:
        """Return the problem with every load times ``f``."""
        return _Bvp(self.sec_mm, self.r, f * self.lam, f * self.fext, f * self.ftip, f * self.ltip, self.coupled)

    def fun(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Return d y / d τ (21 k, m) of every block at the states ``y`` (21 k, m)."""
        out = np.empty_like(y)
        lengths = self.sec_mm[:, 1] - self.sec_mm[:, 0]
        for i in range(len(self.sec_mm)):
            sl = slice(NS * i, NS * (i + 1))
            out[sl] = lengths[i] * _block_rhs(y[sl], self.sec_mm[i], self.sec_mm[i, 10] * self.r, self.lam, self.fext,
                                              self.coupled)
        return out

    def fun_jac(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Return the Jacobian (21 k, 21 k, m) of :meth:`fun` by forward differences.

        The blocks are independent: state ``q`` of every block is perturbed at once (21 evaluations, not 21 k).
        """
        k = len(self.sec_mm)
        f0 = self.fun(x, y)
        jac = np.zeros((y.shape[0], y.shape[0], y.shape[1]))
        for q in range(NS):
            h = 1e-7 * (1.0 + np.abs(y[q::NS]))
            yp = y.copy()
            yp[q::NS] += h
            df = (self.fun(x, yp) - f0)
            for i in range(k):
                jac[NS * i:NS * (i + 1), NS * i + q] = df[NS * i:NS * (i + 1)] / h[i]
        return jac

    def bc(self, ya: np.ndarray, yb: np.ndarray) -> np.ndarray:
        """Return the boundary residuals: clamped base, continuity between blocks, tip loads (and twist ends)."""
        k = len(self.sec_mm)
        res = [ya[0:3], ya[3:12] - np.eye(3).ravel(), ya[18:19]]
        for i in range(k - 1):
            res.append(ya[NS * (i + 1):NS * (i + 2)] - yb[NS * i:NS * (i + 1)])
        tip = yb[NS * (k - 1):]
        rz = tip[[5, 8, 11]]
        res += [tip[12:15] - self.ftip, tip[15:18] - self.ltip]
        if self.coupled:
            res.append(ya[19:21])
        else:
            res.append(np.array([tip[19] - rz @ self.ftip, tip[20] - rz @ self.ltip]))
        return np.concatenate(res)
