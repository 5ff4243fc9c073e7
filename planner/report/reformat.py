"""A slice along each implant needle: a curved planar reformat with the organs, the dose and the clearance.

The slices through the targets show needles projected onto axis-aligned planes, where a needle passing in front of
an organ seems to cross it. Here each needle is straightened instead: the horizontal axis is the arc length along
the needle from its template hole (mm), the vertical axis the offset from the needle (mm) along a direction kept
perpendicular to it. The top panel's direction points from the needle's point of closest approach to the nearest
organ, so that the clearance lies in the panel at its true length and is annotated there; the middle panel is
turned 90° about the needle; the bottom panel gives the needle's dwell times along it.

The reformatted surface is the ruled surface ``p(s) + t e(s)`` (``p`` the centreline, ``e`` a unit vector
perpendicular to the tangent, mm, LPS). Organ outlines are cut exactly from the meshes on a piecewise-planar
version of it (one plane per 2 mm of needle, :func:`curved_section`); the image is sampled trilinearly and the dose
computed at the points of the surface.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import trimesh
from matplotlib.figure import Figure
from matplotlib.lines import Line2D
from scipy.spatial import cKDTree

from reachplan.imaging.types import Volume
from reachplan.planner.case.scene import Scene
from reachplan.planner.delivery import EXPORT_ARM, Delivery
from reachplan.planner.report.figures import (
    ISODOSE_PERCENT,
    ISODOSE_STYLE,
    MIN_FONT_PT,
    STEERED_COLOUR,
    STRAIGHT_COLOUR,
    TITLE_Y,
    DoseOverlay,
    display_window,
    label_edges,
    organ_colour,
    plane_cut,
    png_bytes,
)
from reachplan.planner.report.html import Block, Paragraph, Section
from reachplan.planner.report.html import Figure as FigureBlock

#: Half-width of each reformatted panel, mm on either side of the needle.
HALF_WIDTH_MM = 25.0
#: Arc-length step of the reformat's planes (and of the image samples along the needle), mm.
STEP_MM = 2.0
#: How far the reformat runs on past the needle's tip (straight ahead), mm: what lies beyond the tip shows.
AHEAD_MM = 10.0
#: Sample spacing of the closest-approach search along the needle, mm.
SEARCH_STEP_MM = 0.5
#: Left and right edges of the reformat's axes (figure fractions) and the width between them.
FIGURE_LEFT_RIGHT = (0.08, 0.8, 0.72)


@dataclass(frozen=True, eq=False)
class Closest:
    """Where a needle comes closest to the organs at risk.

    Parameters
    ----------
    organ : str
        The nearest organ.
    s_mm : float, mm
        Arc length along the needle from its base (template hole) to its point of closest approach.
    needle_point_mm : (3,) float, mm, LPS
        That point of the centreline.
    organ_point_mm : (3,) float, mm, LPS
        The nearest point of the organ's surface.
    clearance_mm : float, mm
        Needle surface to organ surface: the centreline's distance less the needle's radius (0 when touching).
    """

    organ: str
    s_mm: float
    needle_point_mm: np.ndarray
    organ_point_mm: np.ndarray
    clearance_mm: float


def arc_length(path_mm: np.ndarray) -> np.ndarray:
    """Return the arc length at each point of a polyline.

    Parameters
    ----------
    path_mm : (n, 3) float, mm, LPS
        The polyline.

    Returns
    -------
    (n,) float, mm
        From 0 at its first point.
    """
    p = np.asarray(path_mm, dtype=float)
    return np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(p, axis=0), axis=1))])


def resample(path_mm: np.ndarray, s_mm: np.ndarray) -> np.ndarray:
    """Return the points of a polyline at given arc lengths (linear between its points).

    Parameters
    ----------
    path_mm : (n, 3) float, mm, LPS
        The polyline.
    s_mm : (m,) float, mm
        Arc lengths, clipped to the polyline's length.

    Returns
    -------
    (m, 3) float, mm, LPS
    """
    p = np.asarray(path_mm, dtype=float)
    s = arc_length(p)
    q = np.clip(np.asarray(s_mm, dtype=float), 0.0, s[-1])
    return np.column_stack([np.interp(q, s, p[:, i]) for i in range(3)])


def closest_approach(path_mm: np.ndarray, meshes: dict[str, trimesh.Trimesh], radius_mm: float) -> Closest | None:
    """Find the needle's point of closest approach to a set of organs (exact point-to-triangle distances).

    The centreline is sampled every :data:`SEARCH_STEP_MM` and each sample's nearest surface point found with
    trimesh; organs whose bounding box lies farther than the best distance so far are skipped.

    Parameters
    ----------
    path_mm : (n, 3) float, mm, LPS
        The needle's centreline, base to tip.
    meshes : dict of str to trimesh.Trimesh
        The organs at risk (mm, LPS).
    radius_mm : float, mm
        The needle's radius.

    Returns
    -------
    Closest or None
        None without organs.
    """
    p = np.asarray(path_mm, dtype=float)
    length = float(arc_length(p)[-1])
    s = np.linspace(0.0, length, max(2, int(np.ceil(length / SEARCH_STEP_MM)) + 1))
    pts = resample(p, s)
    lo, hi = pts.min(axis=0), pts.max(axis=0)

    def box_gap(m: trimesh.Trimesh) -> float:
        b = np.asarray(m.bounds)
        return float(np.linalg.norm(np.maximum(0.0, np.maximum(b[0] - hi, lo - b[1]))))

    best: Closest | None = None
    best_d = np.inf
    for name, mesh in sorted(meshes.items(), key=lambda kv: box_gap(kv[1])):
        if box_gap(mesh) >= best_d:
            break
        i, q, d = _nearest_on_mesh(mesh, pts)
        if d < best_d:
            best_d = d
            best = Closest(name, float(s[i]), pts[i], q, max(best_d - radius_mm, 0.0))
    return best


def longest_edge_mm(v: np.ndarray, f: np.ndarray) -> float:
    """Return the longest edge of a triangle mesh.

    Parameters
    ----------
    v : (n, 3) float, mm
        Vertices.
    f : (m, 3) int
        Triangles.

    Returns
    -------
    float, mm
        0 for a mesh without triangles.
    """
    if not len(f):
        return 0.0
    t = v[f]
    return float(np.sqrt(max(float(np.max(np.sum((t[:, i] - t[:, (i + 1) % 3]) ** 2, axis=1))) for i in range(3))))


def _nearest_on_mesh(mesh: trimesh.Trimesh, pts: np.ndarray) -> tuple[int, np.ndarray, float]:
    """Return the sample of ``pts`` nearest to the mesh's surface, its nearest surface point and the distance (mm).

    Exact: a surface point lies within the longest edge ``L`` of a vertex, so only the samples whose nearest vertex
    is within ``L`` of the best such distance can hold the minimum, and only the faces with a vertex within that
    distance plus ``L`` of them can hold its point; their point-to-triangle distances are computed exactly.
    """
    v, f = np.asarray(mesh.vertices, dtype=float), np.asarray(mesh.faces)
    edge = longest_edge_mm(v, f)
    tree = cKDTree(v)
    dv, _ = tree.query(pts)
    cand = np.flatnonzero(dv <= dv.min() + edge)
    by_vertex = np.argsort(f.ravel(), kind="stable")  # the faces of each vertex: by_vertex[start[i]:start[i + 1]] // 3
    start = np.searchsorted(f.ravel()[by_vertex], np.arange(len(v) + 1))
    sample, faces = [], []
    for c, group in zip(cand, tree.query_ball_point(pts[cand], dv[cand] + edge), strict=True):
        g = np.asarray(group, dtype=int)
        n = start[g + 1] - start[g]
        idx = np.repeat(start[g], n) + np.arange(int(n.sum())) - np.repeat(np.cumsum(n) - n, n)
        own = np.unique(by_vertex[idx] // 3)
        faces.append(own)
        sample.append(np.full(len(own), c))
    fi, si = np.concatenate(faces), np.concatenate(sample)
    q = trimesh.triangles.closest_point(v[f[fi]], pts[si])
    d = np.linalg.norm(q - pts[si], axis=1)
    k = int(np.argmin(d))
    return int(si[k]), q[k], float(d[k])


def _tangents(path_mm: np.ndarray, s_mm: np.ndarray) -> np.ndarray:
    """Return the unit tangents ((m, 3), LPS) at arc lengths ``s_mm``, by central differences over 1 mm."""
    ahead = resample(path_mm, s_mm + 0.5) - resample(path_mm, s_mm - 0.5)
    return ahead / np.maximum(np.linalg.norm(ahead, axis=1, keepdims=True), 1e-12)


def lateral_directions(path_mm: np.ndarray, s_mm: np.ndarray, towards: np.ndarray) -> np.ndarray:
    """Return unit vectors perpendicular to the needle at arc lengths ``s_mm``, as near to ``towards`` as can be.

    Each is ``towards`` less its component along the needle's tangent there, normalised; where the needle runs along
    ``towards`` another perpendicular is taken.

    Parameters
    ----------
    path_mm : (n, 3) float, mm, LPS
        The needle's centreline.
    s_mm : (m,) float, mm
        Arc lengths.
    towards : (3,) float, LPS
        The direction to follow.

    Returns
    -------
    (m, 3) float, unit vectors, LPS
    """
    t = _tangents(path_mm, np.asarray(s_mm, dtype=float))
    w = np.asarray(towards, dtype=float)
    e = w - (t @ w)[:, None] * t
    small = np.linalg.norm(e, axis=1) < 1e-6
    if small.any():  # along the needle: any perpendicular
        alt = np.where(np.abs(t[small, :1]) < 0.9, [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]])
        e[small] = alt - np.sum(alt * t[small], axis=1, keepdims=True) * t[small]
    return e / np.linalg.norm(e, axis=1, keepdims=True)


def _clip_to_strip(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Clip segments ``a``-``b`` ((m, 2) each, (u, t)) to ``0 <= u <= 1``; returns the kept parts."""
    du = b[:, 0] - a[:, 0]
    with np.errstate(divide="ignore", invalid="ignore"):
        l0 = np.where(du != 0, (0.0 - a[:, 0]) / du, -np.inf)
        l1 = np.where(du != 0, (1.0 - a[:, 0]) / du, np.inf)
    lo = np.clip(np.maximum(0.0, np.minimum(l0, l1)), 0.0, 1.0)
    hi = np.clip(np.minimum(1.0, np.maximum(l0, l1)), 0.0, 1.0)
    flat = du == 0
    inside = (a[:, 0] >= 0.0) & (a[:, 0] <= 1.0)
    lo, hi = np.where(flat, np.where(inside, 0.0, 1.0), lo), np.where(flat, np.where(inside, 1.0, 0.0), hi)
    keep = hi > lo
    d = b - a
    return (a + lo[:, None] * d)[keep], (a + hi[:, None] * d)[keep]


