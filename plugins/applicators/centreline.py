"""The centre line of an applicator ROI, curved as drawn: a channel is a polyline (mm, LPS, base to tip).

Two ways an applicator is drawn, both handled by :func:`roi_centreline`:

* **A tube** (closed planar contours, one per slice it crosses): each contour is a planar section of the tube, and
  the area centroid of a planar section of a straight round tube lies on its axis whatever the section's tilt (an
  oblique cut is an ellipse centred on the axis). A bent tube may cut a slice in an elongated section or in two
  separate ones; each closed contour is one node. The nodes are ordered along the tube by the longest path of their
  minimum spanning tree (nodes off that path, e.g. a stray contour, are left out and named in a note), sections that
  cut an end cap are left out, a cubic spline through them gives the curve, and each end is carried straight on
  along its tangent to the farthest point the drawn ROI reaches there (the channel cannot end short of the tube
  wall drawn around it). Last, the line is moved onto the axis the drawn wall implies (:func:`fit_to_wall`): where
  the tube lies along the slices, a section's centroid is not on its axis, but the wall of the slices around it
  places it.
* **A centre line** (an open contour, e.g. a BRACHY_CHANNEL ROI as Eclipse and Oncentra write one): taken as drawn.
  Several open contours or single points are ordered as nodes are.

Measured against known tubes (``tests/plugins/test_centreline.py``): a tube bent 35 degrees and cut on axial slices
at up to 65 degrees is followed within 0.1 mm; tubes bent 110-150 degrees, parts of them along the slices, within
1 mm. Not followed within a millimetre: a bend so tight that one slice's sections of both legs touch and are drawn
as one contour (its centroid lies between the legs).

The line runs from its base (the end with the smaller projection on the template axis, or on patient cranial +z
when none is given) to its tip. An ROI that gives no honest line (nothing drawn, one point, one slice) gives none
and a note that says why; no NaN ever leaves this module.
"""

from __future__ import annotations

import numpy as np
from scipy.interpolate import CubicSpline
from scipy.sparse.csgraph import minimum_spanning_tree, shortest_path
from scipy.spatial import cKDTree

from reachplan._arrays import arc_length_mm
from reachplan.imaging.types import Roi

#: Direction a line is oriented along when no template axis is given: patient cranial (+z, LPS).
CRANIAL = np.array([0.0, 0.0, 1.0])
#: Geometric types of a drawn line (a channel), as against a solid's wall (CLOSED_PLANAR).
LINE_TYPES = ("OPEN_NONPLANAR", "OPEN_PLANAR", "POINT")
#: Sample spacing of a centre line derived from a tube's contours, mm.
SAMPLE_MM = 0.5
#: Contours whose nodes lie closer than this are one node, mm.
MERGE_MM = 0.05
#: An end section with less than this fraction of the area its inner neighbours extrapolate to cuts the end cap.
CAP_AREA_RATIO = 0.93
#: At most this many end-cap sections are dropped at each end.
CAP_NODES = 3
#: Passes of the wall fit (:func:`fit_to_wall`), and the width (mm, a Gaussian's sigma along the line) over which
#: the drawn wall moves each sample.
WALL_PASSES = 12
WALL_SIGMA_MM = 1.5


def polygon_centroid(points_mm: np.ndarray) -> tuple[np.ndarray, float]:
    """Return the area centroid and the area of a closed planar polygon (any orientation in space).

    Triangles fanned from the vertex mean, signed along the polygon's normal (Newell's vector), so that a
    non-convex outline is weighted right.

    Parameters
    ----------
    points_mm : (n, 3) float, mm, LPS
        The polygon's vertices in order (closing from the last back to the first).

    Returns
    -------
    centroid : (3,) float, mm, LPS
        The area centroid; the vertex mean for a polygon of no area.
    area : float, mm²
        Its area (0 for fewer than three vertices or collinear ones).
    """
    p = np.asarray(points_mm, dtype=float).reshape(-1, 3)
    mean = p.mean(axis=0)
    if len(p) < 3:
        return mean, 0.0
    q = p - mean
    cross = np.cross(q, np.roll(q, -1, axis=0))  # twice the area vector of each fan triangle
    normal = cross.sum(axis=0)
    twice = float(np.linalg.norm(normal))
    if not twice > 1e-9:
        return mean, 0.0
    a = cross @ (normal / twice)  # twice the signed triangle areas
    g = (q + np.roll(q, -1, axis=0)) / 3.0
    return mean + (a[:, None] * g).sum(axis=0) / a.sum(), 0.5 * twice


