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

#: Display colour of each organ (matched without regard to case; GTV_res and the like take the GTV's). Chosen
#: so that every two of these, and each against the needle and target colours below, differ by a CIEDE2000 colour
#: difference of at least 20 (tests/planner/report/test_figures_legible.py measures it; docs/report.md lists the
#: palette): rectum brown, sigmoid dark purple and bowel magenta instead of light browns and pinks.
ORGAN_COLOURS = {
    "Bladder": "#f0c808", "Rectum": "#8c510a", "Sigmoid": "#762a83", "Bowel": "#e7298a", "Bone": "#3b5bdb",
    "HR-CTV": "#d62728", "GTV": "#7a0019", "Uterus": "#9e7fd6", "Cervix": "#f4b6c2", "Obturator": "#9a9a9a",
    "Tandem": "#404040",
}
#: Colour of an ROI not in :data:`ORGAN_COLOURS`.
OTHER_COLOUR = "#7f7f7f"
TARGET_COLOUR = "#2ca02c"
STRAIGHT_COLOUR = "#ff7f0e"
STEERED_COLOUR = "#17becf"
#: Smallest font of any text in a report figure, in points at the size the report shows it (figures are rendered
#: at :data:`DISPLAY_DPI`, one image pixel per CSS pixel, so a matplotlib point is a point on the screen).
MIN_FONT_PT = 9.0
#: Dots per inch of the report's PNG figures: CSS's 96 px per inch, so the browser shows them at their own size.
DISPLAY_DPI = 96
#: Widest figure the report shows at its own size (CSS px): ``main`` is 1400 px wide less 2 x 32 px padding.
MAX_DISPLAY_WIDTH_PX = 1336

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
        ax.text(x, y, direction_letter(d), transform=ax.transAxes, ha=ha, va=va, fontsize=11, fontweight="bold",
                color="#1d2b45", bbox=box, gid="orientation")


_UNIT = np.eye(3)
#: Axes titles at a fixed height (just above the axes): matplotlib's automatic placement measures every tick label
#: of the axes on each draw, a sixth of a slice figure's drawing time; no figure here has tick labels on top.
TITLE_Y = 1.0


def png_bytes(fig: Figure, dpi: int = DISPLAY_DPI) -> bytes:
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
    key = name.casefold()
    if key.startswith("target"):
        return TARGET_COLOUR
    by_key = {k.casefold(): v for k, v in ORGAN_COLOURS.items()}
    if key.startswith("gtv"):
        return ORGAN_COLOURS["GTV"]
    return by_key.get(key, OTHER_COLOUR)


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
    return plane_cut(np.asarray(mesh.vertices), np.asarray(mesh.faces), normal, offset_mm)


def plane_cut(v: np.ndarray, f: np.ndarray, normal: np.ndarray, offset_mm: float) -> list[np.ndarray]:
    """Return where the plane ``x · normal = offset_mm`` cuts the triangles ``f`` of the vertices ``v``.

    :func:`plane_section` on arrays (a mesh's faces, or a subset of them).

    Parameters
    ----------
    v : (n, 3) float, mm, LPS
        Vertices.
    f : (m, 3) int
        Triangles, as indices into ``v``.
    normal : (3,) float, unit vector, LPS
        The plane's normal.
    offset_mm : float, mm
        The plane's signed distance from the origin.

    Returns
    -------
    list of (3 n, 3) float, mm, LPS
        One array of the n cut segments, each two points followed by a NaN row; empty when the plane misses.
    """
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


#: The CT window of the slices (HU): a soft-tissue window, level 50 and width 500.
CT_WINDOW_HU = (-200.0, 300.0)
#: Percentiles of an image's own voxels that bound the grey scale of any other modality (MR): the brightest half
#: per cent saturates, not the organs.
WINDOW_PERCENTILES = (1.0, 99.5)


def display_window(volume: Volume) -> tuple[float, float]:
    """Return the grey-scale window (lowest, highest value) the slices draw ``volume`` with.

    CT in Hounsfield units gets the fixed soft-tissue window :data:`CT_WINDOW_HU`; any other modality (MR, in
    arbitrary units) the :data:`WINDOW_PERCENTILES` of its own voxels (on at most about 2 x 10⁵ voxels, evenly
    strided), so that its organs are not saturated at a CT window.

    Parameters
    ----------
    volume : Volume
        The image.

    Returns
    -------
    tuple of float
        (vmin, vmax) in the image's units, vmin < vmax.
    """
    if volume.modality.upper() == "CT":
        return CT_WINDOW_HU
    a = np.asarray(volume.array)
    step = max(1, round((a.size / 2e5) ** (1.0 / 3.0)))
    lo, hi = (float(v) for v in np.percentile(a[::step, ::step, ::step], WINDOW_PERCENTILES))
    return (lo, hi) if hi > lo else (lo, lo + 1.0)


