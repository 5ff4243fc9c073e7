"""Compiled kernel of the Cosserat models: right-hand side, RK4 integration, shooting with continuation.

Plain functions on arrays (SI units), compiled with numba when it is installed; without numba the very same
functions run as plain Python (slowly). The maths is documented in :mod:`reachplan.rod_model.cosserat`.

State ``y`` (22): ``p`` (3, world, m), ``R`` (9, row-major, stylet directors as columns), ``N`` (3, world, N),
``M`` (3, world, N·m), ``θ`` (relative twist of needle against stylet, rad), ``n2z`` (needle axial force, N),
``m2z`` (needle torsional moment, N·m), ``φ`` (wrap angle of the tendon routing from the base, rad), ``s`` (arc
length, m).
External distributed load ``fext`` (3 + 6m): a uniform force per length (3, world, N/m), then an optional elastic
foundation of m nodes ``s (m), k (N/m²), track (3, world, m), slip (m)`` (see :func:`foundation_force`).
Section table ``sec`` (k, 16): ``start, end, ei1, gj1, ea1, ga1, ei2, gj2, ea2, ga2, arm``, then friction:
``mu`` (capstan coefficient of the tendon on its routing), ``jf`` (joint friction arm: Coulomb coefficient ×
ball radius, m; 0 outside the joint section), ``d`` (+1 tension increasing, −1 decreasing), ``λr`` (proximal
tension of tendon 0 at the last reversal, N), ``κr`` (the section's curvature at the last reversal, 1/m).
Unknowns at the base ``x`` (8): ``N(0)``, ``M(0)``, ``n2z(0)``, ``m2z(0)`` (the last two unused when coupled).
"""

from __future__ import annotations

import os
from collections.abc import Callable
from typing import Any

import numpy as np

#: ``REACHPLAN_JIT=0`` in the environment when this module is imported: plain Python, numba not imported (for a
#: process that makes one solve, e.g. ``reachplan rod --tension N``: the solve takes about 50 ms in Python, while
#: importing numba and loading the cached machine code take about 0.8 s).
JIT_WANTED = os.environ.get("REACHPLAN_JIT", "1") != "0"
HAVE_NUMBA = False
if JIT_WANTED:
    try:
        from numba import njit as _njit

        HAVE_NUMBA = True
    except ImportError:  # pragma: no cover - exercised only without numba
        pass


def _jit(fn: Callable[..., Any]) -> Callable[..., Any]:
    """Compile ``fn`` with numba (cached on disk) when available; otherwise return it unchanged."""
    return _njit(cache=True)(fn) if HAVE_NUMBA else fn


NSTATE = 23
# record flags as numpy booleans: a Python True/False passed inside compiled code is typed as a literal, which
# compiled integrate() and integrate_from() twice more (seconds of the first run)
_RECORD, _NO_RECORD = np.True_, np.False_
NX = 8

# status codes of shoot()
OK = 0
NOT_CONVERGED = 1
SINGULAR = 2
NON_FINITE = 3


@_jit
def local_tension(lam0: float, j: int, sec: np.ndarray, phi: float) -> float:
    """Return the tension (N) of tendon ``j`` at wrap angle ``phi`` (rad) for the load-cell tension ``lam0``.

    Capstan law, see :func:`closure`.
    """
    mu = sec[11]
    if mu == 0.0 or lam0 == 0.0:
        return lam0
    lo = lam0 * np.exp(-mu * phi)
    hi = lam0 * np.exp(mu * phi)
    prev = sec[14] * np.exp(sec[13] * mu * phi) if j == 0 else 0.0
    return min(max(prev, lo), hi)


