"""Device instructions (JSON and CSV per needle): resampled schedules checked against hand interpolation."""

from __future__ import annotations

import csv
import json
import re
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

from reachplan.plugins.exporters.base import ExportError, ExportOptions, ExportPlan, NeedleExport, check_exporter
from reachplan.plugins.exporters.device import CSV_EXPORTER, JSON_EXPORTER, schedule_rows
from reachplan.plugins.exporters.device_page import HTML_EXPORTER
from reachplan.plugins.exporters.handoff import (
    RESEARCH_USE,
    ApplicatorChannel,
    CheckDepth,
    InsertList,
    InsertNeedle,
    Margin,
)


def _by_hand(depth: float) -> tuple[float, float]:
    """Tension and roll of the test schedule (0,0,0) (40,0,0) (80,9.9,90) (110,9.9,90) at ``depth``."""
    if depth <= 40.0:
        return 0.0, 0.0
    if depth <= 80.0:
        f = (depth - 40.0) / 40.0
        return 9.9 * f, 90.0 * f
    return 9.9, 90.0


def test_rows_follow_the_breakpoints_piecewise_linearly(make_plan: Callable[..., ExportPlan]) -> None:
    needle = make_plan().needles[0]
    rows = schedule_rows(needle, 5.0)
    assert rows[0, 0] == 0.0 and rows[-1, 0] == pytest.approx(needle.length_mm)
    assert needle.length_mm > 120.0  # the bent needle is longer than its 120 mm chord along z
    np.testing.assert_allclose(np.diff(rows[:-1, 0]), 5.0)
    assert 0 < rows[-1, 0] - rows[-2, 0] <= 5.0
    for d, t, r in rows:
        assert (t, r) == pytest.approx(_by_hand(d), abs=1e-12)
    # a finer step passes through the same values at the shared depths
    fine = schedule_rows(needle, 1.0)
    shared = np.isin(np.round(fine[:, 0], 9), np.round(rows[:, 0], 9))
    np.testing.assert_allclose(fine[shared], rows, atol=1e-12)


def test_json_document(make_plan: Callable[..., ExportPlan], tmp_path: Path) -> None:
    plan = make_plan()
    out = JSON_EXPORTER.export(plan, tmp_path, ExportOptions(step_mm=2.5))
    doc = json.loads(out.path("device_json").read_text(encoding="utf-8"))
    assert doc["format"] == "reachplan-device/2" and doc["step_mm"] == 2.5
    assert [n["hole_id"] for n in doc["needles"]] == [n.hole_id for n in plan.needles]
    assert "Doe" not in out.path("device_json").read_text(encoding="utf-8")  # no patient identity
    for entry, needle in zip(doc["needles"], plan.needles, strict=True):
        assert entry["stylet_preset"] == "15ga_20j_tip"
        assert entry["insertion_depth_mm"] == pytest.approx(needle.length_mm, abs=1e-3)
        for row in entry["rows"]:
            t, r = _by_hand(row["depth_mm"])
            assert row["tension_n"] == pytest.approx(t, abs=1e-3) and row["roll_deg"] == pytest.approx(r, abs=1e-3)
        assert len(entry["rows"]) == int(np.ceil(needle.length_mm / 2.5 - 1e-9)) + 1


def test_csv_per_needle_matches_json(make_plan: Callable[..., ExportPlan], tmp_path: Path) -> None:
    plan = make_plan()
    out = CSV_EXPORTER.export(plan, tmp_path)
    schedules = [f for f in out.files if f.role == "device_csv"]
    assert len(schedules) == len(plan.needles)  # every test needle is steered
    for f, needle in zip(schedules, plan.needles, strict=True):
        assert f.path.name == f"PrePlan1_needle_{needle.hole_id}.csv"
        with f.path.open(newline="", encoding="utf-8") as fh:
            rows = list(csv.DictReader(fh))
        assert {r["hole_id"] for r in rows} == {needle.hole_id}
        got = np.array([[float(r["depth_mm"]), float(r["tension_n"]), float(r["roll_deg"])] for r in rows])
        np.testing.assert_allclose(got, schedule_rows(needle, 5.0), atol=1e-3)


