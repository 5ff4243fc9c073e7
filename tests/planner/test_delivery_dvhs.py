"""Whole-organ DVHs (issue 29, item 7): every plan's on one grid, each organ whole, a cropped organ said so."""

from __future__ import annotations

from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest

from reachplan.imaging.types import Grid
from reachplan.planner.delivery import _dose_region, whole_dvhs
from reachplan.planner.dose.structures import PlanningStructures, Structure


def _planning() -> PlanningStructures:
    shape = (20, 30, 40)  # k, j, i
    affine = np.diag([1.0, 1.5, 2.0, 1.0])
    affine[:3, 3] = (-20.0, -22.0, 5.0)
    grid = Grid(shape, affine)
    k, j, i = np.indices(shape)
    target = (abs(i - 20) < 6) & (abs(j - 15) < 5) & (abs(k - 10) < 4)
    bladder = (abs(i - 8) < 4) & (abs(j - 6) < 5) & (abs(k - 12) < 5)  # away from the target: outside its box
    rectum = (abs(i - 33) < 4) & (abs(j - 25) < 3) & (abs(k - 6) < 3)
    return PlanningStructures(grid, Structure("HR-CTV", target), (Structure("Bladder", bladder),
                                                                   Structure("Rectum", rectum)))


def test_every_plan_gives_every_whole_organ_the_same_volume_and_the_dvh_of_its_voxels() -> None:
    planning = _planning()
    region = _dose_region(planning)
    centres = region.to_patient(np.stack(np.indices(region.shape)[::-1], axis=-1).reshape(-1, 3))
    fractions = 4

    def plan(gain: float) -> Any:  # a dose over all fractions on the dose region (Gy): a ramp along x
        dose = (gain * (centres[:, 0] - centres[:, 0].min())).reshape(region.shape)
        return SimpleNamespace(dose=SimpleNamespace(grid=region, dose_gy=dose * fractions))

    exports = {"delivered": plan(1.0), "straight": plan(0.5), "steered": plan(1.0)}
    whole = whole_dvhs(planning, exports, fractions, own_cc={"Bladder": 0.5, "Rectum": 1e3})
    assert whole is not None and set(whole.by_plan) == set(exports)
    vox = float(np.prod(planning.grid.spacing_mm)) / 1000.0
    # the same dose computed independently on the whole planning grid (no box): x of each voxel centre
    full = planning.grid.to_patient(np.stack(np.indices(planning.grid.shape)[::-1], axis=-1).reshape(-1, 3))
    x = full[:, 0].reshape(planning.grid.shape) - centres[:, 0].min()
    for name, gain in (("straight", 0.5), ("steered", 1.0)):
        curves = dict(whole.by_plan[name])
        for s in (planning.target, *planning.oars):
            dvh = curves[s.name]
            assert dvh.volume_cc[0] == pytest.approx(s.mask.sum() * vox)  # the whole organ, in every plan
            assert whole.volume_cc[s.name] == pytest.approx(s.mask.sum() * vox)
            for d in np.quantile(gain * x[s.mask], [0.1, 0.5, 0.9]):
                at = np.searchsorted(dvh.dose_gy, d)
                expected = np.count_nonzero(gain * x[s.mask] >= dvh.dose_gy[at] - 1e-9) * vox
                assert dvh.volume_cc[at] == pytest.approx(expected, abs=1.01 * vox)
    # the rectum's own (contoured) volume is far larger than the grid holds: cropped, and said so
    assert set(whole.cropped) == {"Rectum"}
    on_grid, own = whole.cropped["Rectum"]
    assert on_grid == pytest.approx(planning.oars[1].mask.sum() * vox) and own == 1e3


def test_no_planned_dose_no_whole_dvhs() -> None:
    planning = _planning()
    assert whole_dvhs(planning, {"delivered": SimpleNamespace(dose=None)}, 4) is None
