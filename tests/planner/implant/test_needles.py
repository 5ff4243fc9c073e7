"""Implant needles checked like ranked ones: the tension reserve, scenario paths, the reference re-solve and robustness.

The end-to-end checks on the demo (plan.json's needle fields, both arms' DICOM folders) are in tests/test_end_to_end.py.
"""

from __future__ import annotations

import argparse
import dataclasses
from types import SimpleNamespace

import numpy as np
import pytest

from reachplan.planner.case.config import PlanConfig, PlanModels
from reachplan.planner.implant.candidates import Channel, NeedleCheck, needle_candidates
from reachplan.planner.implant.needles import (
    NeedleCheckSettings,
    _arc_on,
    _Context,
    _points_at,
    check_needle,
    with_scenarios,
)
from reachplan.planner.implant.settings import ImplantSettings
from reachplan.planner.steering.robustness import Perturbations, perturbed_paths
from reachplan.planner.steering.steered import ScheduleFamily, shape_bank, usable_tension_n
from reachplan.planner.steering.tissue_rod import PLANNER_REFERENCE

from .test_implant import RADIUS, Case, _case

DESIGN = PlanConfig().rod_designs[0]


def test_the_schedule_family_keeps_the_tension_reserve() -> None:
    limit = DESIGN.max_tension_n
    peaks = [s.peak_tension_n for s in ScheduleFamily().schedules(DESIGN, reserve=0.1)]
    assert max(peaks) == pytest.approx(0.9 * limit) and min(peaks) == pytest.approx(0.2 * 0.9 * limit)
    assert max(s.peak_tension_n for s in ScheduleFamily().schedules(DESIGN, reserve=0.0)) == pytest.approx(limit)
    assert usable_tension_n(DESIGN, 0.25) == pytest.approx(0.75 * limit)
    with pytest.raises(ValueError, match="tension reserve"):
        usable_tension_n(DESIGN, 1.0)
    with pytest.raises(ValueError, match="tension_reserve"):
        PlanConfig(tension_reserve=-0.1)
    assert PlanConfig().tension_reserve == 0.1


def test_the_command_line_sets_the_reserve_and_refuses_a_bad_one() -> None:
    from reachplan.planner.cli.plan import add_implant_arguments

    parser = argparse.ArgumentParser(exit_on_error=False)
    add_implant_arguments(parser)
    assert parser.parse_args([]).tension_reserve == 0.1
    assert parser.parse_args(["--tension-reserve", "0"]).tension_reserve == 0.0
    for bad in ("1.5", "-0.1", "nan", "ten"):
        with pytest.raises(argparse.ArgumentError, match=r"fraction|number"):
            parser.parse_args(["--tension-reserve", bad])


def test_perturbed_paths_tilt_about_the_hole_and_shift_a_steered_needle() -> None:
    depth, tilt = 100.0, 2.0
    straight = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, depth]])
    paths = perturbed_paths(straight, depth, np.eye(4), Perturbations(tilt_deg=tilt))
    assert len(paths) == 4  # a straight needle: the entry tilts only
    for label, p in paths:
        assert np.allclose(p[0], 0.0) and "tilt" in label
        # a rigid rotation about the hole: the tip moves by the chord 2 L sin(θ/2), the length is kept
        assert np.linalg.norm(p[-1] - straight[-1]) == pytest.approx(2 * depth * np.sin(np.radians(tilt) / 2))
        assert np.linalg.norm(p[-1]) == pytest.approx(depth)
    bank = shape_bank(DESIGN, ScheduleFamily(), 120.0, reserve=0.1)
    sch = bank.schedules[-1]  # the latest ramp at the highest plateau: bent
    path = bank.shapes_mm[-1]
    steered = perturbed_paths(path, 120.0, np.eye(4), Perturbations(), design=DESIGN, schedule=sch)
    assert [label.split()[0] for label, _ in steered[:4]] == ["tension", "tension", "roll", "roll"]
    assert len(steered) == 8 and all(np.allclose(p[0], path[0]) for _, p in steered)


def test_dwells_keep_their_distance_along_a_path() -> None:
    t = np.linspace(0, np.pi / 2, 50)
    arc = np.column_stack([50 * np.sin(t), np.zeros_like(t), 50 * (1 - np.cos(t))])  # quarter circle, r 50 mm
    s = np.array([5.0, 20.0, 60.0])
    pts = _points_at(arc, s)
    assert _arc_on(arc, pts) == pytest.approx(s, abs=1e-6)
    # on the true circle the points lie 50 mm from the centre (within the polyline's sagitta)
    assert np.linalg.norm(pts - np.array([0.0, 0.0, 50.0]), axis=1) == pytest.approx(50.0, abs=0.02)


