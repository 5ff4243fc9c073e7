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
    merely touch or overlap (a keyhole), do not count; a pass through a vertex visited twice counts when it crosses
    the other pass there. The pairs tested are kept to those whose boxes share a cell of a bucket grid.

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
    uv = uv - uv.min(axis=0)  # cells counted from 0: at most sqrt(n) + 1 along each axis
    p, q = uv, np.roll(uv, -1, axis=0)
    lo, hi = np.minimum(p, q), np.maximum(p, q)
    scale = float(np.ptp(uv, axis=0).max()) or 1.0
    eps = 1e-12 * scale * scale
    cell = max(2.0 * float(np.median((hi - lo).max(axis=1))), scale / np.sqrt(n), 1e-9 * scale)
    seg, cells = _cells(lo, hi, cell)
    order = np.lexsort((seg, cells))
    seg, cells = seg[order], cells[order]
    ends = np.searchsorted(cells, cells, side="right")  # each entry's cell group ends there
    counts = ends - np.arange(len(cells)) - 1
    crossings = 0
    start = 0
    while start < len(cells):
        stop = start + max(1, int(np.searchsorted(np.cumsum(counts[start:]), _CHUNK, side="right")))
        c = counts[start:stop]
        first = np.repeat(np.arange(start, stop), c)
        second = first + 1 + np.arange(int(c.sum())) - np.repeat(np.cumsum(c) - c, c)
        i, j = seg[first], seg[second]
        gap = np.abs(i - j)
        keep = (gap > 1) & (gap != n - 1) & np.all(lo[i] <= hi[j], axis=1) & np.all(lo[j] <= hi[i], axis=1)
        i, j, here = i[keep], j[keep], cells[first[keep]]
        corner = np.floor(np.maximum(lo[i], lo[j]) / cell).astype(np.int64)  # each pair counted in one cell only
        own = _cell_key(corner[:, 0], corner[:, 1]) == here
        crossings += _count_proper(p, q, i[own], j[own], eps)
        start = stop
    return crossings + _vertex_crossings(uv)


def _cell_key(cx: np.ndarray, cy: np.ndarray) -> np.ndarray:
    """One integer per grid cell (x, y), both counted from 0 and below 2**31."""
    return cx.astype(np.int64) * (1 << 31) + cy.astype(np.int64)


def _cells(lo: np.ndarray, hi: np.ndarray, cell: float) -> tuple[np.ndarray, np.ndarray]:
    """(edge index, cell key) of every grid cell each edge's box touches (a bucket grid of side ``cell``)."""
    c0 = np.floor(lo / cell).astype(np.int64)
    span = np.floor(hi / cell).astype(np.int64) - c0 + 1
    n_cells = span[:, 0] * span[:, 1]
    seg = np.repeat(np.arange(len(lo)), n_cells)
    k = np.arange(int(n_cells.sum())) - np.repeat(np.cumsum(n_cells) - n_cells, n_cells)
    return seg, _cell_key(c0[seg, 0] + k % span[seg, 0], c0[seg, 1] + k // span[seg, 0])


def _vertex_crossings(uv: np.ndarray) -> int:
    """Count the crossings through a vertex the contour passes twice (a figure of eight drawn through a point).

    At a vertex visited twice, the second pass crosses the first when its two edges leave on either side of the
    first pass's two edges; a pass along the same edges (a keyhole's cut) only touches.
    """
    n = len(uv)
    order = np.lexsort((uv[:, 1], uv[:, 0]))
    repeat = np.all(uv[order[1:]] == uv[order[:-1]], axis=1)
    if not repeat.any():
        return 0  # the usual case: no vertex visited twice
    crossings = 0
    for k in {int(order[m]) for m in np.flatnonzero(repeat)}:
        visits = np.flatnonzero(np.all(uv == uv[k], axis=1))
        if visits[0] != k:
            continue  # each repeated vertex once, from its first visit
        for a_pos, a in enumerate(visits):
            for b in visits[a_pos + 1:]:
                crossings += _passes_cross(uv, int(a), int(b), n)
    return crossings


def _passes_cross(uv: np.ndarray, a: int, b: int, n: int) -> bool:
    """Whether the pass through vertex ``b`` crosses the pass through vertex ``a`` (the same point)."""
    v = uv[a]

    def angle(k: int) -> float:
        d = uv[k % n] - v
        return float(np.arctan2(d[1], d[0]))

    lo, hi = sorted((angle(a - 1), angle(a + 1)))
    c, d = angle(b - 1), angle(b + 1)
    if len({lo, hi, c, d}) < 4:
        return False  # the passes share a direction: they touch
    return (lo < c < hi) != (lo < d < hi)


def _count_proper(p: np.ndarray, q: np.ndarray, i: np.ndarray, j: np.ndarray, eps: float) -> int:
    """How many edge pairs (i, j) cross properly (each edge's ends strictly on both sides of the other)."""

    def side(a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
        d = (b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (b[:, 1] - a[:, 1]) * (c[:, 0] - a[:, 0])
        return np.where(np.abs(d) <= eps, 0.0, np.sign(d))

    o1, o2 = side(p[i], q[i], p[j]), side(p[i], q[i], q[j])
    o3, o4 = side(p[j], q[j], p[i]), side(p[j], q[j], q[i])
    return int(np.count_nonzero((o1 * o2 < 0) & (o3 * o4 < 0)))
