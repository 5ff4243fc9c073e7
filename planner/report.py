"""Figures and tables of a plan (matplotlib, no screen needed)."""

from __future__ import annotations

import io
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
import trimesh

from imaging.types import Volume
from planner.io import atomic_write_bytes
from planner.pipeline import PlanResult, Scene
from planner.ranking import Candidate

ORGAN_COLOURS = {
    "Bladder": "#e6c229", "Rectum": "#8c564b", "Sigmoid": "#c49c94", "Bowel": "#f7b6d2", "Bone": "#bbbbbb",
    "HR-CTV": "#d62728", "Uterus": "#9467bd", "Cervix": "#ff9896", "Obturator": "#7f7f7f",
}


def top_candidates(result: PlanResult, n_per_target: int = 1) -> list[Candidate]:
    """The best ``n_per_target`` feasible candidates of every target."""
    return [c for cs in result.ranking.values() for c in [c for c in cs if c.feasible][:n_per_target]]


def format_table(result: PlanResult) -> str:
    """Per target: the top-ranked candidate, and the best straight next to the best steered one."""

    def cell(c: Candidate | None) -> str:
        if c is None:
            return f"{'none feasible':<34}"
        return (f"{c.hole_id:>4} {c.hole_distance_mm:5.1f} mm r{c.reach_error_mm:4.1f} c{c.clearance_mm:5.1f} "
                f"{c.peak_tension_n:4.1f} N")

    head = (f"{'target':<15} {'top':<8} {'best straight (hole, from centre, reach, clear)':<34}   "
            f"{'best steered':<34}  model")
    lines = [head, "-" * len(head)]
    for target, cands in result.ranking.items():
        top = cands[0]
        first = ("steered" if top.steered else "straight") if top.feasible else "none"
        steered = result.best(target, True)
        lines.append(f"{target:<15} {first:<8} {cell(result.best(target, False))}   {cell(steered)}  "
                     f"{steered.model if steered else ''}")
    return "\n".join(lines)


def _section(mesh: trimesh.Trimesh, origin: np.ndarray, normal: np.ndarray) -> list[np.ndarray]:
    sec = mesh.section(plane_origin=origin, plane_normal=normal)
    return [] if sec is None else [np.asarray(d) for d in sec.discrete]


def _background(ax: plt.Axes, volume: Volume | None, axis: int, value_mm: float) -> None:
    if volume is None:
        return
    m = volume.grid.patient_from_index
    if not np.allclose(m[:3, :3], np.diag(np.diag(m[:3, :3]))):
        return  # oblique grid: organ outlines only
    idx = volume.grid.to_index(np.array([[value_mm] * 3]))[0]
    nk, nj, ni = volume.grid.shape
    lo = volume.grid.to_patient(np.array([[0, 0, 0]]))[0]
    hi = volume.grid.to_patient(np.array([[ni - 1, nj - 1, nk - 1]]))[0]
    if axis == 2:  # axial: x across, y down
        k = int(np.clip(round(idx[2]), 0, nk - 1))
        ax.imshow(volume.array[k], cmap="gray", vmin=-200, vmax=300, extent=(lo[0], hi[0], hi[1], lo[1]))
    else:  # sagittal: y across, z up
        i = int(np.clip(round(idx[0]), 0, ni - 1))
        ax.imshow(volume.array[:, :, i], cmap="gray", vmin=-200, vmax=300, origin="lower",
                  extent=(lo[1], hi[1], lo[2], hi[2]), aspect="auto")


def overview_figure(scene: Scene, result: PlanResult, path: Path, volume: Volume | None = None) -> None:
    """Axial and sagittal slices with organ outlines and the top needle path of every target (PNG)."""
    top = top_candidates(result)
    tz = float(np.mean([t.position_mm[2] for t in scene.targets]))
    fig, (ax_a, ax_s) = plt.subplots(1, 2, figsize=(12, 6))
    _background(ax_a, volume, 2, tz)
    _background(ax_s, volume, 0, 0.0)
    for name, mesh in scene.meshes.items():
        colour = ORGAN_COLOURS.get(name, "#2ca02c")
        for loop in _section(mesh, np.array([0.0, 0.0, tz]), np.array([0.0, 0.0, 1.0])):
            ax_a.plot(loop[:, 0], loop[:, 1], color=colour, lw=1.2)
        for loop in _section(mesh, np.array([0.0, 0.0, 0.0]), np.array([1.0, 0.0, 0.0])):
            ax_s.plot(loop[:, 1], loop[:, 2], color=colour, lw=1.2)
    for c in top:
        p = c.path_mm
        style = "-" if c.steered else "--"
        ax_a.plot(p[:, 0], p[:, 1], style, color="cyan", lw=1)
        ax_a.plot(p[-1, 0], p[-1, 1], "o", color="cyan", ms=3)
        ax_s.plot(p[:, 1], p[:, 2], style, color="cyan", lw=1)
    for t in scene.targets:
        ax_a.plot(t.position_mm[0], t.position_mm[1], "+", color="red", ms=8)
    handles = [plt.Line2D([], [], color=ORGAN_COLOURS.get(n, "#2ca02c"), label=n) for n in scene.meshes
               if n in ORGAN_COLOURS]
    handles.append(plt.Line2D([], [], color="cyan", label="top needle per target (dashed: straight)"))
    ax_a.legend(handles=handles, loc="lower right", fontsize=7)
    ax_a.set(title=f"axial, z = {tz:.0f} mm", xlabel="x (mm, patient left +)", ylabel="y (mm, posterior +)")
    ax_a.set_aspect("equal")
    ax_a.set_ylim(sorted(ax_a.get_ylim(), reverse=True))  # anterior (-y) at the top, as radiology shows it
    ax_s.set(title="sagittal, x = 0 mm", xlabel="y (mm, posterior +)", ylabel="z (mm, superior +)")
    ax_s.set_aspect("equal")
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110)
    plt.close(fig)
    atomic_write_bytes(path, buf.getvalue())
