"""Compiled TG-43 kernels: one voxel-dwell pair at a time, threads over voxels (numba ``prange``).

Every pair costs one square root, two arctangents (a minimax polynomial, |error| < 1.2e-5 rad on [0, 1],
Abramowitz & Stegun-type odd polynomial of degree 11) and one bilinear look-up in the per-source
(r, θ) table of g_L · F that :class:`reachplan.planner.dose.tg43.Tg43Kernel` builds (Δr = 0.05 cm, Δθ = 1°, every
consensus node on it). The geometry factor is computed, not tabulated: near the axis F changes by up to 25 % per
degree (cable side) and G_L by orders of magnitude near the source ends, which no (z, ρ) table of the whole
product resolves to 0.1 % without tens of MB. Compiled once and cached on disk (``cache=True``).

Units as in :mod:`reachplan.planner.dose.tg43`: positions in cm, rates in cGy h⁻¹ U⁻¹ (before the weights).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

_F = np.float32
_HALF_PI = _F(math.pi / 2.0)
_ONE = _F(1.0)
_ZERO = _F(0.0)
_TINY = _F(1e-30)
_DEG2 = _F(360.0 / math.pi)  # 2·(180/π): α/2 in rad to α in degrees
_D180 = _F(180.0)
_A1, _A3, _A5, _A7, _A9, _A11 = (_F(0.99997726), _F(-0.33262347), _F(0.19354346), _F(-0.11643287), _F(0.05265332),
                                 _F(-0.01172120))


@njit(cache=True, fastmath=True, inline="always")
def _atan_pos(x):  # type: ignore[no-untyped-def]
    """atan(x) for x >= 0 (branch-free select; polynomial on [0, 1], π/2 − atan(1/x) beyond)."""
    inv = x > _ONE
    t = _ONE / x if inv else x
    t2 = t * t
    p = t * (_A1 + t2 * (_A3 + t2 * (_A5 + t2 * (_A7 + t2 * (_A9 + t2 * _A11)))))
    return _HALF_PI - p if inv else p


@njit(cache=True, fastmath=True, inline="always")
def _atan_over_x(x):  # type: ignore[no-untyped-def]
    """atan(x) / x for x >= 0."""
    if x <= _ONE:
        t2 = x * x
        return _A1 + t2 * (_A3 + t2 * (_A5 + t2 * (_A7 + t2 * (_A9 + t2 * _A11))))
    return _atan_pos(x) / x


@njit(cache=True, fastmath=True, inline="always")
def _pair(px, py, pz, sx, sy, sz, ux, uy, uz, table, nt, inv_dr, r_min, length, quarter_l2, eps_y, y_source, point_model):  # type: ignore[no-untyped-def]  # noqa: E501
    """Rate per U before the constant factor, one pair (positions in cm)."""
    dx = px - sx
    dy = py - sy
    dz = pz - sz
    r2 = dx * dx + dy * dy + dz * dz
    r = math.sqrt(r2)
    if point_model:  # a compile-time constant: each model gets its own specialisation
        rc = max(r, r_min)
        ri = rc * inv_dr
        i0 = min(int(ri), table.shape[0] - 2)
        fr = min(ri - i0, _ONE)
        return table[i0, 0] * (_ONE - fr) + table[i0 + 1, 0] * fr
    z = dx * ux + dy * uy + dz * uz
    # distance from the axis as |d × u| (r² − z² cancels in float32 near the axis, where F is steep)
    cx = dy * uz - dz * uy
    cy = dz * ux - dx * uz
    cz = dx * uy - dy * ux
    rho = math.sqrt(cx * cx + cy * cy + cz * cz)
    az = abs(z)
    # θ from the half-angle α/2 = atan(ρ / (|z| + r)), α the angle to the nearer axis direction (the point's own)
    half = _atan_pos(rho / (az + r + _TINY))
    tdeg = half * _DEG2  # α in degrees
    th = tdeg if z >= _ZERO else _D180 - tdeg
    # the line source at the point's own distance (no cap, as tg43.Tg43Kernel): only points beside the source
    # and closer to its axis than y_source are moved out to it, at the same position along the axis
    y = rho
    if y < y_source and az < _F(0.5) * length:
        y = y_source
    y = max(y, eps_y)
    rc = math.sqrt(y * y + az * az)
    ri = rc * inv_dr
    i0 = min(int(ri), table.shape[0] - 2)
    fr = min(ri - i0, _ONE)
    t0 = min(int(th), nt - 2)
    ft = th - t0
    a = table[i0, t0] * (_ONE - ft) + table[i0, t0 + 1] * ft
    b = table[i0 + 1, t0] * (_ONE - ft) + table[i0 + 1, t0 + 1] * ft
    gf = a + (b - a) * fr
    # geometry factor β / y: outside the sphere of diameter L, β = atan(x), x = L y / (r² − L²/4), written as
    # L/(r² − L²/4) · atan(x)/x (finite on the axis); inside it (r² < L²/4, beside the source) β = π − atan(x)
    den = rc * rc - quarter_l2
    if den > _ZERO:
        inv_den = length / den
        return gf * inv_den * _atan_over_x(y * inv_den)
    x = length * y / max(-den, _F(1e-12))
    return gf * (_F(math.pi) - _atan_pos(x)) / y


@njit(cache=True, fastmath=True, parallel=True)
def grid_dose(origin, step_i, step_j, step_k, shape, pos, dirs, w, table, inv_dr, r_min, length, eps_y, y_source, point_model, out):  # type: ignore[no-untyped-def]  # noqa: E501
    """Σ_j w_j · rate(voxel, dwell j) on every voxel of a grid; threads over the k·j rows.

    ``origin`` (3,) and ``step_*`` (3,) cm, the voxel centre of (i, j, k) is origin + i·step_i + j·step_j +
    k·step_k; ``shape`` (nk, nj, ni); ``pos`` and ``dirs`` (3, n) float32, one row per coordinate (contiguous
    loads instead of gathers in the vectorised dwell loop); ``out`` (nk·nj·ni,) float32 written in place (C order).
    """
    nk, nj, ni = shape[0], shape[1], shape[2]
    nt = table.shape[1]
    ql2 = 0.25 * length * length
    nd = pos.shape[1]
    for row in prange(nk * nj):
        k = row // nj
        j = row - k * nj
        bx = origin[0] + j * step_j[0] + k * step_k[0]
        by = origin[1] + j * step_j[1] + k * step_k[1]
        bz = origin[2] + j * step_j[2] + k * step_k[2]
        for i in range(ni):
            px = bx + i * step_i[0]
            py = by + i * step_i[1]
            pz = bz + i * step_i[2]
            acc = _ZERO
            for d in range(nd):
                acc += w[d] * _pair(px, py, pz, pos[0, d], pos[1, d], pos[2, d], dirs[0, d], dirs[1, d],
                                    dirs[2, d], table, nt, inv_dr, r_min, length, ql2, eps_y, y_source,
                                    point_model)
            out[row * ni + i] = acc


@njit(cache=True, fastmath=True, parallel=True)  # threads over points: implant metrics evaluate ~10⁹ pairs
def pair_matrix(pts, pos, dirs, table, inv_dr, r_min, length, eps_y, y_source, point_model, out):  # type: ignore[no-untyped-def]
    """rate(point m, dwell n) into ``out`` (m, n); ``pts`` (m, 3), ``pos``/``dirs`` (3, n), cm."""
    nt = table.shape[1]
    ql2 = 0.25 * length * length
    for m in prange(pts.shape[0]):
        for d in range(pos.shape[1]):
            out[m, d] = _pair(pts[m, 0], pts[m, 1], pts[m, 2], pos[0, d], pos[1, d], pos[2, d], dirs[0, d],
                              dirs[1, d], dirs[2, d], table, nt, inv_dr, r_min, length, ql2, eps_y, y_source,
                                    point_model)


@njit(cache=True, fastmath=True, parallel=True)  # threads over points: the dose without the (m, n) matrix
def pair_dose(pts, pos, dirs, w, table, inv_dr, r_min, length, eps_y, y_source, point_model, out):  # type: ignore[no-untyped-def]
    """Σ_n w[n] rate(point m, dwell n) into ``out`` (m,) float64; ``pts`` (m, 3), ``pos``/``dirs`` (3, n), cm."""
    nt = table.shape[1]
    ql2 = 0.25 * length * length
    for m in prange(pts.shape[0]):
        acc = 0.0
        for d in range(pos.shape[1]):
            acc += w[d] * _pair(pts[m, 0], pts[m, 1], pts[m, 2], pos[0, d], pos[1, d], pos[2, d], dirs[0, d],
                                dirs[1, d], dirs[2, d], table, nt, inv_dr, r_min, length, ql2, eps_y, y_source,
                                point_model)
        out[m] = acc