def curved_section(mesh: trimesh.Trimesh, path_mm: np.ndarray, s_mm: np.ndarray, laterals: Sequence[np.ndarray],
                   half_width_mm: float = HALF_WIDTH_MM) -> list[np.ndarray]:
    """Cut a mesh with reformatted surfaces ``p(s) + t e(s)``, in the reformat's (s, t) coordinates.

    Between two arc lengths a surface is taken as the plane through the needle's chord and the mean of the two
    lateral directions (perpendicular to the chord); the mesh's cut with that plane is kept within the strip
    between the two arc lengths and mapped to (s, t). Exact where the surface is planar (a straight needle, or a
    needle bent in one plane seen in that plane).

    Parameters
    ----------
    mesh : trimesh.Trimesh
        The organ (mm, LPS).
    path_mm : (n, 3) float, mm, LPS
        The needle's centreline.
    s_mm : (m,) float, mm
        Increasing arc lengths of the surfaces' rulings.
    laterals : sequence of (m, 3) float, unit vectors, LPS
        Per surface, the direction ``e`` of each ruling (:func:`lateral_directions`).
    half_width_mm : float, mm
        How far from the needle the surfaces reach.

    Returns
    -------
    list of (3 k, 2) float, mm
        Per surface, the k cut segments in (s, t), each two points followed by a NaN row; (0, 2) when it misses.
    """
    pts = resample(path_mm, s_mm)
    v, f = np.asarray(mesh.vertices, dtype=float), np.asarray(mesh.faces)
    reach = half_width_mm + longest_edge_mm(v, f) + float(np.max(np.diff(s_mm), initial=0.0))
    tree = cKDTree(pts)
    box = np.flatnonzero(np.all((v >= pts.min(axis=0) - reach) & (v <= pts.max(axis=0) + reach), axis=1))
    near = np.zeros(len(v), dtype=bool)
    near[box[np.isfinite(tree.query(v[box], distance_upper_bound=reach)[0])]] = True
    f = f[near[f].any(axis=1)]
    if not len(f):
        return [np.zeros((0, 2)) for _ in laterals]
    # each face belongs to the strips next to the rulings nearest to its vertices (faces sorted by strip)
    used = np.unique(f)
    nearest = np.zeros(len(v), dtype=int)
    nearest[used] = tree.query(v[used])[1]
    j = nearest[f]
    first, last = np.maximum(j.min(axis=1) - 1, 0), np.minimum(j.max(axis=1), len(pts) - 2)
    count = np.maximum(last - first + 1, 0)
    face_of = np.repeat(np.arange(len(f)), count)
    strip = np.repeat(first, count) + np.arange(int(count.sum())) - np.repeat(np.cumsum(count) - count, count)
    order = np.argsort(strip, kind="stable")
    face_of, bounds = face_of[order], np.searchsorted(strip[order], np.arange(len(pts)))
    return [_cut_strips(v, f, face_of, bounds, pts, s_mm, lateral) for lateral in laterals]


