"""What the plan would deliver on the needles as found: its dwell times, each dwell moved onto the found needle.

An afterloader drives the source to programmed distances from each channel's end, whatever shape the needle took:
a planned dwell ``d`` mm from its needle's planned tip (along the needle) lies ``d`` mm from the found tip along the
found needle. The plan's RT Plan with its needle channels' dwells so moved (the times unchanged; channels not found,
such as an intracavitary applicator the finder does not look for, kept as planned), with its structure set's
channel paths the found ones, is an ordinary RT Plan: the dose and the protocol's aims are computed on it exactly as
``reachplan dose`` computes them for any plan.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping

import numpy as np

from reachplan._arrays import arc_length_mm
from reachplan.imaging.brachy_plan import RtPlan
from reachplan.imaging.types import Contour, StructureSet
from reachplan.plugins.exporters.base import project_on_path


def _at_arc(path_mm: np.ndarray, arc_mm: np.ndarray) -> np.ndarray:
    """Points of a polyline at arc lengths ``arc_mm`` from its first point (clipped to its ends)."""
    s = arc_length_mm(path_mm)
    return np.column_stack([np.interp(arc_mm, s, path_mm[:, i]) for i in range(3)])


def moved_dwells(dwells_mm: np.ndarray, planned_mm: np.ndarray, found_mm: np.ndarray) -> np.ndarray:
    """Move dwell positions from a needle's planned path to its found one, at the same distance from the tip.

    Parameters
    ----------
    dwells_mm : (n, 3) float, mm, LPS
        The planned dwell positions (on or near ``planned_mm``).
    planned_mm : (k, 3) float, mm, LPS
        The planned centre line, hole to tip.
    found_mm : (m, 3) float, mm, LPS
        The found centre line, hole to tip.

    Returns
    -------
    (n, 3) float, mm, LPS
        The dwells on the found centre line, each as far from its tip along the needle as it was from the planned
        tip (a dwell beyond the found needle's length stays at its hole end).
    """
    planned = np.asarray(planned_mm, dtype=float)
    found = np.asarray(found_mm, dtype=float)
    arc, _ = project_on_path(planned, np.asarray(dwells_mm, dtype=float).reshape(-1, 3))
    from_tip = arc_length_mm(planned)[-1] - arc
    return _at_arc(found, arc_length_mm(found)[-1] - from_tip)


def as_inserted(plan: RtPlan, structures: StructureSet, planned: Mapping[str, np.ndarray],
                found: Mapping[str, np.ndarray]) -> tuple[RtPlan, StructureSet, tuple[str, ...]]:
    """Return ``plan`` with each found needle's dwells moved onto it (:func:`moved_dwells`), its channel paths too.

    Parameters
    ----------
    plan : RtPlan
        The plan's RT Plan; a channel is a needle's when its Source Applicator ID is the needle's hole.
    structures : StructureSet
        The structure set the plan was exported with (organs, and each channel's path as its referenced ROI).
    planned : mapping of str to (k, 3) float, mm, LPS
        Hole to planned centre line (hole to tip).
    found : mapping of str to (m, 3) float, mm, LPS
        Hole to found centre line (hole to tip).

    Returns
    -------
    plan : RtPlan
        The plan as it would be delivered on the found needles (same times).
    structures : StructureSet
        ``structures`` with each moved channel's ROI the found centre line (tip first, as channels are written).
    kept : tuple of str
        The channels left as planned (their applicator ids): not found, or without a planned path.
    """
    kept: list[str] = []
    paths: dict[int, np.ndarray] = {}
    setups = []
    for setup in plan.setups:
        channels = []
        for c in setup.channels:
            hole = c.applicator_id
            if hole in found and hole in planned and c.n_dwells:
                c = dataclasses.replace(c, dwell_positions_mm=moved_dwells(c.dwell_positions_mm, planned[hole],
                                                                           found[hole]))
                if c.roi_number is not None:
                    paths[c.roi_number] = np.asarray(found[hole], dtype=float)[::-1].copy()
            else:
                kept.append(hole)
            channels.append(c)
        setups.append(dataclasses.replace(setup, channels=tuple(channels)))
    rois = tuple(dataclasses.replace(r, contours=(Contour(paths[r.number], "OPEN_NONPLANAR"),))
                 if r.number in paths else r for r in structures.rois)
    return (dataclasses.replace(plan, setups=tuple(setups)), dataclasses.replace(structures, rois=rois),
            tuple(kept))
