"""Figures of the HTML report, each returned as PNG bytes.

Drawn on :class:`matplotlib.figure.Figure` objects, not pyplot: nothing here selects a backend or keeps a
figure alive, so importing this module changes no global state and needs no screen.

Geometry is in mm, DICOM patient coordinates (LPS: +x patient left, +y posterior, +z superior). Views follow
radiological convention: axial and coronal show the patient's left on the right of the image, axial has
anterior at the top, sagittal has anterior on the left.
"""

from __future__ import annotations

import io
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
import trimesh
from matplotlib.figure import Figure
from matplotlib.lines import Line2D

from reachplan.imaging.types import Volume
from reachplan.planner.pipeline import Scene
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


def png_bytes(fig: Figure, dpi: int = 100) -> bytes:
    """Render a figure to PNG bytes."""
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=dpi)
    return buf.getvalue()


def organ_colour(name: str) -> str:
    """Display colour of an organ (target ROIs green, unknown ones grey)."""
    if name.casefold().startswith("target"):
        return TARGET_COLOUR
    return ORGAN_COLOURS.get(name, "#7f7f7f")


def _section(mesh: trimesh.Trimesh, axis: int, value_mm: float) -> list[np.ndarray]:
    """Return the closed loops (each (n, 3) float, mm, LPS) where the plane ``x[axis] = value_mm`` cuts ``mesh``."""
    lo, hi = mesh.bounds[:, axis]
    if not lo < value_mm < hi:
        return []
    origin = np.zeros(3)
    origin[axis] = value_mm
    normal = np.zeros(3)
    normal[axis] = 1.0
    sec = mesh.section(plane_origin=origin, plane_normal=normal)
    return [] if sec is None else [np.asarray(d) for d in sec.discrete]


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
    return p.min(axis=0) - margin_mm, p.max(axis=0) + margin_mm


def slice_views(scene: Scene, target: str, straight: Candidate | None, steered: Candidate | None,
                volume: Volume | None = None, organs: Sequence[str] | None = None,
                window_mm: float = 120.0) -> bytes:
    """Axial, sagittal and coronal slices through a target with organ outlines and its two needles.

    The needles (best straight: dashed orange, best steered: solid cyan) are drawn projected onto each
    plane, with their tips as dots; the target point is a green cross. ``organs`` names the meshes to
    outline (default: the organs at risk, HR-CTV and the target's own ROI). Each view shows the needles and
    the outlines in its plane, at most ``window_mm`` from the target.
    """
    point = np.asarray(next(t.position_mm for t in scene.targets if t.name == target), dtype=float)
    names = list(organs) if organs is not None else [*(o.name for o in scene.organs), "HR-CTV", target]
    meshes = {n: scene.meshes[n] for n in names if n in scene.meshes}
    needles = [(c, STRAIGHT_COLOUR, "--") for c in (straight,) if c is not None]
    needles += [(c, STEERED_COLOUR, "-") for c in (steered,) if c is not None]
    fig = Figure(figsize=(13.5, 4.8))
    axes = fig.subplots(1, 3)
    for ax, (normal, u, v, view) in zip(axes, VIEWS, strict=True):
        _background(ax, volume, normal, float(point[normal]))
        around = [point[None], *(c.path_mm for c, _, _ in needles)]
        for name, mesh in meshes.items():
            for loop in _section(mesh, normal, float(point[normal])):
                ax.plot(loop[:, u], loop[:, v], color=organ_colour(name), lw=1.4)
                around.append(loop)
        for c, colour, style in needles:
            ax.plot(c.path_mm[:, u], c.path_mm[:, v], style, color=colour, lw=1.6)
            ax.plot(c.path_mm[-1, u], c.path_mm[-1, v], "o", color=colour, ms=4)
        ax.plot(point[u], point[v], "+", color=TARGET_COLOUR, ms=12, mew=2)
        lo, hi = _box(around, 10.0)
        lo, hi = np.maximum(lo, point - window_mm), np.minimum(hi, point + window_mm)
        ax.set_xlim(lo[u], hi[u])
        ax.set_ylim((hi[v], lo[v]) if view == "axial" else (lo[v], hi[v]))  # axial: anterior (-y) at the top
        ax.set_aspect("equal")
        ax.set_title(f"{view}, {'xyz'[normal]} = {point[normal]:.0f} mm", fontsize=10)
        ax.set_xlabel(AXIS_LABELS[u], fontsize=8)
        ax.set_ylabel(AXIS_LABELS[v], fontsize=8)
        ax.tick_params(labelsize=7)
        ax.locator_params(nbins=5)
    handles = [Line2D([], [], color=organ_colour(n), label=n) for n in meshes]
    if straight is not None:
        handles.append(Line2D([], [], color=STRAIGHT_COLOUR, ls="--", label=f"straight {straight.hole_id}"))
    if steered is not None:
        handles.append(Line2D([], [], color=STEERED_COLOUR, label=f"steered {steered.hole_id}"))
    fig.legend(handles=handles, loc="lower center", ncol=min(len(handles), 10), fontsize=8, facecolor="#cfcfcf")
    fig.suptitle(f"{target}: needles projected onto the slices through the target", fontsize=11)
    fig.subplots_adjust(left=0.05, right=0.99, top=0.88, bottom=0.2, wspace=0.25)
    return png_bytes(fig, dpi=90)