@pytest.fixture(scope="module")
def lobe() -> tuple[Case, tuple[Channel, ...], PlanConfig]:
    """The planted lobe case (tests/planner/implant/test_implant.py): a medial hole bends out to a deep lobe."""
    config = PlanConfig(needle_radius_mm=RADIUS)
    case = _case(((17.0, 0.0, 100.0), 7.0), {"Bowel": ((11.0, -14.0, 10.0), (26.0, 14.0, 60.0))})
    bank = shape_bank(DESIGN, config.family, min(config.max_depth_mm, DESIGN.length_mm),
                      PlanModels.for_config(config).screening, config.tension_reserve)
    cands = needle_candidates(case.ids, case.xy, case.dist, np.eye(4), case.planning, case.organs, RADIUS,
                              ImplantSettings(steered_per_hole=1), [bank])
    return case, cands, config


def _scene(case: Case) -> SimpleNamespace:
    holes = tuple(SimpleNamespace(hole_id=h, xy_mm=tuple(xy)) for h, xy in zip(case.ids, case.xy, strict=True))
    return SimpleNamespace(organs=case.organs, patient_from_template=np.eye(4), meshes={},
                           template=SimpleNamespace(needle_holes=holes))


def test_every_steered_candidate_carries_its_scenario_paths(lobe: tuple) -> None:
    case, cands, config = lobe
    out = with_scenarios(cands, _scene(case), config)  # type: ignore[arg-type]
    steered = [c for c in out if c.steered]
    assert steered and all(c.model == "kinematic+planar_beam" for c in steered)
    for c in steered:
        assert len(c.scenario_paths_mm) == 8 and all(p.shape == c.path_mm.shape for p in c.scenario_paths_mm)
        assert c.schedule is not None and c.schedule.peak_tension_n <= 0.9 * DESIGN.max_tension_n + 1e-9
    assert all(c.scenario_paths_mm == () for c in out if not c.steered)


def test_a_steered_needle_is_re_solved_with_the_reference_model_within_its_reserve(lobe: tuple) -> None:
    case, cands, config = lobe
    steered = max((c for c in cands if c.steered), key=lambda c: c.clearance_mm)
    ctx = _Context(_scene(case), config, PlanModels.for_config(config), ImplantSettings(),  # type: ignore[arg-type]
                   NeedleCheckSettings())
    out = check_needle(steered, ctx)
    assert isinstance(out, Channel), out
    check = out.check
    assert isinstance(check, NeedleCheck)
    assert out.model == PLANNER_REFERENCE.info.label
    assert check.tension_limit_n == DESIGN.max_tension_n
    assert check.peak_tension_n == pytest.approx(out.schedule.peak_tension_n)  # type: ignore[union-attr]
    assert check.peak_tension_n <= (1 - config.tension_reserve) * DESIGN.max_tension_n + 1e-6
    # the dwells on the re-solved path, as many, at the same distances from the hole; the shift is theirs
    assert len(out.dwell_positions_mm) == len(steered.dwell_positions_mm)
    assert _arc_on(out.path_mm, out.dwell_positions_mm) == pytest.approx(
        _arc_on(steered.path_mm, steered.dwell_positions_mm), abs=0.1)
    shift = np.linalg.norm(out.dwell_positions_mm - steered.dwell_positions_mm, axis=1).max()
    assert check.dwell_shift_mm == pytest.approx(shift)
    assert check.reach_error_mm == pytest.approx(np.linalg.norm(out.path_mm[-1] - steered.path_mm[-1]))
    # robustness about the reference path: the worst case is no better than the nominal path
    assert np.isfinite(check.worst_reach_mm) and np.isfinite(check.worst_clearance_mm)
    assert check.worst_reach_mm >= check.reach_error_mm and check.worst_clearance_mm <= out.clearance_mm + 1e-9
    assert len(out.scenario_paths_mm) == 8 and all(np.allclose(p[0], out.path_mm[0]) for p in out.scenario_paths_mm)
    assert set(check.to_json()) == set(NeedleCheck.NOT_CHECKED)