def order_nodes(nodes_mm: np.ndarray) -> np.ndarray:
    """Return the indices of ``nodes_mm`` along the longest path of their minimum spanning tree.

    A curve sampled densely enough compared with its bends is a chain in its minimum spanning tree; the tree's
    longest path (its diameter, found by two farthest-node searches) runs from one end of the curve to the other.

    Parameters
    ----------
    nodes_mm : (n, 3) float, mm, LPS
        Points along a curve, in any order; n >= 1.

    Returns
    -------
    (m,) int
        Indices into ``nodes_mm`` from one end to the other; nodes off the path are left out.
    """
    n = len(nodes_mm)
    if n < 3:
        return np.arange(n)
    d = np.linalg.norm(nodes_mm[:, None, :] - nodes_mm[None, :, :], axis=-1) + 1e-6  # 0 would read "no edge"
    np.fill_diagonal(d, 0.0)
    tree = minimum_spanning_tree(d)
    first = shortest_path(tree, directed=False, indices=0)
    a = int(np.argmax(first))
    dist, pred = shortest_path(tree, directed=False, indices=a, return_predecessors=True)
    b = int(np.argmax(dist))
    path = [b]
    while path[-1] != a:
        path.append(int(pred[path[-1]]))
    return np.array(path[::-1])


