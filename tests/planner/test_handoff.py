"""The hand-off (insert list): directions in patient terms, schedules in words, check depths, margins, applicators.

Each number is checked against an independent computation: the bending direction against the path a kinematic
insertion really bends to, the check depths against a circular arc's closed form, the margins of a straight needle
beside a box against the tilt's geometry, the tandem's curvature against the arc it was drawn as.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import trimesh

from reachplan.imaging.types import Contour, Roi, StructureSet
from reachplan.planner.case.config import PlanConfig, PlanModels
from reachplan.planner.case.scene import Scene, build_scene
from reachplan.planner.geometry.collision import make_organ
from reachplan.planner.handoff import (
    bend_direction,
    channel_geometry,
    check_depths,
    insert_list,
    obstacles_line,
    schedule_words,
    toward,
)
from reachplan.planner.lookup import load_template
from reachplan.planner.steering.candidates import Target
from reachplan.planner.steering.kinematic import KINEMATIC
from reachplan.planner.steering.schedule import TensionSchedule
from reachplan.plugins.exporters.base import NeedleExport


def _rot_x(deg: float) -> np.ndarray:
    a = math.radians(deg)
    m = np.eye(4)
    m[1:3, 1:3] = [[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]]
    return m


def test_directions_are_named_in_patient_terms() -> None:
    assert toward(np.array([1.0, 0.0, 0.0])) == "the patient's left"
    assert toward(np.array([-1.0, 0.0, 0.0])) == "the patient's right"
    assert toward(np.array([0.0, -2.0, 0.0])) == "anterior"
    assert toward(np.array([0.0, 0.1, 3.0])) == "superior"
    assert toward(np.array([0.6, -1.0, 0.0])) == "anterior and the patient's left"
    assert toward(np.array([0.4, -1.0, 0.0])) == "anterior"  # under half the largest component: not named
    assert toward(np.zeros(3)) == ""


@pytest.mark.parametrize(("roll_deg", "pose_tilt_deg"), [(-90.0, 0.0), (0.0, 0.0), (135.0, 0.0), (-90.0, 30.0)])
def test_the_named_bending_direction_is_where_the_inserted_needle_goes(roll_deg: float, pose_tilt_deg: float) -> None:
    design = PlanConfig().rod_designs[0]
    schedule = TensionSchedule([0.0, 30.0, 40.0], [0.0, 0.0, 0.8 * design.max_tension_n], [roll_deg] * 3)
    shape = KINEMATIC.insert_array(design, [schedule], 100.0)[0]  # template frame, hole at the origin
    pose = _rot_x(pose_tilt_deg)
    pose[:3, 3] = [5.0, -20.0, 3.0]
    path = shape @ pose[:3, :3].T + pose[:3, 3]
    tip = check_depths(path, np.column_stack([schedule.depth_mm, schedule.tension_n, schedule.roll_deg]), pose)[-1]
    rel = path[-1] - path[0]
    lateral = rel - (rel @ pose[:3, 2]) * pose[:3, 2]
    assert tip.offset_mm == pytest.approx(np.linalg.norm(lateral), abs=1e-9) and tip.offset_mm > 5.0
    # the path bends the way the schedule's roll says, in the patient frame
    assert float(lateral @ bend_direction(roll_deg, pose)) / np.linalg.norm(lateral) > 0.99
    assert tip.toward == toward(bend_direction(roll_deg, pose))
    words = schedule_words(np.column_stack([schedule.depth_mm, schedule.tension_n, schedule.roll_deg]), pose, 100.0)
    assert f"bending toward {tip.toward} " in words


def test_schedule_in_words_follows_the_breakpoints() -> None:
    rows = np.array([[0.0, 0.0, -90.0], [40.0, 0.0, -90.0], [45.0, 5.7, -90.0], [90.0, 5.7, -90.0]])
    words = schedule_words(rows, np.eye(4), 112.0)
    assert words == ("tendon slack from 0 to 40 mm; 40-45 mm: pull from 0.0 to 5.7 N, bending toward anterior "
                     "(roll 270 deg); hold 5.7 N from 45 to 112 mm")


def _arc(radius_mm: float, angle_deg: float, n: int = 400) -> np.ndarray:
    """A circular arc from the origin along +z, bending toward +x (patient left), in LPS."""
    t = np.linspace(0.0, math.radians(angle_deg), n)
    return np.column_stack([radius_mm * (1 - np.cos(t)), np.zeros(n), radius_mm * np.sin(t)])


def test_check_depths_give_the_arc_point_at_each_depth() -> None:
    radius = 200.0
    path = _arc(radius, 30.0)
    rows = np.array([[0.0, 0.0, 0.0], [20.0, 0.0, 0.0], [30.0, 6.0, 0.0]])
    checks = check_depths(path, rows, np.eye(4))
    assert [c.what for c in checks] == ["the pull starts", "full tension", "tip"]
    for c in checks:
        phi = c.depth_mm / radius  # closed form: the arc's point at arc length s
        expected = np.array([radius * (1 - math.cos(phi)), 0.0, radius * math.sin(phi)])
        assert np.allclose(c.tip_mm, expected, atol=0.01)
        assert c.offset_mm == pytest.approx(expected[0], abs=0.01)
    assert checks[-1].toward == "the patient's left"
    assert checks[-1].depth_mm == pytest.approx(radius * math.radians(30.0), abs=0.01)
    straight = check_depths(np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 90.0]]), None, np.eye(4))
    assert [(c.depth_mm, c.what, c.toward) for c in straight] == [(45.0, "half way", ""), (90.0, "tip", "")]
    assert "on the hole's line" in straight[0].text()


def test_tandem_length_and_curvature_are_the_drawn_arcs() -> None:
    radius, angle = 80.0, 40.0
    path = _arc(radius, angle)[:, [1, 0, 2]] * np.array([1.0, -1.0, 1.0])  # bending toward -y: anterior
    tandem = NeedleExport("Tandem", path, path[-3:-1], np.array([10.0, 10.0]), applicator=True)
    geo = channel_geometry(tandem, 2)
    assert geo.length_mm == pytest.approx(radius * math.radians(angle), rel=1e-4)
    assert geo.radius_mm == pytest.approx(radius, rel=1e-3)
    # the ends' 2 mm chords each see half their own turn: 2 mm / R rad less than the arc's
    assert geo.bend_deg == pytest.approx(angle - math.degrees(2.0 / radius), abs=0.05)
    assert geo.toward == "anterior" and "Tandem (channel 2)" in geo.text()
    # a straight part then the arc: the tightest radius is the arc's, the turn still the arc's
    straight = np.column_stack([np.zeros(61), np.zeros(61), np.linspace(-60.0, 0.0, 61)])
    hockey = np.vstack([straight[:-1], _arc(50.0, 45.0)])
    hockey_export = NeedleExport("Tandem", hockey, hockey[[-60, -1]], np.array([1.0, 1.0]), applicator=True)
    geo = channel_geometry(hockey_export, 1)
    assert geo.radius_mm == pytest.approx(50.0, rel=0.02) and geo.toward == "the patient's left"
    assert geo.bend_deg == pytest.approx(45.0 - math.degrees(1.0 / 50.0), abs=0.05)  # only the tip's chord turns


def _scene(organ_mesh: trimesh.Trimesh) -> Scene:
    return Scene((make_organ("Bladder", organ_mesh),), (Target("t", (0.0, 0.0, 100.0)),),
                 load_template("needlefinder_syed_63"), np.eye(4))


def test_margins_of_a_straight_needle_beside_a_box_follow_the_tilt_geometry() -> None:
    gap, depth = 12.0, 100.0  # the box's face 12 mm to the needle's right (-x), along its whole length
    box = trimesh.creation.box(extents=(20.0, 60.0, 200.0))
    box.apply_translation((-gap - 10.0, 0.0, 50.0))
    config = PlanConfig()
    path = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, depth]])
    needle = NeedleExport("Cj", path, np.array([[0.0, 0.0, 95.0]]), np.array([10.0]))
    handoff = insert_list(_export(needle), _scene(box), config, plan="test", clearance_margin_mm=2.0,
                          models=PlanModels())
    (item,) = handoff.needles
    tilt = math.radians(config.perturbations.tilt_deg)
    # a tilt about the hole moves the tip along a chord of the circle of radius `depth`
    assert item.reach.worst_mm == pytest.approx(2 * depth * math.sin(tilt / 2), abs=1e-6)
    assert item.reach.margin_mm == pytest.approx(config.reach_tolerance_mm - item.reach.worst_mm, abs=1e-9)
    assert "entry tilt" in item.reach.cause
    # the tilt toward the box brings the tip closest: clearance = gap - radius - depth sin(tilt)
    expected = gap - config.needle_radius_mm - depth * math.sin(tilt)
    assert item.clearance.worst_mm == pytest.approx(expected, abs=0.05)
    assert item.clearance.margin_mm == pytest.approx(expected - 2.0, abs=0.05)
    assert item.clearance.organ == "Bladder" and "about template y" in item.clearance.cause
    # the margins are the scenarios' extremes: nominal and the four tilts of a straight needle
    assert item.scenarios[0].label == "nominal" and len(item.scenarios) == 5
    assert item.reach.worst_mm == max(sc.reach_mm for sc in item.scenarios) and item.scenarios[0].reach_mm == 0.0
    assert item.clearance.worst_mm == min(sc.clearance_mm for sc in item.scenarios)
    assert item.scenarios[0].clearance_mm == pytest.approx(gap - config.needle_radius_mm, abs=0.05)
    rows = handoff.scenario_rows()
    assert len(rows) == 1 + len(item.scenarios) and rows[1][:4] == ("Cj", "nominal", "0.0", "+2.0")
    assert item.kind == "straight" and item.tension_limit_n is None and item.reserve_n is None
    assert item.steering is None and handoff.details()[0][1] == item.tension_words
    assert handoff.tension_rule == "" and "Karius" in handoff.perturbations


def _export(*needles: NeedleExport):  # type: ignore[no-untyped-def]
    from datetime import datetime

    from reachplan.plugins.exporters.base import ExportPlan, SourceSpec
    from reachplan.plugins.sources import gammamed_plus_hdr

    return ExportPlan("t", needles, SourceSpec.from_source_data(gammamed_plus_hdr(), 40700.0, datetime(2026, 1, 1)))


def _tube(number: int, name: str, z0: float, z1: float, radius: float, y: float = 0.0) -> Roi:
    t = np.linspace(0.0, 2 * np.pi, 24, endpoint=False)
    ring = np.column_stack([radius * np.cos(t), y + radius * np.sin(t), np.zeros(24)])
    return Roi(number, name, tuple(Contour(ring + np.array([0.0, 0.0, z])) for z in np.arange(z0, z1 + 1e-9, 2.5)))


def test_a_tandem_is_an_obstacle_by_default_and_the_line_names_the_applicators() -> None:
    rois = (_tube(1, "Obturator", 0.0, 40.0, 12.0), _tube(2, "Bladder", 40.0, 60.0, 8.0, y=-40.0),
            _tube(3, "Tandem", 40.0, 70.0, 3.0))
    scene = build_scene(StructureSet(rois, "1.2.3"), [], [Target("p", (0.0, 20.0, 90.0))])
    assert "Tandem" in {o.name for o in scene.organs}  # no --oar needed
    line = obstacles_line(scene)
    assert "Tandem (tandem; an obstacle: needles keep off it)" in line
    assert "Obturator (obturator; not an obstacle)" in line


def test_a_steered_needle_gets_its_schedule_reserve_checks_and_steering_errors() -> None:
    config = PlanConfig()
    design = config.rod_designs[0]
    peak = 0.8 * design.max_tension_n
    schedule = TensionSchedule([0.0, 30.0, 40.0], [0.0, 0.0, peak], [-90.0] * 3)
    shape = KINEMATIC.insert_array(design, [schedule], 100.0)[0]  # template = patient frame here (pose identity)
    path = shape + np.array([0.0, -20.0, 0.0])
    rows = np.column_stack([schedule.depth_mm, schedule.tension_n, schedule.roll_deg])
    needle = NeedleExport("Bd", path, path[-3:-2], np.array([10.0]), design=design.name, schedule=rows)
    box = trimesh.creation.box(extents=(20.0, 20.0, 20.0))
    box.apply_translation((60.0, 0.0, 50.0))  # far away: the clearance is not the point here
    handoff = insert_list(_export(needle), _scene(box), config, plan="test", clearance_margin_mm=2.0,
                          models=PlanModels())
    (item,) = handoff.needles
    assert f"Bd {design.max_tension_n:g} N (plan {peak:.1f} N, reserve {0.2 * design.max_tension_n:.1f} N)" in (
        handoff.tension_rule)
    assert item.kind == "steered" and item.stylet == design.name and item.needle.startswith(f"{design.needle.gauge} ga")
    assert item.peak_tension_n == pytest.approx(peak) and item.reserve_n == pytest.approx(0.2 * design.max_tension_n)
    assert "30-40 mm: pull from 0.0 to" in item.tension_words and "bending toward anterior" in item.tension_words
    assert [c.what for c in item.checks] == ["the pull starts", "full tension", "tip"]
    assert item.checks[-1].toward == "anterior"
    labels = [s.label for s in item.scenarios]
    assert labels[:5] == ["nominal", "tension x0.90", "tension x1.10", "roll -10 deg", "roll +10 deg"]
    assert len(labels) == 9  # and four entry tilts
    # the tension error moves the tip as the kinematic model says, independently re-inserted here
    more = TensionSchedule(schedule.depth_mm, schedule.tension_n * 1.1, schedule.roll_deg)
    moved = KINEMATIC.insert_array(design, [more], 100.0)[0][-1] - shape[-1]
    assert item.scenarios[2].reach_mm == pytest.approx(float(np.linalg.norm(moved)), abs=1e-4)
    assert item.reach.worst_mm == max(s.reach_mm for s in item.scenarios)
    # what sets a steered needle apart: its margins over the tension and roll errors alone (the tilts left out)
    assert item.steering is not None
    steer_reach, steer_clear = item.steering
    assert steer_reach.worst_mm == max(s.reach_mm for s in item.scenarios[:5])
    assert steer_reach.cause in labels[1:5] and steer_clear.worst_mm == min(s.clearance_mm for s in item.scenarios[:5])
    assert "Steering errors alone: reach margin" in handoff.details()[0][1]
