"""The report section of a needle reconstruction: the needles over the image, and per needle a straightened view.

The overview draws every needle found (and, with the plan, its planned line dashed) over a coronal and a sagittal
slab of the image, 20 mm thick (six planes averaged), through the needles' middle. Each needle then gets a
straightened view: the image sampled along its found centre line (vertical: depth from the template plane, mm) and
across it (+-10 mm, horizontal), so a needle tracked well runs straight down the middle and ends where the bright (or
dark) line ends.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np

from reachplan.imaging.types import Volume
from reachplan.planner.report.figures import display_window, png_bytes
from reachplan.planner.report.html import Figure, Paragraph, Section, Table
from reachplan.planner.verify.compare import Matching
from reachplan.planner.verify.find import FoundNeedle

#: How many needles get a straightened view in one figure.
MAX_STRAIGHTENED = 12


def _sample(volume: Volume, pts: np.ndarray) -> np.ndarray:
    """Trilinear samples of the volume at LPS points (..., 3)."""
    from scipy.ndimage import map_coordinates

    inv = np.linalg.inv(volume.grid.patient_from_index)
    p = pts.reshape(-1, 3)
    ijk = p @ inv[:3, :3].T + inv[:3, 3]
    out = map_coordinates(np.asarray(volume.array, dtype=np.float32), [ijk[:, 2], ijk[:, 1], ijk[:, 0]], order=1,
                          mode="nearest")
    return np.asarray(out).reshape(pts.shape[:-1])


def overview_png(volume: Volume, found: Sequence[FoundNeedle], planned: Mapping[str, np.ndarray] | None = None,
                 ) -> bytes:
    """Draw the needles over a coronal and a sagittal slab of the image (module docstring).

    Parameters
    ----------
    volume : Volume
        The image.
    found : sequence of FoundNeedle
        The needles found (mm, LPS).
    planned : mapping of str to (n, 3) float, optional
        Hole to planned centre line (mm, LPS), drawn dashed.

    Returns
    -------
    bytes
        A PNG.
    """
    from matplotlib.figure import Figure as MplFigure

    pts = np.concatenate([f.points_mm for f in found]) if found else np.zeros((1, 3))
    lo, hi = pts.min(axis=0) - 25.0, pts.max(axis=0) + 25.0
    window = display_window(volume)
    fig = MplFigure(figsize=(10, 5.2))
    for k, (a, b, across, name) in enumerate(((0, 2, 1, "coronal"), (1, 2, 0, "sagittal"))):
        ax = fig.add_subplot(1, 2, k + 1)
        ua = np.arange(lo[a], hi[a], 0.75)
        vb = np.arange(lo[b], hi[b], 0.75)
        mid = float(np.median(pts[:, across]))
        offsets = np.linspace(-10.0, 10.0, 6)
        grid = np.zeros((len(offsets), len(vb), len(ua), 3))
        grid[..., a] = ua[None, None, :]
        grid[..., b] = vb[None, :, None]
        grid[..., across] = mid + offsets[:, None, None]
        img = _sample(volume, grid).mean(axis=0)
        ax.imshow(img, cmap="gray", vmin=window[0], vmax=window[1], origin="lower",
                  extent=(ua[0], ua[-1], vb[0], vb[-1]))
        for f in found:
            ax.plot(f.points_mm[:, a], f.points_mm[:, b], color="yellow", lw=1.0)
            ax.text(f.tip_mm[a], f.tip_mm[b] + 2.0, f.hole_id, color="yellow", fontsize=7, ha="center")
            if planned and f.hole_id in planned:
                p = planned[f.hole_id]
                ax.plot(p[:, a], p[:, b], color="cyan", lw=0.8, ls="--")
        ax.set_title(f"{name} slab ({'LPS'[across]} {mid:.0f} mm +-10)", fontsize=9)
        ax.set_xlabel(f"{'LPS'[a]} (mm)")
        ax.set_ylabel("S (mm)")
    fig.tight_layout()
    return png_bytes(fig)


def straightened_png(volume: Volume, found: Sequence[FoundNeedle]) -> bytes:
    """Each needle's straightened view (module docstring), side by side.

    Parameters
    ----------
    volume : Volume
        The image.
    found : sequence of FoundNeedle
        The needles found (at most :data:`MAX_STRAIGHTENED` are drawn).

    Returns
    -------
    bytes
        A PNG.
    """
    from matplotlib.figure import Figure as MplFigure

    from reachplan.planner.verify.implant import resample_mm

    shown = list(found)[:MAX_STRAIGHTENED]
    window = display_window(volume)
    fig = MplFigure(figsize=(1.3 * max(len(shown), 1) + 0.6, 5.0))
    across = np.arange(-10.0, 10.01, 0.5)
    for k, f in enumerate(shown):
        ax = fig.add_subplot(1, max(len(shown), 1), k + 1)
        line = resample_mm(f.points_mm, 0.5)
        ext = np.vstack([line, line[-1] + (line[-1] - line[-2]) / np.linalg.norm(line[-1] - line[-2])
                         * np.arange(0.5, 10.01, 0.5)[:, None]])
        t = np.gradient(ext, axis=0)
        t /= np.linalg.norm(t, axis=1, keepdims=True)
        side = np.cross(t, np.array([0.0, 1.0, 0.0]))
        side /= np.maximum(np.linalg.norm(side, axis=1, keepdims=True), 1e-9)
        grid = ext[:, None, :] + across[None, :, None] * side[:, None, :]
        depth = np.arange(len(ext)) * 0.5
        ax.imshow(_sample(volume, grid), cmap="gray", vmin=window[0], vmax=window[1], origin="upper",
                  extent=(across[0], across[-1], depth[-1], depth[0]), aspect="auto")
        ax.axhline(f.length_mm, color="yellow", lw=0.8, ls=":")
        ax.set_title(f.hole_id, fontsize=8)
        ax.tick_params(labelsize=6)
        if k == 0:
            ax.set_ylabel("along the needle (mm)", fontsize=7)
    fig.tight_layout()
    return png_bytes(fig)


def reconstruction_section(volume: Volume, found: Sequence[FoundNeedle], about: str,
                           planned: Mapping[str, np.ndarray] | None = None,
                           versus_plan: Matching | None = None) -> Section:
    """Return the report section: what was found, the figures, and with the plan the planned-versus-actual table.

    Parameters
    ----------
    volume : Volume
        The image.
    found : sequence of FoundNeedle
        The needles found.
    about : str
        One paragraph: the image, the template pose, how the needles were found.
    planned : mapping of str to (n, 3) float, optional
        Hole to planned centre line (mm, LPS).
    versus_plan : Matching, optional
        The needles against the plan.

    Returns
    -------
    Section
        Anchor ``needles-found``.
    """
    rows = tuple((f.hole_id, f"{f.length_mm:.1f}", ", ".join(f"{v:.1f}" for v in f.tip_mm), f"{f.contrast:.0f}",
                  f"{f.confidence:.2f}", f"{f.seconds:.2f}") for f in found)
    blocks: list[Paragraph | Table | Figure] = [
        Paragraph(about),
        Table(("hole", "length from template (mm)", "tip (mm, LPS)", "contrast", "confidence", "time (s)"), rows,
              caption=f"{len(found)} needles found", numeric=(1, 3, 4, 5)),
    ]
    blocks += [Paragraph(f"Needle {f.hole_id}: {f.note}.") for f in found if f.note]
    if versus_plan is not None:
        blocks.append(Table(
            ("hole", "tip error (mm)", "largest lateral deviation (mm)", "depth error (mm, + deeper)"),
            tuple((e.hole_id, f"{e.tip_mm:.1f}", f"{e.shaft_max_mm:.1f}", f"{e.depth_mm:+.1f}")
                  for e in versus_plan.errors),
            caption="planned versus actual" + (f"; planned but not found: {', '.join(versus_plan.missed)}"
                                               if versus_plan.missed else "")
                    + (f"; found but not planned: {', '.join(versus_plan.false)}" if versus_plan.false else ""),
            numeric=(1, 2, 3)))
    if found:
        blocks.append(Figure(overview_png(volume, found, planned),
                             "The needles found (yellow; planned dashed cyan) over coronal and sagittal slabs"))
        blocks.append(Figure(straightened_png(volume, found),
                             "Each needle straightened: the image along its found centre line (dotted: the tip)"))
    return Section("Needles found in the image", "needles-found", tuple(blocks))
