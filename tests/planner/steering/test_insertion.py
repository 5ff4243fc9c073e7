"""Insertion models against closed forms, limits and a finer discretisation of themselves."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from reachplan.planner.errors import PlanInputError
from reachplan.planner.steering.factors import (
    TIP_FOLLOWING_MIN_PA,
    curvature_factor,
    design_key,
    factor_table,
    fit_curvature_factor,
)
from reachplan.planner.steering.insertion import SIMUGEL_MODULUS_PA, curvature_table
from reachplan.planner.steering.kinematic import KinematicInsertion
from reachplan.planner.steering.schedule import TensionSchedule
from reachplan.planner.steering.tissue_rod import TissueRodInsertion
from reachplan.rod_model.beam import PLANAR_BEAM
from reachplan.rod_model.design import PRESET_NAMES, preset


@pytest.fixture(scope="module")
def design():  # type: ignore[no-untyped-def]
    return preset("15ga-20j-tip")


def test_kinematic_constant_tension_cuts_a_circular_arc(design) -> None:  # type: ignore[no-untyped-def]
    model = KinematicInsertion(tissue_factor=0.7, step_mm=2.0)
    path = model.insert_array(design, [TensionSchedule.constant(8.0)], 120.0)[0]
    kappa = 0.7 * curvature_table(design).joint(np.array([8.0]))[0]
    s = np.linspace(0.0, 120.0, len(path))
    expected = np.column_stack([(1 - np.cos(kappa * s)) / kappa, np.zeros_like(s), np.sin(kappa * s) / kappa])
    np.testing.assert_allclose(path, expected, atol=1e-9)


def test_kinematic_roll_and_zero_tension(design) -> None:  # type: ignore[no-untyped-def]
    paths = KinematicInsertion().insert_array(
        design, [TensionSchedule.constant(0.0), TensionSchedule.constant(6.0, 90.0)], 100.0)
    np.testing.assert_allclose(paths[0][:, :2], 0.0, atol=1e-12)
    assert paths[1][-1, 1] > 5.0 and abs(paths[1][-1, 0]) < 1e-9


def test_curvature_factor_is_monotone_and_tends_to_tip_following() -> None:
    # the reference design (30 joints) is past its peak over the whole tip-following range
    moduli = np.geomspace(TIP_FOLLOWING_MIN_PA, 1e12, 40)
    c = np.array([curvature_factor(float(e)) for e in moduli])
    assert np.all(np.diff(c) < 0) and c[-1] == pytest.approx(1.0, abs=0.01) and c[0] < 1.5
    with pytest.raises(PlanInputError, match="tip-following range"):
        KinematicInsertion(tissue_modulus_pa=1e4)
    assert KinematicInsertion(tissue_modulus_pa=1e4, tissue_factor=0.8).factor_for(preset("15ga-30j-tip")) == 0.8


def test_every_preset_has_a_fitted_curvature_factor_and_they_differ() -> None:
    table = factor_table()
    curves = {name: table.get(design_key(preset(name))) for name in PRESET_NAMES}
    missing = [n for n, c in curves.items() if c is None]
    assert not missing, f"no packaged curvature factor for {missing}: run reachplan bench factors --install"
    for c in curves.values():
        assert c is not None and c.moduli_pa[0] == TIP_FOLLOWING_MIN_PA and np.all(np.diff(c.moduli_pa) > 0)
        # the kinematic model with the factor against the rod's tips (worst: 15ga-20j-asym at 0.1 MPa, 2.17 mm)
        assert max(c.rms_mm) < 2.5
    gel = {n: curvature_factor(SIMUGEL_MODULUS_PA, preset(n)) for n in PRESET_NAMES}
    assert gel["15ga-30j-tip"] > 1.2 and gel["15ga-15j-tip"] < 1.0  # one factor cannot serve every design
    # a renamed design is the same mechanics: the same factor, from the table
    renamed = dataclasses.replace(preset("15ga-15j-tip"), name="my stylet")
    assert curvature_factor(SIMUGEL_MODULUS_PA, renamed) == gel["15ga-15j-tip"]


def test_a_design_not_in_the_table_is_fitted_once(monkeypatch: pytest.MonkeyPatch) -> None:
    import reachplan.planner.steering.factors as factors

    calls: list[tuple[str, float]] = []

    def fake_fit(design, modulus_pa):  # type: ignore[no-untyped-def]
        calls.append((design.name, modulus_pa))
        return factors.FactorFit(0.9, 0.5, 32)

    monkeypatch.setattr(factors, "fit_curvature_factor", fake_fit)
    factors._fitted_factor.cache_clear()
    other = dataclasses.replace(preset("15ga-30j-tip"), name="stiffer tendon limit", max_tension_n=9.0)
    assert design_key(other) not in factor_table()
    model = KinematicInsertion(tissue_modulus_pa=3e5)
    assert model.factor_for(other) == 0.9 and model.factor_for(other) == 0.9
    assert calls == [("stiffer tendon limit", 3e5)]  # memoised
    factors._fitted_factor.cache_clear()


@pytest.mark.slow
@pytest.mark.parametrize("name", ["15ga-30j-tip", "15ga-15j-tip"])
def test_curvature_factor_matches_the_in_tissue_rod_where_it_was_not_fitted(name: str) -> None:
    # 0.5 MPa is not among the tabulated moduli: the factor fitted to the rod there against the table's
    # interpolation (the 15-joint design rises through it, the 30-joint one falls)
    design = preset(name)
    fit = fit_curvature_factor(design, 5e5)
    assert fit.tips == 32 and fit.rms_mm < 1.5
    assert fit.factor == pytest.approx(curvature_factor(5e5, design), abs=0.03)


def test_bad_inputs_are_typed_errors(design) -> None:  # type: ignore[no-untyped-def]
    with pytest.raises(PlanInputError):
        KinematicInsertion().insert_array(design, [TensionSchedule.constant(50.0)], 100.0)
    with pytest.raises(PlanInputError):
        TissueRodInsertion().insert_one(design, TensionSchedule.constant(1.0), 500.0)
    with pytest.raises(PlanInputError, match="modulus_profile"):
        TissueRodInsertion().insert_one(design, TensionSchedule.constant(1.0), 10.0,
                                        (np.array([10.0, 5.0]), np.array([1.0, 2.0])))
    with pytest.raises(ValueError, match="only pulls"):
        TensionSchedule.constant(-1.0)


def test_planar_fast_path_equals_the_3d_integration(design) -> None:  # type: ignore[no-untyped-def]
    model = KinematicInsertion()
    sch = TensionSchedule.ramp(10.0, 30.0, 7.0, roll_deg=40.0)
    planar = model.insert_array(design, [sch], 120.0)[0]
    # the same schedule with a roll change of 1e-9 deg at the end takes the general 3-D integration
    wobble = TensionSchedule(np.r_[sch.depth_mm, 119.0], np.r_[sch.tension_n, 7.0], np.r_[sch.roll_deg, 40.0 + 1e-9])
    general = model.insert_array(design, [wobble], 120.0)[0]
    np.testing.assert_allclose(planar, general, atol=1e-8)


def test_workspace_radius_is_positive_and_below_the_stylets_reach(design) -> None:  # type: ignore[no-untyped-def]
    from reachplan.planner.steering.steered import reach_radius_mm, shape_bank

    # the workspace radius at a depth bounds what any schedule reaches there
    radius = reach_radius_mm(shape_bank(design), np.array([60.0]))[0]
    assert 45.0 > radius > 0.0


def test_insertion_models_use_the_rod_model_object_they_hold(design) -> None:  # type: ignore[no-untyped-def]
    from dataclasses import dataclass
    from typing import ClassVar

    from reachplan.rod_model.beam import PlanarBeam

    @dataclass(frozen=True)
    class Unregistered(PlanarBeam):  # the same mechanics under a name no plugin registry knows
        name: ClassVar[str] = "unregistered_beam"

    sch = [TensionSchedule.ramp(20.0, 10.0, 6.0)]
    model = KinematicInsertion(tissue_factor=0.9, rod_model=Unregistered())
    (path,) = model.insert(design, sch, 100.0)
    assert path and path.model.label == "kinematic+unregistered_beam"
    assert dict(path.model.settings)["tissue_factor"] == 0.9 and dict(path.model.settings)["step_mm"] == 1.0
    assert path.model.to_json()["rod_model"] == "unregistered_beam"
    same = KinematicInsertion(tissue_factor=0.9, rod_model=PLANAR_BEAM).insert_array(design, sch, 100.0)[0]
    np.testing.assert_array_equal(path.positions_mm, same)
