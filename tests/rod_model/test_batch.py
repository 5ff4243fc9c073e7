"""Batched evaluation: the same answers as single solves, and curvature tables against closed forms."""

from __future__ import annotations

import numpy as np
import pytest

from reachplan.rod_model.beam import PLANAR_BEAM
from reachplan.rod_model.cosserat import COSSERAT_ROD, TWO_TUBE_COSSERAT
from reachplan.rod_model.design import preset
from reachplan.rod_model.kinematic import CONSTANT_CURVATURE
from reachplan.rod_model.result import RodPath, section_curvatures

MODELS = [CONSTANT_CURVATURE, PLANAR_BEAM, COSSERAT_ROD, TWO_TUBE_COSSERAT]


@pytest.mark.filterwarnings("ignore::reachplan.rod_model.errors.TensionAboveLimitWarning")  # 15 N on purpose
@pytest.mark.parametrize("model", MODELS, ids=lambda m: m.name)
@pytest.mark.parametrize("name", ["15ga-20j-tip", "15ga-20j-mid"])
def test_batch_matches_single_solves(model: object, name: str) -> None:
    d = preset(name)
    tensions = np.array([0.0, 2.5, 9.9, 15.0])
    batch = model.solve_batch(d, tensions, roll_deg=25.0)  # type: ignore[attr-defined]
    assert batch.converged.all()
    for i, t in enumerate(tensions):
        r = model.solve(d, d.loads(float(t), 25.0))  # type: ignore[attr-defined]
        assert isinstance(r, RodPath)
        np.testing.assert_allclose(batch.tip_positions_mm[i], r.tip_position_mm, atol=1e-9)
        bounds = batch.section_bounds_mm
        np.testing.assert_allclose(batch.section_curvature_per_m[i],
                                   section_curvatures(r.frames, r.s_mm, bounds), atol=1e-9)


def test_planar_curvature_table_is_the_closed_form() -> None:
    d = preset("15ga-20j-tip")
    batch = PLANAR_BEAM.solve_batch(d, np.array([1.0, 10.0]))
    joint = d.sections()[batch.joint_section]
    assert joint.kind == "joints"
    np.testing.assert_allclose(batch.joint_curvature_per_m, np.array([1.0, 10.0]) * joint.arm_m /
                               (joint.ei1 + joint.ei2), rtol=1e-12)


def test_cosserat_joint_curvature_is_close_to_beam_theory() -> None:
    # independent physics check: in free space the Cosserat curvature differs from λ r / EI only by the
    # rods' axial and shear strain (~λ/EA ~ 1e-3)
    d = preset("15ga-20j-tip")
    t = np.linspace(0.5, 15.0, 7)
    two = TWO_TUBE_COSSERAT.solve_batch(d, t).joint_curvature_per_m
    beam = PLANAR_BEAM.solve_batch(d, t).joint_curvature_per_m
    np.testing.assert_allclose(two, beam, rtol=2e-3)


def test_batch_rejects_negative_tensions() -> None:
    with pytest.raises(ValueError, match="non-negative"):
        TWO_TUBE_COSSERAT.solve_batch(preset("15ga-20j-tip"), np.array([1.0, -1.0]))


@pytest.mark.parametrize("model", [PLANAR_BEAM, TWO_TUBE_COSSERAT], ids=lambda m: m.name)
def test_curvature_table_is_exact_to_its_model(model: object) -> None:
    from reachplan.rod_model.table import curvature_table

    d = preset("15ga-20j-tip")
    table = curvature_table(model, d)  # type: ignore[arg-type]
    assert table.tensions_n[-1] == d.max_tension_n
    assert table.max_interp_error_per_m < 1e-6
    t = np.array([0.3, 4.44, 9.99])
    direct = model.solve_batch(d, t).section_curvature_per_m  # type: ignore[attr-defined]
    np.testing.assert_allclose(table.curvature(t), direct, atol=1e-6)
    assert table.joint_curvature(t).shape == (3,)
    with pytest.raises(ValueError, match="outside the table"):
        table.curvature(d.max_tension_n + 1.0)


