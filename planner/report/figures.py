"""Figures of the HTML report, each returned as PNG bytes: slices, the overview, the template map.

The charts (speed against accuracy, DVHs, Pareto curves) are :mod:`reachplan.planner.report.charts`.

Drawn on :class:`matplotlib.figure.Figure` objects, not pyplot: nothing here selects a backend or keeps a
figure alive, so importing this module changes no global state and needs no screen.

Geometry is in mm, DICOM patient coordinates (LPS: +x patient left, +y posterior, +z superior). Every view follows
one convention, the radiological one, and says so with A/P, L/R, S/I letters on its edges: axial slices and the
template map are seen from the patient's feet (the operator's view along the needles), patient left on the right
of the image and anterior at the top; coronal slices have the patient's left on the right and superior at the
top; sagittal slices are seen from the patient's left, anterior on the left and superior at the top.

The drawing functions ending in ``_figure`` return the :class:`matplotlib.figure.Figure` (tests read its
coordinates); the others return PNG bytes.
"""

from __future__ import annotations

import io
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import trimesh
from matplotlib.figure import Figure
from matplotlib.lines import Line2D
from matplotlib.ticker import FuncFormatter, NullFormatter

from reachplan.imaging.types import Volume
from reachplan.planner.case.scene import Scene
from reachplan.planner.steering.candidates import Candidate

ORGAN_COLOURS = {
    "Bladder": "#e6c229", "Rectum": "#8c564b", "Sigmoid": "#c49c94", "Bowel": "#f7b6d2", "Bone": "#5b7bd5",
    "HR-CTV": "#d62728", "Uterus": "#9467bd", "Cervix": "#ff9896", "Obturator": "#7f7f7f",
}
TARGET_COLOUR = "#2ca02c"
STRAIGHT_COLOUR = "#ff7f0e"
STEERED_COLOUR = "#17becf"

#: (axis normal to the plane, horizontal axis, vertical axis, name) of the three slice views.
VIEWS: tuple[tuple[int, int, int, str], ...] = ((2, 0, 1, "axial"), (0, 1, 2, "sagittal"), (1, 0, 2, "coronal"))
AXIS_LABELS = ("x (mm, patient left +)", "y (mm, posterior +)", "z (mm, superior +)")
#: Letters of the negative and positive ends of the LPS axes.
DIRECTION_LETTERS = (("R", "L"), ("A", "P"), ("I", "S"))
#: Caption words for the orientation of the axial slices and the template map.
RADIOLOGICAL = ("seen from the patient's feet, as the operator sees the template (radiological convention): "
                "patient left on the right, anterior at the top")


def direction_letter(v: np.ndarray) -> str:
    """Return the anatomical letter (R/L, A/P, I/S) of the LPS component that dominates a direction.

    Parameters
    ----------
    v : (3,) float, LPS
        The direction.

    Returns
    -------
    str
        One letter: the negative or positive end of the dominant axis.
    """
    v = np.asarray(v, dtype=float)
    i = int(np.argmax(np.abs(v)))
    return DIRECTION_LETTERS[i][int(v[i] > 0)]


def label_edges(ax: Any, right: np.ndarray, up: np.ndarray) -> None:
    """Write the anatomical letter of each edge of a 2-D axes inside it (inverted axes are taken into account).

    Parameters
    ----------
    ax : matplotlib.axes.Axes
        The axes.
    right : (3,) float, LPS
        Patient direction of the axes' +horizontal data axis.
    up : (3,) float, LPS
        Patient direction of the axes' +vertical data axis.
    """
    r = -np.asarray(right, float) if ax.xaxis_inverted() else np.asarray(right, float)
    u = -np.asarray(up, float) if ax.yaxis_inverted() else np.asarray(up, float)
    box = {"boxstyle": "round,pad=0.15", "fc": "white", "ec": "none", "alpha": 0.75}
    for (x, y), d, ha, va in (((0.01, 0.5), -r, "left", "center"), ((0.99, 0.5), r, "right", "center"),
                              ((0.5, 0.99), u, "center", "top"), ((0.5, 0.01), -u, "center", "bottom")):
        ax.text(x, y, direction_letter(d), transform=ax.transAxes, ha=ha, va=va, fontsize=10, fontweight="bold",
                color="#1d2b45", bbox=box, gid="orientation")


