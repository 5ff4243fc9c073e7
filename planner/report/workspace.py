"""Reachable-workspace map: where each hole's steered needle can put its tip at a given depth."""

from __future__ import annotations

import matplotlib
import numpy as np
from matplotlib.figure import Figure
from matplotlib.patches import Circle

from reachplan.planner.case.config import PlanConfig
from reachplan.planner.case.scene import Scene
from reachplan.planner.report.figures import label_edges, plane_section, png_bytes
from reachplan.planner.steering.steered import reach_radius_mm, shape_bank


def workspace_figure(scene: Scene, config: PlanConfig, depth_mm: float | None = None) -> bytes:
    """Draw the reachable-workspace map at ``depth_mm`` beyond the template plane as PNG bytes.

    An axial map in the template plane's coordinates (mm) at ``depth_mm``: every needle hole with the disk its
    needle reaches there (first design of ``config``), the targets, and the organs' outlines at that depth.

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
    bytes
        PNG.
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
    fig = Figure(figsize=(7, 7))
    ax = fig.add_subplot()
    holes = scene.template.needle_holes
    dist = np.array([h.distance_mm for h in holes])
    cmap = matplotlib.colormaps["viridis"]
    for h, d in zip(holes, dist, strict=True):
        colour = cmap(d / max(dist.max(), 1.0))
        ax.add_patch(Circle(h.xy_mm, radius, color=colour, alpha=0.08, lw=0))
        ax.plot(*h.xy_mm, "o", color=colour, ms=3)
    centre = scene.patient_from_template[:3, 3] + depth * scene.patient_from_template[:3, 2]
    normal = scene.patient_from_template[:3, 2]
    targets = {t.name for t in scene.targets}
    for name, mesh in scene.meshes.items():
        for cut in plane_section(mesh, normal, float(centre @ normal)):  # segments split by NaN rows
            local = (cut - scene.patient_from_template[:3, 3]) @ scene.patient_from_template[:3, :3]
            ax.plot(local[:, 0], local[:, 1], lw=1, color="red" if name in targets else "0.3")
    ax.plot(t_local[:, 0], t_local[:, 1], "r+", ms=9, label="targets")
    ax.set(title=f"reachable workspace per hole ({label})", xlabel="template x (mm)", ylabel="template y (mm)")
    ax.set_aspect("equal")
    m = scene.patient_from_template  # seen from the feet, like the template map and the axial slices
    if m[0, 0] < 0:
        ax.invert_xaxis()
    if m[1, 1] > 0:
        ax.invert_yaxis()
    label_edges(ax, m[:3, 0], m[:3, 1])
    ax.legend(loc="lower right", fontsize=8)
    fig.subplots_adjust(left=0.12, right=0.96, top=0.94, bottom=0.08)  # fixed margins: no tight-layout pass
    return png_bytes(fig, dpi=110)