def test_selector_uses_measured_errors_and_capabilities() -> None:
    from reachplan.rod_model.beam import PLANAR_BEAM
    from reachplan.rod_model.cosserat import COSSERAT_ROD, TWO_TUBE_COSSERAT
    from reachplan.rod_model.errors import NoModelWithinToleranceError
    from reachplan.rod_model.kinematic import CONSTANT_CURVATURE
    from reachplan.rod_model.select import ErrorRow, Scene, select_model

    caps = {m.name: m.capabilities for m in (CONSTANT_CURVATURE, PLANAR_BEAM, COSSERAT_ROD, TWO_TUBE_COSSERAT)}

    rows = (ErrorRow("constant_curvature", "default", 12.0, 0.01, 1e6, 1.0),
            ErrorRow("planar_beam", "default", 0.08, 0.3, 2e6, 1.0),
            ErrorRow("cosserat_rod", "default", 0.006, 0.1, 4e3, 1.0),
            ErrorRow("two_tube_cosserat", "default", 0.0, 0.4, 5e3, 1.0),
            ErrorRow("two_tube_cosserat", "0.02 steps/mm", 0.001, 0.05, None, 1.0))
    planar = Scene()
    assert select_model(20.0, planar, caps, rows) == "constant_curvature"
    assert select_model(1.0, planar, caps, rows) == "cosserat_rod"
    assert select_model(1.0, planar, caps, rows, batched=True) == "planar_beam"
    assert select_model(1e-3, planar, caps, rows) == "two_tube_cosserat"  # the coarse row is not the plugin's config
    assert select_model(20.0, Scene(external_load=True), caps, rows) == "cosserat_rod"
    assert select_model(20.0, Scene(planar=False, twist=True), caps, rows) == "two_tube_cosserat"
    from reachplan.rod_model.design import Loads

    d = preset("15ga-20j-tip")
    assert Scene.of(Loads((3.0, 0.0, 3.0, 0.0)), d) == Scene()
    assert Scene.of(Loads((3.0,), tip_moment_nm=(0.0, 0.0, 1e-3)), d) == Scene(False, True, True)
    with pytest.raises(NoModelWithinToleranceError, match="best measured"):
        select_model(1e-3, Scene(), caps, rows[:3])


def test_packaged_error_table_comes_from_the_benchmark() -> None:
    from reachplan.rod_model.select import error_table

    rows = error_table()
    names = {r.model for r in rows if r.resolution == "default"}
    assert {"constant_curvature", "planar_beam", "cosserat_rod", "two_tube_cosserat"} <= names
    # the benchmark's own finding: the constant-curvature model misses the tube's bending by millimetres
    cc = next(r for r in rows if r.model == "constant_curvature")
    assert cc.max_tip_error_mm > 1.0


@pytest.mark.parametrize("name", ["15ga-20j-tip", "15ga-20j-base", "15ga-20j-asym", "13ga-30j-tip"])
def test_tendon_compression_stays_internal_up_to_15_n(name: str) -> None:
    # a tendon modelled as an external compressive tip load buckles near 0.4 N; with the load kept internal the
    # two-tube tip stays within 0.1 mm of the closed-form arcs (which carry no compression) up to 15 N
    d = preset(name)
    t = np.array([0.4, 5.0, 15.0])
    two = TWO_TUBE_COSSERAT.solve_batch(d, t)
    beam = PLANAR_BEAM.solve_batch(d, t)
    assert two.converged.all()
    np.testing.assert_allclose(two.tip_positions_mm, beam.tip_positions_mm, atol=0.1)
    assert np.all(np.diff(two.tip_deflection_mm) > 0)


