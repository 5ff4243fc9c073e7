"""Learning the tissue (issue 32.4): the curvature factor recovered from steered needles as a tissue drew them.

The found needles are made here, independently of the fit: the kinematic model at a true factor 15 % above the
plan's, each needle with the planner's own perturbations drawn (tension x (1 +- 10 %), roll +- 10 deg, entry tilt up
to 2 deg), sampled every mm with 0.2 mm of reconstruction noise; five implants, two steered needles each.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from reachplan.planner.errors import PlanInputError
from reachplan.planner.steering.calibration import FoundSteered, fit_needle, pool
from reachplan.planner.steering.kinematic import KinematicInsertion
from reachplan.planner.steering.schedule import TensionSchedule
from reachplan.rod_model.design import preset

DESIGN = "15ga-30j-tip"
MODULUS_PA = 1.9e5
TRUE_RATIO = 1.15
#: The plan's model: the kinematic model in the gel.
PLANNED = KinematicInsertion(tissue_modulus_pa=MODULUS_PA)


def _rotation_about(axis: np.ndarray, angle_rad: float) -> np.ndarray:
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + math.sin(angle_rad) * k + (1 - math.cos(angle_rad)) * k @ k


def _found(rng: np.random.Generator, schedule: TensionSchedule, depth_mm: float, noise_mm: float,
           perturbed: bool, tension_fraction: float) -> np.ndarray:
    """A needle as the true tissue bends it (template frame of its hole), every mm, with reconstruction noise."""
    design = preset(DESIGN)
    tension = 1.0 + (rng.uniform(-tension_fraction, tension_fraction) if perturbed else 0.0)
    roll = rng.uniform(-10.0, 10.0) if perturbed else 0.0
    true = KinematicInsertion(tissue_factor=PLANNED.factor_for(design) * TRUE_RATIO)
    drawn = TensionSchedule(schedule.depth_mm, np.minimum(schedule.tension_n * tension, design.max_tension_n),
                            schedule.roll_deg + roll)
    path = true.insert_array(design, [drawn], depth_mm)[0]
    if perturbed:
        azimuth = rng.uniform(0.0, 2 * math.pi)
        axis = np.array([-math.sin(azimuth), math.cos(azimuth), 0.0])
        path = path @ _rotation_about(axis, math.radians(rng.uniform(0.0, 2.0))).T
    return path + rng.normal(0.0, noise_mm, path.shape) * (noise_mm > 0)


def _needles(perturbed: bool, seed: int = 0, tension_fraction: float = 0.1) -> list[FoundSteered]:
    rng = np.random.default_rng(seed)
    design = preset(DESIGN)
    out = []
    for case in range(5):  # five implants, two steered needles each
        for k, (onset, plateau, roll, depth) in enumerate([(20.0, 6.0, 0.0, 100.0), (30.0, 8.0, 180.0, 100.0)]):
            schedule = TensionSchedule.ramp(onset + 5 * case, 20.0, plateau - 0.5 * case, roll + 30 * case)
            planned = PLANNED.insert_array(design, [schedule], depth)[0]
            out.append(FoundSteered(f"case{case}", f"H{k}", DESIGN, PLANNED.factor_for(design), planned,
                                    _found(rng, schedule, depth, 0.2 if perturbed else 0.0, perturbed,
                                           tension_fraction)))
    return out


def test_an_unperturbed_needle_gives_the_true_factor() -> None:
    fit = fit_needle(_needles(perturbed=False)[0])
    assert fit.ratio == pytest.approx(TRUE_RATIO, rel=0.01)  # the departure is linear in the factor to 2nd order
    assert abs(fit.roll_offset_deg) < 0.1 and fit.tilt_deg < 0.01 and fit.rms_mm < 0.05


def test_five_cases_recover_the_factor_within_3_percent_when_roll_tilt_and_noise_are_the_only_errors() -> None:
    # the roll offset and the entry tilt are fitted away: what is left is the reconstruction noise
    fits = [fit_needle(n) for n in _needles(perturbed=True, tension_fraction=0.0)]
    (estimate,) = pool(fits)
    assert estimate.design == DESIGN and len(estimate.fits) == 10
    assert abs(estimate.ratio / TRUE_RATIO - 1.0) < 0.03
    assert all(f.rms_mm < 1.25 * 0.2 * math.sqrt(2) for f in fits)  # the lateral noise, 0.2 mm per axis
    doc = estimate.to_json()
    assert doc["needles"] == 10 and doc["factor"] == pytest.approx(estimate.planned_factor * estimate.ratio, 1e-4)


def test_with_the_planners_tension_errors_the_interval_is_as_wide_as_they_make_it_and_holds_the_truth() -> None:
    # a tension error scales the curvature as the factor does: per needle they cannot be told apart, so the
    # needles' ratios spread as 1.15 (1 + U(-10 %, 10 %)) (sd 1.15 * 0.1 / sqrt(3)); ten needles give a t interval
    # of about +- 2.26 * sd / sqrt(10)
    (estimate,) = pool([fit_needle(n) for n in _needles(perturbed=True)])
    lo, hi = estimate.ci95
    expected = 2.262 * TRUE_RATIO * 0.1 / math.sqrt(3) / math.sqrt(10)
    assert lo < TRUE_RATIO < hi and 0.5 * expected < (hi - lo) / 2 < 2.0 * expected
    assert abs(estimate.ratio / TRUE_RATIO - 1.0) < 0.05


def test_one_needle_has_no_interval_and_a_straight_one_tells_nothing() -> None:
    (one,) = pool([fit_needle(_needles(perturbed=False)[0])])
    assert all(math.isnan(v) for v in one.ci95) and one.to_json()["ci95_ratio"] == [None, None]
    line = np.column_stack([np.zeros(81), np.zeros(81), np.arange(81.0)])
    straight = FoundSteered("c", "H", DESIGN, 1.0, line, line)
    with pytest.raises(PlanInputError, match="tells nothing of the curvature"):
        fit_needle(straight)
    short = FoundSteered("c", "H", DESIGN, 1.0, _needles(perturbed=False)[0].planned_mm, np.zeros((3, 3)))
    with pytest.raises(PlanInputError, match="a fit needs at least"):
        fit_needle(short)
    # a found track that leaves the planned shape half way (it took another needle's) is not used
    planned = _needles(perturbed=False)[0].planned_mm
    swapped = planned.copy()
    swapped[len(swapped) // 2:, 0] -= np.linspace(0.0, 12.0, len(swapped) - len(swapped) // 2)
    with pytest.raises(PlanInputError, match="not used"):
        fit_needle(FoundSteered("c", "H", DESIGN, 1.0, planned, swapped))


def test_a_site_file_round_trips_refits_replace_and_every_model_of_a_plan_applies_it(tmp_path: Path) -> None:
    import argparse
    import json

    from reachplan.planner.case.config import PlanConfig, PlanModels
    from reachplan.planner.cli.tissue import site_calibration
    from reachplan.planner.steering.calibration import site_document, site_fits, site_scales
    from reachplan.planner.steering.tissue_rod import TissueRodInsertion

    fits = [fit_needle(n) for n in _needles(perturbed=True, tension_fraction=0.0)]
    doc = site_document(fits[:6])
    doc = site_document(fits[4:], previous=json.loads(json.dumps(doc)))  # needles 4 and 5 fitted again
    assert len(site_fits(doc)) == 10 and json.loads(json.dumps(doc))["designs"][0]["needles"] == 10
    ((name, ratio),) = site_scales(doc)
    assert name == DESIGN and ratio == pytest.approx(pool(fits)[0].ratio, abs=1e-5)
    path = tmp_path / "site.json"
    path.write_text(json.dumps(doc))
    assert site_calibration(str(path)) == ((DESIGN, ratio),)
    for bad in ({"format": "other"}, {"format": doc["format"], "designs": []},
                {"format": doc["format"], "designs": [{"design": DESIGN, "fits": [{"factor": "x"}]}]}):
        path.write_text(json.dumps(bad))
        with pytest.raises(argparse.ArgumentTypeError, match=r"site calibration|format"):
            site_calibration(str(path))
    with pytest.raises(ValueError, match="curvature calibration"):
        PlanConfig(curvature_scale=((DESIGN, 9.0),))
    # the plan's models: the kinematic factor times the ratio, the rod's departure from the hole's axis times it
    models = PlanModels.for_config(PlanConfig(curvature_scale=((DESIGN, 1.2),)))
    design = preset(DESIGN)
    plain = PlanModels.for_config(PlanConfig())
    for m, p in ((models.screening, plain.screening), (models.robustness, plain.robustness)):
        assert m.factor_for(design) == pytest.approx(1.2 * p.factor_for(design))
        assert m.factor_for(preset("13ga-20j-tip")) == pytest.approx(p.factor_for(preset("13ga-20j-tip")))
    ramp = TensionSchedule.ramp(0.0, 10.0, 6.0)
    rod, rod_plain = (TissueRodInsertion(step_mm=4.0, curvature_scale=s) for s in (((DESIGN, 1.2),), ()))
    scaled, unscaled = rod.insert_one(design, ramp, 30.0), rod_plain.insert_one(design, ramp, 30.0)
    assert isinstance(scaled, np.ndarray) and isinstance(unscaled, np.ndarray)
    np.testing.assert_allclose(scaled, unscaled * np.array([1.2, 1.2, 1.0]), atol=1e-12)
    assert models.reference.curvature_scale == ((DESIGN, 1.2),)
    assert ("curvature_scale", f"{DESIGN}=1.2") in models.reference.info.settings
