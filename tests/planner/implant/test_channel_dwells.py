"""A channel's dwells: their source axis points toward the tip, and they lie in the target grown by the margin."""

from __future__ import annotations

import numpy as np
import pytest

from reachplan.imaging.types import Grid
from reachplan.planner.dose.structures import PlanningStructures, Structure
from reachplan.planner.implant.candidates import Channel, intracavitary_channel
from reachplan.planner.implant.settings import ImplantSettings


def _sphere(radius_mm: float = 10.0) -> PlanningStructures:
    h = 1.0
    aff = np.diag([h, h, h, 1.0])
    aff[:3, 3] = [-20.0, -20.0, 20.0]
    grid = Grid((61, 41, 41), aff)  # z 20 .. 80 mm, x and y -20 .. 20 mm
    k, j, i = np.meshgrid(np.arange(61), np.arange(41), np.arange(41), indexing="ij")
    p = grid.to_patient(np.stack([i.ravel(), j.ravel(), k.ravel()], 1)).reshape(61, 41, 41, 3)
    return PlanningStructures(grid, Structure("HR-CTV", np.linalg.norm(p - [0, 0, 50], axis=-1) <= radius_mm), ())


def test_dwell_axes_point_toward_the_tip() -> None:
    """The planner's dwell axes (θ = 0 toward the tip) are those ``reachplan dose`` reads from the exported channel
    (issue 27: reversed, the planner's RT Dose differed by up to 35 % along the axes beyond the tip and the base)."""
    base, tip = np.array([0.0, 0.0, 0.0]), np.array([0.0, 30.0, 40.0])
    path = np.stack([base, 0.5 * (base + tip), tip])
    c = Channel("A1", "straight", path, tip - np.outer([5.0, 10.0], (tip - base) / 50.0))
    assert np.allclose(c.dwell_directions, (tip - base) / 50.0)


@pytest.mark.parametrize("margin", [0.0, 2.5])
def test_dwells_lie_in_the_target_grown_by_the_margin(margin: float) -> None:
    planning = _sphere()
    path = np.array([[0.0, 3.0, 0.0], [0.0, 3.0, 100.0]])  # base to tip, through the sphere 3 mm off its centre
    c = intracavitary_channel("Tandem", path, planning, ImplantSettings(dwell_margin_mm=margin))
    assert c is not None
    d = np.linalg.norm(c.dwell_positions_mm - [0, 0, 50], axis=1) - 10.0  # distance outside the sphere, mm
    assert d.max() <= margin + 0.5 * np.sqrt(3)  # within the margin, to the voxel's half diagonal
    if margin == 0.0:
        assert d.max() <= 0.5 * np.sqrt(3)
    else:
        assert d.max() > 1.0  # the margin is used