def test_needle_without_schedule_is_straight_and_noted(make_plan: Callable[..., ExportPlan], tmp_path: Path) -> None:
    n0 = make_plan().needles[0]
    plain = NeedleExport("D4", n0.path_mm, n0.dwell_positions_mm, n0.dwell_times_s)
    out = CSV_EXPORTER.export(make_plan(needles=(n0, plain)), tmp_path)
    assert any("D4" in n and "straight" in n for n in out.notes)
    # no rows of zeros: a straight needle gets no schedule file and no rows, but its dwells are listed
    assert [f.path.name for f in out.files if f.role == "device_csv"] == ["PrePlan1_needle_A1.csv"]
    JSON_EXPORTER.export(make_plan(needles=(n0, plain)), tmp_path)
    doc = json.loads(next(tmp_path.glob("*_device.json")).read_text())
    straight = doc["needles"][1]
    assert straight["hole_id"] == "D4" and straight["kind"] == "straight" and straight["rows"] == []
    with out.path("device_dwells").open(newline="", encoding="utf-8") as fh:
        dwells = [r for r in csv.DictReader(fh) if r["name"] == "D4"]
    assert sorted(float(r["time_s"]) for r in dwells) == pytest.approx(sorted(plain.dwell_times_s), abs=1e-3)
    dist = sorted(float(r["distance_from_tip_mm"]) for r in dwells)
    assert dist == pytest.approx(sorted(plain.dwell_distance_from_tip_mm), abs=1e-3)


def test_colliding_safe_names_and_existing_files_are_refused(make_plan: Callable[..., ExportPlan],
                                                             tmp_path: Path) -> None:
    n0 = make_plan().needles[0]
    twins = tuple(NeedleExport(h, n0.path_mm, n0.dwell_positions_mm, n0.dwell_times_s, n0.design, n0.schedule)
                  for h in ("A/1", "A_1"))
    with pytest.raises(ExportError, match="two outputs"):
        CSV_EXPORTER.export(make_plan(needles=twins), tmp_path)
    assert not list(tmp_path.iterdir())
    JSON_EXPORTER.export(make_plan(), tmp_path)
    with pytest.raises(ExportError, match="exists"):
        JSON_EXPORTER.export(make_plan(), tmp_path)


def test_schedule_validation() -> None:
    path = np.column_stack([np.zeros(3), np.zeros(3), [0.0, 50.0, 100.0]])
    with pytest.raises(ValueError, match="increase strictly"):
        NeedleExport("A1", path, path[1:2], [1.0], schedule=[[0, 0, 0], [0, 1, 0]])
    with pytest.raises(ValueError, match="tension"):
        NeedleExport("A1", path, path[1:2], [1.0], schedule=[[0, -1, 0]])
    with pytest.raises(ValueError, match="off the needle path"):
        NeedleExport("A1", path, path[1:2] + np.array([2.0, 0.0, 0.0]), [1.0])
    with pytest.raises(ValueError, match="dwell times"):
        NeedleExport("A1", path, path[1:2], [-1.0])
    with pytest.raises(ValueError, match="hole_id"):
        NeedleExport("A" * 17, path, path[1:2], [1.0])


def test_device_exporters_pass_their_protocol_check() -> None:
    check_exporter(JSON_EXPORTER)
    check_exporter(CSV_EXPORTER)
    check_exporter(HTML_EXPORTER)


def test_applicator_channels_get_no_device_rows(make_plan: Callable[..., ExportPlan], tmp_path: Path) -> None:
    """A tandem is a channel of the plan placed by hand: the handheld's instructions skip it, and every needle keeps
    its channel number of the RT Plan."""
    import dataclasses

    base = make_plan()
    tandem = dataclasses.replace(base.needles[1], hole_id="Tandem", schedule=None, design="", applicator=True)
    plan = dataclasses.replace(base, needles=(base.needles[0], tandem, base.needles[2]))
    JSON_EXPORTER.export(plan, tmp_path)
    doc = json.loads(next(tmp_path.glob("*_device.json")).read_text())
    assert [(n["channel_number"], n["hole_id"]) for n in doc["needles"]] == [(1, "A1"), (3, "C3")]
    written = CSV_EXPORTER.export(plan, tmp_path)
    assert sorted(f.path.name.split("_needle_")[1] for f in written.files if f.role == "device_csv") == [
        "A1.csv", "C3.csv"]
    assert not [n for n in written.notes if "Tandem" in n]