def _cut_strips(v: np.ndarray, f: np.ndarray, face_of: np.ndarray, bounds: np.ndarray, pts: np.ndarray,
                s_mm: np.ndarray, lateral: np.ndarray) -> np.ndarray:
    """Cut each strip's faces (``face_of[bounds[i]:bounds[i + 1]]``) with its plane; segments in (s, t), NaN-split."""
    out = []
    for i in range(len(pts) - 1):
        a, chord = pts[i], pts[i + 1] - pts[i]
        ds = float(np.linalg.norm(chord))
        local = face_of[bounds[i]:bounds[i + 1]]
        if ds <= 1e-9 or not len(local):
            continue
        d = chord / ds
        e = lateral[i] + lateral[i + 1]
        e = e - (e @ d) * d
        e /= np.linalg.norm(e)
        cuts = plane_cut(v, f[local], np.cross(d, e), float(np.cross(d, e) @ a))
        if not cuts:
            continue
        seg = cuts[0].reshape(-1, 3, 3)[:, :2]  # (k, 2 points, 3)
        uv = np.stack([((seg - a) @ d) / ds, (seg - a) @ e], axis=-1)  # (k, 2, 2): u in [0, 1] across the strip
        p0, p1 = _clip_to_strip(uv[:, 0], uv[:, 1])
        if len(p0):
            st = np.stack([p0, p1], axis=1)
            st[..., 0] = s_mm[i] + st[..., 0] * (s_mm[i + 1] - s_mm[i])
            out.append(np.concatenate([st, np.full((len(st), 1, 2), np.nan)], axis=1).reshape(-1, 2))
    return np.concatenate(out) if out else np.zeros((0, 2))


