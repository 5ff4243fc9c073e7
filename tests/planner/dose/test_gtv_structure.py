"""The residual GTV (GTV_res) is found by name on a real structure set and rasterised on the planning grid."""

from __future__ import annotations

import math

import numpy as np

from reachplan.imaging.types import Contour, Roi, StructureSet
from reachplan.planner.dose.structures import gtv_structure, planning_structures


def _disc(z: float, r: float) -> Contour:
    t = np.linspace(0.0, 2 * np.pi, 64, endpoint=False)
    return Contour(np.stack([r * np.cos(t), r * np.sin(t), np.full_like(t, z)], 1), "CLOSED_PLANAR")


def _cylinder(number: int, name: str, r: float) -> Roi:
    return Roi(number, name, tuple(_disc(z, r) for z in np.arange(0.0, 30.0 + 1e-9, 2.0)))


def _grid(rois: tuple[Roi, ...]):  # the planning grid of a structure set with an HR-CTV
    return planning_structures(StructureSet(rois, "1.2.3"), None, "HR-CTV", [], ()).grid


def test_the_residual_gtv_is_preferred_and_the_gtv_at_diagnosis_is_not_taken() -> None:
    ctv = _cylinder(1, "HR-CTV", 15.0)
    rois = (ctv, _cylinder(2, "GTV_init", 12.0), _cylinder(3, "GTV", 9.0), _cylinder(4, "GTV-T_res", 6.0))
    grid = _grid(rois)
    gtv = gtv_structure(StructureSet(rois, "1.2.3"), grid)
    assert gtv is not None and gtv.name == "GTV-T_res"
    # without a residual GTV a plain one is taken; a GTV at diagnosis alone is none
    plain = gtv_structure(StructureSet(rois[:3], "1.2.3"), grid)
    assert plain is not None and plain.name == "GTV"
    # the masks nest as the drawn cylinders do (r 6 inside r 9 inside the HR-CTV's r 15), areas in their ratio
    ctv_mask = planning_structures(StructureSet(rois, "1.2.3"), grid, "HR-CTV", [], ()).target.mask
    assert gtv.mask.any() and not (gtv.mask & ~plain.mask).any() and not (plain.mask & ~ctv_mask).any()
    assert math.isclose(gtv.mask.sum() / plain.mask.sum(), (6.0 / 9.0) ** 2, rel_tol=0.2)
    assert gtv_structure(StructureSet(rois[:2], "1.2.3"), grid) is None


def test_a_gtv_drawn_as_an_open_line_is_skipped() -> None:
    line = Contour(np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 30.0]]), "OPEN_NONPLANAR")
    rois = (_cylinder(1, "HR-CTV", 15.0), Roi(2, "GTV_res", (line,)))
    assert gtv_structure(StructureSet(rois, "1.2.3"), _grid(rois)) is None
