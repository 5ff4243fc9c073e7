"""The tissue band: scales, the band's paths against direct rod solves, the worst case over the band."""

from __future__ import annotations

import numpy as np
import pytest

from reachplan.planner.errors import PlanInputError
from reachplan.planner.steering.candidates import Target, TissueBand, score_path
from reachplan.planner.steering.insertion import SIMUGEL_MODULUS_PA
from reachplan.planner.steering.schedule import TensionSchedule
from reachplan.planner.steering.steered import place
from reachplan.planner.steering.tissue_band import (
    BAND_MODEL,
    DEFAULT_SOURCE,
    ModulusBand,
    assess_band,
    band_paths,
    uniform_profile,
)
from reachplan.rod_model.design import preset

DESIGN = preset("15ga-30j-tip")
DEPTH_MM = 45.0  # short: a few cheap rod solves
SCHEDULE = TensionSchedule.ramp(20.0, 5.0, 9.0, 0.0)  # pulled with the joints in the tissue: it resists
ROLL_DEG = 90.0
HOLE_XY = np.array([10.0, -20.0])


def _pose() -> np.ndarray:
    """A template pose turned 30 degrees about patient y and shifted: the band must follow the frames."""
    a = np.radians(30.0)
    m = np.eye(4)
    m[:3, :3] = [[np.cos(a), 0.0, np.sin(a)], [0.0, 1.0, 0.0], [-np.sin(a), 0.0, np.cos(a)]]
    m[:3, 3] = [5.0, -40.0, 12.0]
    return m


def _placed(modulus_pa: float) -> np.ndarray:
    """The band model's path in uniform tissue, rolled and placed at the hole (independent of band_paths)."""
    shape = BAND_MODEL.insert_one(DESIGN, SCHEDULE, DEPTH_MM, uniform_profile(modulus_pa))
    assert isinstance(shape, np.ndarray)
    return place(shape, DEPTH_MM / (len(shape) - 1), DEPTH_MM, ROLL_DEG, HOLE_XY, _pose(), sample_mm=1.0)


def test_band_scales_span_the_factor_with_the_nominal_in_the_middle() -> None:
    assert ModulusBand().scales == pytest.approx((1 / 3, 1.0, 3.0))
    assert ModulusBand(4.0, steps=2).scales == pytest.approx((0.25, 0.5, 1.0, 2.0, 4.0))
    assert ModulusBand().enabled and not ModulusBand(1.0).enabled
    assert "ASSUMED" in DEFAULT_SOURCE and ModulusBand().source == DEFAULT_SOURCE
    for bad in ({"factor": 0.5}, {"factor": float("nan")}, {"steps": 0}, {"source": ""}):
        with pytest.raises(ValueError):
            ModulusBand(**bad)  # type: ignore[arg-type]


def test_band_paths_equal_the_rod_placed_in_the_scaled_tissue() -> None:
    """The nominal path plus the rod's change of shape, rolled and posed, is the rod's own path in that tissue."""
    nominal = _placed(SIMUGEL_MODULUS_PA)
    rolled = TensionSchedule(SCHEDULE.depth_mm, SCHEDULE.tension_n, np.full(len(SCHEDULE.depth_mm), ROLL_DEG))
    band = ModulusBand(3.0)
    paths = band_paths(nominal, DEPTH_MM, DESIGN, rolled, uniform_profile(SIMUGEL_MODULUS_PA), _pose(), band)
    assert len(paths) == 3 and np.array_equal(paths[1], nominal)
    for scale, path in zip(band.scales, paths, strict=True):
        direct = _placed(SIMUGEL_MODULUS_PA * scale)
        assert np.allclose(path, direct, atol=1e-6), scale
    # the tissue matters: softer tissue lets the joints bend further (2.8 against 1.8 mm off the axis at the tip)
    assert np.linalg.norm(paths[0][-1] - paths[2][-1]) > 0.5


def test_band_needs_a_constant_roll() -> None:
    varying = TensionSchedule(np.array([0.0, 20.0]), np.array([5.0, 5.0]), np.array([0.0, 45.0]))
    with pytest.raises(PlanInputError, match="roll must be constant"):
        band_paths(np.zeros((3, 3)), DEPTH_MM, DESIGN, varying, uniform_profile(), np.eye(4))


def test_assess_band_reports_the_worst_path_and_its_modulus() -> None:
    nominal = _placed(SIMUGEL_MODULUS_PA)
    rolled = TensionSchedule(SCHEDULE.depth_mm, SCHEDULE.tension_n, np.full(len(SCHEDULE.depth_mm), ROLL_DEG))
    aim = Target("aim", tuple(float(v) for v in nominal[-1]))  # type: ignore[arg-type]
    cand = score_path(aim, "Ab", 10.0, nominal, (), 0.9, 2.0, BAND_MODEL.info, steered=True, design=DESIGN,
                      schedule=rolled, depth_mm=DEPTH_MM)
    band = assess_band(cand, aim, (), _pose(), 0.9, uniform_profile(SIMUGEL_MODULUS_PA), ModulusBand(3.0))
    tips = [np.linalg.norm(_placed(SIMUGEL_MODULUS_PA * s)[-1] - nominal[-1]) for s in (1 / 3, 1.0, 3.0)]
    assert band.reach_mm == pytest.approx(tips, abs=1e-6)
    assert band.worst_reach_mm == pytest.approx(max(tips)) and band.reach_mm[1] == pytest.approx(0.0, abs=1e-9)
    worst = int(np.argmax(tips))
    assert band.worst_case.startswith("tissue x3" if worst == 2 else "tissue ÷3")
    assert band.moduli_pa == pytest.approx((SIMUGEL_MODULUS_PA / 3, SIMUGEL_MODULUS_PA, SIMUGEL_MODULUS_PA * 3))
    assert np.isinf(band.worst_clearance_mm)  # no organ to touch
    doc = band.to_json()
    assert doc["worst_reach_mm"] == pytest.approx(max(tips), abs=1e-3) and doc["clearance_mm"] == [None] * 3
    assert len(doc["tip_position_mm"]) == 3 and doc["source"] == DEFAULT_SOURCE
    failed = TissueBand.failed("rod did not converge", "x").to_json()
    assert failed["worst_reach_mm"] is None and failed["worst_case"] == "not computed: rod did not converge"
