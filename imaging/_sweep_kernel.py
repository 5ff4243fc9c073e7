"""Compiled kernels of :meth:`reachplan.imaging.sweep.Sweep.field` (numba, cached on disk).

The same arithmetic as the vectorised NumPy it replaced, point by point without temporaries: the case's CT is
painted and its contours traced from about ten million field values, where NumPy's gathers and ``einsum`` took
seconds.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit


@njit(cache=True)
def _interp(x, xp, fp):  # type: ignore[no-untyped-def]
    """``np.interp(x, xp, fp)`` for one value (ends held constant)."""
    n = xp.shape[0]
    if x <= xp[0]:
        return fp[0]
    if x >= xp[n - 1]:
        return fp[n - 1]
    lo, hi = 0, n - 1
    while hi - lo > 1:
        mid = (lo + hi) // 2
        if xp[mid] <= x:
            lo = mid
        else:
            hi = mid
    return (fp[lo + 1] - fp[lo]) / (xp[lo + 1] - xp[lo]) * (x - xp[lo]) + fp[lo]


#: centreline samples per chunk of the nearest-sample search (4 mm of centreline at 0.25 mm)
CHUNK = 16


@njit(cache=True)
def nearest_samples(points, samples, centres, radii, chunks, reach, lo, hi, idx):  # type: ignore[no-untyped-def]
    """Write the index of the nearest sample to each point (-1: none within ``reach`` mm, or outside ``lo``..``hi``).

    The samples are searched in chunks of :data:`CHUNK` consecutive ones, each inside the ball ``centres[c]``,
    ``radii[c]`` (mm); a chunk whose ball is farther than the best sample so far (at first the previous point's
    nearest) is skipped whole. ``chunks`` lists the chunks to search; of equal distances the first sample is kept,
    so the result is that of comparing every sample in order.
    """
    r2 = reach * reach
    n = samples.shape[0]
    k = -1
    for p in range(points.shape[0]):
        x, y, z = points[p, 0], points[p, 1], points[p, 2]
        if not (lo[0] <= x <= hi[0] and lo[1] <= y <= hi[1] and lo[2] <= z <= hi[2]):
            idx[p] = -1
            continue
        best = r2
        if k >= 0:  # start from the previous point's nearest sample (neighbours share it): most chunks are skipped
            dx = x - samples[k, 0]
            dy = y - samples[k, 1]
            dz = z - samples[k, 2]
            d2 = dx * dx + dy * dy + dz * dz
            if d2 < r2:
                best = d2
            else:
                k = -1
        reach_c = math.sqrt(best)
        for c in chunks:
            ex = x - centres[c, 0]
            ey = y - centres[c, 1]
            ez = z - centres[c, 2]
            far = reach_c + radii[c]
            if ex * ex + ey * ey + ez * ez >= far * far:
                continue
            for i in range(c * CHUNK, min(n, (c + 1) * CHUNK)):
                dx = x - samples[i, 0]
                dy = y - samples[i, 1]
                dz = z - samples[i, 2]
                d2 = dx * dx + dy * dy + dz * dz
                if d2 < best or (d2 == best and i < k):  # the first of equal distances, as a plain scan keeps
                    best = d2
                    k = i
                    reach_c = math.sqrt(best)
        idx[p] = k


@njit(cache=True)
def axial_samples(z, z0, sign, step, n, reach, idx):  # type: ignore[no-untyped-def]
    """Write the sample of a sweep straight along z nearest to each height ``z`` (mm), -1 beyond ``reach`` of its ends.

    The samples are ``step`` mm apart from ``z0`` in the direction ``sign`` (+1 or -1); ties go to the even index,
    as ``np.round``.
    """
    lo, hi = -reach / step, n - 1 + reach / step
    for p in range(z.shape[0]):
        i_f = (z[p] - z0) * sign / step
        idx[p] = int(min(max(np.rint(i_f), 0.0), n - 1.0)) if lo < i_f < hi else -1


@njit(cache=True)
def field_at(points, idx, samples, s_arc, frames, semi_a, semi_b, reach, out):  # type: ignore[no-untyped-def]
    """Write the sweep's signed field at each point, in the frame of its sample ``idx`` (``reach`` where idx < 0)."""
    length = s_arc[s_arc.shape[0] - 1]
    last_s, a, b = np.nan, 1e-6, 1e-6  # the section at the previous point's s (a whole slice of a straight sweep)
    for p in range(points.shape[0]):
        i = idx[p]
        if i < 0:
            out[p] = reach
            continue
        dx = points[p, 0] - samples[i, 0]
        dy = points[p, 1] - samples[i, 1]
        dz = points[p, 2] - samples[i, 2]
        s = s_arc[i] + dx * frames[i, 0, 0] + dy * frames[i, 0, 1] + dz * frames[i, 0, 2]
        u = dx * frames[i, 1, 0] + dy * frames[i, 1, 1] + dz * frames[i, 1, 2]
        v = dx * frames[i, 2, 0] + dy * frames[i, 2, 1] + dz * frames[i, 2, 2]
        if s != last_s:
            a = max(_interp(s, s_arc, semi_a), 1e-6)
            b = max(_interp(s, s_arc, semi_b), 1e-6)
            last_s = s
        f = (math.hypot(u / a, v / b) - 1.0) * min(a, b)
        out[p] = max(f, max(-s, s - length))


def warm_up() -> None:
    """Compile (or load) the kernels: for the first-run benchmark."""
    pts = np.zeros((1, 3))
    samples = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    idx = np.zeros(1, dtype=np.int64)
    nearest_samples(pts, samples, np.zeros((1, 3)), np.ones(1), np.zeros(1, dtype=np.int64), 1.0,
                    np.full(3, -1.0), np.ones(3), idx)
    axial_samples(np.zeros(1), 0.0, 1.0, 1.0, 2, 1.0, idx)
    frames = np.zeros((2, 3, 3))
    field_at(pts, idx, samples, np.array([0.0, 1.0]), frames, np.ones(2), np.ones(2), 1.0, np.empty(1))
