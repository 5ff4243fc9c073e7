"""In-tissue Cosserat insertion: zero-modulus limit, the trend with modulus, per-organ moduli, honest failures."""

from __future__ import annotations

from functools import cache

import numpy as np
import pytest

from reachplan.planner.steering.insertion import FailedInsertion, InsertionPath
from reachplan.planner.steering.schedule import TensionSchedule
from reachplan.planner.steering.tissue_rod import TissueRodInsertion
from reachplan.rod_model.cosserat import TwoTubeCosserat
from reachplan.rod_model.design import preset
from reachplan.rod_model.result import RodPath

DESIGN = preset("15ga-20j-tip")
PULL = TensionSchedule.constant(10.0)


def _tip_deflection(modulus_pa: float, depth_mm: float) -> float:
    path = TissueRodInsertion(tissue_modulus_pa=modulus_pa).insert_one(DESIGN, PULL, depth_mm)
    assert isinstance(path, np.ndarray), getattr(path, "reason", "")
    return float(np.hypot(path[-1, 0], path[-1, 1]))


def test_zero_modulus_is_the_free_space_shape_of_the_inserted_length() -> None:
    model = TissueRodInsertion(tissue_modulus_pa=0.0)
    path = model.insert_one(DESIGN, PULL, 90.0)
    free = model.rod_model.solve(DESIGN, DESIGN.loads(10.0), inserted_mm=90.0)
    assert isinstance(path, np.ndarray) and isinstance(free, RodPath)
    np.testing.assert_allclose(path, free.positions_mm, atol=1e-6)
    assert free.tip_deflection_mm > 1.0  # the inserted distal 90 mm (joint section first) bends


def test_inserted_length_is_the_distal_rod_clamped_at_the_template() -> None:
    # the whole rod inserted equals the ordinary clamped solve
    model = TwoTubeCosserat(steps_per_mm=2.0)
    whole = model.solve(DESIGN, DESIGN.loads(8.0))
    inserted = model.solve(DESIGN, DESIGN.loads(8.0), inserted_mm=DESIGN.length_mm)
    assert isinstance(whole, RodPath) and isinstance(inserted, RodPath)
    np.testing.assert_allclose(inserted.positions_mm, whole.positions_mm, atol=1e-9)


def test_soft_tissue_holds_the_track_so_deflection_rises_with_modulus() -> None:
    # soft regime: the more the tissue holds the needle on the track its tip cut, the more the tip's heading
    # accumulates (tip following); at zero modulus nothing holds it and the rod keeps its free shape
    tips = [_tip_deflection(e, 120.0) for e in (0.0, 1e3, 1e4, 1e5)]
    assert np.all(np.diff(tips) > 0.5), tips


def test_a_tendon_pulled_before_insertion_is_not_resisted_by_the_tissue() -> None:
    # pulled at the template, the joint section cuts its own curved track: at a depth within the joint section
    # the tip is where the free-space shape of the inserted length puts it, however stiff the tissue
    free = TissueRodInsertion(tissue_modulus_pa=0.0).insert_one(DESIGN, PULL, 30.0)
    assert isinstance(free, np.ndarray)
    for e in (1e5, 1e6, 1e7):
        assert _tip_deflection(e, 30.0) == pytest.approx(float(np.hypot(*free[-1, :2])), rel=0.02)


def test_stiff_tissue_resists_a_tendon_pulled_while_inserted() -> None:
    # pulled once the joint section is embedded in a straight track, the stiffer the tissue the less the
    # embedded joints bend: only about a Winkler length (4 EI / k)^(1/4) ~ k^(-1/4) near the tip still turns
    ramp = TensionSchedule.ramp(40.0, 5.0, 10.0)
    tips = []
    for e in (1e5, 1e6, 1e7):
        path = TissueRodInsertion(tissue_modulus_pa=e, step_mm=4.0).insert_one(DESIGN, ramp, 72.0)
        assert isinstance(path, np.ndarray), getattr(path, "reason", "")
        tips.append(float(np.hypot(*path[-1, :2])))
    assert np.all(np.diff(tips) < -0.1), tips