_UNIT = np.eye(3)
#: Axes titles at a fixed height (just above the axes): matplotlib's automatic placement measures every tick label
#: of the axes on each draw, a sixth of a slice figure's drawing time; no figure here has tick labels on top.
TITLE_Y = 1.0


def png_bytes(fig: Figure, dpi: int = 100) -> bytes:
    """Render a figure to PNG bytes at the size it is shown: an 8-bit palette image.

    256 colours (fast octree quantisation) keep the line art and the grey image underneath, at about a third of the
    size of matplotlib's RGBA PNG.

    Parameters
    ----------
    fig : matplotlib.figure.Figure
        The figure (its log axes get plain labels, :func:`plain_log_labels`).
    dpi : int
        Dots per inch.

    Returns
    -------
    bytes
        The PNG file.
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from PIL import Image

    plain_log_labels(fig)
    fig.set_dpi(dpi)
    canvas = FigureCanvasAgg(fig)
    canvas.draw()  # drawn once, straight to pixels: no intermediate RGBA PNG to encode and decode
    rgba = Image.frombuffer("RGBA", canvas.get_width_height(), canvas.buffer_rgba(), "raw", "RGBA", 0, 1)
    out = io.BytesIO()
    rgba.convert("RGB").quantize(256, method=Image.Quantize.FASTOCTREE).save(out, format="PNG")
    return out.getvalue()


def plain_log_labels(fig: Figure) -> None:
    """Label the log axes of ``fig`` in plain numbers (0.1, 1, 10) rather than mathtext powers of ten.

    Matplotlib parses every ``$10^{n}$`` tick label with its mathtext parser, about a tenth of the report's
    drawing time; plain labels read as well.

    Parameters
    ----------
    fig : matplotlib.figure.Figure
        The figure, changed in place.
    """
    for ax in fig.axes:
        for axis in (ax.xaxis, ax.yaxis):
            if axis.get_scale() == "log":
                axis.set_major_formatter(FuncFormatter(lambda v, _: f"{v:g}"))
                axis.set_minor_formatter(NullFormatter())


def organ_colour(name: str) -> str:
    """Display colour of an organ (target ROIs green, unknown ones grey).

    Parameters
    ----------
    name : str
        The organ's or ROI's name.

    Returns
    -------
    str
        ``#rrggbb``.
    """
    if name.casefold().startswith("target"):
        return TARGET_COLOUR
    return ORGAN_COLOURS.get(name, "#7f7f7f")


def _section(mesh: trimesh.Trimesh, axis: int, value_mm: float) -> list[np.ndarray]:
    """Return where the plane ``x[axis] = value_mm`` cuts ``mesh``, as drawable outlines.

    One (3 n, 3) float array (mm, LPS) of the n cut segments, each two points followed by a NaN row (so one
    ``plot`` call draws them all), in a list; an empty list when the plane misses the mesh. Computed directly from
    the faces the plane crosses (a vertex on the plane counts as above it), without chaining the segments into
    loops.
    """
    lo, hi = mesh.bounds[:, axis]
    if not lo < value_mm <= hi:  # the plane misses the mesh (every vertex on one side): nothing to cut
        return []
    return plane_section(mesh, _UNIT[axis], value_mm)


def plane_section(mesh: trimesh.Trimesh, normal: np.ndarray, offset_mm: float) -> list[np.ndarray]:
    """Return where the plane ``x · normal = offset_mm`` cuts ``mesh``, as :func:`_section` does.

    Parameters
    ----------
    mesh : trimesh.Trimesh
        The organ's mesh, mm, LPS.
    normal : (3,) float, unit vector, LPS
        The plane's normal.
    offset_mm : float, mm
        The plane's signed distance from the origin.

    Returns
    -------
    list of (3 n, 3) float, mm, LPS
        One array of the n cut segments, each two points followed by a NaN row; empty when the plane misses.
    """
    v, f = np.asarray(mesh.vertices), np.asarray(mesh.faces)
    height = v @ np.asarray(normal, dtype=float) - offset_mm  # signed distance of each vertex, mm
    above = height >= 0.0
    side = above[f]
    crossed = (side[:, 0] != side[:, 1]) | (side[:, 1] != side[:, 2])  # not all three on one side
    if not crossed.any():
        return []
    tri, side = v[f[crossed]], side[crossed]
    d = height[f[crossed]]
    pts, cuts = [], []
    for i, j in ((0, 1), (1, 2), (2, 0)):
        cut = side[:, i] != side[:, j]
        t = np.where(cut, d[:, i] / np.where(cut, d[:, i] - d[:, j], 1.0), 0.0)
        pts.append(tri[:, i] + t[:, None] * (tri[:, j] - tri[:, i]))
        cuts.append(cut)
    seg = np.stack(pts, axis=1)[np.stack(cuts, axis=1)].reshape(-1, 2, 3)  # two crossed edges per face
    out = np.concatenate([seg, np.full((len(seg), 1, 3), np.nan)], axis=1)
    return [out.reshape(-1, 3)]


def _background(ax: Any, volume: Volume | None, axis: int, value_mm: float) -> None:
    """Draw the image slice of ``volume`` at ``x[axis] = value_mm`` (axis-aligned grids only) in grey."""
    if volume is None:
        return
    m = volume.grid.patient_from_index
    if not np.allclose(m[:3, :3], np.diag(np.diag(m[:3, :3]))) or np.any(np.diag(m[:3, :3]) <= 0):
        return  # oblique or flipped grid: organ outlines only
    nk, nj, ni = volume.grid.shape
    idx = float(volume.grid.to_index(np.array([[value_mm] * 3]))[0][axis])
    if not -0.5 <= idx <= (ni, nj, nk)[axis] - 0.5:
        return
    n = round(idx)
    lo = volume.grid.to_patient(np.array([[0, 0, 0]]))[0]
    hi = volume.grid.to_patient(np.array([[ni - 1, nj - 1, nk - 1]]))[0]
    if axis == 2:
        img, ext = volume.array[n], (lo[0], hi[0], lo[1], hi[1])
    elif axis == 0:
        img, ext = volume.array[:, :, n], (lo[1], hi[1], lo[2], hi[2])
    else:
        img, ext = volume.array[:, n, :], (lo[0], hi[0], lo[2], hi[2])
    ax.imshow(img, cmap="gray", vmin=-200, vmax=300, origin="lower", extent=ext, interpolation="nearest")


def _box(points: Sequence[np.ndarray], margin_mm: float) -> tuple[np.ndarray, np.ndarray]:
    p = np.concatenate([np.atleast_2d(q) for q in points])
    return np.nanmin(p, axis=0) - margin_mm, np.nanmax(p, axis=0) + margin_mm


@dataclass(frozen=True, eq=False)
class DoseOverlay:
    """The delivered dose, for isodose lines and dwell positions on the slices.

    Parameters
    ----------
    dose_at : callable, (n, 3) float mm LPS -> (n,) float Gy
        Dose per fraction at points.
    prescription_gy : float
        Per-fraction prescription (Gy); the lines are drawn at :data:`ISODOSE_PERCENT` of it.
    dwell_positions_mm : (m, 3) float, mm, LPS
        Active dwell positions (time > 0).
    dwell_times_s : (m,) float, s
    """

    dose_at: Callable[[np.ndarray], np.ndarray]
    prescription_gy: float
    dwell_positions_mm: np.ndarray
    dwell_times_s: np.ndarray


#: Isodose levels, % of the prescription, and their colours.
ISODOSE_PERCENT: tuple[tuple[int, str], ...] = ((50, "#1f77b4"), (100, "#00e5a0"), (150, "#ff00ff"),
                                                (200, "#ffee00"))
#: Isodose lines are dash-dotted, organ outlines solid.
ISODOSE_STYLE = "-."


def _isodoses(ax: Any, dose: DoseOverlay, normal: int, value_mm: float, u: int, v: int, lo: np.ndarray,
              hi: np.ndarray, n: int = 70) -> None:
    """Draw isodose lines of ``dose`` on the plane ``x[normal] = value_mm`` and the dwells near it.

    Over the box ``lo``..``hi`` (mm, LPS); the dwell positions within 2.5 mm of the plane are dots sized by dwell
    time, labelled in s.
    """
    gu, gv = np.linspace(lo[u], hi[u], n), np.linspace(lo[v], hi[v], n)
    uu, vv = np.meshgrid(gu, gv)
    pts = np.zeros((uu.size, 3))
    pts[:, normal], pts[:, u], pts[:, v] = value_mm, uu.ravel(), vv.ravel()
    d = dose.dose_at(pts).reshape(uu.shape) / dose.prescription_gy * 100.0
    for pct, colour in ISODOSE_PERCENT:
        if d.min() < pct < d.max():
            cs = ax.contour(uu, vv, d, levels=[pct], colors=[colour], linewidths=1.2, linestyles=ISODOSE_STYLE)
            cs.set_gid(f"isodose:{pct}")
    near = np.abs(dose.dwell_positions_mm[:, normal] - value_mm) <= 2.5
    p, t = dose.dwell_positions_mm[near], dose.dwell_times_s[near]
    if len(p):
        ax.scatter(p[:, u], p[:, v], s=6 + 40 * t / max(float(dose.dwell_times_s.max()), 1e-9), color="k",
                   zorder=6, gid="dwells")
        for q, ti in zip(p, t, strict=True):
            ax.annotate(f"{ti:.0f}", (q[u], q[v]), xytext=(2, 2), textcoords="offset points", fontsize=5)


def slice_figure(scene: Scene, target: str, straight: Candidate | None, steered: Candidate | None,
                 volume: Volume | None = None, organs: Sequence[str] | None = None,
                 window_mm: float = 120.0, dose: DoseOverlay | None = None) -> Figure:
    """Axial, sagittal and coronal slices through a target with organ outlines and its two needles.

    The needles (best straight: dashed orange, best steered: solid cyan) are drawn projected onto each
    plane, with their tips as dots; the target point is a green cross. Each view shows the needles and
    the outlines in its plane, at most ``window_mm`` from the target. Organ outlines carry the gid
    ``organ:NAME``, the axes the gid of their view (``axial``, ``sagittal``, ``coronal``).

    Parameters
    ----------
    scene : Scene
        Organ meshes and targets, mm, LPS.
    target : str
        The target's name; the planes pass through its point.
    straight : Candidate or None
        Its best straight needle.
    steered : Candidate or None
        Its best steered needle.
    volume : Volume or None
        The image, drawn in grey underneath (axis-aligned grids only).
    organs : sequence of str or None
        The meshes to outline (default: the organs at risk, HR-CTV and the target's own ROI).
    window_mm : float, mm
        Half-width of each view.
    dose : DoseOverlay or None
        Isodose lines (50, 100, 150, 200 % of the prescription) and dwell positions with their times (s).

    Returns
    -------
    matplotlib.figure.Figure
        Three axes, in the radiological convention (see the module docstring).
    """
    point = np.asarray(next(t.position_mm for t in scene.targets if t.name == target), dtype=float)
    names = list(organs) if organs is not None else [*(o.name for o in scene.organs), "HR-CTV", target]
    meshes = {n: scene.meshes[n] for n in names if n in scene.meshes}
    needles = [(c, STRAIGHT_COLOUR, "--") for c in (straight,) if c is not None]
    needles += [(c, STEERED_COLOUR, "-") for c in (steered,) if c is not None]
    fig = Figure(figsize=(13.5, 5.2))
    axes = fig.subplots(1, 3)
    for ax, (normal, u, v, view) in zip(axes, VIEWS, strict=True):
        ax.set_gid(view)
        _background(ax, volume, normal, float(point[normal]))
        around = [point[None], *(c.path_mm for c, _, _ in needles)]
        for name, mesh in meshes.items():
            for loop in _section(mesh, normal, float(point[normal])):
                ax.plot(loop[:, u], loop[:, v], color=organ_colour(name), lw=1.4, gid=f"organ:{name}")
                around.append(loop)
        for c, colour, style in needles:
            ax.plot(c.path_mm[:, u], c.path_mm[:, v], style, color=colour, lw=1.6)
            ax.plot(c.path_mm[-1, u], c.path_mm[-1, v], "o", color=colour, ms=4)
        ax.plot(point[u], point[v], "+", color=TARGET_COLOUR, ms=12, mew=2)
        lo, hi = _box(around, 10.0)
        lo, hi = np.maximum(lo, point - window_mm), np.minimum(hi, point + window_mm)
        span = max(hi[u] - lo[u], hi[v] - lo[v]) / 2  # square panels: no view cropped to a thin strip
        lo[[u, v]] = (lo[[u, v]] + hi[[u, v]]) / 2 - span
        hi[[u, v]] = lo[[u, v]] + 2 * span
        if dose is not None:
            _isodoses(ax, dose, normal, float(point[normal]), u, v, lo, hi)
        ax.set_xlim(lo[u], hi[u])
        ax.set_ylim((hi[v], lo[v]) if view == "axial" else (lo[v], hi[v]))  # axial: anterior (-y) at the top
        ax.set_aspect("equal")
        seen = {"axial": "from the feet", "sagittal": "from the patient's left", "coronal": "from the front"}[view]
        ax.set_title(f"{view} ({seen}), {'xyz'[normal]} = {point[normal]:.0f} mm", fontsize=10, y=TITLE_Y)
        ax.set_xlabel(AXIS_LABELS[u], fontsize=8)
        ax.set_ylabel(AXIS_LABELS[v], fontsize=8)
        ax.tick_params(labelsize=7)
        ax.locator_params(nbins=5)
        label_edges(ax, _UNIT[u], _UNIT[v])
    handles = [Line2D([], [], color=organ_colour(n), label=n) for n in meshes]
    if straight is not None:
        handles.append(Line2D([], [], color=STRAIGHT_COLOUR, ls="--", label=f"straight {straight.hole_id}"))
    if steered is not None:
        handles.append(Line2D([], [], color=STEERED_COLOUR, label=f"steered {steered.hole_id}"))
    if dose is not None:
        handles += [Line2D([], [], color=c, lw=1.2, ls=ISODOSE_STYLE, label=f"{p} %") for p, c in ISODOSE_PERCENT]
        handles.append(Line2D([], [], color="k", marker="o", ls="", ms=3, label="dwell (s)"))
    fig.legend(handles=handles, loc="lower center", ncol=min(len(handles), 9), fontsize=8, facecolor="#cfcfcf")
    fig.suptitle(f"{target}: needles projected onto the slices through the target", fontsize=11)
    fig.subplots_adjust(left=0.05, right=0.99, top=0.9, bottom=0.2, wspace=0.25)
    return fig


def slice_views(scene: Scene, target: str, straight: Candidate | None, steered: Candidate | None,
                volume: Volume | None = None, organs: Sequence[str] | None = None,
                window_mm: float = 120.0, dose: DoseOverlay | None = None) -> bytes:
    """:func:`slice_figure` as PNG bytes.

    Parameters
    ----------
    scene : Scene
        Organ meshes and targets, mm, LPS.
    target : str
        The target's name.
    straight : Candidate or None
        Its best straight needle.
    steered : Candidate or None
        Its best steered needle.
    volume : Volume or None
        The image underneath.
    organs : sequence of str or None
        The meshes to outline.
    window_mm : float, mm
        Half-width of each view.
    dose : DoseOverlay or None
        Isodoses and dwells.

    Returns
    -------
    bytes
        PNG at 90 dpi.
    """
    return png_bytes(slice_figure(scene, target, straight, steered, volume, organs, window_mm, dose), dpi=90)


def overview(scene: Scene, needles: Sequence[Candidate], volume: Volume | None = None) -> bytes:
    """Draw the axial slice at the targets' mean height and the mid-sagittal slice (x = 0 mm) as PNG bytes.

    With organ outlines, the target points (green crosses) and ``needles`` (steered: solid cyan, straight: dashed
    orange).

    Parameters
    ----------
    scene : Scene
        Organ meshes and targets, mm, LPS.
    needles : sequence of Candidate
        The needles to draw.
    volume : Volume or None
        The image underneath.

    Returns
    -------
    bytes
        PNG.
    """
    points = np.array([t.position_mm for t in scene.targets], dtype=float).reshape(-1, 3)
    tz = float(np.mean(points[:, 2]))
    fig = Figure(figsize=(12, 6))
    axes = fig.subplots(1, 2)
    for ax, (normal, u, v, view), value in zip(axes, VIEWS[:2], (tz, 0.0), strict=True):
        _background(ax, volume, normal, value)
        for name, mesh in scene.meshes.items():
            for loop in _section(mesh, normal, value):
                ax.plot(loop[:, u], loop[:, v], color=organ_colour(name), lw=1.2)
        for c in needles:
            colour, style = (STEERED_COLOUR, "-") if c.steered else (STRAIGHT_COLOUR, "--")
            ax.plot(c.path_mm[:, u], c.path_mm[:, v], style, color=colour, lw=1)
            ax.plot(c.path_mm[-1, u], c.path_mm[-1, v], "o", color=colour, ms=3)
        if view == "axial":
            ax.plot(points[:, u], points[:, v], "+", color=TARGET_COLOUR, ms=8, ls="")
        ax.set(title=f"{view}, {'xyz'[normal]} = {value:.0f} mm", xlabel=AXIS_LABELS[u], ylabel=AXIS_LABELS[v])
        ax.set_aspect("equal")
    axes[0].set_ylim(sorted(axes[0].get_ylim(), reverse=True))  # axial: anterior (-y) at the top
    axes[0].set_title(f"axial (from the feet), z = {tz:.0f} mm")
    axes[1].set_title("sagittal (from the patient's left), x = 0 mm")
    for ax, (_, u, v, _) in zip(axes, VIEWS[:2], strict=True):
        label_edges(ax, _UNIT[u], _UNIT[v])
    handles = [Line2D([], [], color=organ_colour(n), label=n) for n in scene.meshes
               if not n.casefold().startswith("target")]
    handles += [Line2D([], [], color=TARGET_COLOUR, marker="+", ls="", label="target points and ROIs"),
                Line2D([], [], color=STEERED_COLOUR, label="top needle per target: steered"),
                Line2D([], [], color=STRAIGHT_COLOUR, ls="--", label="top needle per target: straight")]
    fig.legend(handles=handles, loc="lower center", ncol=min(len(handles), 6), fontsize=8, frameon=False)
    fig.subplots_adjust(left=0.06, right=0.985, top=0.94, bottom=0.19, wspace=0.22)  # fixed: no tight-layout pass
    return png_bytes(fig, dpi=110)


#: Faces of an organ in the 3-D view: quadric decimation keeps the organs' shapes (bladder, rectum, pelvic bone)
#: recognisable at this size and the report small.
VIEW_FACES = 1500
#: A mesh with more than this many times :data:`VIEW_FACES` faces is first clustered down to that many
#: (:func:`cluster_vertices`): quadric decimation of the demo's 243k-face pelvic bone took 0.49 s and stopped at
#: 3.5k faces with parts of the bone gone (64 mm from the original at worst); clustered first, 0.07 s in all and
#: within 2.3 mm.
CLUSTER_FACTOR = 4


def cluster_vertices(mesh: trimesh.Trimesh, face_count: int) -> trimesh.Trimesh:
    """Return ``mesh`` simplified to about ``face_count`` faces by vertex clustering (mm, LPS).

    The vertices are binned on a cubic grid whose cell, ``sqrt(2 area / face_count)``, holds about two faces of a
    smooth surface; each cell's vertices merge into their mean, and faces that collapse or repeat are dropped
    (Rossignac and Borrel, "Multi-resolution 3D approximations for rendering complex scenes", 1993). Linear in
    the faces, vectorised; the result is for drawing (it may be non-manifold where thin parts meet). A mesh with
    no area is returned as it is.

    Parameters
    ----------
    mesh : trimesh.Trimesh
        The mesh, mm, LPS.
    face_count : int
        About how many faces to keep.

    Returns
    -------
    trimesh.Trimesh
        The simplified mesh, mm, LPS.
    """
    v0 = np.asarray(mesh.vertices, dtype=float)
    area = float(mesh.area)
    if not np.isfinite(area) or area <= 0.0 or face_count < 1:
        return mesh
    cell_mm = float(np.sqrt(2.0 * area / face_count))
    key3 = np.floor((v0 - v0.min(axis=0)) / cell_mm).astype(np.int64)
    dims = key3.max(axis=0) + 1
    _, inv, counts = np.unique((key3[:, 0] * dims[1] + key3[:, 1]) * dims[2] + key3[:, 2], return_inverse=True,
                               return_counts=True)
    inv = inv.ravel()
    sums = np.stack([np.bincount(inv, weights=v0[:, i], minlength=counts.size) for i in range(3)], axis=1)
    merged = sums / counts[:, None].astype(float)
    f = inv[np.asarray(mesh.faces)]
    f = f[(f[:, 0] != f[:, 1]) & (f[:, 1] != f[:, 2]) & (f[:, 2] != f[:, 0])]
    s, n = np.sort(f, axis=1), counts.size
    if n < 2**20:  # one integer per vertex triple (n**3 < 2**63)
        _, first = np.unique((s[:, 0] * n + s[:, 1]) * n + s[:, 2], return_index=True)
    else:
        _, first = np.unique(s, axis=0, return_index=True)
    return trimesh.Trimesh(merged, f[np.sort(first)], process=False)


def light_mesh(mesh: trimesh.Trimesh, max_faces: int = VIEW_FACES) -> trimesh.Trimesh:
    """Return a mesh with at most about ``max_faces`` faces for 3-D drawing (mm, LPS).

    Quadric decimation (trimesh with the ``fast-simplification`` package, aggressiveness 9 of 10: a fifth faster than
    its default 7 and alike at this size), after :func:`cluster_vertices` down to :data:`CLUSTER_FACTOR` times the
    budget for a mesh larger than that; a mesh already within the budget is returned as it is.

    Parameters
    ----------
    mesh : trimesh.Trimesh
        The mesh, mm, LPS.
    max_faces : int
        Face budget.

    Returns
    -------
    trimesh.Trimesh
        mm, LPS.
    """
    if len(mesh.faces) <= max_faces:
        return mesh
    if len(mesh.faces) > CLUSTER_FACTOR * max_faces:
        mesh = cluster_vertices(mesh, CLUSTER_FACTOR * max_faces)
    return mesh.simplify_quadric_decimation(face_count=max_faces, aggression=9)


def template_map_figure(scene: Scene, straight: Sequence[Candidate], steered: Sequence[Candidate]) -> Figure:
    """Draw the template's holes with their names (mm, template frame), as the operator sees the template.

    Seen from the patient's feet along the needles: the same orientation as the axial slices
    (:data:`RADIOLOGICAL`). The axes are flipped as the pose requires (patient left to the right, anterior up)
    and the edges carry the anatomical letters of the pose. The holes of the chosen needles are filled and named
    in bold; the hole markers carry the gid ``holes``.

    Parameters
    ----------
    scene : Scene
        The template and its pose.
    straight : sequence of Candidate
        The chosen straight needles.
    steered : sequence of Candidate
        The chosen steered needles.

    Returns
    -------
    matplotlib.figure.Figure
        One axes in template coordinates (mm).
    """
    m = scene.patient_from_template
    fig = Figure(figsize=(8.0, 5.2))
    ax = fig.add_subplot()
    holes = {h.hole_id: h for h in scene.template.holes}
    xy = np.array([h.xy_mm for h in scene.template.holes])
    ax.scatter(xy[:, 0], xy[:, 1], s=22, facecolors="none", edgecolors="#999999", label="hole", gid="holes")
    for h in scene.template.holes:
        if h.kind != "needle":
            ax.scatter(*h.xy_mm, s=60, marker="s", color="#7f7f7f", label=h.kind)
    used_all: set[str] = set()
    for cands, colour, label in ((straight, STRAIGHT_COLOUR, "straight"), (steered, STEERED_COLOUR, "steered")):
        used = sorted({c.hole_id for c in cands})
        used_all |= set(used)
        if not used:
            continue
        p = np.array([holes[u].xy_mm for u in used])
        ax.scatter(p[:, 0], p[:, 1], s=70 if label == "straight" else 34, color=colour, label=f"{label} needle")
    for h in scene.template.holes:
        ax.annotate(h.hole_id, h.xy_mm, xytext=(0, 4.5), textcoords="offset points", fontsize=5.5, ha="center",
                    fontweight="bold" if h.hole_id in used_all else "normal",
                    color="#000000" if h.hole_id in used_all else "#555555")
    ax.set_aspect("equal")
    ax.margins(0.08)
    if m[0, 0] < 0:  # template +x towards the patient's right: flip so that the patient's left is on the right
        ax.invert_xaxis()
    if m[1, 1] > 0:  # template +y posterior: flip so that anterior is at the top
        ax.invert_yaxis()
    label_edges(ax, m[:3, 0], m[:3, 1])
    ax.set(xlabel="template x (mm)", ylabel="template y (mm)")
    ax.set_title(f"template {scene.template.name}, seen from the patient's feet (operator's view)", fontsize=10,
                 y=TITLE_Y)
    ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.02, 1.0))
    fig.subplots_adjust(left=0.08, right=0.79, top=0.93, bottom=0.1)  # fixed margins: no tight-layout pass
    return fig


def template_map(scene: Scene, straight: Sequence[Candidate], steered: Sequence[Candidate]) -> bytes:
    """:func:`template_map_figure` as PNG bytes.

    Parameters
    ----------
    scene : Scene
        Template and pose, as for :func:`template_map_figure`.
    straight : sequence of Candidate
        Straight needles whose holes are marked.
    steered : sequence of Candidate
        Steered needles whose holes are marked.

    Returns
    -------
    bytes
        PNG at 90 dpi.
    """
    return png_bytes(template_map_figure(scene, straight, steered), dpi=90)