@_jit
def closure(y: np.ndarray, sec: np.ndarray, rdir: np.ndarray, lam: np.ndarray, coupled: bool,
             out: np.ndarray) -> None:
    """Compute the strains from the loads: ``out = (u (3), v (3), u2z, beta)`` in the stylet's body frame."""
    ei1, gj1, ea1, ga1, ei2, gj2, ea2, ga2, arm = (sec[2], sec[3], sec[4], sec[5], sec[6], sec[7], sec[8],
                                                     sec[9], sec[10])
    nb0 = y[3] * y[12] + y[6] * y[13] + y[9] * y[14]
    nb1 = y[4] * y[12] + y[7] * y[13] + y[10] * y[14]
    nb2 = y[5] * y[12] + y[8] * y[13] + y[11] * y[14]
    mb0 = y[3] * y[15] + y[6] * y[16] + y[9] * y[17]
    mb1 = y[4] * y[15] + y[7] * y[16] + y[10] * y[17]
    mb2 = y[5] * y[15] + y[8] * y[16] + y[11] * y[17]
    n2z = y[19]
    m2z = y[20]
    u0 = u1 = u2 = 0.0
    v0 = v1 = 0.0
    v2 = 1.0
    u2z = 0.0
    beta = 1.0
    ei = ei1 + ei2
    # Capstan friction (tendon sliding in its routing): with the load-cell (proximal) tension λ0 the local
    # tension lies within λ0 exp(∓μ φ) of the wrap angle φ; where the tendon sticks it keeps the profile of
    # the last reversal (``λr exp(d μ φ)``, exact for one reversal): clip(previous, λ0 e^{−μφ}, λ0 e^{μφ}).
    compression = 0.0
    if sec[12] > 0.0:
        for j in range(lam.shape[0]):
            compression += local_tension(lam[j], j, sec, y[21])
    for _ in range(4):  # fixed point on the tendon directions (coupling ~ λ/GA, λ·r²/EI ~ 1e-3)
        ft0 = ft1 = ft2 = 0.0
        mt0 = mt1 = mt2 = 0.0
        for j in range(lam.shape[0]):
            lamj = lam[j] if sec[11] == 0.0 else local_tension(lam[j], j, sec, y[21])
            if lamj == 0.0:
                continue
            rx = arm * rdir[j, 0]
            ry = arm * rdir[j, 1]
            # tendon tangent ~ v + u x r (r has no z component)
            tx = v0 - u2 * ry
            ty = v1 + u2 * rx
            tz = v2 + u0 * ry - u1 * rx
            nt = np.sqrt(tx * tx + ty * ty + tz * tz)
            tx, ty, tz = lamj * tx / nt, lamj * ty / nt, lamj * tz / nt
            ft0 += tx
            ft1 += ty
            ft2 += tz
            mt0 += ry * tz
            mt1 += -rx * tz
            mt2 += rx * ty - ry * tx
        nr0, nr1, nr2 = nb0 - ft0, nb1 - ft1, nb2 - ft2
        mr0, mr1, mr2 = mb0 - mt0, mb1 - mt1, mb2 - mt2
        u0 = mr0 / ei
        u1 = mr1 / ei
        if sec[12] > 0.0:
            # Coulomb friction in the ball joints: a moment jf·(stack compression) opposes any change of the
            # joint curvature; the curvature sticks at its value of the last reversal κr until the bending
            # moment has changed by twice the friction moment (play operator).
            um = np.sqrt(u0 * u0 + u1 * u1)
            if um > 0.0:
                slack = sec[12] * compression / ei
                ue = min(max(sec[15], um - slack), um + slack)
                ue = max(ue, 0.0)
                u0 *= ue / um
                u1 *= ue / um
        if coupled:
            v2 = 1.0 + nr2 / (ea1 + ea2)
            beta = 1.0
            v0 = nr0 / (ga1 + ga2)
            v1 = nr1 / (ga1 + ga2)
            u2 = mr2 / (gj1 + gj2)
            u2z = u2
        else:
            v2 = 1.0 + (nr2 - n2z) / ea1
            beta = (1.0 + n2z / ea2) / v2
            v0 = nr0 / (ga1 + beta * ga2)
            v1 = nr1 / (ga1 + beta * ga2)
            u2 = (mr2 - m2z) / gj1
            u2z = m2z / gj2
    out[0] = u0
    out[1] = u1
    out[2] = u2
    out[3] = v0
    out[4] = v1
    out[5] = v2
    out[6] = u2z
    out[7] = beta