def test_selector_breaks_cost_ties_by_model_rank_not_by_timing_noise() -> None:
    from reachplan.rod_model.beam import PLANAR_BEAM
    from reachplan.rod_model.cosserat import COSSERAT_ROD, TWO_TUBE_COSSERAT
    from reachplan.rod_model.select import COST_TIE_FACTOR, MODEL_RANK, ErrorRow, Scene, select_model

    caps = {m.name: m.capabilities for m in (PLANAR_BEAM, COSSERAT_ROD, TWO_TUBE_COSSERAT)}
    rng = np.random.default_rng(3)
    picks = set()
    for _ in range(50):  # medians that wobble by +-20 % around the same cost: always the same choice
        ms = 0.4 * (1 + 0.2 * rng.uniform(-1, 1, 3))
        rows = (ErrorRow("two_tube_cosserat", "default", 0.0, ms[0], None, 1.0),
                ErrorRow("cosserat_rod", "default", 0.006, ms[1], None, 1.0),
                ErrorRow("planar_beam", "default", 0.08, ms[2], None, 1.0))
        picks.add(select_model(0.5, Scene(), caps, rows))
    assert picks == {"planar_beam"}
    assert MODEL_RANK["planar_beam"] < MODEL_RANK["cosserat_rod"] < MODEL_RANK["two_tube_cosserat"]
    # a model clearly cheaper (beyond the tie factor) still wins on cost, whatever its rank
    rows = (ErrorRow("two_tube_cosserat", "default", 0.0, 0.1, None, 1.0),
            ErrorRow("planar_beam", "default", 0.08, 0.1 * COST_TIE_FACTOR * 1.1, None, 1.0))
    assert select_model(0.5, Scene(), caps, rows) == "two_tube_cosserat"
    # the tolerance is against the two-tube model, which the docstring says (not against experiment)
    assert "not against experiment" in (select_model.__doc__ or "")


@pytest.mark.parametrize("roll_deg", [0.0, 90.0, 37.0])
def test_twist_is_the_torque_about_the_needles_axis_whatever_the_frame(roll_deg: float) -> None:
    from reachplan.rod_model.design import Loads
    from reachplan.rod_model.select import Scene, axial_torque_nm

    d = preset("15ga-30j-tip")
    a = np.radians(roll_deg)
    toward = np.array([np.cos(a), np.sin(a), 0.0])  # the bending direction of tendon 0 at this roll
    normal = np.array([-np.sin(a), np.cos(a), 0.0])  # the bending plane's normal

    def scene(moment: np.ndarray, force: np.ndarray | None = None) -> Scene:
        f = np.zeros(3) if force is None else force
        return Scene.of(Loads((5.0, 0.0, 0.0, 0.0), roll_deg=roll_deg, tip_moment_nm=tuple(moment),
                              tip_force_n=(float(f[0]), float(f[1]), float(f[2]))), d)

    m = 5e-3  # N·m
    # about the bending direction (world x at roll 0: the case) it twists the bent needle, as about z
    assert scene(m * toward).twist and scene(np.array([0.0, 0.0, m])).twist
    assert axial_torque_nm(Loads((5.0, 0, 0, 0), roll_deg=roll_deg, tip_moment_nm=tuple(m * toward)), d) == \
        pytest.approx(m)
    # about the plane's normal it only bends the needle in its plane; a force in the plane does not twist it either
    assert not scene(m * normal).twist and not scene(np.zeros(3), 0.1 * toward).twist
    assert scene(np.zeros(3), 0.1 * normal).twist  # a force out of the plane does, through its lever arm


def test_a_twisting_moment_about_x_picks_the_two_tube_model_which_the_single_rod_misses() -> None:
    from reachplan.rod_model.design import Loads
    from reachplan.rod_model.select import Scene, select_model

    caps = {m.name: m.capabilities for m in (CONSTANT_CURVATURE, PLANAR_BEAM, COSSERAT_ROD, TWO_TUBE_COSSERAT)}
    d = preset("15ga-30j-tip")
    loads = Loads((5.0, 0.0, 0.0, 0.0), tip_moment_nm=(5e-3, 0.0, 0.0))
    assert select_model(0.01, Scene.of(loads, d), caps) == "two_tube_cosserat"
    single, double = COSSERAT_ROD.solve(d, loads), TWO_TUBE_COSSERAT.solve(d, loads)
    assert isinstance(single, RodPath) and isinstance(double, RodPath)
    assert np.linalg.norm(single.positions_mm[-1] - double.positions_mm[-1]) > 0.01  # why it must not be picked
