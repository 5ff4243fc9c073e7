"""The discrete joint-section model against closed forms, a finer discretisation and the Cosserat rod."""

from __future__ import annotations

import itertools
from dataclasses import replace

import numpy as np
import pytest
from scipy.optimize import brentq

from reachplan.rod_model import _kernel
from reachplan.rod_model.beam import PLANAR_BEAM
from reachplan.rod_model.calibrate import CALIBRATION_ROWS, VALIDATION_ROWS, calibrate, every_published_row, predict
from reachplan.rod_model.cosserat import COSSERAT_ROD, TWO_TUBE_COSSERAT
from reachplan.rod_model.design import (
    Calibration,
    Foundation,
    Loads,
    RodDesign,
    TensionHistory,
    gravity_load,
    preset,
)
from reachplan.rod_model.errors import TensionAboveLimitWarning, UnsupportedLoadError
from reachplan.rod_model.friction import joint_curvature_per_m, loop_width_mm, solve_sweep
from reachplan.rod_model.joints import (
    DISCRETE_JOINTS,
    JOINTS_CALIBRATION,
    DiscreteJoints,
    PlanarLoads,
    build_chain,
    max_matvec,
    max_positive_definite,
    max_solve,
    routing_tensions,
    tendon_moment,
)
from reachplan.rod_model.protocol import check_rod_model
from reachplan.rod_model.result import RodPath


def _ok(r: object) -> RodPath:
    assert isinstance(r, RodPath), getattr(r, "reason", r)
    return r


def _with_joints(design: RodDesign, n: int, **stylet: float) -> RodDesign:
    """The same joint-section length split into ``n`` joints (stiffness per length unchanged)."""
    st = replace(design.stylet, n_joints=n, joint_pitch_mm=design.stylet.joint_length_mm / n, **stylet)
    return replace(design, name=f"{design.name}-{n}", stylet=st)


def test_chord_moment_is_the_virtual_work_of_the_tendon() -> None:
    # independent: a tendon of constant tension λ stores λ × its length; the chord from the proximal exit
    # (r, −a) to the distal one, (r, a) turned by θ, so the generalised moment is −λ d|chord|/dθ
    rng = np.random.default_rng(3)
    r, a, theta, lam = rng.uniform(0.1, 0.5, 50), rng.uniform(0.1, 0.8, 50), rng.uniform(-0.3, 0.3, 50), 7.0

    def chord(th: np.ndarray) -> np.ndarray:
        q = np.stack([r * np.cos(th) + a * np.sin(th), -r * np.sin(th) + a * np.cos(th)])
        return np.hypot(r - q[0], -a - q[1])

    h = 1e-5
    expected = -lam * (chord(theta + h) - chord(theta - h)) / (2 * h)
    chain = replace(build_chain(preset("15ga-20j-tip"), 1.0, 0.4), arm_m=r, half_gap_m=a)
    moment, slope = tendon_moment(chain, np.full((1, 50), lam), theta[None, :])
    np.testing.assert_allclose(moment[0], expected, rtol=1e-7)
    h = 1e-4
    expected_slope = -lam * (chord(theta + h) - 2 * chord(theta) + chord(theta - h)) / h**2
    np.testing.assert_allclose(slope[0], expected_slope, rtol=1e-5, atol=1e-6)


