"""Calibration: the data copied from the reference, the fit, and the shipped defaults."""

from __future__ import annotations

import re
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

from reachplan.rod_model.calibrate import CALIBRATION_ROWS, calibrate, predict
from reachplan.rod_model.design import Calibration


def test_rows_are_the_reference_calibration_subset(reference_file: Callable[[str], Path]) -> None:
    text = reference_file("oncoreach.md").read_text(encoding="utf-8")
    table = text.split("(calibration subset)")[1].split("\n\n")[0]
    rows = re.findall(r"\|\s*(\d+) ga, (\d+) joints, (\w+)\s*\|\s*([\d.]+)\s*\|\s*([\d.]+)\s*\|", table)
    expected = {(f"{g}ga-{j}j-{p}", float(t), float(d)) for g, j, p, t, d in rows}
    assert len(expected) == 3
    assert {(r.preset, r.tension_n, r.tip_deflection_mm) for r in CALIBRATION_ROWS} == expected


def test_fit_is_within_aim_and_is_the_shipped_default() -> None:
    result = calibrate()
    assert result.max_abs_residual_mm <= 1.5, result.residual_mm
    shipped = Calibration()
    assert result.calibration.joint_stiffness_scale == pytest.approx(shipped.joint_stiffness_scale, rel=2e-3)
    assert result.calibration.tube_arm_fraction == pytest.approx(shipped.tube_arm_fraction, rel=2e-3)
    # physically plausible: the joints are softer in the needle than measured free, the tendon is inside the lumen
    assert 0.0 < result.calibration.joint_stiffness_scale < 1.0
    assert 0.0 < result.calibration.tube_arm_fraction < 1.0
    np.testing.assert_allclose(predict(shipped), result.predicted_mm, atol=0.01)


def test_one_moment_arm_cannot_fit_tip_and_base() -> None:
    # the reason for a second parameter: with the measured joint stiffness (scale 1) the best single tube arm
    # still misses the rows by far more than the two-parameter fit
    best = min(np.max(np.abs(predict(Calibration(1.0, f)) - [r.tip_deflection_mm for r in CALIBRATION_ROWS]))
               for f in np.linspace(0.3, 1.0, 8))
    assert best > 3.0


def test_every_published_row_is_reported_and_fitted_ones_are_marked() -> None:
    from reachplan.rod_model.calibrate import VALIDATION_ROWS, CalibrationResult, every_published_row

    shipped = Calibration()
    pred = predict(shipped)
    result = CalibrationResult(shipped, CALIBRATION_ROWS, pred, pred - [r.tip_deflection_mm for r in CALIBRATION_ROWS])
    table = every_published_row(result)
    assert [r for r, _, _ in table] == list(CALIBRATION_ROWS + VALIDATION_ROWS)
    assert [f for _, _, f in table] == [True] * 3 + [False] * 2
    # the validation rows really are predictions: the pilot design (30 joints) is over-predicted by ~1.6 mm
    over = {r.preset: p - r.tip_deflection_mm for r, p, _ in table}
    assert 0.5 < over["15ga-30j-tip"] < 3.0


def test_calibration_can_fit_a_friction_coefficient() -> None:
    base = calibrate()
    fitted = calibrate(fit_friction=("joint_friction_coefficient",))
    assert fitted.friction[0] == 0.0 and fitted.friction[1] >= 0.0
    # one more free parameter never fits worse (least squares, same start)
    assert np.sum(fitted.residual_mm**2) <= np.sum(base.residual_mm**2) + 1e-9
    with pytest.raises(ValueError, match="unknown friction"):
        calibrate(fit_friction=("nope",))