def _background(ax: Any, volume: Volume | None, axis: int, value_mm: float,
                window: tuple[float, float] | None = None) -> None:
    """Draw the image slice of ``volume`` at ``x[axis] = value_mm`` (axis-aligned grids only) in grey.

    ``window``: (vmin, vmax) of the grey scale; None: :func:`display_window`.
    """
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
    vmin, vmax = display_window(volume) if window is None else window
    ax.imshow(img, cmap="gray", vmin=vmin, vmax=vmax, origin="lower", extent=ext, interpolation="nearest",
              gid="image")


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
    time (their times are in each needle's reformat, :mod:`reachplan.planner.report.reformat`: labels 2.5 mm apart
    would cover one another at a legible size).
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


#: A needle is drawn solid (or dashed) where it lies within this distance of a slice's plane, faint elsewhere: a
#: needle passing in front of an organ is not drawn across it.
IN_PLANE_MM = 5.0


def draw_needle(ax: Any, path_mm: np.ndarray, normal: int, value_mm: float, u: int, v: int, colour: str,
                style: str, gid: str) -> None:
    """Draw a needle on the slice ``x[normal] = value_mm``: full strength within :data:`IN_PLANE_MM`, faint beyond.

    Parameters
    ----------
    ax : matplotlib.axes.Axes
        The slice's axes (horizontal ``x[u]``, vertical ``x[v]``, mm).
    path_mm : (n, 3) float, mm, LPS
        The needle's centreline, base to tip; its tip is a dot.
    normal : int
        LPS axis of the plane's normal.
    value_mm : float, mm
        The plane's position along ``normal``.
    u : int
        LPS axis of the axes' horizontal direction.
    v : int
        LPS axis of the axes' vertical direction.
    colour : str
        Line colour.
    style : str
        Line style (``"-"`` steered, ``"--"`` straight).
    gid : str
        The in-plane line's gid (the faint one gets ``GID:projected``).
    """
    p = np.asarray(path_mm, dtype=float)
    ax.plot(p[:, u], p[:, v], style, color=colour, lw=1.1, alpha=0.35, gid=f"{gid}:projected")
    near = np.where((np.abs(p[:, normal] - value_mm) <= IN_PLANE_MM)[:, None], p, np.nan)
    ax.plot(near[:, u], near[:, v], style, color=colour, lw=1.8, gid=gid)
    ax.plot(p[-1, u], p[-1, v], "o", color=colour, ms=4, alpha=1.0 if np.isfinite(near[-1, 0]) else 0.35)