def test_free_space_is_each_joint_solving_its_own_equation_and_the_tip_their_polygon() -> None:
    d = preset("15ga-30j-tip")
    lam = 10.0
    r = _ok(DISCRETE_JOINTS.solve(d, d.loads(lam)))
    # second implementation: per hinge brentq on k θ = λ (r cos θ/2 + a sin θ/2), stiffness from the sections
    secs = {s.kind: s for s in d.sections()}
    pitch = d.stylet.joint_pitch_mm * 1e-3
    j, t = secs["joints"], secs["tube"]
    n_tube = int(np.ceil(t.length_m * 1e3 / DISCRETE_JOINTS.tube_step_mm - 1e-9))
    step = t.length_m / n_tube

    def angle(k: float, arm: float, gap: float) -> float:
        return brentq(lambda th: k * th - lam * (arm * np.cos(th / 2) + gap * np.sin(th / 2)), 0.0, 0.5, xtol=1e-15)

    th_tube = angle((t.ei1 + t.ei2) / step, t.arm_m, step / 2)
    th_joint = angle((j.ei1 + j.ei2) / pitch, j.arm_m, 0.4e-3)
    thetas = np.r_[np.full(n_tube, th_tube), np.full(d.stylet.n_joints, th_joint)]
    hinges = np.r_[(np.arange(n_tube) + 0.5) * step, t.length_m + (np.arange(d.stylet.n_joints) + 0.5) * pitch]
    links = np.diff(np.r_[0.0, hinges, d.length_mm * 1e-3])
    psi = np.r_[0.0, np.cumsum(thetas)]
    tip = np.array([np.sum(links * np.sin(psi)), 0.0, np.sum(links * np.cos(psi))]) * 1e3
    np.testing.assert_allclose(r.tip_position_mm, tip, atol=1e-9)
    assert r.tip_deflection_mm > 10.0
    assert 0.005 < th_joint < 0.01  # about 0.4° per ball at 10 N


def test_many_frictionless_joints_and_a_finer_tube_converge_to_the_continuum_arcs() -> None:
    # closed form: the beam's piecewise circular arcs (κ = λ r / EI per section). With a zero half-gap the chain
    # differs from them only by its discretisation, second order in the tube step and in the joints' pitch
    d = preset("15ga-20j-tip")

    def error(n: int, step: float) -> float:
        dn = _with_joints(d, n)
        tip = _ok(DiscreteJoints(tube_step_mm=step, joint_half_gap_mm=0.0).solve(dn, dn.loads(10.0)))
        return float(np.linalg.norm(tip.tip_position_mm - PLANAR_BEAM.solve(dn, dn.loads(10.0)).tip_position_mm))

    by_step = [error(160, h) for h in (2.0, 1.0, 0.5)]  # joints fine: the tube's error
    by_joints = [error(n, 0.125) for n in (5, 10, 20)]  # tube fine: the joints' error
    for errs in (by_step, by_joints):
        assert all(3.5 < a / b < 4.5 for a, b in itertools.pairwise(errs)), (by_step, by_joints)
    assert by_joints[-1] < 2e-4  # the real 20 joints: within 0.2 µm of the continuum at the same stiffness


def test_a_finer_tube_step_moves_the_tip_by_micrometres() -> None:
    d = preset("15ga-30j-tip")
    tips = [_ok(DiscreteJoints(tube_step_mm=h).solve(d, d.loads(10.0))).tip_position_mm for h in (1.0, 0.5, 0.25)]
    assert np.linalg.norm(tips[0] - tips[1]) < 0.003
    assert np.linalg.norm(tips[1] - tips[2]) < np.linalg.norm(tips[0] - tips[1]) / 3  # second order


def test_a_small_tip_force_gives_linear_beam_theory() -> None:
    # unit-load method over the piecewise stiffness (hinge stiffness × its length = EI), no tendon
    d = preset("15ga-20j-base")
    f = 0.002
    r = _ok(DISCRETE_JOINTS.solve(d, Loads((0.0,) * 4, tip_force_n=(f, 0.0, 0.0))))
    length = d.length_mm * 1e-3
    expected = sum(f * ((length - s.start_m) ** 3 - (length - s.end_m) ** 3) / 3 / (s.ei1 + s.ei2)
                   for s in d.sections()) * 1e3
    assert r.tip_position_mm[0] == pytest.approx(expected, rel=0.01)
    assert abs(r.tip_position_mm[1]) < 1e-12 and r.tip_deflection_mm > 1.0