def test_multiple_shooting_agrees_with_single_shooting() -> None:
    # a gel case that single shooting solves: the two solvers (different grids) give the same shape
    from reachplan.rod_model import _kernel, multiple_shooting
    from reachplan.rod_model.cosserat import _distal, linear_guess, section_table

    captured = []

    class Capture(TwoTubeCosserat):
        def solve(self, design, loads, initial_guess=None, **kw):  # type: ignore[no-untyped-def]
            captured.append((loads, kw["inserted_mm"]))
            return super().solve(design, loads, initial_guess, **kw)

    TissueRodInsertion(rod_model=Capture(steps_per_mm=2.0)).insert_one(DESIGN, PULL, 60.0)
    loads, inserted = captured[-1]
    single = TwoTubeCosserat(steps_per_mm=2.0).solve(DESIGN, loads, inserted_mm=inserted)
    assert isinstance(single, RodPath)
    sec = _distal(section_table(DESIGN), inserted * 1e-3)
    fext = np.r_[np.array(loads.distributed_n_per_m), loads.foundation.packed_si()]
    assert multiple_shooting.growth(sec, fext) > 2.0  # more than one leg
    ms = multiple_shooting.solve(linear_guess(DESIGN, loads, inserted * 1e-3), sec, 2.0,
                                 DESIGN.tendon_unit_offsets(0.0), np.array(loads.tensions_n), fext, np.zeros(3),
                                 np.zeros(3), False, 1e-10)
    assert ms.status == _kernel.OK and ms.legs >= 2
    assert np.linalg.norm(ms.traj[-1, 0:3] * 1e3 - single.positions_mm[-1]) < 0.01


def test_per_organ_modulus_profile() -> None:
    model = TissueRodInsertion(tissue_modulus_pa=1e4)
    uniform = model.insert_one(DESIGN, PULL, 60.0)
    same = model.insert_one(DESIGN, PULL, 60.0, modulus_profile=(np.array([0.0]), np.array([1e4])))
    assert isinstance(uniform, np.ndarray) and isinstance(same, np.ndarray)
    np.testing.assert_allclose(same, uniform, atol=1e-12)
    # the distal half in a soft organ (1 kPa): less of the track is held than in uniform 10 kPa tissue
    mixed = model.insert_one(DESIGN, PULL, 60.0, modulus_profile=(np.array([0.0, 30.0]), np.array([1e4, 1e3])))
    assert isinstance(mixed, np.ndarray)
    assert np.hypot(*mixed[-1, :2]) != pytest.approx(np.hypot(*uniform[-1, :2]), abs=1e-3)


STRICT = TwoTubeCosserat(steps_per_mm=2.0, max_step_error_mm=1e-9)  # no solve passes its integration check


def test_unsolvable_insertion_is_a_failure_with_its_reason() -> None:
    r = TissueRodInsertion(tissue_modulus_pa=1e7, rod_model=STRICT).insert_one(DESIGN, PULL, 20.0)
    assert isinstance(r, FailedInsertion)
    assert "at depth" in r.reason and "integration error" in r.reason


def test_stiff_tissue_is_solved_deep() -> None:
    # 10 MPa: single shooting used to fail past 36 mm; multiple shooting solves it
    assert _tip_deflection(1e7, 60.0) > 5.0


def test_paths_and_failures_name_the_model_and_its_settings() -> None:
    model = TissueRodInsertion(tissue_modulus_pa=1e7, step_mm=4.0)
    failing = TissueRodInsertion(tissue_modulus_pa=1e7, step_mm=4.0, rod_model=STRICT)
    path, failed = model.insert(DESIGN, [PULL], 20.0)[0], failing.insert(DESIGN, [PULL], 20.0)[0]
    assert isinstance(path, InsertionPath) and isinstance(failed, FailedInsertion)
    for m, info in ((model, path.model), (failing, failed.model)):
        assert info == m.info and info.label == "tissue_rod+two_tube_cosserat"
        settings = dict(info.settings)
        assert settings["tissue_modulus_pa"] == 1e7 and settings["step_mm"] == 4.0
        assert settings["rod_model.steps_per_mm"] == m.rod_model.steps_per_mm


def test_insertion_step_refinement_converges() -> None:
    # the track is cut along the tip's path extrapolated from the last step: it converges in the insertion step
    tips = []
    for step in (5.0, 2.5, 1.25):
        path = TissueRodInsertion(tissue_modulus_pa=1.9e5, step_mm=step).insert_one(DESIGN, PULL, 90.0)
        assert isinstance(path, np.ndarray)
        tips.append(float(np.hypot(path[-1, 0], path[-1, 1])))
    d1, d2 = abs(tips[1] - tips[0]), abs(tips[2] - tips[1])
    assert d1 > 1e-3 and d2 < 0.7 * d1, tips


@cache
def _tip_at(design_name: str, modulus_pa: float, depth_mm: float = 120.0) -> float:
    """Tip deflection (mm) of a stylet pulled to 10 N at the template and inserted to ``depth_mm``."""
    path = TissueRodInsertion(tissue_modulus_pa=modulus_pa, step_mm=4.0).insert_one(
        preset(design_name), PULL, depth_mm)
    assert isinstance(path, np.ndarray), getattr(path, "reason", "")
    return float(np.hypot(*path[-1, :2]))