def _sample_image(volume: Volume, points_mm: np.ndarray) -> np.ndarray:
    """Trilinear image values at points ((..., 3) mm, LPS); NaN outside the image."""
    from scipy.ndimage import map_coordinates

    shape = points_mm.shape[:-1]
    ijk = volume.grid.to_index(points_mm.reshape(-1, 3))  # (n, 3): i, j, k
    vals = map_coordinates(np.asarray(volume.array), [ijk[:, 2], ijk[:, 1], ijk[:, 0]], order=1, output=float,
                           mode="constant", cval=np.nan)
    return vals.reshape(shape)


def _outlines(scene: Scene, path: np.ndarray, s: np.ndarray, laterals: Sequence[np.ndarray],
              half_width_mm: float) -> list[dict[str, np.ndarray]]:
    """Per reformatted surface, the organs it cuts: name -> (s, t) segments (:func:`curved_section`)."""
    p_lo, p_hi = path.min(axis=0) - half_width_mm, path.max(axis=0) + half_width_mm
    out: list[dict[str, np.ndarray]] = [{} for _ in laterals]
    for name, mesh in scene.meshes.items():
        b = np.asarray(mesh.bounds)
        if np.any(b[0] > p_hi) or np.any(b[1] < p_lo):
            continue
        for panel, cut in zip(out, curved_section(mesh, path, s, laterals, half_width_mm), strict=True):
            if len(cut):
                panel[name] = cut
    return out