@_jit
def foundation_force(y: np.ndarray, fext: np.ndarray) -> tuple[float, float, float]:
    """Return the distributed force (N/m, world frame) on the rod at state ``y``.

    The uniform part of ``fext`` plus the elastic foundation tied to its track: ``−k δ`` with ``δ`` the lateral
    offset (perpendicular to the rod's tangent) of the centreline from the track point at the same arc length,
    capped at ``k·slip`` (beyond the slip offset the tissue gives way: it cannot hold the rod harder). Node
    values are interpolated linearly in ``s``.
    """
    m = (fext.shape[0] - 3) // 6
    if m == 0:
        return fext[0], fext[1], fext[2]
    s = y[22]
    lo = 0
    hi = m - 1
    if s <= fext[3]:
        hi = 0
    elif s >= fext[3 + 6 * (m - 1)]:
        lo = m - 1
    else:
        while hi - lo > 1:
            mid = (lo + hi) // 2
            if fext[3 + 6 * mid] <= s:
                lo = mid
            else:
                hi = mid
    a = 3 + 6 * lo
    b = 3 + 6 * hi
    w = 0.0 if hi == lo else (s - fext[a]) / (fext[b] - fext[a])
    k = (1 - w) * fext[a + 1] + w * fext[b + 1]
    if k <= 0.0:
        return fext[0], fext[1], fext[2]
    dx = y[0] - ((1 - w) * fext[a + 2] + w * fext[b + 2])
    dy_ = y[1] - ((1 - w) * fext[a + 3] + w * fext[b + 3])
    dz = y[2] - ((1 - w) * fext[a + 4] + w * fext[b + 4])
    slip = (1 - w) * fext[a + 5] + w * fext[b + 5]
    t0, t1, t2 = y[5], y[8], y[11]  # d3
    along = dx * t0 + dy_ * t1 + dz * t2
    dx -= along * t0
    dy_ -= along * t1
    dz -= along * t2
    mag = np.sqrt(dx * dx + dy_ * dy_ + dz * dz)
    scale = k if mag <= slip else k * slip / mag
    return fext[0] - scale * dx, fext[1] - scale * dy_, fext[2] - scale * dz


@_jit
def rhs(y: np.ndarray, sec: np.ndarray, rdir: np.ndarray, lam: np.ndarray, fext: np.ndarray, coupled: bool,
         st: np.ndarray, dy: np.ndarray) -> None:
    closure(y, sec, rdir, lam, coupled, st)
    u0, u1, u2, v0, v1, v2, u2z, beta = st[0], st[1], st[2], st[3], st[4], st[5], st[6], st[7]
    fo0, fo1, fo2 = foundation_force(y, fext)
    # p' = R v
    for i in range(3):
        dy[i] = y[3 + 3 * i] * v0 + y[4 + 3 * i] * v1 + y[5 + 3 * i] * v2
    # R' = R [u]x  (row i: (R_i1 u2 - R_i2 u1, R_i2 u0 - R_i0 u2, R_i0 u1 - R_i1 u0))
    for i in range(3):
        r0, r1, r2 = y[3 + 3 * i], y[4 + 3 * i], y[5 + 3 * i]
        dy[3 + 3 * i] = r1 * u2 - r2 * u1
        dy[4 + 3 * i] = r2 * u0 - r0 * u2
        dy[5 + 3 * i] = r0 * u1 - r1 * u0
    dy[12] = -fo0
    dy[13] = -fo1
    dy[14] = -fo2
    # M' = -p' x N
    px, py, pz = dy[0], dy[1], dy[2]
    nx, ny, nz = y[12], y[13], y[14]
    dy[15] = -(py * nz - pz * ny)
    dy[16] = -(pz * nx - px * nz)
    dy[17] = -(px * ny - py * nx)
    if coupled:
        dy[18] = 0.0
        dy[19] = 0.0
    else:
        dy[18] = u2z - u2
        fz = y[5] * fo0 + y[8] * fo1 + y[11] * fo2  # (R^T f)_z
        dy[19] = -sec[9] * beta * (u0 * v1 - u1 * v0) - fz
    dy[20] = 0.0  # isotropic needle, no distributed torque: (u2 x m2)_z = (v2 x n2)_z = 0
    dy[21] = np.sqrt(u0 * u0 + u1 * u1)  # the tendon turns with the centreline (offset/radius ~1 % neglected)
    dy[22] = 1.0


@_jit
def integrate(x: np.ndarray, sec: np.ndarray, nsteps: np.ndarray, rdir: np.ndarray, lam: np.ndarray,
               fext: np.ndarray, coupled: bool, traj: np.ndarray, record: bool) -> np.ndarray:
    """RK4 from the base with unknowns ``x``; returns the tip state; fills ``traj`` (n+1, 21) if ``record``."""
    y = np.zeros(NSTATE)
    y[3] = 1.0
    y[7] = 1.0
    y[11] = 1.0
    for q in range(6):  # element loops, not slice assignment: numba's slice-shape error message alone costs
        y[12 + q] = x[q]  # seconds of the first compile (it compiles the whole unicode formatting machinery)
    y[19] = x[6]
    y[20] = x[7]
    y[22] = sec[0, 0]
    return integrate_from(y, sec, nsteps, rdir, lam, fext, coupled, traj, record)