def _tip_following(design_name: str, depth_mm: float = 120.0) -> float:
    """The rigid-tissue limit: pure tip following at the joint section's free-space curvature (mm)."""
    from reachplan.planner.steering.kinematic import KinematicInsertion

    path = KinematicInsertion(tissue_factor=1.0).insert_array(preset(design_name), [PULL], depth_mm)[0]
    return float(np.hypot(*path[-1, :2]))


def test_past_the_peak_the_deflection_falls_to_tip_following() -> None:
    # the planner's design, pulled at the template: above the peak (0.1 MPa for its 49.5 mm joint section) the
    # deflection falls, and from about 1 MPa on it is the tip-following path (the rigid-tissue limit) to within
    # the insertion step's error (measured 0.1-0.25 mm at 4 mm steps against 1 mm)
    follow = _tip_following("15ga-30j-tip")
    peak, stiff, rigid = (_tip_at("15ga-30j-tip", e) for e in (1e5, 1e6, 3e6))
    assert peak > stiff + 1.5 and peak > follow + 1.5
    assert stiff == pytest.approx(follow, abs=0.25) and rigid == pytest.approx(follow, abs=0.25)


def test_the_peak_moves_to_stiffer_tissue_with_a_shorter_joint_section() -> None:
    # the overshoot over tip following lasts while the shaft's Winkler length (4 EI / k)^(1/4) is longer than
    # about 0.6 joint-section lengths: 29 mm at 0.1 MPa, 16 mm at 1 MPa. 30 joints (49.5 mm): past the peak
    # between 0.1 and 1 MPa (the deflection falls); 15 joints (24.7 mm): before it (rises, and overshoots)
    assert _tip_at("15ga-30j-tip", 1e5) > _tip_at("15ga-30j-tip", 1e6) + 1.5
    short_soft, short_stiff = _tip_at("15ga-15j-tip", 1e5), _tip_at("15ga-15j-tip", 1e6)
    assert short_stiff > short_soft + 5.0 and short_stiff > _tip_following("15ga-15j-tip") + 1.5


def test_richardson_extrapolation_in_the_insertion_step() -> None:
    # the step error is first order: 2 P(2 mm) - P(4 mm) lands nearer the limit (estimated from 1 and 2 mm)
    # than either plain solve, and is sampled evenly from the template (origin) to the tip
    ramp = TensionSchedule.ramp(0.0, 20.0, 10.0)
    tips = {}
    for h in (4.0, 2.0, 1.0):
        path = TissueRodInsertion(step_mm=h).insert_one(DESIGN, ramp, 100.0)
        assert isinstance(path, np.ndarray)
        tips[h] = path[-1]
    limit = 2 * tips[1.0] - tips[2.0]
    extrapolated = TissueRodInsertion(step_mm=2.0, richardson=True).insert_one(DESIGN, ramp, 100.0)
    assert isinstance(extrapolated, np.ndarray) and len(extrapolated) == 101
    np.testing.assert_allclose(extrapolated[-1], 2 * tips[2.0] - tips[4.0], atol=1e-9)
    np.testing.assert_allclose(extrapolated[0], 0.0, atol=1e-12)
    err = np.linalg.norm(extrapolated[-1] - limit)
    assert err < 0.5 * np.linalg.norm(tips[1.0] - limit) and err < 0.25 * np.linalg.norm(tips[2.0] - limit)


def test_models_made_of_the_same_runs_share_them_and_the_shared_run_is_the_fresh_one() -> None:
    # the reference (2 mm extrapolated with 4 mm) and a rung at 4 mm solve the same 4 mm run: it is solved once,
    # is what a cold solve gives, and cannot be changed by a caller
    from reachplan.planner.steering.tissue_rod import _run_memo, forget_runs

    ramp = TensionSchedule.ramp(0.0, 20.0, 8.0)
    forget_runs()
    reference = TissueRodInsertion(step_mm=2.0, richardson=True).insert_one(DESIGN, ramp, 40.0)
    misses = _run_memo.cache_info().misses
    coarse = TissueRodInsertion(step_mm=4.0).insert_one(DESIGN, ramp, 40.0)
    assert _run_memo.cache_info().misses == misses == 2  # the 4 mm run was reused
    forget_runs()
    fresh = TissueRodInsertion(step_mm=4.0).insert_one(DESIGN, ramp, 40.0)
    assert isinstance(coarse, np.ndarray) and isinstance(fresh, np.ndarray) and isinstance(reference, np.ndarray)
    np.testing.assert_array_equal(coarse, fresh)
    with pytest.raises(ValueError, match="read-only"):
        coarse[0, 0] = 1.0
    # a missing profile is the model's own modulus everywhere: the same run as that one-piece profile
    one_piece = (np.zeros(1), np.full(1, TissueRodInsertion().tissue_modulus_pa))
    same = TissueRodInsertion(step_mm=4.0).insert_one(DESIGN, ramp, 40.0, modulus_profile=one_piece)
    assert same is fresh