def slice_figure(scene: Scene, target: str, straight: Candidate | None, steered: Candidate | None,
                 volume: Volume | None = None, organs: Sequence[str] | None = None,
                 window_mm: float = 120.0, dose: DoseOverlay | None = None) -> Figure:
    """Axial, sagittal and coronal slices through a target with organ outlines and its two needles.

    The needles (best straight: dashed orange, best steered: solid cyan) are drawn projected onto each
    plane, at full strength within :data:`IN_PLANE_MM` of it and faint beyond, with their tips as dots; the
    target point is a green cross. Each view shows the needles and
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
    fig = Figure(figsize=(13.5, 5.6))
    axes = fig.subplots(1, 3)
    grey = None if volume is None else display_window(volume)
    for ax, (normal, u, v, view) in zip(axes, VIEWS, strict=True):
        ax.set_gid(view)
        _background(ax, volume, normal, float(point[normal]), grey)
        around = [point[None], *(c.path_mm for c, _, _ in needles)]
        for name, mesh in meshes.items():
            for loop in _section(mesh, normal, float(point[normal])):
                ax.plot(loop[:, u], loop[:, v], color=organ_colour(name), lw=1.4, gid=f"organ:{name}")
                around.append(loop)
        for c, colour, style in needles:
            draw_needle(ax, c.path_mm, normal, float(point[normal]), u, v, colour, style, f"needle:{c.hole_id}")
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
        ax.set_title(f"{view} ({seen}), {'xyz'[normal]} = {point[normal]:.0f} mm", fontsize=11, y=TITLE_Y)
        ax.set_xlabel(AXIS_LABELS[u], fontsize=MIN_FONT_PT)
        ax.set_ylabel(AXIS_LABELS[v], fontsize=MIN_FONT_PT)
        ax.tick_params(labelsize=MIN_FONT_PT)
        ax.locator_params(nbins=5)
        label_edges(ax, _UNIT[u], _UNIT[v])
    handles = [Line2D([], [], color=organ_colour(n), label=n) for n in meshes]
    if straight is not None:
        handles.append(Line2D([], [], color=STRAIGHT_COLOUR, ls="--", label=f"straight {straight.hole_id}"))
    if steered is not None:
        handles.append(Line2D([], [], color=STEERED_COLOUR, label=f"steered {steered.hole_id}"))
    if dose is not None:
        handles += [Line2D([], [], color=c, lw=1.2, ls=ISODOSE_STYLE, label=f"{p} %") for p, c in ISODOSE_PERCENT]
        handles.append(Line2D([], [], color="k", marker="o", ls="", ms=3, label="dwell (size: time)"))
    fig.legend(handles=handles, loc="lower center", ncol=min(len(handles), 8), fontsize=MIN_FONT_PT,
               facecolor="#cfcfcf")
    fig.suptitle(f"{target}: needles projected onto the slices through the target (faint: more than "
                 f"{IN_PLANE_MM:g} mm from the slice)", fontsize=12)
    fig.subplots_adjust(left=0.055, right=0.99, top=0.89, bottom=0.24, wspace=0.28)
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
        PNG at :data:`DISPLAY_DPI`.
    """
    return png_bytes(slice_figure(scene, target, straight, steered, volume, organs, window_mm, dose))


def overview(scene: Scene, needles: Sequence[Candidate], volume: Volume | None = None) -> bytes:
    """:func:`overview_figure` as PNG bytes.

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
        PNG at :data:`DISPLAY_DPI`.
    """
    return png_bytes(overview_figure(scene, needles, volume))


def overview_figure(scene: Scene, needles: Sequence[Candidate], volume: Volume | None = None) -> Figure:
    """Draw the axial slice at the targets' mean height and the mid-sagittal slice (x = 0 mm).

    With organ outlines, the target points (green crosses) and ``needles`` (steered: solid cyan, straight: dashed
    orange; faint more than :data:`IN_PLANE_MM` from the slice), the image in the window of
    :func:`display_window`.

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
    matplotlib.figure.Figure
        Two axes (gids ``axial`` and ``sagittal``); the image carries the gid ``image``.
    """
    points = np.array([t.position_mm for t in scene.targets], dtype=float).reshape(-1, 3)
    tz = float(np.mean(points[:, 2]))
    fig = Figure(figsize=(12, 6.2))
    axes = fig.subplots(1, 2)
    grey = None if volume is None else display_window(volume)
    for ax, (normal, u, v, view), value in zip(axes, VIEWS[:2], (tz, 0.0), strict=True):
        ax.set_gid(view)
        _background(ax, volume, normal, value, grey)
        for name, mesh in scene.meshes.items():
            for loop in _section(mesh, normal, value):
                ax.plot(loop[:, u], loop[:, v], color=organ_colour(name), lw=1.2, gid=f"organ:{name}")
        for c in needles:
            colour, style = (STEERED_COLOUR, "-") if c.steered else (STRAIGHT_COLOUR, "--")
            draw_needle(ax, c.path_mm, normal, value, u, v, colour, style, f"needle:{c.hole_id}")
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
    fig.legend(handles=handles, loc="lower center", ncol=min(len(handles), 5), fontsize=MIN_FONT_PT, frameon=False)
    fig.subplots_adjust(left=0.07, right=0.985, top=0.94, bottom=0.22, wspace=0.22)  # fixed: no tight-layout pass
    return fig


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


def implant_holes(needles: Sequence[Any]) -> list[tuple[str, bool]]:
    """Return the template holes of an implant's needles, each with whether its needle is steered.

    Parameters
    ----------
    needles : sequence of NeedleExport
        The delivered plan's channels (:class:`reachplan.plugins.exporters.NeedleExport`); applicator channels
        (``applicator``) are left out, a needle with a tension ``schedule`` is steered.

    Returns
    -------
    list of (str, bool)
        (hole id, steered) in channel order.
    """
    return [(n.hole_id, n.schedule is not None) for n in needles if not n.applicator]


