"""The main job end to end: ``reachplan demo`` on the built-in phantom, through DICOM on disk."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from reachplan.planner.cli import main

FIELDS = {"target", "hole_id", "hole_distance_mm", "reach_error_mm", "clearance_mm", "closest_organ",
          "insertion_depth_mm", "steered", "peak_tension_n", "model"}


@pytest.fixture(scope="module")
def demo(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("demo")
    assert main(["demo", "--out", str(out), "--quiet"]) == 0
    return out


def test_demo_writes_ranking_plan_figure_and_exports(demo: Path) -> None:
    ranking = json.loads((demo / "ranking.json").read_text())
    assert len(ranking) >= 10
    for cands in ranking.values():
        assert cands and all(set(c) >= FIELDS for c in cands)
    assert (demo / "overview.png").stat().st_size > 10_000
    plan = json.loads((demo / "plan.json").read_text())
    assert plan["delivery"]["optimisation"]["success"]
    for f in plan["delivery"]["files"]:
        assert Path(f).is_file()


def test_demo_reaches_a_lateral_target_from_a_more_medial_hole_by_steering(demo: Path) -> None:
    plan = json.loads((demo / "plan.json").read_text())
    gains = {t: v for t, v in plan["targets"].items() if v["medial_gain_mm"] is not None}
    assert gains, "no target has both a feasible straight and a feasible steered needle"
    target, best = max(gains.items(), key=lambda kv: kv[1]["medial_gain_mm"])
    assert best["medial_gain_mm"] >= 10.0
    steered = [c for c in best["candidates"] if c["steered"] and c["feasible"]
               and c["hole_distance_mm"] == best["most_medial_steered_mm"]]
    assert steered and steered[0]["reach_error_mm"] <= 2.0 and steered[0]["clearance_mm"] >= 2.0
    # lateral: the target lies at least 30 mm from the obturator axis
    tip = steered[0]["tip_position_mm"]
    assert (tip[0] ** 2 + tip[1] ** 2) ** 0.5 >= 30.0, target


def test_demo_is_deterministic(demo: Path, tmp_path: Path) -> None:
    assert main(["demo", "--out", str(tmp_path), "--quiet"]) == 0
    a = json.loads((demo / "ranking.json").read_text())
    b = json.loads((tmp_path / "ranking.json").read_text())
    assert a == b


def test_demo_plans_the_implant_straight_against_steered(demo: Path) -> None:
    """Both implant arms in plan.json: the keys tools read, every needle with time on at least three dwells, no
    dwell over the configured share, and device files for exactly the loaded needles of each arm."""
    from reachplan.planner.dose.implant import ImplantSettings

    plan = json.loads((demo / "plan.json").read_text())
    keys = {"needles", "aims_met", "hrctv_d90_eqd2_gy", "hrctv_d98_eqd2_gy", "hrctv_v100_percent",
            "hrctv_v150_percent", "hrctv_v200_percent", "oar_d2cc_eqd2_gy", "max_dwell_share", "loaded_dwells",
            "pareto"}
    share = ImplantSettings().max_dwell_share
    for name in ("straight", "steered"):
        arm = plan["implant"][name]
        assert set(arm) >= keys
        assert arm["needles"], f"{name}: no implant"
        assert arm["max_dwell_share"] <= share + 1e-6
        for n in arm["needles"]:
            assert {"hole_id", "design", "schedule", "dwell_positions_mm", "dwell_times_s"} <= set(n)
            assert sum(t > 0 for t in n["dwell_times_s"]) >= 3
            assert max(n["dwell_times_s"]) <= share * sum(sum(m["dwell_times_s"]) for m in arm["needles"]) + 1e-3
        assert all({"n_needles", "hrctv_d90_eqd2_gy", "aims_met"} <= set(p) for p in arm["pareto"])
        assert any(p["n_needles"] == arm["n_needles"] for p in arm["pareto"])
        device = json.loads(next((demo / "export" / f"implant_{name}").glob("*.json")).read_text())
        text = json.dumps(device)
        assert all(n["hole_id"] in text for n in arm["needles"])
    steered_kinds = {n["kind"] for n in plan["implant"]["steered"]["needles"]}
    assert steered_kinds <= {"straight", "steered", "intracavitary"}
    assert {n["kind"] for n in plan["implant"]["straight"]["needles"]} <= {"straight", "intracavitary"}
