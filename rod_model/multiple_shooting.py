"""Multiple shooting for a rod held by a stiff elastic foundation (a needle deep in stiff tissue).

Single shooting integrates the whole rod from the clamp: on a Winkler foundation of modulus ``k`` the
homogeneous solutions grow like ``exp(β s)`` with ``β = (k / 4 EI)^(1/4)`` (Hetényi, *Beams on Elastic
Foundation*, 1946, ch. 2), so for ``∫β ds`` beyond about 6 a base guess off by 1e-6 sends the tip far away and
Newton's basin shrinks below what the line search finds (seen: 10 MPa tissue at 36 mm of insertion, 3 MPa at
84 mm). Here the rod is cut into legs of ``∫β ds <=`` :data:`LEG_GROWTH` each; the unknowns are the base
loads and the full state at the start of every further leg; the equations are the tip conditions and the
continuity of the state across each cut (Keller, *Numerical Methods for Two-Point Boundary-Value Problems*,
1968; Ascher, Mattheij & Russell, 1995, ch. 4). Newton with a finite-difference Jacobian (each column
re-integrates one leg) and a backtracking line search; the legs are integrated by the same compiled RK4 as
single shooting (:func:`reachplan.rod_model._kernel.integrate_from`).
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass

import numpy as np

from reachplan.rod_model import _kernel

#: Largest growth exponent ``∫β ds`` of one leg (the error amplification ``e^2 ≈ 7`` per leg).
LEG_GROWTH = 2.0
#: Above this growth exponent over the whole rod single shooting is not tried.
SINGLE_GROWTH = 5.0
#: Unknowns per cut: p (3), rotation vector (3), N (3), M (3), θ, n2z, m2z, φ.
_NODE = 16


@dataclass(frozen=True)
class MultipleShot:
    """A multiple-shooting solve.

    Parameters
    ----------
    status : int
        A :mod:`reachplan.rod_model._kernel` status (``OK``, ``NOT_CONVERGED``, ``NON_FINITE``).
    residual_n : float
        Largest scaled residual (tip conditions and continuity), N.
    iterations : int
        Newton iterations.
    x : (8,) float
        Base unknowns ``N(0), M(0), n2z(0), m2z(0)`` (SI, base frame).
    traj : (n + 1, 23) float
        Kernel states along the rod (all legs, the cuts once).
    s_m : (n + 1,) float
        Arc length of each row of ``traj``, m.
    legs : int
        Number of legs.
    step_error_mm : float
        Largest tip change of a leg when its RK4 step is halved (from the converged start state), mm.
    """

    status: int
    residual_n: float
    iterations: int
    x: np.ndarray
    traj: np.ndarray
    s_m: np.ndarray
    legs: int
    step_error_mm: float


def growth(sec: np.ndarray, fext: np.ndarray) -> float:
    """Growth exponent ``∫ (k / 4 EI)^(1/4) ds`` of a section table under the foundation packed in ``fext``.

    ``k`` is the foundation's largest modulus (N/m²), ``EI = ei1 + ei2`` per section (N·m²); 0 without a
    foundation.
    """
    m = (len(fext) - 3) // 6
    if m == 0:
        return 0.0
    k = float(np.max(fext[3:].reshape(m, 6)[:, 1]))
    return float(np.sum((k / (4.0 * (sec[:, 2] + sec[:, 6]))) ** 0.25 * (sec[:, 1] - sec[:, 0])))


def _split(sec: np.ndarray, steps_per_mm: float, legs: int) -> list[tuple[np.ndarray, np.ndarray]]:
    """Cut the section table into ``legs`` equal lengths: (table, RK4 steps per row) per leg."""
    cuts = np.linspace(sec[0, 0], sec[-1, 1], legs + 1)
    out = []
    for a, b in itertools.pairwise(cuts):
        rows = sec[(sec[:, 1] > a + 1e-12) & (sec[:, 0] < b - 1e-12)].copy()
        rows[0, 0], rows[-1, 1] = a, b
        n = np.array([max(2, math.ceil((e - s) * 1e3 * steps_per_mm)) for s, e in rows[:, :2]], dtype=np.int64)
        out.append((rows, n))
    return out


def _rotation(w: np.ndarray) -> np.ndarray:
    """Rotation matrix of the rotation vector ``w`` (3,), rad (Rodrigues)."""
    a = float(np.linalg.norm(w))
    k = np.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])
    if a < 1e-12:
        return np.eye(3) + k
    return np.eye(3) + math.sin(a) / a * k + (1 - math.cos(a)) / a**2 * (k @ k)


def _frame_along(t: np.ndarray) -> np.ndarray:
    """Return the rotation taking ``e3`` to the unit vector ``t`` by the shortest arc (directors as columns)."""
    e3 = np.array([0.0, 0.0, 1.0])
    axis = np.cross(e3, t)
    s = float(np.linalg.norm(axis))
    return _rotation(axis / s * math.atan2(s, float(t @ e3))) if s > 1e-12 else np.eye(3)


def _track_at(fext: np.ndarray, s_m: float) -> tuple[np.ndarray, np.ndarray]:
    """Foundation track position (3,) m and its unit tangent at arc length ``s_m``."""
    m = (len(fext) - 3) // 6
    nodes = fext[3:].reshape(m, 6)

    def at(s: float) -> np.ndarray:
        return np.array([np.interp(s, nodes[:, 0], nodes[:, 2 + i]) for i in range(3)])

    h = 5e-4
    t = at(s_m + h) - at(s_m - h)
    n = float(np.linalg.norm(t))
    return at(s_m), (t / n if n > 0 else np.array([0.0, 0.0, 1.0]))


def solve(x0: np.ndarray, sec: np.ndarray, steps_per_mm: float, rdir: np.ndarray, lam: np.ndarray,
          fext: np.ndarray, ftip: np.ndarray, ltip: np.ndarray, coupled: bool, tol: float,
          max_iter: int = 40) -> MultipleShot:
    """Solve the clamped rod by multiple shooting.

    Parameters
    ----------
    x0 : (8,) float
        Guess of the base unknowns (SI, base frame); the cut states are guessed on the foundation's track
        (position and tangent there, loads zero).
    sec, rdir, lam, fext, ftip, ltip, coupled
        The kernel's inputs (:mod:`reachplan.rod_model._kernel`, SI); ``fext`` should hold a foundation.
    steps_per_mm : float
        RK4 steps per millimetre in every leg.
    tol : float
        Convergence threshold relative to the load scale ``1 N + Σλ + |tip force|``.
    max_iter : int
        Newton iterations.

    Returns
    -------
    MultipleShot
    """
    length = float(sec[-1, 1] - sec[0, 0])
    n_legs = max(2, math.ceil(growth(sec, fext) / LEG_GROWTH))
    parts = _split(sec, steps_per_mm, n_legs)
    fscale = 1.0 + float(np.sum(lam) + np.sum(np.abs(ftip)) + np.sum(np.abs(ltip)) / length)
    scale = np.r_[np.full(3, length), np.ones(3), np.full(3, fscale), np.full(3, fscale * length),
                  1.0, fscale, fscale * length, 1.0]
    refs: list[np.ndarray] = []
    z = [np.array(x0, dtype=float)]
    for rows, _ in parts[1:]:
        p, t = _track_at(fext, float(rows[0, 0]))
        refs.append(_frame_along(t))
        z.append(np.r_[p, np.zeros(_NODE - 3)])
    scratch = [np.empty((int(n.sum()) + 1, _kernel.NSTATE)) for _, n in parts]
    legs = _Legs(parts, refs, scratch, rdir, lam, fext, ftip, ltip, coupled, length, fscale, scale)
    z, res, it, status = _newton(legs, z, tol, max_iter)
    traj, s_m, step_err = _trajectory(legs, z)
    return MultipleShot(status, res, it, z[0].copy(), traj, s_m, n_legs,
                        step_err if math.isfinite(step_err) else math.inf)


@dataclass(frozen=True)
class _Legs:
    """The rod cut into legs, with what every leg's integration and residual needs (kernel inputs, SI).

    Parameters
    ----------
    parts : list of (table, steps)
        Each leg's section rows and RK4 steps per row (:func:`_split`).
    refs : list of (3, 3) float
        Reference frame of each cut (legs 1, 2, ...): a cut's rotation unknown is relative to it.
    scratch : list of (n_j + 1, NSTATE) float
        Trajectory buffer of each leg, overwritten by every integration.
    rdir, lam, fext, ftip, ltip, coupled
        The kernel's inputs (:mod:`reachplan.rod_model._kernel`).
    length : float, m
        Length of the rod.
    fscale : float, N
        Load scale ``1 N + Σλ + |tip force| + |tip moment| / length``.
    scale : (16,) float
        Scale of each cut unknown (m, rad, N, N·m, ...).
    """

    parts: list[tuple[np.ndarray, np.ndarray]]
    refs: list[np.ndarray]
    scratch: list[np.ndarray]
    rdir: np.ndarray
    lam: np.ndarray
    fext: np.ndarray
    ftip: np.ndarray
    ltip: np.ndarray
    coupled: bool
    length: float
    fscale: float
    scale: np.ndarray

    @property
    def n(self) -> int:
        """Number of legs."""
        return len(self.parts)

    def start(self, j: int, zj: np.ndarray) -> np.ndarray:
        """Return the kernel state at the start of leg ``j`` from its unknowns ``zj``."""
        if j == 0:
            y = np.zeros(_kernel.NSTATE)
            y[[3, 7, 11]] = 1.0
            y[12:18] = zj[0:6]
            y[19:21] = zj[6:8]
        else:
            y = np.empty(_kernel.NSTATE)
            y[0:3] = zj[0:3]
            y[3:12] = (self.refs[j - 1] @ _rotation(zj[3:6])).ravel()
            y[12:22] = zj[6:16]
        y[22] = self.parts[j][0][0, 0]
        return y

    def end(self, j: int, zj: np.ndarray, record: bool = False, refine: int = 1) -> np.ndarray:
        """Integrate leg ``j`` from its unknowns ``zj`` (``refine`` times the steps) and return its end state."""
        rows, n = self.parts[j]
        traj = self.scratch[j] if refine == 1 else np.empty((int(n.sum()) * refine + 1, _kernel.NSTATE))
        return _kernel.integrate_from(self.start(j, zj), rows, n * refine, self.rdir, self.lam, self.fext,
                                      self.coupled, traj, record)

    def block(self, j: int, e: np.ndarray, nxt: np.ndarray | None) -> np.ndarray:
        """Residual of leg ``j`` from its end state: continuity with the next start, or the tip conditions."""
        if nxt is None:
            r = np.empty(_kernel.NX)
            _kernel.residual(e, self.ftip, self.ltip, self.length, self.coupled, r)
            return r
        s = self.start(j + 1, nxt)
        ra = s[3:12].reshape(3, 3).T @ e[3:12].reshape(3, 3)
        rot = 0.5 * np.array([ra[2, 1] - ra[1, 2], ra[0, 2] - ra[2, 0], ra[1, 0] - ra[0, 1]])
        d = np.r_[e[0:3] - s[0:3], rot, e[12:22] - s[12:22]]
        return d * self.fscale / self.scale

    def residuals(self, zs: list[np.ndarray], ends: list[np.ndarray]) -> np.ndarray:
        """All residuals: the continuity at every cut, then the tip conditions."""
        return np.concatenate([self.block(j, ends[j], zs[j + 1] if j + 1 < self.n else None) for j in range(self.n)])


def _newton(legs: _Legs, z: list[np.ndarray], tol: float,
            max_iter: int) -> tuple[list[np.ndarray], float, int, int]:
    """Newton's method with a backtracking line search on the unknowns of every leg.

    Parameters
    ----------
    legs : _Legs
        The cut rod.
    z : list of (8,) and (16,) float
        Initial unknowns: the base loads, then the state at each cut.
    tol : float
        Convergence threshold relative to the load scale.
    max_iter : int
        Newton iterations.

    Returns
    -------
    z : list of arrays
        The last accepted unknowns.
    residual : float
        Their largest scaled residual, N (inf when not finite).
    iterations : int
        Newton iterations done.
    status : int
        ``OK``, ``NOT_CONVERGED`` or ``NON_FINITE`` (:mod:`reachplan.rod_model._kernel`).
    """
    ends = [legs.end(j, z[j]) for j in range(legs.n)]
    r = legs.residuals(z, ends)
    res = float(np.max(np.abs(r))) if np.all(np.isfinite(r)) else math.inf
    it = 0
    status = _kernel.OK if res <= tol * legs.fscale else _kernel.NOT_CONVERGED
    while status != _kernel.OK and it < max_iter and math.isfinite(res):
        it += 1
        dz = np.linalg.lstsq(_jacobian(legs, z, ends, r), -r, rcond=None)[0]
        offs = _offsets(legs.n)[0]
        alpha = 1.0
        improved = False
        for _ in range(20):
            zt_all = [z[j] + alpha * dz[offs[j]:offs[j + 1]] for j in range(legs.n)]
            ends_t = [legs.end(j, zt_all[j]) for j in range(legs.n)]
            rt = legs.residuals(zt_all, ends_t)
            rn = float(np.max(np.abs(rt))) if np.all(np.isfinite(rt)) else math.inf
            if rn < res:
                improved = True
                break
            alpha *= 0.5
        if not improved:
            break
        z, ends, r, res = zt_all, ends_t, rt, rn
        status = _kernel.OK if res <= tol * legs.fscale else _kernel.NOT_CONVERGED
    if not math.isfinite(res):
        status = _kernel.NON_FINITE
    return z, res, it, status


def _offsets(n_legs: int) -> tuple[np.ndarray, np.ndarray, list[int]]:
    """Where each leg's unknowns and residuals start.

    Returns
    -------
    offs : (n_legs + 1,) int
        Unknowns: the base loads, then one cut state per further leg.
    roffs : (n_legs + 1,) int
        Residuals: the continuity at each cut, then the tip conditions.
    sizes : list of int
        Number of unknowns of each leg.
    """
    sizes = [_kernel.NX] + [_NODE] * (n_legs - 1)
    offs = np.r_[0, np.cumsum(sizes)]
    roffs = np.r_[0, np.cumsum([_NODE] * (n_legs - 1) + [_kernel.NX])]
    return offs, roffs, sizes


def _jacobian(legs: _Legs, z: list[np.ndarray], ends: list[np.ndarray], r: np.ndarray) -> np.ndarray:
    """Return the Jacobian of the residuals by forward differences, one leg re-integrated per column.

    A leg's unknowns move its own residual block and, for a cut, the continuity of the previous leg.
    """
    offs, roffs, sizes = _offsets(legs.n)
    fscale, length = legs.fscale, legs.length
    jac = np.zeros((len(r), offs[-1]))
    for j in range(legs.n):
        eps = 1e-7 * (np.r_[np.full(3, fscale), np.full(3, fscale * length), fscale, fscale * length]
                      if j == 0 else legs.scale)
        for c in range(sizes[j]):
            zt = z[j].copy()
            zt[c] += eps[c]
            et = legs.end(j, zt)
            rows_j = slice(roffs[j], roffs[j + 1])  # leg j's own residual block
            jac[rows_j, offs[j] + c] = (legs.block(j, et, z[j + 1] if j + 1 < legs.n else None) - r[rows_j]) / eps[c]
            if j > 0:  # the previous leg's continuity sees this start
                prev = slice(roffs[j - 1], roffs[j])
                jac[prev, offs[j] + c] = (legs.block(j - 1, ends[j - 1], zt) - r[prev]) / eps[c]
    return jac


def _trajectory(legs: _Legs, z: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray, float]:
    """Record the states along every leg and estimate the step error by re-integrating with twice the steps.

    Returns
    -------
    traj : (n + 1, 23) float
        Kernel states along the rod (all legs, the cuts once).
    s_m : (n + 1,) float
        Arc length of each row, m.
    step_error_mm : float
        Largest change of a leg's end position when its RK4 steps are doubled, mm.
    """
    pieces, s_pieces, step_err = [], [], 0.0
    for j, (rows, n) in enumerate(legs.parts):
        e = legs.end(j, z[j], record=True)
        traj = legs.scratch[j].copy()
        fine = legs.end(j, z[j], refine=2)
        step_err = max(step_err, float(np.linalg.norm(fine[0:3] - e[0:3])) * 1e3)
        s = np.concatenate([[rows[0, 0]], np.concatenate([np.linspace(a, b, k + 1)[1:]
                                                          for (a, b), k in zip(rows[:, :2], n, strict=True)])])
        pieces.append(traj if j == 0 else traj[1:])
        s_pieces.append(s if j == 0 else s[1:])
    return np.concatenate(pieces), np.concatenate(s_pieces), step_err