@_jit
def integrate_from(y: np.ndarray, sec: np.ndarray, nsteps: np.ndarray, rdir: np.ndarray, lam: np.ndarray,
                   fext: np.ndarray, coupled: bool, traj: np.ndarray, record: bool) -> np.ndarray:
    """RK4 over ``sec`` from the full state ``y`` (23,), updated in place and returned (a multiple-shooting leg)."""
    k1 = np.empty(NSTATE)
    k2 = np.empty(NSTATE)
    k3 = np.empty(NSTATE)
    k4 = np.empty(NSTATE)
    yt = np.empty(NSTATE)
    st = np.empty(8)
    row = 0
    if record:
        for q in range(NSTATE):
            traj[0, q] = y[q]
    for i in range(sec.shape[0]):
        h = (sec[i, 1] - sec[i, 0]) / nsteps[i]
        s = sec[i]
        for _ in range(nsteps[i]):
            rhs(y, s, rdir, lam, fext, coupled, st, k1)
            for q in range(NSTATE):
                yt[q] = y[q] + 0.5 * h * k1[q]
            rhs(yt, s, rdir, lam, fext, coupled, st, k2)
            for q in range(NSTATE):
                yt[q] = y[q] + 0.5 * h * k2[q]
            rhs(yt, s, rdir, lam, fext, coupled, st, k3)
            for q in range(NSTATE):
                yt[q] = y[q] + h * k3[q]
            rhs(yt, s, rdir, lam, fext, coupled, st, k4)
            for q in range(NSTATE):
                y[q] += h / 6.0 * (k1[q] + 2.0 * k2[q] + 2.0 * k3[q] + k4[q])
            row += 1
            if record:
                for q in range(NSTATE):
                    traj[row, q] = y[q]
    return y


@_jit
def residual(y: np.ndarray, ftip: np.ndarray, ltip: np.ndarray, length: float, coupled: bool,
              r: np.ndarray) -> float:
    """Tip boundary residual (8) in newtons (moments divided by the rod length); returns its max-norm."""
    for i in range(3):
        r[i] = y[12 + i] - ftip[i]
        r[3 + i] = (y[15 + i] - ltip[i]) / length
    if coupled:
        r[6] = 0.0
        r[7] = 0.0
    else:
        r[6] = y[19] - (y[5] * ftip[0] + y[8] * ftip[1] + y[11] * ftip[2])
        r[7] = (y[20] - (y[5] * ltip[0] + y[8] * ltip[1] + y[11] * ltip[2])) / length
    worst = 0.0
    for i in range(NX):
        if not np.isfinite(r[i]):
            return np.inf
        worst = max(worst, abs(r[i]))
    return worst


@_jit
def solve_linear(a: np.ndarray, b: np.ndarray, n: int) -> bool:
    """Gaussian elimination with partial pivoting on the leading n x n block; b <- a^-1 b. False if singular."""
    for c in range(n):
        p = c
        for i in range(c + 1, n):
            if abs(a[i, c]) > abs(a[p, c]):
                p = i
        if not abs(a[p, c]) > 1e-300:
            return False
        if p != c:
            for j in range(n):
                a[c, j], a[p, j] = a[p, j], a[c, j]
            b[c], b[p] = b[p], b[c]
        for i in range(c + 1, n):
            f = a[i, c] / a[c, c]
            for j in range(c, n):
                a[i, j] -= f * a[c, j]
            b[i] -= f * b[c]
    for c in range(n - 1, -1, -1):
        acc = b[c]
        for j in range(c + 1, n):
            acc -= a[c, j] * b[j]
        b[c] = acc / a[c, c]
    return True


