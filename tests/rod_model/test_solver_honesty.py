"""Solver honesty: blown-up integrations, unstable branches and over-limit tensions are never a converged shape."""

from __future__ import annotations

import math

import numpy as np
import pytest

from reachplan.planner.cli import main
from reachplan.rod_model.cosserat import COSSERAT_ROD, TWO_TUBE_COSSERAT, TwoTubeCosserat
from reachplan.rod_model.design import Loads, RodDesign, preset
from reachplan.rod_model.errors import TensionAboveLimitWarning
from reachplan.rod_model.result import FailedSolve, RodPath

MODELS = [COSSERAT_ROD, TWO_TUBE_COSSERAT]


@pytest.mark.parametrize("model", MODELS, ids=lambda m: m.name)
def test_blown_up_integration_is_a_failed_solve_with_its_reason(model: TwoTubeCosserat) -> None:
    d = preset("15ga-20j-tip")
    with pytest.warns(TensionAboveLimitWarning, match="exceeds"):
        r = model.solve(d, d.loads(5000.0))
    assert isinstance(r, FailedSolve)
    assert "integration error" in r.reason and "step is halved" in r.reason


def test_integration_error_check_passes_ordinary_solves() -> None:
    d = preset("15ga-20j-base")
    r = TWO_TUBE_COSSERAT.solve(d, d.loads(9.9))
    assert isinstance(r, RodPath)
    frames = r.frames
    assert np.max(np.abs(np.einsum("nki,nkj->nij", frames, frames) - np.eye(3))) < 1e-3


def _potential_energy_sign(r: RodPath, force_n: np.ndarray) -> float:
    """Work of the dead tip force on the tip displacement (N·mm): positive when the tip moved with the force."""
    return float(force_n @ (r.tip_position_mm - np.array([0.0, 0.0, r.s_mm[-1]])))


@pytest.mark.parametrize("model", MODELS, ids=lambda m: m.name)
@pytest.mark.parametrize("tension", [0.0, 9.9])
def test_lateral_tip_force_is_solved_on_the_stable_branch(model: TwoTubeCosserat, tension: float) -> None:
    # issue 15: 15ga-20j-base with a 2 N lateral tip force used to end 67 mm on the side opposite the force
    d = preset("15ga-20j-base")
    force = np.array([0.0, 2.0, 0.0])
    loads = Loads((tension, 0.0, 0.0, 0.0), tip_force_n=tuple(force))
    r = model.solve(d, loads)
    assert isinstance(r, RodPath), getattr(r, "reason", "")
    assert r.tip_position_mm[1] > 100.0  # bent far toward the force
    assert _potential_energy_sign(r, force) > 0
    # a direct solve (no continuation) either finds the same branch or says the one it found is unstable
    direct = model.solve(d, loads, continuation=False)
    if isinstance(direct, RodPath):
        np.testing.assert_allclose(direct.tip_position_mm, r.tip_position_mm, atol=1e-6)
    else:
        assert "unstable" in direct.reason and "conjugate point" in direct.reason


@pytest.mark.parametrize("model", MODELS, ids=lambda m: m.name)
def test_stability_check_finds_the_euler_load(model: TwoTubeCosserat, uniform_design: RodDesign) -> None:
    # a uniform clamped-free column under a dead axial load: the straight shape is stable below
    # P_cr = π² EI / (4 L²) and unstable above (closed form); the solver must say so, not return it
    sec = uniform_design.sections()[0]
    length_m = uniform_design.length_mm * 1e-3
    p_cr = math.pi**2 * (sec.ei1 + sec.ei2) / (4 * length_m**2)
    below = model.solve(uniform_design, Loads((0.0,) * 4, tip_force_n=(0.0, 0.0, -0.9 * p_cr)))
    assert isinstance(below, RodPath), getattr(below, "reason", "")
    assert below.tip_deflection_mm < 1e-9
    above = model.solve(uniform_design, Loads((0.0,) * 4, tip_force_n=(0.0, 0.0, -1.1 * p_cr)))
    assert isinstance(above, FailedSolve)
    assert "unstable" in above.reason and "conjugate point" in above.reason


def test_imperfect_column_above_the_euler_load_buckles_toward_the_imperfection(uniform_design: RodDesign) -> None:
    sec = uniform_design.sections()[0]
    p_cr = math.pi**2 * (sec.ei1 + sec.ei2) / (4 * (uniform_design.length_mm * 1e-3) ** 2)
    r = TWO_TUBE_COSSERAT.solve(uniform_design, Loads((0.0,) * 4, tip_force_n=(0.01 * p_cr, 0.0, -1.5 * p_cr)))
    assert isinstance(r, RodPath), getattr(r, "reason", "")
    assert r.tip_position_mm[0] > 50.0  # buckled, toward the lateral imperfection (not the straight branch)


def test_tension_above_the_limit_warns_in_the_api() -> None:
    d = preset("15ga-20j-tip")
    with pytest.warns(TensionAboveLimitWarning, match="limit of 10 N"):
        r = TWO_TUBE_COSSERAT.solve(d, d.loads(12.0))
    assert isinstance(r, RodPath)


def test_tension_above_the_limit_is_an_error_in_the_cli(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["rod", "--preset", "15ga-20j-tip", "--tension", "500", "--json"]) == 2
    err = capsys.readouterr().err
    assert "--allow-over-limit" in err and err.count("\n") == 1
    assert main(["rod", "--preset", "15ga-20j-tip", "--tensions", "5,12", "--allow-over-limit", "--json"]) == 0
    capsys.readouterr()


def test_collocation_reports_an_unstable_equilibrium_too(uniform_design: RodDesign) -> None:
    from reachplan.rod_model.collocation import CollocationCosserat

    sec = uniform_design.sections()[0]
    p_cr = math.pi**2 * (sec.ei1 + sec.ei2) / (4 * (uniform_design.length_mm * 1e-3) ** 2)
    coll = CollocationCosserat(tol=1e-6)
    above = coll.solve(uniform_design, Loads((0.0,) * 4, tip_force_n=(0.0, 0.0, -1.1 * p_cr)))
    assert isinstance(above, FailedSolve) and "unstable" in above.reason
    below = coll.solve(uniform_design, Loads((0.0,) * 4, tip_force_n=(0.0, 0.0, -0.9 * p_cr)))
    assert isinstance(below, RodPath), getattr(below, "reason", "")
