"""Straight candidates and their ranking on a small synthetic scene."""

from __future__ import annotations

import numpy as np
import trimesh

from planner.collision import make_organ
from planner.pipeline import PlanConfig, Scene, load_template, plan
from planner.ranking import Target, rank


def _scene(targets: tuple) -> Scene:
    sphere = trimesh.creation.icosphere(subdivisions=3, radius=8.0)
    sphere.apply_translation([0.0, -20.0, 40.0])  # sits on the straight path of hole Bd (0, -20)
    return Scene((make_organ("Bladder", sphere),), targets, load_template("needlefinder_syed_63"), np.eye(4))


def test_blocked_straight_path_is_rejected_with_reason() -> None:
    result = plan(_scene((Target("T", (0.0, -20.0, 70.0)),)), PlanConfig())
    bd = next(c for c in result.candidates if c.hole_id == "Bd")
    assert bd.collides and not bd.feasible and bd.closest_organ == "Bladder"
    assert "collides with Bladder" in bd.reason
    # no straight needle reaches the target without passing through the sphere
    assert not any(c.feasible for c in result.ranking["T"])


def test_reachable_target_ranks_most_medial_hole_first() -> None:
    result = plan(_scene((Target("T", (20.0, 0.0, 60.0)),)), PlanConfig())
    best = result.ranking["T"][0]
    assert best.feasible and best.hole_id == "Bg"  # the 20 mm ring hole at template (20, 0)
    assert best.reach_error_mm < 1e-6
    assert best.insertion_depth_mm == 60.0
    feasible = [c for c in result.ranking["T"] if c.feasible]
    assert [c.hole_distance_mm for c in feasible] == sorted(c.hole_distance_mm for c in feasible)


def test_ranking_is_deterministic_under_input_order() -> None:
    result = plan(_scene((Target("A", (20.0, 0.0, 60.0)), Target("B", (-30.0, 5.0, 80.0)))), PlanConfig())
    rng = np.random.default_rng(0)
    shuffled = [result.candidates[i] for i in rng.permutation(len(result.candidates))]
    again = rank(shuffled)
    for t in result.ranking:
        assert [(c.hole_id, c.target) for c in again[t]] == [(c.hole_id, c.target) for c in result.ranking[t]]
    json_a = [c.to_json() for c in result.ranking["A"]]
    json_b = [c.to_json() for c in plan(_scene((Target("A", (20.0, 0.0, 60.0)),)), PlanConfig()).ranking["A"]]
    assert json_a == json_b