@_jit
def fd_jacobian(x: np.ndarray, sec: np.ndarray, nsteps: np.ndarray, rdir: np.ndarray,
                lam: np.ndarray, fext: np.ndarray, ftip: np.ndarray, ltip: np.ndarray, coupled: bool, fscale: float,
                n: int, jac: np.ndarray, traj: np.ndarray) -> None:
    """Fill ``jac`` with the forward-difference Jacobian of the tip residual with respect to the base unknowns.

    It is taken on the (coarser) grid ``nsteps``: a quasi-Newton iteration only needs an approximate Jacobian,
    the residual it drives to zero is always evaluated on the full grid.
    """
    length = sec[sec.shape[0] - 1, 1]
    xt = np.empty(NX)
    rt = np.empty(NX)
    r = np.empty(NX)
    y0 = integrate(x, sec, nsteps, rdir, lam, fext, coupled, traj, _NO_RECORD)
    residual(y0, ftip, ltip, length, coupled, r)
    for c in range(n):
        eps = 1e-7 * fscale * (length if 3 <= c < 6 or c == 7 else 1.0)
        for q in range(NX):
            xt[q] = x[q]
        xt[c] += eps
        yt = integrate(xt, sec, nsteps, rdir, lam, fext, coupled, traj, _NO_RECORD)
        residual(yt, ftip, ltip, length, coupled, rt)
        for q in range(n):
            jac[q, c] = (rt[q] - r[q]) / eps