def overview(scene: Scene, needles: Sequence[Candidate], volume: Volume | None = None) -> bytes:
    """Draw the axial slice at the targets' mean height and the mid-sagittal slice (x = 0 mm) as PNG bytes.

    With organ outlines, the target points (green crosses) and ``needles`` (steered: solid cyan, straight: dashed
    orange).
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
    handles = [Line2D([], [], color=organ_colour(n), label=n) for n in scene.meshes
               if not n.casefold().startswith("target")]
    handles += [Line2D([], [], color=TARGET_COLOUR, marker="+", ls="", label="target points and ROIs"),
                Line2D([], [], color=STEERED_COLOUR, label="top needle per target: steered"),
                Line2D([], [], color=STRAIGHT_COLOUR, ls="--", label="top needle per target: straight")]
    axes[0].legend(handles=handles, loc="lower right", fontsize=7)
    fig.tight_layout()
    return png_bytes(fig, dpi=110)


def coarse_mesh(mesh: trimesh.Trimesh, pitch_mm: float = 4.0) -> trimesh.Trimesh:
    """Return a light version of a closed mesh for 3-D drawing.

    Voxelised at ``pitch_mm``, filled and re-meshed by marching cubes (mm, LPS; a few thousand faces for an organ).
    """
    vox = mesh.voxelized(pitch=pitch_mm).fill()
    out = vox.marching_cubes
    out.apply_transform(vox.transform)
    return out


#: (elevation, azimuth, title) of the 3-D views.
VIEWS_3D: tuple[tuple[float, float, str], ...] = (
    (15.0, -60.0, "anterior-oblique"), (5.0, 0.0, "from the patient's left"), (-70.0, -90.0, "from the template"),
)


def views_3d(scene: Scene, needles: Sequence[Candidate], organs: Sequence[str] | None = None,
             pitch_mm: float = 4.0, meshes: Mapping[str, trimesh.Trimesh] | None = None) -> bytes:
    """Draw organs, target points (green dots) and needles in 3-D from three angles as PNG bytes.

    Steered needles solid cyan, straight dashed orange.

    ``organs``: meshes to draw (default: organs at risk without bone, and HR-CTV);
    ``meshes``: pre-coarsened meshes by name (default: :func:`coarse_mesh` of the scene's).
    """
    from mpl_toolkits.mplot3d.art3d import Poly3DCollection  # type: ignore[import-untyped]

    names = list(organs) if organs is not None else (
        [o.name for o in scene.organs if o.name != "Bone"] + ["HR-CTV"])
    light = dict(meshes) if meshes is not None else {}
    for n in names:
        if n not in light and n in scene.meshes:
            light[n] = coarse_mesh(scene.meshes[n], pitch_mm)
    fig = Figure(figsize=(15, 5.4))
    points = np.array([t.position_mm for t in scene.targets], dtype=float).reshape(-1, 3)
    pts = [points, *(m.vertices for n, m in light.items() if n in names), *(c.path_mm for c in needles)]
    lo, hi = _box(pts, 5.0)
    centre, half = (lo + hi) / 2, float((hi - lo).max()) / 2
    for i, (elev, azim, title) in enumerate(VIEWS_3D):
        ax = fig.add_subplot(1, 3, i + 1, projection="3d")
        for n in names:
            if n not in light:
                continue
            m = light[n]
            alpha = 0.35 if n.casefold().startswith("target") else 0.18
            ax.add_collection3d(Poly3DCollection(m.vertices[m.faces], facecolor=organ_colour(n), alpha=alpha,
                                                 edgecolor="none"))
        for c in needles:
            colour, style = (STEERED_COLOUR, "-") if c.steered else (STRAIGHT_COLOUR, "--")
            ax.plot(c.path_mm[:, 0], c.path_mm[:, 1], c.path_mm[:, 2], style, color=colour, lw=1.5)
            ax.scatter(*c.path_mm[-1], color=colour, s=8)
        ax.scatter(points[:, 0], points[:, 1], points[:, 2], marker="o", color=TARGET_COLOUR, s=30,
                   depthshade=False)
        ax.set_xlim(centre[0] - half, centre[0] + half)
        ax.set_ylim(centre[1] - half, centre[1] + half)
        ax.set_zlim(centre[2] - half, centre[2] + half)
        ax.set_box_aspect((1, 1, 1))
        ax.view_init(elev=elev, azim=azim)
        ax.set_title(title, fontsize=10)
        ax.set_xlabel("x (L+)", fontsize=7)
        ax.set_ylabel("y (P+)", fontsize=7)
        ax.set_zlabel("z (S+)", fontsize=7)
        ax.tick_params(labelsize=6)
    handles = [Line2D([], [], color=organ_colour(n), lw=6, alpha=0.5, label=n) for n in names
               if n in light and not n.casefold().startswith("target")]
    handles += [Line2D([], [], color=TARGET_COLOUR, marker="o", ls="", label="target points"),
                Line2D([], [], color=STEERED_COLOUR, label="steered needle"),
                Line2D([], [], color=STRAIGHT_COLOUR, ls="--", label="straight needle")]
    fig.legend(handles=handles, loc="lower center", ncol=len(handles), fontsize=8, frameon=False)
    fig.subplots_adjust(left=0.0, right=1.0, top=0.95, bottom=0.08, wspace=0.0)
    return png_bytes(fig, dpi=90)


def template_map(scene: Scene, straight: Sequence[Candidate], steered: Sequence[Candidate]) -> bytes:
    """Draw the template's holes (mm, template frame) with the holes the chosen needles use, as PNG bytes."""
    fig = Figure(figsize=(6.4, 4.4))
    ax = fig.add_subplot()
    holes = {h.hole_id: h for h in scene.template.holes}
    xy = np.array([h.xy_mm for h in scene.template.holes])
    ax.scatter(xy[:, 0], xy[:, 1], s=18, facecolors="none", edgecolors="#999999", label="hole")
    for h in scene.template.holes:
        if h.kind != "needle":
            ax.scatter(*h.xy_mm, s=60, marker="s", color="#7f7f7f", label=h.kind)
    for cands, colour, label in ((straight, STRAIGHT_COLOUR, "straight"), (steered, STEERED_COLOUR, "steered")):
        used = sorted({c.hole_id for c in cands})
        if not used:
            continue
        p = np.array([holes[u].xy_mm for u in used])
        ax.scatter(p[:, 0], p[:, 1], s=60 if label == "straight" else 30, color=colour, label=f"{label} needle")
        for u, q in zip(used, p, strict=True):
            ax.annotate(u, q, xytext=(3, 3), textcoords="offset points", fontsize=7)
    ax.set_aspect("equal")
    ax.set(xlabel="template x (mm)", ylabel="template y (mm)", title=f"template {scene.template.name}")
    ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.02, 1.0))
    fig.tight_layout()
    return png_bytes(fig, dpi=90)