def _panel(ax: Any, outlines: dict[str, np.ndarray], path: np.ndarray, s: np.ndarray, e: np.ndarray,
           volume: Volume | None, dose: DoseOverlay | None, half_width_mm: float) -> None:
    """Draw one reformatted panel on ``ax``: the image, the organ ``outlines`` ((s, t) mm) and the isodoses."""
    t = np.linspace(-half_width_mm, half_width_mm, round(2 * half_width_mm) + 1)
    surface = resample(path, s)[:, None, :] + t[None, :, None] * e[:, None, :]  # (ns, nt, 3), mm, LPS
    if volume is not None:
        lo, hi = display_window(volume)
        ax.imshow(_sample_image(volume, surface).T, cmap="gray", vmin=lo, vmax=hi, origin="lower",
                  extent=(s[0], s[-1], t[0], t[-1]), interpolation="bilinear", gid="image")
    for name, cut in outlines.items():
        ax.plot(cut[:, 0], cut[:, 1], color=organ_colour(name), lw=1.6, gid=f"organ:{name}")
    if dose is not None:
        coarse = surface[::2, ::2]
        pct = dose.dose_at(coarse.reshape(-1, 3)).reshape(coarse.shape[:2]) / dose.prescription_gy * 100.0
        for level, colour in ISODOSE_PERCENT:
            if pct.min() < level < pct.max():
                cs = ax.contour(s[::2], t[::2], pct.T, levels=[level], colors=[colour], linewidths=1.3,
                                linestyles=ISODOSE_STYLE)
                cs.set_gid(f"isodose:{level}")


def _dwell_s(path: np.ndarray, positions_mm: np.ndarray) -> np.ndarray:
    """Arc length (mm) of the centreline point nearest to each dwell position."""
    s = np.arange(0.0, arc_length(path)[-1] + 0.25, 0.25)
    if not len(positions_mm):
        return np.zeros(0)
    return s[cKDTree(resample(path, s)).query(np.asarray(positions_mm, dtype=float).reshape(-1, 3))[1]]