def _handoff(plan: ExportPlan) -> InsertList:
    """An insert list for the test plan: A1 steered, B12 straight, a tandem."""
    def margin(worst: float, limit: float, cause: str, organ: str = "") -> Margin:
        return Margin(worst, limit, limit - worst if not organ else worst - limit, cause, organ)

    checks = (CheckDepth(40.0, (0.0, -20.0, -60.0), 0.0, "", "the pull starts"),
              CheckDepth(120.0, (8.0, -20.0, 20.0), 8.0, "the patient's left", "tip"))
    needles = (InsertNeedle(1, "A1", "steered", "15 ga plastic needle, 1.83 mm OD", "15ga_20j_tip", 121.0,
                            "pull to 9.9 N toward the patient's left", 9.9, 10.0, margin(1.2, 2.0, "roll +10 deg"),
                            margin(4.0, 2.0, "tension x1.10", "Bladder"), checks, "kinematic"),
               InsertNeedle(2, "B12", "straight", "plastic needle, 1.83 mm OD", "", 120.0, "straight: no tendon", 0.0,
                            None, margin(3.3, 2.0, "entry tilt +2 deg about template x"),
                            margin(9.0, 2.0, "entry tilt -2 deg about template y", "Rectum"), checks[1:], "straight"))
    tandem = ApplicatorChannel(3, "Tandem", 60.0, 30.0, 80.0, "anterior")
    return InsertList("implant, straight + steered", needles, (tandem,), "perturbations ...", "never pull past 10 N",
                      "applicators: Tandem (tandem; an obstacle: needles keep off it)")


def test_the_insert_list_leads_every_device_file_with_the_same_names(make_plan: Callable[..., ExportPlan],
                                                                      tmp_path: Path) -> None:
    import dataclasses

    base = make_plan()
    tandem = dataclasses.replace(base.needles[2], hole_id="Tandem", schedule=None, design="", applicator=True)
    straight = dataclasses.replace(base.needles[1], schedule=None, design="")
    plan = dataclasses.replace(base, needles=(base.needles[0], straight, tandem))
    plan = dataclasses.replace(plan, handoff=_handoff(plan))
    doc = json.loads(JSON_EXPORTER.export(plan, tmp_path).path("device_json").read_text(encoding="utf-8"))
    assert doc["statement"] == RESEARCH_USE
    assert [n["hole_id"] for n in doc["insert_list"]["needles"]] == ["A1", "B12"]
    assert doc["insert_list"]["needles"][0]["tension_reserve_n"] == pytest.approx(0.1)
    assert [c["name"] for c in doc["channels"]] == ["A1", "B12", "Tandem"]
    for channel, needle in zip(doc["channels"], plan.needles, strict=True):
        total = sum(d["time_s"] for d in channel["dwells"])
        assert total == pytest.approx(float(needle.dwell_times_s.sum()), abs=1e-2)
    out = CSV_EXPORTER.export(plan, tmp_path)
    with out.path("device_insert_list").open(newline="", encoding="utf-8") as fh:
        rows = list(csv.DictReader(fh))
    assert [r["hole"] for r in rows] == ["A1", "B12"] and rows[0]["reserve (N)"] == "0.1"
    assert rows[1]["reach margin (mm)"].startswith("-1.3 (entry tilt")
    page = HTML_EXPORTER.export(plan, tmp_path).path("device_html").read_text(encoding="utf-8")
    assert page.index('id="statement"') < page.index('id="insert-these"') < page.index('id="dwells"')
    assert page.count('id="needle-') == 2
    assert "Tandem (channel 3): 60.0 mm long, bent 30 deg toward anterior" in page
    assert "never pull past 10 N" in page and "<script" not in page and "Doe" not in page
    table = page[page.index('class="insert"'):page.index("</table>", page.index('class="insert"'))]
    assert re.findall(r"<tr><td[^>]*>\d+</td><td>([^<]+)</td>", table) == ["A1", "B12"]