@pytest.mark.parametrize("loads", [
    Loads((10.0, 0.0, 0.0, 0.0), tip_force_n=(0.1, 0.0, -0.5)),
    Loads((0.0,) * 4, tip_moment_nm=(0.0, 0.004, 0.0)),
], ids=["tendon+oblique force", "end moment"])
def test_loaded_solves_agree_with_the_cosserat_rod(loads: Loads) -> None:
    # a second, continuous model of the same rod: large deflections agree to the shear/axial strain it adds
    d = preset("15ga-30j-tip")
    a = _ok(DISCRETE_JOINTS.solve(d, loads))
    b = _ok(COSSERAT_ROD.solve(d, loads))
    assert np.linalg.norm(a.tip_position_mm - b.tip_position_mm) < 0.12
    assert a.tip_deflection_mm > 10.0


def test_the_loads_tangent_is_their_moments_derivative_and_solved_in_linear_time() -> None:
    # finite differences of the loads' moment against the analytic −s_max(i, j), then the O(h) solve against
    # a dense one
    chain = build_chain(preset("15ga-20j-base"), 4.0, 0.4)
    loads = PlanarLoads((0.3, -0.8), 0.002, (0.5, 0.2))
    rng = np.random.default_rng(7)
    theta = rng.uniform(-0.05, 0.05, len(chain.stiffness_nm))
    _, lever = loads.moment(chain, theta, 1.0)
    idx = np.arange(len(theta))
    tangent = -lever[np.maximum(idx[:, None], idx[None, :])]
    h = 1e-7
    fd = np.stack([(loads.moment(chain, theta + h * np.eye(len(theta))[j], 1.0)[0]
                    - loads.moment(chain, theta - h * np.eye(len(theta))[j], 1.0)[0]) / (2 * h)
                   for j in range(len(theta))], axis=1)
    np.testing.assert_allclose(tangent, fd, atol=1e-8 * np.max(np.abs(fd)))
    diag = rng.uniform(1.0, 2.0, len(theta))
    rhs = rng.normal(size=len(theta))
    dense = np.diag(diag) - tangent
    np.testing.assert_allclose(max_solve(diag, lever, rhs), np.linalg.solve(dense, rhs), rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(max_matvec(lever, rhs), -tangent @ rhs, rtol=1e-12, atol=1e-14)
    for scale in (1.0, 1e3):
        assert max_positive_definite(diag, scale * lever) == bool(np.all(np.linalg.eigvalsh(
            np.diag(diag) - scale * tangent) > 0))


def test_an_axial_load_beyond_euler_is_refused_and_below_it_solved() -> None:
    d = preset("15ga-20j-tip")
    s = d.sections()[0]
    euler = np.pi**2 * (s.ei1 + s.ei2) / (4 * (d.length_mm * 1e-3) ** 2)  # the stiff tube's: an upper bound
    below = _ok(DiscreteJoints().solve(d, Loads((0.0,) * 4, tip_force_n=(0.0, 0.0, -0.2 * euler))))
    assert below.tip_deflection_mm < 1e-9
    above = DiscreteJoints().solve(d, Loads((0.0,) * 4, tip_force_n=(0.0, 0.0, -1.5 * euler)))
    assert not above and "unstable" in above.reason


def test_a_tension_that_would_close_the_disks_is_refused_not_coiled() -> None:
    # 5000 N turns each ball by about 3 rad; the disks' rims touch at 2 atan(a / R_disk) = 59.5°
    d = preset("15ga-20j-tip")
    with pytest.warns(TensionAboveLimitWarning):
        r = DISCRETE_JOINTS.solve(d, d.loads(5000.0))
    assert not r and "rims touch" in r.reason
    batch = DISCRETE_JOINTS.solve_batch(d, np.array([10.0, 5000.0]))
    assert batch.converged.tolist() == [True, False] and np.isnan(batch.tip_positions_mm[1]).all()
    limit = DISCRETE_JOINTS.chain(d).contact_angle_rad[DISCRETE_JOINTS.chain(d).is_joint][0]
    assert limit == pytest.approx(2 * np.arctan(0.4 / 0.7))


def test_joint_friction_holds_each_ball_by_its_coulomb_moment() -> None:
    # closed form per joint: k θ = λ (r cos θ/2 + a sin θ/2) − μ r_ball λ; above r / r_ball no joint moves
    d = preset("15ga-30j-tip")
    lam, mu = 10.0, 0.5
    df = replace(d, stylet=replace(d.stylet, joint_friction_coefficient=mu))
    chain = DISCRETE_JOINTS.chain(df)
    j = chain.is_joint
    k, arm, gap = chain.stiffness_nm[j][0], chain.arm_m[j][0], chain.half_gap_m[j][0]
    fr = mu * d.stylet.ball_diameter_mm / 2 * 1e-3 * lam
    expected = brentq(lambda th: k * th - lam * (arm * np.cos(th / 2) + gap * np.sin(th / 2)) + fr, 0, 0.5,
                      xtol=1e-15)
    sol = DISCRETE_JOINTS._free(chain, np.array([lam]), TensionHistory())
    np.testing.assert_allclose(sol.theta[0, j], expected, rtol=1e-9)
    stuck = replace(d, stylet=replace(d.stylet, joint_friction_coefficient=1.2))  # μ r_ball > r
    sol = DISCRETE_JOINTS._free(DISCRETE_JOINTS.chain(stuck), np.array([lam]), TensionHistory())
    assert np.all(sol.theta[0, j] == 0.0) and np.all(sol.theta[0, ~j] > 0)


def test_friction_loop_matches_the_cosserat_friction_model() -> None:
    # the same play operator and capstan law, per ball instead of smeared: the loops agree point by point
    d = preset("15ga-20j-tip")
    df = replace(d, stylet=replace(d.stylet, joint_friction_coefficient=0.3, tendon_friction_coefficient=0.2))
    sweep = [0.0, 5.0, 10.0, 5.0, 0.0]
    a = [_ok(r) for r in solve_sweep(DISCRETE_JOINTS, df, sweep)]
    b = [_ok(r) for r in solve_sweep(TWO_TUBE_COSSERAT, df, sweep)]
    np.testing.assert_allclose([r.tip_deflection_mm for r in a], [r.tip_deflection_mm for r in b], atol=0.05)
    width = loop_width_mm(sweep, [r.tip_deflection_mm for r in a])
    assert width > 0.1  # released, the joints hold their bend
    assert joint_curvature_per_m(df, a[3]) > joint_curvature_per_m(df, a[1])


def test_friction_under_a_tip_force_while_pulled_and_released_matches_the_cosserat_model() -> None:
    # the coupled (loaded) solve with stuck and sliding joints: the same history in both models
    d = preset("15ga-20j-tip")
    df = replace(d, stylet=replace(d.stylet, joint_friction_coefficient=0.3, tendon_friction_coefficient=0.2))
    for history in (TensionHistory(), TensionHistory(False, 10.0, 3.0)):
        loads = Loads((6.0, 0.0, 0.0, 0.0), tip_force_n=(0.05, 0.0, -0.1), history=history)
        a, b = _ok(DISCRETE_JOINTS.solve(df, loads)), _ok(TWO_TUBE_COSSERAT.solve(df, loads))
        assert np.linalg.norm(a.tip_position_mm - b.tip_position_mm) < 0.06
    assert a.tip_deflection_mm > 29.0


def test_routing_tensions_are_the_kernels_capstan_rule() -> None:
    rng = np.random.default_rng(5)
    theta = rng.uniform(-0.05, 0.1, (1, 40))
    for hist in (TensionHistory(), TensionHistory(False, 10.0, 3.0), TensionHistory(True, 4.0, 1.0)):
        got = routing_tensions(np.array([7.0]), theta, 0.3, hist)[0]
        turn = np.abs(theta[0])
        wrap = np.cumsum(turn) - turn / 2
        row = np.zeros(16)
        row[11], row[13], row[14] = 0.3, 1.0 if hist.increasing else -1.0, hist.reversal_tension_n
        expected = [_kernel.local_tension(7.0, 0, row, w) for w in wrap]
        np.testing.assert_allclose(got, expected, rtol=1e-12)


def test_batch_equals_single_solves_and_rolls_the_plane() -> None:
    d = preset("13ga-20j-tip")
    t = np.array([0.0, 3.0, 14.0])
    batch = DISCRETE_JOINTS.solve_batch(d, t, roll_deg=90.0)
    single = [_ok(DISCRETE_JOINTS.solve(d, d.loads(x, 90.0))) for x in t]
    np.testing.assert_allclose(batch.tip_positions_mm, [s.tip_position_mm for s in single], atol=1e-12)
    assert abs(single[2].tip_position_mm[0]) < 1e-9 and single[2].tip_position_mm[1] > 5.0  # roll 90°: toward +y
    np.testing.assert_allclose(batch.joint_curvature_per_m, [joint_curvature_per_m(d, s) for s in single],
                               rtol=1e-9, atol=1e-12)
    assert batch.converged.all()


def test_what_it_cannot_represent_is_refused() -> None:
    d = preset("15ga-20j-tip")
    with pytest.raises(UnsupportedLoadError, match="planar"):
        DISCRETE_JOINTS.solve(d, Loads((5.0, 0.0, 0.0, 0.0), tip_force_n=(0.0, 0.1, 0.0)))
    # without tension the plane is the loads' own: weight along y bends the rod toward y, as the Cosserat rod does
    weight = Loads((0.0,) * 4, distributed_n_per_m=gravity_load(d, (0.0, 1.0, 0.0)))
    a, b = _ok(DISCRETE_JOINTS.solve(d, weight)), _ok(COSSERAT_ROD.solve(d, weight))
    assert a.tip_position_mm[1] > 0.2 and abs(a.tip_position_mm[0]) < 1e-12
    assert np.linalg.norm(a.tip_position_mm - b.tip_position_mm) < 0.02
    with pytest.raises(UnsupportedLoadError, match="one pulled tendon"):
        DISCRETE_JOINTS.solve(d, Loads((5.0, 5.0, 0.0, 0.0)))
    fnd = Foundation(np.array([0.0, 100.0]), np.array([0.1, 0.1]), np.zeros((2, 3)), np.ones(2))
    with pytest.raises(UnsupportedLoadError, match="tissue"):
        DISCRETE_JOINTS.solve(d, Loads((5.0, 0.0, 0.0, 0.0), foundation=fnd))


def test_registered_as_a_rod_model_plugin() -> None:
    from reachplan.plugins import registry

    check_rod_model(DISCRETE_JOINTS)
    assert registry.get("rod_models", "discrete_joints") is DISCRETE_JOINTS


def test_calibrated_on_the_calibration_rows_only_and_every_row_reported() -> None:
    fit = calibrate(model=DISCRETE_JOINTS)
    assert fit.rows == CALIBRATION_ROWS
    assert fit.calibration.joint_stiffness_scale == pytest.approx(JOINTS_CALIBRATION.joint_stiffness_scale, rel=2e-3)
    assert fit.calibration.tube_arm_fraction == pytest.approx(JOINTS_CALIBRATION.tube_arm_fraction, rel=2e-3)
    assert fit.max_abs_residual_mm <= 1.5
    table = every_published_row(fit, DISCRETE_JOINTS)
    roles = [(r, True) for r in CALIBRATION_ROWS] + [(r, False) for r in VALIDATION_ROWS]
    assert [(r, f) for r, _, f in table] == roles
    over = {r.preset: p - r.tip_deflection_mm for r, p, _ in table}
    # the honest result (docs/mechanics.md): discreteness does not cure the pilot design's over-prediction
    continuum = predict(Calibration(), VALIDATION_ROWS)  # the shipped Cosserat calibration
    assert 1.4 < over["15ga-30j-tip"] < 1.9
    assert abs(over["15ga-30j-tip"] - (continuum[1] - VALIDATION_ROWS[1].tip_deflection_mm)) < 0.1