def needle_reformat_figure(scene: Scene, needle: Any, radius_mm: float, volume: Volume | None = None,
                           dose: DoseOverlay | None = None,
                           half_width_mm: float = HALF_WIDTH_MM) -> tuple[Figure, Closest | None]:
    """Draw the straightened slice along one needle: two panels 90° apart and its dwell times.

    Parameters
    ----------
    scene : Scene
        Organ meshes (mm, LPS); the clearance is measured to ``scene.organs``, the organs at risk.
    needle : NeedleExport
        The needle (:class:`reachplan.plugins.exporters.NeedleExport`): ``hole_id``, ``path_mm`` ((n, 3) mm, LPS,
        base to tip), ``dwell_positions_mm`` ((d, 3) mm, LPS), ``dwell_times_s`` ((d,) s) and ``schedule`` (None for
        a straight needle).
    radius_mm : float, mm
        The needle's radius (clearance is surface to surface).
    volume : Volume or None
        The image, sampled on the reformatted surface.
    dose : DoseOverlay or None
        The delivered plan's dose: isodose lines at :data:`~reachplan.planner.report.figures.ISODOSE_PERCENT`.
    half_width_mm : float, mm
        How far each panel reaches on either side of the needle (farther when the nearest organ is farther).

    Returns
    -------
    matplotlib.figure.Figure
        Axes with gids ``toward-organ`` (the clearance annotated, gid ``clearance``), ``turned`` and
        ``dwell-times`` (one bar per dwell, at its arc length).
    Closest or None
        The closest approach annotated (None without organs at risk).
    """
    path = np.asarray(needle.path_mm, dtype=float)
    steered = needle.schedule is not None
    colour, style = (STEERED_COLOUR, "-") if steered else (STRAIGHT_COLOUR, "--")
    closest = closest_approach(path, {o.name: o.mesh for o in scene.organs}, radius_mm)
    length = float(arc_length(path)[-1])
    if closest is not None:  # the nearest organ within the panel, however far
        half_width_mm = max(half_width_mm, closest.clearance_mm + radius_mm + 6.0)
    path, s, e1, e2, tan = _rulings(path, closest, scene.patient_from_template[:3, 1])
    at = int(np.argmin(np.abs(s - (closest.s_mm if closest is not None else length))))
    # mm square in both panels at the width available: the figure's height follows the needle's length
    width_in, bars_in, gap_in, top_in, bottom_in = 12.5, 1.5, 0.6, 0.95, 0.75
    panel_in = min(2 * half_width_mm * FIGURE_LEFT_RIGHT[2] * width_in / (s[-1] + 3.0), 3.6)
    height_in = top_in + 2 * panel_in + bars_in + 2 * gap_in + bottom_in
    fig = Figure(figsize=(width_in, height_in))
    axes = fig.subplots(3, 1, sharex=True, gridspec_kw={"height_ratios": [panel_in, panel_in, bars_in],
                                                         "hspace": gap_in / ((2 * panel_in + bars_in) / 3)})
    outlines = _outlines(scene, path, s, (e1, e2), half_width_mm)
    drawn = list(dict.fromkeys(n for panel in outlines for n in panel))
    d_s = _dwell_s(path, needle.dwell_positions_mm)
    for ax, e, gid, cuts in ((axes[0], e1, "toward-organ", outlines[0]), (axes[1], e2, "turned", outlines[1])):
        ax.set_gid(gid)
        _panel(ax, cuts, path, s, e, volume, dose, half_width_mm)
        ax.plot([0.0, length], [0.0, 0.0], style, color=colour, lw=2.4, gid=f"needle:{needle.hole_id}")
        ax.plot([length], [0.0], "o", color=colour, ms=6)
        ax.scatter(d_s, np.zeros(len(d_s)), s=14, color="k", zorder=5, gid="dwells")
        ax.set_xlim(-2.0, s[-1] + 1.0)
        ax.set_ylim(-half_width_mm, half_width_mm)
        ax.set_aspect("equal")
        ax.set_ylabel("offset from the\nneedle (mm)", fontsize=MIN_FONT_PT + 1)
        ax.tick_params(labelsize=MIN_FONT_PT)
        label_edges(ax, tan[at], e[at])
    _annotate(axes[0], closest, tan[at], e1[at])
    ax3 = axes[2]
    ax3.set_gid("dwell-times")
    ax3.bar(d_s, needle.dwell_times_s, width=1.6, color=colour, edgecolor="k", lw=0.5, gid="dwell-times")
    ax3.set_ylabel("dwell time (s)", fontsize=MIN_FONT_PT + 1)
    ax3.set_xlabel("arc length along the needle from its template hole (mm)", fontsize=MIN_FONT_PT + 1)
    ax3.tick_params(labelsize=MIN_FONT_PT)
    ax3.grid(True, axis="y", alpha=0.3)
    total = float(np.sum(needle.dwell_times_s))
    ax3.set_title(f"{len(d_s)} dwells, {total:.0f} s in all", fontsize=MIN_FONT_PT + 1, y=TITLE_Y)
    where = "no organ at risk" if closest is None else \
        f"toward the nearest organ at risk, {closest.organ}, {closest.clearance_mm:.1f} mm away"
    axes[0].set_title(f"turned {where}", fontsize=MIN_FONT_PT + 2, y=TITLE_Y)
    axes[1].set_title("turned 90° about the needle", fontsize=MIN_FONT_PT + 2, y=TITLE_Y)
    handles = [Line2D([], [], color=organ_colour(n), lw=1.6, label=n) for n in drawn]
    handles.append(Line2D([], [], color=colour, ls=style, lw=2.4,
                          label=f"{'steered' if steered else 'straight'} needle {needle.hole_id}"))
    if dose is not None:
        handles += [Line2D([], [], color=c, lw=1.3, ls=ISODOSE_STYLE, label=f"{p} % isodose")
                    for p, c in ISODOSE_PERCENT]
    handles.append(Line2D([], [], color="k", marker="o", ls="", ms=4, label="dwell positions"))
    fig.legend(handles=handles, loc="center right", fontsize=MIN_FONT_PT + 1, frameon=False)
    fig.suptitle(f"Needle {needle.hole_id}: the slice along it, straightened (base at the template hole, left)",
                 fontsize=13)
    fig.subplots_adjust(left=FIGURE_LEFT_RIGHT[0], right=FIGURE_LEFT_RIGHT[1], top=1 - top_in / height_in,
                        bottom=bottom_in / height_in)
    axes[0].apply_aspect()  # the panels keep mm square: the bars below take their width, so depths line up
    p0, p3 = axes[0].get_position(), ax3.get_position()
    ax3.set_position((p0.x0, p3.y0, p0.width, p3.height))
    return fig, closest