def _plan(channels: tuple[Channel, ...], d90: float, aims_met: bool) -> object:
    from reachplan.planner.dose.coverage import StructureMetrics
    from reachplan.planner.dose.dwells import DwellSet
    from reachplan.planner.implant.arms import ImplantPlan

    pos = np.vstack([c.dwell_positions_mm for c in channels])
    ch = np.concatenate([np.full(len(c.dwell_positions_mm), i + 1) for i, c in enumerate(channels)])
    target = StructureMetrics("HR-CTV", 30.0, 7.0, 6.0, 0.0, 95.0, 50.0, d90, d90 - 10, 0.0, 10.0)
    return ImplantPlan(channels, DwellSet(pos, np.tile([0.0, 0.0, 1.0], (len(pos), 1)), np.ones(len(pos)), ch),
                       target, 20.0, (), aims_met)


def test_a_rejected_needle_sends_the_arm_to_its_next_plan(lobe: tuple, monkeypatch: pytest.MonkeyPatch) -> None:
    """check_arm: the chosen plan's steered needle fails its check, so the arm keeps its next plan whose needles all
    pass (here a plan of straight needles, which needs no re-load), and says which needle was rejected and why."""
    import reachplan.planner.implant.needles as needles
    from reachplan.planner.implant.arms import ImplantArm

    case, cands, config = lobe
    steered = next(c for c in cands if c.steered)
    straight = tuple(Channel(f"S{k}", "straight", np.array([[x, 0.0, 0.0], [x, 0.0, 90.0]]),
                             np.array([[x, 0.0, 85.0], [x, 0.0, 82.5], [x, 0.0, 80.0]]), abs(x), 90.0, 10.0)
                     for k, x in enumerate((-5.0, 5.0)))
    chosen, fallback = _plan((steered,), 95.0, True), _plan(straight, 92.0, True)
    arm = ImplantArm("steered", len(cands), (), chosen, 1.0, plans=(chosen,))  # type: ignore[arg-type]

    def fake(channel: Channel, ctx: object) -> Channel | str:
        if channel.steered:
            return "the reference path comes 1.0 mm from Bowel (margin 2 mm)"
        return dataclasses.replace(channel, check=NeedleCheck(0.0, None, 0.0, 0.0, 3.0, 5.0, "tilt", "kinematic"))

    monkeypatch.setattr(needles, "check_needle", fake)
    out = needles.check_arm(arm, _scene(case), case.planning, config, None, 1.0, ImplantSettings(),  # type: ignore
                            extra_plans=(fallback,))
    assert out.plan is not None and [c.name for c in out.plan.channels] == [c.name for c in straight]
    assert all(c.check is not None for c in out.plan.channels)
    rec = out.needle_check
    assert rec["chosen_replaced"] and not rec["reloaded"]
    assert rec["rejected"] == [{"hole_id": steered.name, "reason": "the reference path comes 1.0 mm from Bowel "
                                                                  "(margin 2 mm)"}]
    # past MAX_TRIES plans with a steered needle, plans of straight needles are still tried (no re-solve needed)
    monkeypatch.setattr(needles, "MAX_TRIES", 0)
    quick = needles.check_arm(arm, _scene(case), case.planning, config, None, 1.0, ImplantSettings(),  # type: ignore
                              extra_plans=(fallback,))
    assert quick.plan is not None and not quick.needle_check["rejected"] and quick.needle_check["chosen_replaced"]
    monkeypatch.setattr(needles, "MAX_TRIES", 3)
    # with no plan whose needles pass, the arm has none, and says so
    alone = needles.check_arm(arm, _scene(case), case.planning, config, None, 1.0, ImplantSettings())  # type: ignore
    assert alone.plan is None and "needle check" in alone.reason


def test_without_a_reserve_the_implant_candidates_use_the_full_limit(lobe: tuple) -> None:
    """``--tension-reserve 0``: the deep lateral lobe's steered candidates bend with up to the stylet's whole limit;
    with the default reserve none passes 90 % of it."""
    case, cands, config = lobe
    limit = DESIGN.max_tension_n
    assert max(c.schedule.peak_tension_n for c in cands if c.steered) <= 0.9 * limit + 1e-9
    bank = shape_bank(DESIGN, config.family, min(config.max_depth_mm, DESIGN.length_mm),
                      PlanModels.for_config(config).screening, 0.0)
    full = needle_candidates(case.ids, case.xy, case.dist, np.eye(4), case.planning, case.organs, RADIUS,
                             ImplantSettings(steered_per_hole=1), [bank])
    assert max(c.schedule.peak_tension_n for c in full if c.steered) == pytest.approx(limit)