def _merge(nodes: np.ndarray, weights: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Merge nodes closer than :data:`MERGE_MM` (a hole's centroid on its outline's) into their weighted mean."""
    keep_n: list[np.ndarray] = []
    keep_w: list[float] = []
    for p, w in zip(nodes, weights, strict=True):
        for k, q in enumerate(keep_n):
            if np.linalg.norm(p - q) < MERGE_MM:
                total = keep_w[k] + w
                keep_n[k] = (q * keep_w[k] + p * w) / total if total > 0 else q
                keep_w[k] = total
                break
        else:
            keep_n.append(p)
            keep_w.append(float(w))
    return np.array(keep_n), np.array(keep_w)


def _trim_caps(order: np.ndarray, areas: np.ndarray) -> np.ndarray:
    """Drop end nodes whose section is smaller than the trend of the sections next to them predicts.

    A slice through the end of a tilted tube cuts only part of it (its end cap), and that part's centroid is off the
    axis; a full section's area changes smoothly along the tube (as the tube's tilt to the slices does), so an end
    section with less than :data:`CAP_AREA_RATIO` of the area its two inner neighbours extrapolate to is a cap. The
    ends are found again from every drawn point (:func:`_extend`).
    """
    keep = list(order)
    for _ in range(2):
        keep = keep[::-1]
        for _ in range(CAP_NODES):
            if len(keep) < 5:
                break
            a1, a2 = float(areas[keep[1]]), float(areas[keep[2]])
            if not areas[keep[0]] < CAP_AREA_RATIO * max(a1 + (a1 - a2), a1):
                break
            keep = keep[1:]
    return np.array(keep)


def resample(line_mm: np.ndarray, sample_mm: float = SAMPLE_MM) -> np.ndarray:
    """Return a polyline resampled every ``sample_mm`` of its arc length (about; its ends kept).

    Parameters
    ----------
    line_mm : (n, 3) float, mm, LPS
        The polyline, n >= 2, of some length.
    sample_mm : float, mm
        The spacing wanted.

    Returns
    -------
    (k, 3) float, mm, LPS
        Evenly spaced samples on it, k >= 2.
    """
    s = arc_length_mm(line_mm)
    u = np.linspace(0.0, s[-1], max(2, int(np.ceil(s[-1] / sample_mm)) + 1))
    return np.column_stack([np.interp(u, s, line_mm[:, k]) for k in range(3)])


def smooth_curve(nodes_mm: np.ndarray, sample_mm: float = SAMPLE_MM) -> np.ndarray:
    """Return a smooth curve through ordered nodes, sampled every ``sample_mm`` of arc length.

    A natural cubic spline through the nodes against their cumulative chord length (the section centroids are
    precise; :func:`fit_to_wall` then places the line on the drawn wall); two nodes are joined by a straight line.

    Parameters
    ----------
    nodes_mm : (n, 3) float, mm, LPS
        Ordered, distinct nodes; n >= 2.
    sample_mm : float, mm
        Spacing of the returned samples.

    Returns
    -------
    (k, 3) float, mm, LPS
        The curve from the first node to the last; k >= 2.
    """
    t = arc_length_mm(nodes_mm)
    if len(nodes_mm) >= 3:
        u = np.linspace(0.0, t[-1], max(2, int(np.ceil(t[-1] / sample_mm)) + 1))
        return resample(CubicSpline(t, nodes_mm, bc_type="natural")(u), sample_mm)
    return resample(nodes_mm, sample_mm)


def _resampled(contour_mm: np.ndarray, step_mm: float) -> np.ndarray:
    """Return points every ``step_mm`` along a closed contour (so that each stretch of wall counts alike)."""
    ring = np.vstack([contour_mm, contour_mm[:1]])
    s = arc_length_mm(ring)
    u = np.arange(0.0, s[-1], step_mm)
    return np.column_stack([np.interp(u, s, ring[:, k]) for k in range(3)])


def fit_to_wall(curve: np.ndarray, contours_mm: list[np.ndarray], passes: int = WALL_PASSES,
                sigma_mm: float = WALL_SIGMA_MM) -> np.ndarray:
    """Move a tube's centre line onto the axis its drawn wall implies (a round tube of one radius).

    Each wall point (the contours, resampled every 1 mm) tells, in the normal plane of its foot on the line, how far
    the foot should move for the point to lie the tube's radius from it (the radius: the points' median distance to
    the first line). Each sample of the line moves, across the line only, by the Gaussian-weighted mean (along the
    line) of what the wall around it tells; a few passes. The centroids of the sections are exact where a slice cuts
    the tube across; where the tube lies along the slices (a slice cuts it lengthwise, in a long section, or twice),
    the wall of the slices above and below places it. Within a radius of the ends the line keeps its place (the ends
    are capped, with another radius), tapering in over the next radius.

    Parameters
    ----------
    curve : (n, 3) float, mm, LPS
        The first line, samples about :data:`SAMPLE_MM` apart.
    contours_mm : list of (k, 3) float, mm, LPS
        The tube's closed contours.
    passes : int
        How many passes.
    sigma_mm : float, mm
        The Gaussian's sigma along the line.

    Returns
    -------
    (n, 3) float, mm, LPS
        The line, each sample moved across it.
    """
    wall = np.concatenate([_resampled(c, 1.0) for c in contours_mm])
    line = np.array(curve, dtype=float)
    radius = None
    for _ in range(passes):
        s = arc_length_mm(line)
        tangent = np.gradient(line, axis=0)
        tangent /= np.maximum(np.linalg.norm(tangent, axis=1), 1e-12)[:, None]
        foot = cKDTree(line).query(wall)[1]
        inner = (foot > 0) & (foot < len(line) - 1)  # a point beyond an end is its cap's
        at, t = line[foot[inner]], tangent[foot[inner]]
        offset = wall[inner] - at
        offset -= np.sum(offset * t, axis=1)[:, None] * t  # in the foot's normal plane
        dist = np.linalg.norm(offset, axis=1)
        if radius is None:
            radius = float(np.median(dist)) if len(dist) else 0.0
        if not radius > 0 or len(dist) == 0:
            break
        shift = offset * (1.0 - radius / np.maximum(dist, 1e-9))[:, None]  # where the foot should be, in-plane
        w = np.exp(-0.5 * ((s[:, None] - s[foot[inner]][None, :]) / sigma_mm) ** 2)
        total = w.sum(axis=1)
        move = (w @ shift) / np.maximum(total, 1e-12)[:, None]
        move -= np.sum(move * tangent, axis=1)[:, None] * tangent  # across the line only: it keeps its length
        taper = np.clip((np.minimum(s, s[-1] - s) - radius) / radius, 0.0, 1.0) * (total > 2.0)
        line += taper[:, None] * move
    return line


def _extend(curve: np.ndarray, points_mm: np.ndarray, reach_mm: float) -> np.ndarray:
    """Carry the curve's last point on along its end tangent to the farthest ROI point beyond it (within reach)."""
    end = curve[-1]
    s = arc_length_mm(curve)
    back = curve[int(np.searchsorted(s, s[-1] - 3.0, side="right")) - 1] if s[-1] > 3.0 else curve[0]
    t = end - back
    norm = float(np.linalg.norm(t))
    if not norm > 0:
        return curve
    t = t / norm
    rel = points_mm - end
    ahead = rel @ t
    lateral = np.linalg.norm(rel - np.outer(ahead, t), axis=1)
    beyond = ahead[(ahead > 0) & (lateral <= reach_mm)]
    if len(beyond) == 0:
        return curve
    return np.vstack([curve, end + float(beyond.max()) * t])