def template_map_figure(scene: Scene, implant: Sequence[tuple[str, bool]], what: str = "implant") -> Figure:
    """Draw the template's holes with their names (mm, template frame), as the operator sees the template.

    Seen from the patient's feet along the needles: the same orientation as the axial slices
    (:data:`RADIOLOGICAL`). The axes are flipped as the pose requires (patient left to the right, anterior up)
    and the edges carry the anatomical letters of the pose, in margins kept free of holes. Exactly the holes of
    ``implant`` are filled (gids ``implant:steered`` and ``implant:straight``) and named in bold; every hole marker
    carries the gid ``holes``.

    Parameters
    ----------
    scene : Scene
        The template and its pose.
    implant : sequence of (str, bool)
        The implant's needles: hole id and whether steered (:func:`implant_holes`).
    what : str
        What the filled holes are, for the legend (``implant`` or, without a delivered plan, the per-target
        needles).

    Returns
    -------
    matplotlib.figure.Figure
        One axes in template coordinates (mm).
    """
    m = scene.patient_from_template
    fig = Figure(figsize=(10.5, 7.0))
    ax = fig.add_subplot()
    holes = {h.hole_id: h for h in scene.template.holes}
    xy = np.array([h.xy_mm for h in scene.template.holes])
    ax.scatter(xy[:, 0], xy[:, 1], s=26, facecolors="none", edgecolors="#888888", label="hole", gid="holes")
    for h in scene.template.holes:
        if h.kind != "needle":
            ax.scatter(*h.xy_mm, s=70, marker="s", color="#7f7f7f", label=h.kind)
    chosen = dict(implant)
    for steered, colour in ((False, STRAIGHT_COLOUR), (True, STEERED_COLOUR)):
        used = [hole for hole, st in chosen.items() if st == steered]
        if used:
            p = np.array([holes[u].xy_mm for u in used])
            ax.scatter(p[:, 0], p[:, 1], s=90, color=colour, edgecolors="k", linewidths=0.8, zorder=4,
                       label=f"{what}: {'steered' if steered else 'straight'} needle",
                       gid=f"implant:{'steered' if steered else 'straight'}")
    for h in scene.template.holes:
        ax.annotate(h.hole_id, h.xy_mm, xytext=(0, 5), textcoords="offset points", fontsize=MIN_FONT_PT,
                    ha="center", va="bottom", fontweight="bold" if h.hole_id in chosen else "normal",
                    color="#000000" if h.hole_id in chosen else "#555555", gid=f"hole:{h.hole_id}")
    ax.set_aspect("equal")
    lo, hi = xy.min(axis=0), xy.max(axis=0)
    pad = 0.1 * (hi - lo) + 6.0  # mm: a margin on every side for the orientation letters, free of holes and names
    ax.set_xlim(lo[0] - pad[0], hi[0] + pad[0])
    ax.set_ylim(lo[1] - pad[1], hi[1] + pad[1] + 3.0)  # a name sits above its hole
    if m[0, 0] < 0:  # template +x towards the patient's right: flip so that the patient's left is on the right
        ax.invert_xaxis()
    if m[1, 1] > 0:  # template +y posterior: flip so that anterior is at the top
        ax.invert_yaxis()
    label_edges(ax, m[:3, 0], m[:3, 1])
    ax.set(xlabel="template x (mm)", ylabel="template y (mm)")
    ax.set_title(f"template {scene.template.name}, seen from the patient's feet (operator's view)", fontsize=12,
                 y=TITLE_Y)
    ax.legend(fontsize=MIN_FONT_PT + 1, loc="upper left", bbox_to_anchor=(1.02, 1.0))
    fig.subplots_adjust(left=0.08, right=0.75, top=0.94, bottom=0.09)  # fixed margins: no tight-layout pass
    return fig


def template_map(scene: Scene, implant: Sequence[tuple[str, bool]], what: str = "implant") -> bytes:
    """:func:`template_map_figure` as PNG bytes.

    Parameters
    ----------
    scene : Scene
        Template and pose, as for :func:`template_map_figure`.
    implant : sequence of (str, bool)
        The holes to fill: hole id and whether steered.
    what : str
        What the filled holes are.

    Returns
    -------
    bytes
        PNG at :data:`DISPLAY_DPI`.
    """
    return png_bytes(template_map_figure(scene, implant, what))