def speed_accuracy(rows: Sequence[Any], used: Mapping[str, str]) -> bytes:
    """Rod models: median time per solve against worst tip error (log-log), from the measured error table.

    Parameters
    ----------
    rows : sequence of :class:`reachplan.rod_model.select.ErrorRow`
        The packaged benchmark table (``rod_model/model_errors.json``).
    used : mapping rod model name -> how this plan used it (e.g. ``"screening"``)
        The registered (``default``) configuration of these models is ringed and labelled.
    """
    floor = 1e-10
    fig = Figure(figsize=(8.5, 5.4))
    ax = fig.add_subplot()
    models = list(dict.fromkeys(r.model for r in rows))
    for i, name in enumerate(models):
        pts = sorted((r for r in rows if r.model == name), key=lambda r: r.median_ms)
        ax.plot([r.median_ms for r in pts], [max(r.max_tip_error_mm, floor) for r in pts],
                "o-" if len(pts) > 1 else "o", color=f"C{i}", label=name, ms=6)
        for r in pts:
            if r.resolution == "default" and name in used:
                y = max(r.max_tip_error_mm, floor)
                ax.scatter([r.median_ms], [y], s=260, facecolors="none", edgecolors="k", lw=1.5, zorder=5)
                ax.annotate(f"{name}: {used[name]}\n{r.median_ms:.2f} ms, max error {r.max_tip_error_mm:.2g} mm",
                            (r.median_ms, y), xytext=(12, -4), textcoords="offset points", fontsize=8,
                            bbox={"boxstyle": "round", "fc": "#fffbe6", "ec": "#c9b458"})
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("median time per solve (ms, log)")
    ax.set_ylabel(f"max tip error vs converged two-tube reference (mm; floor {floor:g})")
    ax.set_title("Rod models: speed vs accuracy (ringed: used in this plan)", fontsize=11)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8, loc="upper right")
    fig.tight_layout()
    return png_bytes(fig, dpi=90)


def dvh_png(comparison: Any) -> bytes:
    """Render the DVH figure of a :class:`reachplan.planner.dose.optimize.Comparison` as PNG bytes."""
    return png_bytes(comparison.figure(), dpi=90)
