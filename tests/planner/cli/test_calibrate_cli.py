"""``reachplan calibrate`` (issue 32.4): reconstructions of steered needles in, a site calibration file out.

Two reconstructions are written here by hand: a plan's delivered steered needles (the kinematic model's paths in a
tilted template pose) and needles found where a tissue that bends them 1.15 times as much put them. The command must
find the ratio from the files alone, keep it across updates, and ``plan --calibration`` must read it.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from reachplan.planner.cli import main
from reachplan.planner.lookup import load_template
from reachplan.planner.steering.kinematic import KinematicInsertion
from reachplan.planner.steering.schedule import TensionSchedule
from reachplan.rod_model.design import preset

DESIGN = "15ga-30j-tip"
RATIO = 1.15
HOLES = {h.hole_id: np.array([*h.xy_mm, 0.0]) for h in load_template("needlefinder_syed_63").needle_holes}


def _pose() -> np.ndarray:
    a = np.radians(10.0)
    m = np.eye(4)
    m[:3, :3] = [[1.0, 0.0, 0.0], [0.0, np.cos(a), -np.sin(a)], [0.0, np.sin(a), np.cos(a)]]
    m[:3, 3] = [5.0, -60.0, -30.0]
    return m


def _write(folder: Path, holes: list[str], schedules: list[TensionSchedule]) -> dict[str, np.ndarray]:
    """Write ``folder/plan.json`` and ``folder/rec/needles.json``; return the planned paths (LPS) by hole."""
    m, design = _pose(), preset(DESIGN)
    planned, found, needles = {}, [], []
    for hole, sch in zip(holes, schedules, strict=True):
        local = KinematicInsertion().insert_array(design, [sch], 100.0)[0]
        to_lps = (local + HOLES[hole]) @ m[:3, :3].T + m[:3, 3]
        bent = (local * [RATIO, RATIO, 1.0] + HOLES[hole]) @ m[:3, :3].T + m[:3, 3]
        planned[hole] = to_lps
        found.append({"hole_id": hole, "points_mm": bent.tolist(), "tip_mm": bent[-1].tolist()})
        needles.append({"hole_id": hole, "kind": "steered", "tissue_length_mm": 100.0, "design": DESIGN,
                        "schedule": np.column_stack([sch.depth_mm, sch.tension_n, sch.roll_deg]).tolist()})
    plan = {"config": {"tissue_modulus_pa": 1.9e5}, "delivery": {"needles": holes, "files": []},
            "implant": {"steered": {"needles": needles}, "straight": {"needles": []}}}
    folder.mkdir(parents=True)
    (folder / "plan.json").write_text(json.dumps(plan))
    (folder / "rec").mkdir()
    (folder / "rec" / "needles.json").write_text(json.dumps({
        "plan": str(folder / "plan.json"), "template": "needlefinder_syed_63",
        "template_pose": {"patient_from_template": _pose().tolist()}, "needles": found}))
    return planned


def test_calibrate_finds_the_tissues_ratio_from_reconstructions_and_plan_reads_it(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]) -> None:
    planned: dict[str, np.ndarray] = {}
    planned |= _write(tmp_path / "a", ["Cc", "Ce"], [TensionSchedule.ramp(20.0, 20.0, 6.0, 0.0),
                                                     TensionSchedule.ramp(30.0, 20.0, 8.0, 180.0)])
    planned |= _write(tmp_path / "b", ["Bd"], [TensionSchedule.ramp(10.0, 20.0, 5.0, 90.0)])
    # the planned centre lines come from each plan's exported structure set; here, from the paths written above
    monkeypatch.setattr("reachplan.planner.verify.implant.plan_channel_paths",
                        lambda _path, doc: {h: planned[h] for h in doc["delivery"]["needles"]})
    site = tmp_path / "site.json"
    assert main(["calibrate", "--from", str(tmp_path / "a" / "rec"), "--site", str(site), "--json"]) == 0
    first = json.loads(capsys.readouterr().out)
    assert first["fitted"] == 2 and first["designs"][0]["ratio"] == pytest.approx(RATIO, rel=0.01)
    assert main(["calibrate", "--from", str(tmp_path / "a" / "rec"), str(tmp_path / "b" / "rec"), "--site",
                 str(site), "--json"]) == 0  # a's needles fitted again replace their fits: three in all
    doc = json.loads(site.read_text())
    (design,) = doc["designs"]
    assert design["needles"] == 3 and design["ratio"] == pytest.approx(RATIO, rel=0.01)
    lo, hi = design["ci95_ratio"]
    assert lo <= design["ratio"] <= hi
    capsys.readouterr()
    # plan and demo read it as --calibration (each design's ratio, applied by the plan's models)
    from reachplan.planner.cli import build_parser
    from reachplan.planner.cli.tissue import tissue_options

    for command in (["plan", "--rtstruct", "rs.dcm", "--targets", "T"], ["demo"]):
        args = build_parser().parse_args([*command, "--out", "o", "--calibration", str(site)])
        ((name, ratio),) = tissue_options(args)["curvature_scale"]
        assert name == DESIGN and ratio == pytest.approx(RATIO, rel=0.01)
    # a reconstruction made without --plan is a one-line error
    bare = tmp_path / "bare"
    bare.mkdir()
    (bare / "needles.json").write_text(json.dumps({"needles": []}))
    assert main(["calibrate", "--from", str(bare), "--site", str(tmp_path / "other.json")]) == 2
    assert "reconstruct it with --plan" in capsys.readouterr().err
    assert not (tmp_path / "other.json").exists()


def test_a_drawn_tissue_bends_steered_needles_by_its_ratio_and_leaves_straight_ones() -> None:
    from reachplan.planner.verify.implant import PlannedNeedle, draw_needles, planned_paths

    template, m = load_template("needlefinder_syed_63"), _pose()
    sch = TensionSchedule.ramp(20.0, 20.0, 6.0, 45.0)
    steered = PlannedNeedle("Cc", 100.0, DESIGN, np.column_stack([sch.depth_mm, sch.tension_n, sch.roll_deg]))
    straight = PlannedNeedle("Ce", 90.0)
    still = {"tension_fraction": 0.0, "roll_deg": 0.0, "tilt_deg": 0.0}
    drawn = draw_needles([steered, straight], template, m, still, 0, planned_paths([steered], template, m),
                         curvature_scale=RATIO)
    for d in drawn:
        local_planned, local_actual = ((p - m[:3, 3]) @ m[:3, :3] - HOLES[d.needle.hole_id]
                                       for p in (d.planned_mm, d.actual_mm))
        scale = RATIO if d.needle.steered else 1.0
        np.testing.assert_allclose(local_actual[:, :2], scale * local_planned[:, :2], atol=1e-9)
        np.testing.assert_allclose(local_actual[:, 2], local_planned[:, 2], atol=1e-9)


def test_a_needle_inserted_as_one_of_the_plans_steered_candidates_is_fitted_too(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]) -> None:
    """A clinician may insert one of the report's steered alternatives: found in its hole, bent as the tissue bends
    it, it is fitted against that candidate's planned path; a straight needle in a candidate's hole is not."""
    from reachplan.planner.verify.implant import plan_candidates, steered_alternates

    planned = _write(tmp_path / "a", ["Cc"], [TensionSchedule.ramp(20.0, 20.0, 6.0, 0.0)])
    m, design = _pose(), preset(DESIGN)
    schedules = {"Cg": TensionSchedule.ramp(20.0, 20.0, 7.0, 270.0), "Ca": TensionSchedule.ramp(20.0, 20.0, 6.0, 90.0)}

    def candidate(hole: str, sch: TensionSchedule | None, feasible: bool = True) -> dict[str, object]:
        rows = None if sch is None else np.column_stack([sch.depth_mm, sch.tension_n, sch.roll_deg]).tolist()
        return {"hole_id": hole, "steered": sch is not None, "feasible": feasible, "design": DESIGN if sch else None,
                "schedule": rows, "insertion_depth_mm": 100.0}

    plan_path = tmp_path / "a" / "plan.json"
    plan = json.loads(plan_path.read_text())
    plan["targets"] = {"T1": {"candidates": [candidate("Ce", None), candidate("Cg", schedules["Cg"]),
                                             candidate("Ci", schedules["Cg"], feasible=False)]},
                       "T2": {"candidates": [candidate("Ca", schedules["Ca"]), candidate("Cg", schedules["Cg"])]}}
    plan_path.write_text(json.dumps(plan))
    # ranked per target, targets interleaved, a repeated shape once, infeasible and straight ones left out
    assert [c.hole_id for c in plan_candidates(plan)] == ["Cg", "Ca"]
    template = load_template("needlefinder_syed_63")
    assert [c.hole_id for c in steered_alternates(plan_candidates(plan), template, ["Cc"], 5)] == ["Cg", "Ca"]
    assert steered_alternates(plan_candidates(plan), template, ["Cg"], 5)[0].hole_id == "Ca"
    rec = json.loads((tmp_path / "a" / "rec" / "needles.json").read_text())
    local = KinematicInsertion().insert_array(design, [schedules["Cg"]], 100.0)[0]
    bent = (local * [RATIO, RATIO, 1.0] + HOLES["Cg"]) @ m[:3, :3].T + m[:3, 3]
    line = (np.column_stack([np.zeros(101), np.zeros(101), np.arange(101.0)]) + HOLES["Ca"]) @ m[:3, :3].T + m[:3, 3]
    rec["needles"] += [{"hole_id": h, "points_mm": p.tolist(), "tip_mm": p[-1].tolist()}
                       for h, p in (("Cg", bent), ("Ca", line))]
    (tmp_path / "a" / "rec" / "needles.json").write_text(json.dumps(rec))
    monkeypatch.setattr("reachplan.planner.verify.implant.plan_channel_paths",
                        lambda _path, doc: {h: planned[h] for h in doc["delivery"]["needles"]})
    assert main(["calibrate", "--from", str(tmp_path / "a" / "rec"), "--site", str(tmp_path / "s.json"),
                 "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["fitted"] == 2 and out["designs"][0]["ratio"] == pytest.approx(RATIO, rel=0.01)
    fitted = json.loads((tmp_path / "s.json").read_text())
    assert sorted(n["hole_id"] for n in fitted["designs"][0]["fits"]) == ["Cc", "Cg"]
