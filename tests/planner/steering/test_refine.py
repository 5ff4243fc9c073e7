"""The reference re-solve: the in-tissue rod re-aimed by space mapping against the kinematic model."""

from __future__ import annotations

import numpy as np

from reachplan._arrays import arc_length_mm
from reachplan.planner.steering.kinematic import KINEMATIC
from reachplan.planner.steering.schedule import TensionSchedule
from reachplan.planner.steering.steered import refine_with
from reachplan.planner.steering.tissue_rod import TissueRodInsertion
from reachplan.rod_model.cosserat import TwoTubeCosserat
from reachplan.rod_model.design import preset

DESIGN = preset("15ga-30j-tip")
MODEL = TissueRodInsertion(step_mm=4.0, rod_model=TwoTubeCosserat(steps_per_mm=1.0))


def test_space_mapping_brings_the_in_tissue_rod_onto_the_target() -> None:
    depth = 80.0
    screened = TensionSchedule.ramp(0.0, 5.0, 7.0)
    # a target the screening (kinematic) model reaches with this schedule, 30 degrees off the x axis
    tip = KINEMATIC.insert_array(DESIGN, [screened], depth)[0, -1]
    rel = np.array([tip[0] * np.cos(np.radians(30)), tip[0] * np.sin(np.radians(30)), tip[2]])
    target = np.array([tip[0], 0.0, tip[2]])  # in the bending plane (roll 0)
    first = MODEL.insert_one(DESIGN, screened, depth)
    assert isinstance(first, np.ndarray)
    miss_first = float(np.linalg.norm(first[-1] - target))
    assert miss_first > 1.0  # the two models differ: there is something to correct

    sch, path = refine_with(MODEL, DESIGN, screened, depth, rel)
    miss = float(np.linalg.norm(path.positions_mm[-1] - target))
    assert miss < 0.25 and sch.peak_tension_n != screened.peak_tension_n
    np.testing.assert_allclose(sch.tension_n / sch.peak_tension_n, screened.tension_n / screened.peak_tension_n)
    # the path is the rod's own solve of the returned schedule, resampled evenly in arc length (tip exact)
    direct = MODEL.insert_one(DESIGN, sch, depth)
    assert isinstance(direct, np.ndarray)
    np.testing.assert_allclose(path.positions_mm[-1], direct[-1], atol=1e-9)
    steps = np.diff(arc_length_mm(path.positions_mm))
    assert np.ptp(steps) < 1e-3 and abs(steps.sum() - arc_length_mm(direct)[-1]) < 1e-3  # chords of 1 mm
    assert path.model.label == "tissue_rod+two_tube_cosserat"
