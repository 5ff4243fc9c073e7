"""Checks of one closed planar contour: whether it encloses any area and whether it crosses itself.

A contour whose points lie on a line encloses nothing (zero area); a contour that crosses itself (a figure of
eight) has no inside of its own, and the masks fill it by the even-odd rule (:mod:`reachplan.imaging.meshing`).
Touching without crossing (a keyhole contour's cut, traced there and back) is not a crossing.
"""

from __future__ import annotations

import numpy as np

#: A contour encloses no area when its points lie within this distance (mm, root mean square) of one line: below the
#: 0.01 mm to which coordinates are written and far below any voxel.
ZERO_AREA_WIDTH_MM = 0.01
#: Segment pairs tested at once (memory of the vectorised test).
_CHUNK = 1_000_000


def encloses_no_area(points_mm: np.ndarray) -> bool:
    """Tell whether a closed contour encloses no area: its points lie on a line (or on one point).

    A figure of eight whose lobes' signed areas cancel still encloses area (it is checked for crossings instead).

    Parameters
    ----------
    points_mm : (n, 3) float, mm, LPS
        The contour's vertices.

    Returns
    -------
    bool
        The points lie within :data:`ZERO_AREA_WIDTH_MM` (root mean square) of their main line.
    """
    a = np.asarray(points_mm, dtype=float)
    if len(a) < 3:
        return True
    spread = np.linalg.svd(a - a.mean(axis=0), compute_uv=False)
    return bool(spread[1] <= ZERO_AREA_WIDTH_MM * np.sqrt(len(a)))


def _plane_coordinates(points_mm: np.ndarray) -> np.ndarray:
    """(n, 2) coordinates of planar points: the axis closest to the plane's normal (least spread) dropped."""
    a = np.asarray(points_mm, dtype=float)
    normal = np.linalg.svd(a - a.mean(axis=0), full_matrices=False)[2][-1]  # not Newell's: a figure 8 cancels
    drop = int(np.argmax(np.abs(normal)))
    return np.delete(a, drop, axis=1)


def self_crossings(points_mm: np.ndarray) -> int:
    """Count the proper crossings of a closed contour's edges with each other.

    Two edges cross when each one's end points lie strictly on both sides of the other; edges that share an end, or
    merely touch or overlap (a keyhole), do not count. A sweep along the first plane axis keeps the pairs tested to
    those whose extents overlap.

    Parameters
    ----------
    points_mm : (n, 3) float, mm, LPS
        The contour's vertices (planar), not repeated at the end.

    Returns
    -------
    int
        Crossing edge pairs; 0 for a simple polygon.
    """
    uv = _plane_coordinates(points_mm)
    uv = uv[np.any(uv != np.roll(uv, -1, axis=0), axis=1)]  # repeated points make zero-length edges
    n = len(uv)
    if n < 4:
        return 0
    p, q = uv, np.roll(uv, -1, axis=0)
    lo, hi = np.minimum(p, q), np.maximum(p, q)
    order = np.argsort(lo[:, 0], kind="stable")
    ends = np.searchsorted(lo[order, 0], hi[order, 0], side="right")
    counts = np.maximum(ends - np.arange(n) - 1, 0)
    scale = float(np.ptp(uv, axis=0).max()) or 1.0
    eps = 1e-12 * scale * scale
    crossings = 0
    start = 0
    while start < n:
        stop = start + max(1, int(np.searchsorted(np.cumsum(counts[start:]), _CHUNK, side="right")))
        c = counts[start:stop]
        first = np.repeat(np.arange(start, stop), c)
        second = first + 1 + np.arange(int(c.sum())) - np.repeat(np.cumsum(c) - c, c)
        i, j = order[first], order[second]
        gap = np.abs(i - j)
        keep = (gap != 1) & (gap != n - 1) & np.all(lo[i] <= hi[j], axis=1) & np.all(lo[j] <= hi[i], axis=1)
        i, j = i[keep], j[keep]
        crossings += _count_proper(p, q, i, j, eps)
        start = stop
    return crossings


def _count_proper(p: np.ndarray, q: np.ndarray, i: np.ndarray, j: np.ndarray, eps: float) -> int:
    """How many edge pairs (i, j) cross properly (each edge's ends strictly on both sides of the other)."""

    def side(a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
        d = (b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (b[:, 1] - a[:, 1]) * (c[:, 0] - a[:, 0])
        return np.where(np.abs(d) <= eps, 0.0, np.sign(d))

    o1, o2 = side(p[i], q[i], p[j]), side(p[i], q[i], q[j])
    o3, o4 = side(p[j], q[j], p[i]), side(p[j], q[j], q[i])
    return int(np.count_nonzero((o1 * o2 < 0) & (o3 * o4 < 0)))
