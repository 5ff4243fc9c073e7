"""Friction: capstan law along the tendon routing, Coulomb friction in the joints, hysteresis of a sweep."""

from __future__ import annotations

import json
import math
from dataclasses import replace

import numpy as np
import pytest

from reachplan.planner.cli import main
from reachplan.rod_model.beam import PLANAR_BEAM
from reachplan.rod_model.cosserat import TWO_TUBE_COSSERAT
from reachplan.rod_model.design import RodDesign, preset
from reachplan.rod_model.errors import UnsupportedLoadError
from reachplan.rod_model.friction import loop_width_mm, solve_sweep
from reachplan.rod_model.result import RodPath

UP_DOWN = [0.0, 2.0, 4.0, 6.0, 8.0, 10.0, 8.0, 6.0, 4.0, 2.0, 0.0]


def _with(design: RodDesign, tendon: float = 0.0, joint: float = 0.0) -> RodDesign:
    return replace(design, stylet=replace(design.stylet, tendon_friction_coefficient=tendon,
                                          joint_friction_coefficient=joint))


def _width(design: RodDesign) -> float:
    results = solve_sweep(TWO_TUBE_COSSERAT, design, UP_DOWN)
    assert all(isinstance(r, RodPath) for r in results)
    return loop_width_mm(UP_DOWN, [r.tip_deflection_mm for r in results])  # type: ignore[union-attr]


def test_capstan_decay_matches_the_closed_form(uniform_design: RodDesign) -> None:
    # uniform rod, tendon at constant arm r: curvature κ(s) = λ(s) r / EI with λ = λ0 exp(−μ φ) and φ' = κ, so
    # exp(μ φ) = 1 + μ κ0 s and the tip tangent turns by φ(L) = ln(1 + μ κ0 L) / μ (κ0 = λ0 r / EI)
    tension, mu = 9.0, 0.4
    sec = uniform_design.sections()[0]
    kappa0 = tension * sec.arm_m / (sec.ei1 + sec.ei2)
    length = uniform_design.length_mm * 1e-3
    for m, expected in ((0.0, kappa0 * length), (mu, math.log1p(mu * kappa0 * length) / mu)):
        d = _with(uniform_design, tendon=m)
        r = TWO_TUBE_COSSERAT.solve(d, d.loads(tension))
        assert isinstance(r, RodPath)
        tip_angle = math.atan2(r.frames[-1, 0, 2], r.frames[-1, 2, 2])
        assert tip_angle == pytest.approx(expected, rel=2e-3)


@pytest.mark.parametrize("name", ["15ga-20j-tip", "15ga-20j-base"])
def test_without_friction_a_sweep_has_no_loop(name: str) -> None:
    d = preset(name)
    results = solve_sweep(TWO_TUBE_COSSERAT, d, UP_DOWN)
    for t, r in zip(UP_DOWN, results, strict=True):
        single = TWO_TUBE_COSSERAT.solve(d, d.loads(t))
        np.testing.assert_allclose(r.tip_position_mm, single.tip_position_mm, atol=1e-12)  # type: ignore[union-attr]
    assert _width(d) == 0.0


@pytest.mark.parametrize("kind", ["tendon", "joint"])
def test_loop_width_grows_with_the_coefficient(kind: str) -> None:
    d = preset("15ga-20j-base")
    widths = [_width(_with(d, **{kind: mu})) for mu in (0.0, 0.05, 0.15, 0.3)]
    assert widths[0] == 0.0
    assert np.all(np.diff(widths) > 0), widths
    # releasing keeps the needle bent more than pulling did at the same load-cell tension
    results = solve_sweep(TWO_TUBE_COSSERAT, _with(d, **{kind: 0.15}), UP_DOWN)
    tips = [r.tip_deflection_mm for r in results]  # type: ignore[union-attr]
    assert tips[6] > tips[4] and tips[8] > tips[2]


def test_models_without_friction_refuse_a_design_with_friction() -> None:
    d = _with(preset("15ga-20j-tip"), joint=0.1)
    with pytest.raises(UnsupportedLoadError, match="friction"):
        PLANAR_BEAM.solve(d, d.loads(5.0))


def test_cli_sweep_shows_the_loop(capsys: pytest.CaptureFixture[str]) -> None:
    argv = ["rod", "--preset", "15ga-20j-base", "--tensions", ",".join(f"{t:g}" for t in UP_DOWN),
            "--joint-friction", "0.1", "--json"]
    assert main(argv) == 0
    docs = json.loads(capsys.readouterr().out)
    assert [d["pulling"] for d in docs] == [None] + [True] * 5 + [False] * 5
    tips = [d["tip_deflection_mm"] for d in docs]
    assert loop_width_mm(UP_DOWN, tips) > 1.0
    assert main([*argv[:-1]]) == 0
    assert "hysteresis" in capsys.readouterr().out
