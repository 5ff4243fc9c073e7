"""Cosserat solvers against closed forms (never against their own output)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from scipy.special import ellipe, ellipeinc, ellipk, ellipkinc

from reachplan.rod_model.beam import PLANAR_BEAM
from reachplan.rod_model.collocation import CollocationCosserat
from reachplan.rod_model.cosserat import COSSERAT_ROD, TWO_TUBE_COSSERAT, CosseratRod, TwoTubeCosserat
from reachplan.rod_model.design import Loads, RodDesign, preset
from reachplan.rod_model.kinematic import CONSTANT_CURVATURE
from reachplan.rod_model.result import RodPath

SHOOTERS = [COSSERAT_ROD, TWO_TUBE_COSSERAT]
ALL = [CONSTANT_CURVATURE, PLANAR_BEAM, *SHOOTERS]


def _ok(r: object) -> RodPath:
    assert isinstance(r, RodPath), getattr(r, "reason", r)
    return r


def _ei(design: RodDesign) -> float:
    s = design.sections()[0]
    return s.ei1 + s.ei2


@pytest.mark.parametrize("model", ALL, ids=lambda m: m.name)
@pytest.mark.parametrize("name", ["15ga-20j-tip", "15ga-20j-base", "13ga-20j-tip"])
def test_zero_tension_is_straight(model: object, name: str) -> None:
    d = preset(name)
    r = _ok(model.solve(d, d.loads(0.0)))  # type: ignore[attr-defined]
    assert np.max(np.abs(r.positions_mm[:, :2])) < 1e-12
    np.testing.assert_allclose(r.positions_mm[:, 2], r.s_mm, atol=1e-9)
    np.testing.assert_allclose(r.frames, np.broadcast_to(np.eye(3), r.frames.shape), atol=1e-12)


@pytest.mark.parametrize("model", SHOOTERS, ids=lambda m: m.name)
def test_pure_end_moment_gives_circular_arc(model: object, uniform_design: RodDesign) -> None:
    moment = 0.004  # N·m about +y: bends toward +x
    loads = Loads((0.0,) * 4, tip_moment_nm=(0.0, moment, 0.0))
    r = _ok(model.solve(uniform_design, loads))  # type: ignore[attr-defined]
    k = moment / _ei(uniform_design) * 1e-3  # 1/mm
    s = r.s_mm
    expected = np.stack([(1 - np.cos(k * s)) / k, np.zeros_like(s), np.sin(k * s) / k], axis=1)
    np.testing.assert_allclose(r.positions_mm, expected, atol=1e-6)
    assert r.tip_deflection_mm > 10.0  # a real bend, not a trivial pass


@pytest.mark.parametrize("model", SHOOTERS, ids=lambda m: m.name)
@pytest.mark.parametrize("name", ["15ga-20j-tip", "15ga-20j-mid", "15ga-20j-base"])
def test_small_loads_match_linear_beam_theory(model: object, name: str) -> None:
    d = preset(name)
    secs = d.sections()
    length = secs[-1].end_m
    # tip force F (unit-load method over piecewise EI, plus Timoshenko shear)
    f = 1e-3
    flex = sum(((length - s.start_m) ** 3 - (length - s.end_m) ** 3) / 3 / (s.ei1 + s.ei2)
               + s.length_m / (s.ga1 + s.ga2) for s in secs)
    r = _ok(model.solve(d, Loads((0.0,) * 4, tip_force_n=(f, 0, 0))))  # type: ignore[attr-defined]
    assert r.tip_position_mm[0] == pytest.approx(f * flex * 1e3, rel=1e-4)
    # uniform distributed load w: M = w (L - s)² / 2, unit-load moment (L - s)
    w = 5e-3
    flex_w = sum(((length - s.start_m) ** 4 - (length - s.end_m) ** 4) / 8 / (s.ei1 + s.ei2) for s in secs)
    r = _ok(model.solve(d, Loads((0.0,) * 4, distributed_n_per_m=(w, 0, 0))))  # type: ignore[attr-defined]
    assert r.tip_position_mm[0] == pytest.approx(w * flex_w * 1e3, rel=1e-3)
    # small tension: moment λ r(s) per section, deflection ∫ κ (L - s) ds
    lam = 1e-2
    lin = sum(lam * s.arm_m / (s.ei1 + s.ei2) * ((length - s.start_m) ** 2 - (length - s.end_m) ** 2) / 2
              for s in secs)
    r = _ok(model.solve(d, d.loads(lam)))  # type: ignore[attr-defined]
    assert r.tip_position_mm[0] == pytest.approx(lin * 1e3, rel=1e-4)


def _elastica_tip(alpha: float) -> tuple[float, float, float]:
    """Bisshopp & Drucker (1945): cantilever of length 1 with a dead tip force P perpendicular to its
    undeformed axis, alpha = P L² / EI. Returns (tip angle θ0, axial projection, lateral deflection)."""
    from scipy.optimize import brentq

    def g(theta0: float) -> float:
        p = np.sqrt((1 + np.sin(theta0)) / 2)
        phi1 = np.arcsin(1 / (p * np.sqrt(2)))
        return ellipk(p**2) - ellipkinc(phi1, p**2) - np.sqrt(alpha)

    theta0 = brentq(g, 1e-9, np.pi / 2 - 1e-9)
    p = np.sqrt((1 + np.sin(theta0)) / 2)
    phi1 = np.arcsin(1 / (p * np.sqrt(2)))
    axial = np.sqrt(2 * np.sin(theta0) / alpha)
    lateral = 1 - 2 / np.sqrt(alpha) * (ellipe(p**2) - ellipeinc(phi1, p**2))
    return theta0, axial, lateral


@pytest.mark.parametrize("model", SHOOTERS, ids=lambda m: m.name)
@pytest.mark.parametrize("alpha", [0.5, 2.0, 5.0])
def test_tip_force_matches_euler_elastica(model: object, alpha: float, uniform_design: RodDesign) -> None:
    length_m = uniform_design.length_mm * 1e-3
    force = alpha * _ei(uniform_design) / length_m**2
    r = _ok(model.solve(uniform_design, Loads((0.0,) * 4, tip_force_n=(force, 0, 0))))  # type: ignore[attr-defined]
    theta0, axial, lateral = _elastica_tip(alpha)
    lateral_mm = r.tip_position_mm[0]
    assert lateral_mm > 0.1 * uniform_design.length_mm
    # the elastica is inextensible and unshearable: allow the rod's shear/axial strain (F/GA ~ 1e-4)
    assert lateral_mm / uniform_design.length_mm == pytest.approx(lateral, abs=3e-4)
    assert r.tip_position_mm[2] / uniform_design.length_mm == pytest.approx(axial, abs=3e-4)
    tangent = r.frames[-1][:, 2]
    assert np.arccos(tangent[2]) == pytest.approx(theta0, abs=1e-3)


@pytest.mark.parametrize("model", ALL, ids=lambda m: m.name)
def test_opposite_equal_tendons_stay_straight(model: object) -> None:
    d = preset("15ga-20j-tip")
    r = _ok(model.solve(d, Loads((6.0, 0.0, 6.0, 0.0))))  # type: ignore[attr-defined]
    assert np.max(np.abs(r.positions_mm[:, :2])) < 1e-9
    one = _ok(model.solve(d, d.loads(6.0)))  # type: ignore[attr-defined]
    assert one.tip_deflection_mm > 1.0


@pytest.mark.parametrize("model", ALL, ids=lambda m: m.name)
@pytest.mark.parametrize("roll", [30.0, 90.0, 200.0])
def test_roll_rolls_the_shape(model: object, roll: float) -> None:
    d = preset("15ga-20j-mid")
    r0 = _ok(model.solve(d, d.loads(8.0)))  # type: ignore[attr-defined]
    r1 = _ok(model.solve(d, d.loads(8.0, roll_deg=roll)))  # type: ignore[attr-defined]
    c, s = np.cos(np.radians(roll)), np.sin(np.radians(roll))
    rz = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])
    np.testing.assert_allclose(r1.positions_mm, r0.positions_mm @ rz.T, atol=1e-9)
    assert r0.tip_deflection_mm > 5.0


@pytest.mark.parametrize("cls", [CosseratRod, TwoTubeCosserat], ids=["cosserat_rod", "two_tube_cosserat"])
def test_refinement_converges_at_fourth_order(cls: type) -> None:
    base = preset("15ga-20j-base")  # 40 mm joint section, 160 mm tube: the step counts double exactly
    d = replace(base, stylet=replace(base.stylet, joint_pitch_mm=2.0))
    loads = Loads((8.0, 0.0, 0.0, 0.0), tip_force_n=(0.0, 0.3, -0.1), distributed_n_per_m=(0.2, 0.0, 0.0))
    ref = _ok(cls(steps_per_mm=4.0).solve(d, loads)).tip_position_mm
    coarse = {"max_step_error_mm": 10.0, "max_frame_error": 1.0}  # the point is to measure the coarse error
    errs = [np.linalg.norm(_ok(cls(steps_per_mm=h, **coarse).solve(d, loads)).tip_position_mm - ref)
            for h in (0.05, 0.1, 0.2)]
    orders = np.log2(np.array(errs[:-1]) / np.array(errs[1:]))
    assert errs[0] > 1e-6  # the coarse solve really is inexact
    assert np.all((orders > 3.5) & (orders < 4.6)), orders


CASES = [
    ("15ga-20j-tip", Loads((9.9, 0, 0, 0))),
    ("15ga-20j-base", Loads((12.0, 0, 0, 0), roll_deg=40.0)),
    ("13ga-20j-mid", Loads((14.0, 0, 0, 0), tip_force_n=(0.0, 0.4, -0.2))),
    ("15ga-20j-tip", Loads((5.0, 0, 2.0, 0), tip_force_n=(0.2, 0.1, -0.5), tip_moment_nm=(0, 0, 0.002),
                           distributed_n_per_m=(0.0, 0.03, 0.0))),
]


@pytest.mark.filterwarnings("ignore::reachplan.rod_model.errors.TensionAboveLimitWarning")
@pytest.mark.parametrize(("name", "loads"), CASES)
def test_shooting_and_collocation_agree_within_a_micrometre(name: str, loads: Loads) -> None:
    d = preset(name)
    a = _ok(TwoTubeCosserat(steps_per_mm=2.0).solve(d, loads))
    b = _ok(CollocationCosserat(tol=1e-9).solve(d, loads))
    assert np.linalg.norm(a.tip_position_mm - b.tip_position_mm) <= 1e-3
    assert a.twist_rad is not None and b.twist_rad is not None
    assert a.twist_rad[-1] == pytest.approx(b.twist_rad[-1], abs=1e-6)
    # whole centreline, compared at collocation nodes by interpolation of the fine shooting solution
    for k in range(3):
        assert np.max(np.abs(np.interp(b.s_mm, a.s_mm, a.positions_mm[:, k]) - b.positions_mm[:, k])) < 5e-3


def test_two_tube_twists_under_tip_torque_but_single_rod_cannot() -> None:
    d = preset("15ga-20j-tip")
    loads = Loads((0.0,) * 4, tip_moment_nm=(0, 0, 0.001))
    r = _ok(TWO_TUBE_COSSERAT.solve(d, loads))
    secs = d.sections()
    # the needle alone carries the torque (it is applied to the needle; no friction between the tubes)
    expected = 0.001 * secs[0].length_m / secs[0].gj2 + 0.001 * secs[1].length_m / secs[1].gj2
    assert r.twist_rad is not None
    assert r.twist_rad[-1] == pytest.approx(expected, rel=1e-9)


@pytest.mark.filterwarnings("ignore::reachplan.rod_model.errors.TensionAboveLimitWarning")
def test_nonconvergence_is_a_failed_result_with_reason() -> None:
    d = preset("15ga-20j-base")
    loads = Loads((15.0, 0, 0, 0), tip_force_n=(0.5, 0.5, -0.3))
    bad = np.array([50.0, -80.0, 30.0, 9.0, -7.0, 4.0, 0.0, 0.0])
    r = TwoTubeCosserat(max_iter=2).solve(d, loads, initial_guess=bad, continuation=False)
    assert not r
    assert not r.converged
    assert "residual" in r.reason  # type: ignore[union-attr]
    rescued = TWO_TUBE_COSSERAT.solve(d, loads, initial_guess=bad)
    assert rescued, getattr(rescued, "reason", "")


def test_axial_tip_force_stretches_the_needle_not_the_stylet() -> None:
    # external loads act on the needle; without friction the stylet (whose centreline is reported) carries no
    # part of an axial pull, while the welded single rod shares it: z_tip = L (1 + F / (EA1 + EA2))
    d = preset("15ga-20j-tip")
    loads = Loads((0.0,) * 4, tip_force_n=(0.0, 0.0, 2.0))
    two = _ok(TWO_TUBE_COSSERAT.solve(d, loads))
    one = _ok(COSSERAT_ROD.solve(d, loads))
    assert two.tip_position_mm[2] == pytest.approx(d.length_mm, abs=1e-9)
    s = d.sections()[0]
    assert one.tip_position_mm[2] == pytest.approx(d.length_mm * (1 + 2.0 / (s.ea1 + s.ea2)), rel=1e-9)