@_jit
def newton(x: np.ndarray, sec: np.ndarray, nsteps: np.ndarray, rdir: np.ndarray, lam: np.ndarray,
           fext: np.ndarray, ftip: np.ndarray, ltip: np.ndarray, coupled: bool, tol: float, max_iter: int,
           fscale: float, traj: np.ndarray) -> tuple[int, float, int]:
    """Solve for the base unknowns ``x`` (in place) by damped quasi-Newton.

    Finite-difference Jacobian, Broyden rank-one updates while they keep reducing the residual, a fresh
    Jacobian when they stop. Returns (status, residual, iters).
    """
    n = 6 if coupled else NX
    length = sec[sec.shape[0] - 1, 1]
    nsteps_j = np.empty_like(nsteps)
    coarsen = 1 if fext.shape[0] > 3 else 4  # an elastic foundation: its Jacobian needs the full grid
    for i in range(nsteps.shape[0]):
        nsteps_j[i] = max(2, (nsteps[i] + coarsen - 1) // coarsen)
    r = np.empty(NX)
    rt = np.empty(NX)
    jac = np.zeros((NX, NX))
    work = np.empty((NX, NX))
    xt = np.empty(NX)
    step = np.zeros(NX)
    y = integrate(x, sec, nsteps, rdir, lam, fext, coupled, traj, _NO_RECORD)
    res = residual(y, ftip, ltip, length, coupled, r)
    if not np.isfinite(res):
        return NON_FINITE, res, 0
    it = 0
    fresh = False
    if res > tol:
        fd_jacobian(x, sec, nsteps_j, rdir, lam, fext, ftip, ltip, coupled, fscale, n, jac, traj)
        fresh = True
    while res > tol and it < max_iter:
        it += 1
        for q in range(NX):
            step[q] = 0.0
            for c in range(NX):
                work[q, c] = jac[q, c]
        for q in range(n):
            step[q] = -r[q]
        solved = solve_linear(work, step, n)
        alpha = 1.0
        improved = False
        rnew = res
        for _ in range((12 if fresh else 2) if solved else 0):  # backtracking line search on the residual
            for q in range(n):
                xt[q] = x[q] + alpha * step[q]
            yt = integrate(xt, sec, nsteps, rdir, lam, fext, coupled, traj, _NO_RECORD)
            rnew = residual(yt, ftip, ltip, length, coupled, rt)
            if np.isfinite(rnew) and rnew < res:
                improved = True
                break
            alpha *= 0.5
        if not improved:  # a singular or useless step: retry once with a fresh finite-difference Jacobian
            if fresh:
                return (NOT_CONVERGED if solved else SINGULAR), res, it
            fd_jacobian(x, sec, nsteps_j, rdir, lam, fext, ftip, ltip, coupled, fscale, n, jac, traj)
            fresh = True
            continue
        # Broyden update J += (dr - J dx) dx^T / (dx^T dx)
        dxx = 0.0
        for q in range(n):
            dxx += (alpha * step[q]) ** 2
        if dxx > 0.0:
            for q in range(n):
                jdx = 0.0
                for c in range(n):
                    jdx += jac[q, c] * alpha * step[c]
                g = (rt[q] - r[q] - jdx) / dxx
                for c in range(n):
                    jac[q, c] += g * alpha * step[c]
        fresh = False
        for q in range(NX):
            x[q] = xt[q]
            r[q] = rt[q]
        res = rnew
    return (OK if res <= tol else NOT_CONVERGED), res, it


@_jit
def shoot(x: np.ndarray, sec: np.ndarray, nsteps: np.ndarray, rdir: np.ndarray, lam: np.ndarray,
           fext: np.ndarray, ftip: np.ndarray, ltip: np.ndarray, coupled: bool, tol: float, max_iter: int,
           max_ramp: int, traj: np.ndarray, min_ramp: int, predictor: np.ndarray) -> tuple[int, float, int, int]:
    """Shoot with continuation: try the full load from ``x`` (when ``min_ramp`` is 1), then ramp it up from zero.

    On failure tension and external loads are ramped from zero in ``4 min_ramp``, then ``16 min_ramp``, ... steps
    (each step starting from the previous solution plus ``predictor / ramp``, the undeformed rod's share of the load
    step, e.g. :func:`reachplan.rod_model.cosserat.linear_guess`; ``min_ramp > 1`` starts with a ramp of that many
    steps). ``x`` is updated in place; ``traj`` receives the converged trajectory. Returns (status, residual in N,
    iterations, ramp steps). ``tol`` is relative to the load scale ``1 N + Σλ + |external loads|``.
    """
    fscale = 1.0
    for j in range(lam.shape[0]):
        fscale += lam[j]
    length = sec[sec.shape[0] - 1, 1]
    for i in range(3):
        fscale += abs(ftip[i]) + abs(fext[i]) * length + abs(ltip[i]) / length
    x_start = x.copy()
    ramp = max(1, min_ramp)
    total_it = 0
    status = NOT_CONVERGED
    res = np.inf
    while ramp <= max_ramp:
        if ramp == 1:
            for q in range(NX):
                x[q] = x_start[q]
        else:
            for q in range(NX):
                x[q] = 0.0
        status = OK
        for k in range(1, ramp + 1):
            f = k / ramp
            if ramp > 1:
                for q in range(NX):
                    x[q] += predictor[q] / ramp
            fx = fext.copy()
            for q in range(3):
                fx[q] *= f  # the uniform load ramps; a foundation is a stiffness, not a load
            status, res, it = newton(x, sec, nsteps, rdir, f * lam, fx, f * ftip, f * ltip, coupled,
                                      tol * fscale, max_iter, fscale, traj)
            total_it += it
            if status != OK:
                break
        if status == OK:
            integrate(x, sec, nsteps, rdir, lam, fext, coupled, traj, _RECORD)
            return OK, res, total_it, ramp
        ramp *= 4
    return status, res, total_it, ramp // 4


@_jit
def batch_free(tensions: np.ndarray, sec: np.ndarray, nsteps: np.ndarray, rdir: np.ndarray, coupled: bool,
                tol: float, max_iter: int, max_ramp: int, tips: np.ndarray, tangents: np.ndarray,
                status: np.ndarray, resid: np.ndarray) -> None:
    """Solve free-space pulls of tendon 0 with each of ``tensions`` (b,), N, into the output arrays.

    Outputs: tip positions ``tips`` (b, 3), m, base frame; unit tangents at the section bounds ``tangents``
    (b, k + 1, 3); ``status`` (b,); residual ``resid`` (b,), N.
    """
    nrow = 1
    for i in range(nsteps.shape[0]):
        nrow += nsteps[i]
    traj = np.empty((nrow, NSTATE))
    lam = np.zeros(rdir.shape[0])
    zero = np.zeros(3)
    x = np.zeros(NX)
    nopred = np.zeros(NX)
    for b in range(tensions.shape[0]):
        lam[0] = tensions[b]
        for q in range(NX):
            x[q] = 0.0
        st, res, _, _ = shoot(x, sec, nsteps, rdir, lam, zero, zero, zero, coupled, tol, max_iter, max_ramp,
                               traj, 1, nopred)
        status[b] = st
        resid[b] = res
        for q in range(3):
            tips[b, q] = traj[nrow - 1, q]
        row = 0
        tangents[b, 0, 0] = traj[0, 5]
        tangents[b, 0, 1] = traj[0, 8]
        tangents[b, 0, 2] = traj[0, 11]
        for i in range(nsteps.shape[0]):
            row += nsteps[i]
            tangents[b, i + 1, 0] = traj[row, 5]
            tangents[b, i + 1, 1] = traj[row, 8]
            tangents[b, i + 1, 2] = traj[row, 11]