def _rulings(path: np.ndarray, closest: Closest | None,
             default: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Return the reformat's path (run on :data:`AHEAD_MM` past the tip), its arc lengths and directions.

    The arc lengths are every :data:`STEP_MM` with the tip and the point of closest approach; the directions the
    first panel's (toward the nearest organ, else ``default``), the second's (turned 90° about the needle) and the
    tangents, each (m, 3), unit vectors, LPS.
    """
    length = float(arc_length(path)[-1])
    ext = np.vstack([path, path[-1] + AHEAD_MM * _tangents(path, np.array([length]))[0]])
    s = np.unique(np.concatenate([np.arange(0.0, length + AHEAD_MM, STEP_MM), [length, length + AHEAD_MM],
                                  [] if closest is None else [closest.s_mm]]))
    towards = default if closest is None else closest.organ_point_mm - closest.needle_point_mm
    e1 = lateral_directions(ext, s, towards)
    tan = _tangents(ext, s)
    return ext, s, e1, np.cross(tan, e1), tan


def _annotate(ax: Any, closest: Closest | None, tangent: np.ndarray, lateral: np.ndarray) -> None:
    """Mark the closest approach on the panel turned toward it: a double arrow from the needle to the organ.

    The gap from the needle's point to the organ's lies in the plane of the needle's ``tangent`` and the panel's
    ``lateral`` direction there (the lateral is the gap less its component along the tangent), so the arrow is drawn
    at its true length: across the needle for a point along it, slanting ahead at the tip.
    """
    if closest is None:
        return
    gap = closest.organ_point_mm - closest.needle_point_mm
    s_o, t_o = closest.s_mm + float(gap @ tangent), float(gap @ lateral)
    ax.annotate("", xy=(s_o, t_o), xytext=(closest.s_mm, 0.0),
                arrowprops={"arrowstyle": "<->", "color": "#ffffff", "lw": 1.6, "shrinkA": 0, "shrinkB": 0},
                gid="clearance")
    ax.plot([s_o], [t_o], "x", color="#ffffff", ms=8, mew=2, gid="closest-point")
    left = closest.s_mm > 0.75 * ax.get_xlim()[1]
    ax.text((closest.s_mm + s_o) / 2 + (-2.0 if left else 2.0), t_o / 2, f"{closest.clearance_mm:.1f} mm",
            ha="right" if left else "left", va="center", fontsize=MIN_FONT_PT + 2, fontweight="bold",
            color="#000000", bbox={"boxstyle": "round,pad=0.2", "fc": "#ffffff", "ec": "none", "alpha": 0.85},
            gid="clearance-label")


def needle_reformat(scene: Scene, needle: Any, radius_mm: float, volume: Volume | None = None,
                    dose: DoseOverlay | None = None) -> tuple[bytes, Closest | None]:
    """:func:`needle_reformat_figure` as PNG bytes.

    Parameters
    ----------
    scene : Scene
        Organ meshes (mm, LPS).
    needle : NeedleExport
        The needle.
    radius_mm : float, mm
        The needle's radius.
    volume : Volume or None
        The image.
    dose : DoseOverlay or None
        The delivered plan's dose.

    Returns
    -------
    bytes
        PNG at the report's display resolution.
    Closest or None
        The closest approach annotated.
    """
    fig, closest = needle_reformat_figure(scene, needle, radius_mm, volume, dose)
    return png_bytes(fig), closest


def reformat_section(scene: Scene, radius_mm: float, volume: Volume | None, delivery: Delivery | None,
                     dose: DoseOverlay | None) -> Section | None:
    """Return the report's section of slices along each needle of the delivered implant.

    Parameters
    ----------
    scene : Scene
        Organ meshes (mm, LPS).
    radius_mm : float, mm
        The needles' radius.
    volume : Volume or None
        The image.
    delivery : Delivery or None
        The delivered plan: its exported needles (applicator channels left out) and, from the implant arm that
        holds them, each needle's worst case.
    dose : DoseOverlay or None
        The delivered plan's dose.

    Returns
    -------
    Section or None
        One figure per needle (alt text ``reformat along needle HOLE``); None without a delivered needle.
    """
    if delivery is None:
        return None
    needles = [n for n in delivery.export.needles if not n.applicator]
    if not needles:
        return None
    delivered = EXPORT_ARM if delivery.kind == "implant, straight + steered" else \
        delivery.kind.removeprefix("implant, ")
    arm = next((a for a in delivery.implant.arms if a.name == delivered), None) if delivery.implant else None
    checks = {c.name: c.check for c in arm.plan.channels} if arm is not None and arm.plan is not None else {}
    blocks: list[Block] = [Paragraph(
        "Each needle of the delivered implant, straightened: left to right along the needle from its template hole "
        "to its tip, up and down the offset from it. The upper panel is turned toward the nearest organ at risk, "
        "so that the needle's clearance (surface to surface, exact point-to-mesh distance) lies in it at its true "
        "length, marked by the white arrow; the middle panel is turned 90° about the needle; the letters on the "
        "edges give the patient directions at the point of closest approach. Organ outlines are cut from the "
        "meshes, the image is sampled along the same surface, the isodoses are the delivered plan's (50-200 % of "
        "the prescription), and the bars below give the needle's dwell times along it.")]
    for n in needles:
        png, closest = needle_reformat(scene, n, radius_mm, volume, dose)
        k = checks.get(n.hole_id)
        worst = "" if k is None or not np.isfinite(k.worst_clearance_mm) else (
            f"; worst case {k.worst_clearance_mm:.1f} mm under {k.worst_case}")
        near = "no organ at risk" if closest is None else (
            f"closest to {closest.organ}: {closest.clearance_mm:.1f} mm at {closest.s_mm:.0f} mm along the needle")
        blocks.append(FigureBlock(png, f"Needle {n.hole_id} ({'steered' if n.schedule is not None else 'straight'}): "
                                  f"{near}{worst}.", alt=f"reformat along needle {n.hole_id}"))
    return Section("Along each implant needle", "reformat", tuple(blocks))