def _oriented(line: np.ndarray, axis: np.ndarray | None) -> np.ndarray:
    """Return ``line`` base to tip: its tip projects farther along ``axis`` (None: patient cranial, +z)."""
    toward = CRANIAL if axis is None else np.asarray(axis, dtype=float)
    return line if (line[-1] - line[0]) @ toward >= 0 else line[::-1].copy()


def _tube_centreline(roi: Roi) -> tuple[np.ndarray | None, tuple[str, ...]]:
    """Return the centre line of a tube drawn as closed planar contours (see the module docstring)."""
    closed = [c.points_mm for c in roi.contours if c.geometric_type == "CLOSED_PLANAR" and len(c.points_mm) >= 3]
    if not closed:
        return None, (f"ROI {roi.name!r} has no closed contour of three or more points: no centre line",)
    sections = [polygon_centroid(c) for c in closed]
    nodes, weights = _merge(np.array([c for c, _ in sections]), np.array([a for _, a in sections]))
    every = np.concatenate(closed)
    spread = np.linalg.svd(every - every.mean(axis=0), compute_uv=False)
    if len(nodes) < 2 or not spread[-1] > 1e-3 * max(spread[0], 1e-9):
        return None, (f"ROI {roi.name!r} is drawn on one slice only: no centre line (draw the tube on every slice it "
                      "crosses, or give its channel as a line or in an RT Plan)",)
    order = order_nodes(nodes)
    notes: tuple[str, ...] = ()
    if len(order) < len(nodes):
        notes = (f"ROI {roi.name!r}: {len(nodes) - len(order)} of {len(nodes)} contour centroids lie off the tube's "
                 "course and were left out of its centre line",)
    curve = smooth_curve(nodes[_trim_caps(order, weights)])
    reach = max(float(np.max(np.linalg.norm(c - q, axis=1))) for c, (q, _) in zip(closed, sections, strict=True))
    curve = _extend(curve, every, reach + 1.0)
    curve = _extend(curve[::-1], every, reach + 1.0)[::-1]
    return fit_to_wall(resample(curve), closed), notes


def _line_centreline(roi: Roi) -> tuple[np.ndarray | None, tuple[str, ...]]:
    """Return the centre line drawn as open contours or points: one line as drawn, else its points ordered."""
    lines = [c.points_mm for c in roi.contours if c.geometric_type in LINE_TYPES]
    pts = np.concatenate(lines)
    if len(lines) == 1 and len(pts) >= 2:
        keep = np.concatenate([[True], np.linalg.norm(np.diff(pts, axis=0), axis=1) > 1e-9])
        line = pts[keep]
    else:
        nodes, _ = _merge(pts, np.ones(len(pts)))
        line = nodes[order_nodes(nodes)] if len(nodes) >= 2 else nodes
    if len(line) < 2 or not float(arc_length_mm(line)[-1]) > 0:
        return None, (f"ROI {roi.name!r} is drawn as a single point: no centre line (draw the channel as a line)",)
    return np.asarray(line, dtype=float), ()


def roi_centreline(roi: Roi, axis: np.ndarray | None = None) -> tuple[np.ndarray | None, tuple[str, ...]]:
    """Return the centre line of an applicator ROI, curved as drawn, base to tip.

    A drawn line (open contours; points when there is no tube) is the centre line as drawn; otherwise the closed
    contours are taken as a tube's sections (see the module docstring).

    Parameters
    ----------
    roi : Roi
        The applicator ROI (contour points mm, LPS).
    axis : (3,) float, LPS, or None
        The template's insertion direction, to orient the line base to tip (None: patient cranial, +z).

    Returns
    -------
    line : (n, 3) float, mm, LPS, base to tip, or None
        n >= 2, finite; the tip is the channel's end. None when the ROI gives no honest line.
    notes : tuple of str
        Why there is no line, or what was left out.
    """
    drawn_line = any(c.geometric_type in ("OPEN_NONPLANAR", "OPEN_PLANAR") for c in roi.contours)
    tube = any(c.geometric_type == "CLOSED_PLANAR" and len(c.points_mm) >= 3 for c in roi.contours)
    if drawn_line or (not tube and any(c.geometric_type == "POINT" for c in roi.contours)):
        line, notes = _line_centreline(roi)
        if line is None and tube:  # a line that gives none beside a tube drawn around it: the tube
            line, notes = _tube_centreline(roi)
    else:
        line, notes = _tube_centreline(roi)
    if line is None:
        return None, notes
    if not np.all(np.isfinite(line)):  # a guard: the steps above give finite points from finite contours
        return None, (f"ROI {roi.name!r}: its centre line could not be computed (not finite)",)
    return _oriented(line, axis), notes
