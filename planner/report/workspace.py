"""Reachable-workspace map: where each hole's steered needle can put its tip at a given depth."""

from __future__ import annotations

import matplotlib
import numpy as np
from matplotlib.colors import Normalize
from matplotlib.figure import Figure
from matplotlib.lines import Line2D
from matplotlib.patches import Circle

from reachplan.planner.case.config import PlanConfig
from reachplan.planner.case.scene import Scene
from reachplan.planner.report.figures import (
    MIN_FONT_PT,
    TARGET_COLOUR,
    TITLE_Y,
    label_edges,
    organ_colour,
    plane_section,
    png_bytes,
)
from reachplan.planner.steering.steered import reach_radius_mm, shape_bank


def workspace_figure(scene: Scene, config: PlanConfig, depth_mm: float | None = None) -> bytes:
    """:func:`workspace_map_figure` as PNG bytes.

    Parameters
    ----------
    scene : Scene
        Template pose, targets and organ meshes (mm, LPS).
    config : PlanConfig
        Its first stylet design and schedule family set the reach.
    depth_mm : float or None, mm
        Depth along the template's z axis; None: the targets' mean depth.

    Returns
    -------
    bytes
        PNG at the report's display resolution.
    """
    return png_bytes(workspace_map_figure(scene, config, depth_mm))


def workspace_map_figure(scene: Scene, config: PlanConfig, depth_mm: float | None = None) -> Figure:
    """Draw the reachable-workspace map at ``depth_mm`` beyond the template plane.

    An axial map in the template plane's coordinates (mm) at ``depth_mm``: every needle hole with the disk its
    needle reaches there (first design of ``config``), coloured by the hole's distance from the template centre
    (colour bar), the targets, and the organs' outlines at that depth in their report colours, named in the legend
    (gids ``organ:NAME``).

    Parameters
    ----------
    scene : Scene
        Template pose, targets and organ meshes (mm, LPS).
    config : PlanConfig
        Its first stylet design and schedule family set the reach; no design: straight only (radius 0).
    depth_mm : float or None, mm
        Depth along the template's z axis; None: the targets' mean depth.

    Returns
    -------
    matplotlib.figure.Figure
        The map (one axes and its colour bar).
    """
    inv = np.linalg.inv(scene.patient_from_template)
    t_local = np.array([inv[:3, :3] @ np.asarray(t.position_mm) + inv[:3, 3] for t in scene.targets])
    depth = float(np.mean(t_local[:, 2])) if depth_mm is None else depth_mm
    radius = 0.0
    label = "straight only"
    if config.designs:
        design = config.rod_designs[0]
        bank = shape_bank(design, config.family, min(config.max_depth_mm, design.length_mm),
                          reserve=config.tension_reserve)
        radius = float(reach_radius_mm(bank, np.array([depth]))[0])
        label = f"{design.name}: reach {radius:.1f} mm at {depth:.0f} mm depth"
    fig = Figure(figsize=(9.0, 8.6))
    ax = fig.add_subplot()
    holes = scene.template.needle_holes
    dist = np.array([h.distance_mm for h in holes])
    cmap, norm = matplotlib.colormaps["viridis"], Normalize(0.0, max(float(dist.max()), 1.0))
    for h, d in zip(holes, dist, strict=True):
        colour = cmap(norm(d))
        ax.add_patch(Circle(h.xy_mm, radius, color=colour, alpha=0.08, lw=0))
        ax.plot(*h.xy_mm, "o", color=colour, ms=3.5)
    centre = scene.patient_from_template[:3, 3] + depth * scene.patient_from_template[:3, 2]
    normal = scene.patient_from_template[:3, 2]
    targets = {t.name for t in scene.targets}
    handles = []
    for name, mesh in scene.meshes.items():
        cuts = plane_section(mesh, normal, float(centre @ normal))  # segments split by NaN rows
        for cut in cuts:
            local = (cut - scene.patient_from_template[:3, 3]) @ scene.patient_from_template[:3, :3]
            ax.plot(local[:, 0], local[:, 1], lw=1.3, color=organ_colour(name), gid=f"organ:{name}")
        if cuts and name not in targets:
            handles.append(Line2D([], [], color=organ_colour(name), lw=1.6, label=name))
    handles.append(ax.plot(t_local[:, 0], t_local[:, 1], "+", color=TARGET_COLOUR, ms=11, mew=2, ls="",
                           label="targets")[0])
    ax.set_title(f"reachable workspace per hole\n{label}", fontsize=12, y=TITLE_Y)
    ax.set(xlabel="template x (mm)", ylabel="template y (mm)")
    ax.set_aspect("equal")
    m = scene.patient_from_template  # seen from the feet, like the template map and the axial slices
    if m[0, 0] < 0:
        ax.invert_xaxis()
    if m[1, 1] > 0:
        ax.invert_yaxis()
    label_edges(ax, m[:3, 0], m[:3, 1])
    bar = fig.colorbar(matplotlib.cm.ScalarMappable(norm=norm, cmap=cmap), ax=ax, fraction=0.04, pad=0.02)
    bar.set_label("hole's distance from the template centre (mm)", fontsize=MIN_FONT_PT + 1)
    bar.ax.tick_params(labelsize=MIN_FONT_PT)
    fig.legend(handles=handles, loc="lower center", ncol=min(len(handles), 5), fontsize=MIN_FONT_PT + 1,
               title="outlines at this depth", title_fontsize=MIN_FONT_PT + 1, frameon=False)
    fig.subplots_adjust(left=0.08, right=0.86, top=0.9, bottom=0.08 + 0.035 * (1 + (len(handles) + 4) // 5))
    return fig
