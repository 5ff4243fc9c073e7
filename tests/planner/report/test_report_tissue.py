"""The tissue band in a plan and its report: the chosen steered needle's band, the implant's, the 3-D ribbon.

Acceptance (issue 29, item 4): two tissue moduli give a steered needle different worst-case reach over the band, in
the report's table and in plan.json's candidate. Planned on the pilot phantom's structures, one target, without the
reference re-solve and the robustness check (the band applies to whatever path the plan has; keeps the test fast).
"""

from __future__ import annotations

import dataclasses
import html
import re

import numpy as np
import pytest

from reachplan.imaging.phantom import write_phantom
from reachplan.imaging.rtstruct import read_rtstruct
from reachplan.imaging.types import StructureSet
from reachplan.planner.case.config import PlanConfig
from reachplan.planner.case.result import PlanResult, choose_needles
from reachplan.planner.case.scene import Scene, build_scene
from reachplan.planner.case.search import band_shortlist, plan
from reachplan.planner.dose.coverage import StructureMetrics
from reachplan.planner.dose.dwells import DwellSet
from reachplan.planner.errors import PlanInputError
from reachplan.planner.implant.arms import ImplantArm, ImplantPlan
from reachplan.planner.implant.candidates import Channel
from reachplan.planner.implant.tissue import channel_band, with_tissue_bands
from reachplan.planner.report.html import Report, render_html
from reachplan.planner.report.tissue import band_section, tissue_bands
from reachplan.planner.report.view3d import with_tissue_bands as draw_bands
from reachplan.planner.steering.candidates import Target
from reachplan.planner.steering.tissue_band import DEFAULT_SOURCE, assess_band, uniform_profile

TARGET = "Target_80_030"


def _config(modulus_pa: float = 0.19e6) -> PlanConfig:
    return PlanConfig(tissue_modulus_pa=modulus_pa, refine_top=0, robust_top=0)


@pytest.fixture(scope="module")
def structures(tmp_path_factory: pytest.TempPathFactory) -> StructureSet:
    return read_rtstruct(write_phantom(tmp_path_factory.mktemp("phantom")).rtstruct_path)


@pytest.fixture(scope="module")
def scene(structures: StructureSet) -> Scene:
    return build_scene(structures, [TARGET], config=_config())


@pytest.fixture(scope="module")
def plans(scene: Scene) -> dict[float, PlanResult]:
    return {e: plan(scene, _config(e)) for e in (0.19e6, 0.6e6)}


def _report_rows(config: PlanConfig, result: PlanResult) -> dict[str, list[str]]:
    """The rendered report's tissue-band table: needle -> cells."""
    section = band_section(config, tissue_bands(choose_needles(result, steered=True), None))
    assert section is not None
    text = render_html(Report("t", "", (section,)))
    rows = {}
    for row in re.findall(r"<tr>(.*?)</tr>", text, flags=re.S):
        cells = [html.unescape(re.sub(r"<[^>]+>", "", c)).strip() for c in re.findall(r"<td[^>]*>(.*?)</td>", row,
                                                                                        flags=re.S)]
        if cells:
            rows[cells[0]] = cells
    assert "ASSUMED" in html.unescape(text)
    return rows


def test_two_moduli_change_a_steered_needles_worst_case_reach_in_the_report(
        plans: dict[float, PlanResult]) -> None:
    worst = {}
    for e, result in plans.items():
        (needle,) = choose_needles(result, steered=True)
        band = needle.tissue_band
        assert band is not None and band.moduli_pa == pytest.approx((e / 3, e, 3 * e))
        assert band.worst_reach_mm == pytest.approx(max(band.reach_mm))
        assert band.reach_mm[1] == pytest.approx(needle.reach_error_mm)  # the middle path is the planned one
        doc = result.to_json()["targets"][TARGET]["candidates"]  # plan.json and the ranking data
        banded = [c for c in doc if c["tissue_band"] is not None]
        assert [c["hole_id"] for c in banded] == [needle.hole_id] and banded[0]["steered"]
        assert banded[0]["tissue_band"]["worst_reach_mm"] == pytest.approx(band.worst_reach_mm, abs=1e-3)
        assert banded[0]["tissue_band"]["source"] == DEFAULT_SOURCE
        row = _report_rows(result.config, result)[f"{needle.hole_id} → {TARGET}"]
        assert float(row[3]) == pytest.approx(band.worst_reach_mm, abs=0.051)
        worst[e] = (needle.hole_id, band.worst_reach_mm, row[3])
    (_, a, cell_a), (_, b, cell_b) = worst.values()
    assert cell_a != cell_b and abs(a - b) > 0.02, worst


def test_the_3d_view_draws_each_band_as_a_ribbon_between_its_softest_and_stiffest_path(
        plans: dict[float, PlanResult]) -> None:
    (needle,) = choose_needles(plans[0.19e6], steered=True)
    band = needle.tissue_band
    assert band is not None
    base = {"data": [{"type": "scatter3d", "meta": "needle"}], "layout": {}}
    fig = draw_bands(base, [("Ch", band), ("failed", dataclasses.replace(band, paths_mm=()))])
    assert fig["data"][0] == base["data"][0] and len(base["data"]) == 1  # not changed in place
    ribbon, edges = fig["data"][1:]
    assert ribbon["type"] == "mesh3d" and ribbon["meta"] == edges["meta"] == "tissue band"
    assert ribbon["legendgroup"] == edges["legendgroup"] and ribbon["showlegend"] and edges["showlegend"]
    n = len(band.paths_mm[0])
    assert len(ribbon["x"]) == 3 * n and len(ribbon["i"]) == 2 * 2 * (n - 1)  # two triangles a quad
    assert max(ribbon["i"] + ribbon["j"] + ribbon["k"]) == 3 * n - 1
    assert len(edges["x"]) == 2 * n + 1 and edges["x"][n] is None  # softest, a gap, stiffest
    assert edges["x"][n - 1] == pytest.approx(band.paths_mm[0][-1][0], abs=0.05)
    assert edges["z"][-1] == pytest.approx(band.paths_mm[-1][-1][2], abs=0.05)
    assert "0.0633 / 0.57 MPa" in edges["name"]


def test_an_implant_needle_is_banded_about_its_own_tip_once_for_both_arms(
        scene: Scene, plans: dict[float, PlanResult]) -> None:
    config = _config()
    (needle,) = choose_needles(plans[0.19e6], steered=True)
    assert needle.schedule is not None
    channel = Channel(needle.hole_id, "steered", needle.path_mm, needle.path_mm[-3:], needle.hole_distance_mm,
                      needle.insertion_depth_mm, design=needle.design_name, schedule=needle.schedule)
    band = channel_band(channel, scene, config)
    tip = needle.path_mm[-1]
    aim = Target("tip", (float(tip[0]), float(tip[1]), float(tip[2])))
    expected = assess_band(dataclasses.replace(needle, reach_error_mm=0.0), aim, scene.organs,
                           scene.patient_from_template, 0.915, uniform_profile(config.tissue_modulus_pa))
    assert band.reach_mm[1] == 0.0 and band.reach_mm == pytest.approx(expected.reach_mm)
    assert band.worst_clearance_mm == pytest.approx(expected.worst_clearance_mm, abs=1e-6)
    metrics = StructureMetrics("HR-CTV", 1.0, *(0.0,) * 8, 10.0)
    empty = DwellSet(np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0))
    straight = dataclasses.replace(channel, kind="straight", schedule=None, design="")
    arms = tuple(ImplantArm(name, 1, (), ImplantPlan(chans, empty, metrics, 0.0, (), True), 0.0)
                 for name, chans in (("straight", (straight,)), ("steered", (channel, straight))))
    out = with_tissue_bands(arms, scene, config)
    assert out[0] is arms[0]  # no steered needle: unchanged
    banded = out[1].plan.channels  # type: ignore[union-attr]
    assert banded[0].tissue_band is not None and banded[1].tissue_band is None
    assert banded[0].tissue_band.reach_mm == pytest.approx(band.reach_mm)
    unplanned = dataclasses.replace(channel, design="no-such-design")
    assert channel_band(unplanned, scene, config).worst_case.startswith("not computed")


def test_an_organ_modulus_for_a_missing_roi_is_a_typed_error(structures: StructureSet) -> None:
    with pytest.raises(PlanInputError, match="--organ-modulus names 'Parametrium'"):
        build_scene(structures, [TARGET], config=PlanConfig(tissue_moduli_pa=(("Parametrium", 0.3e6),)))


def test_an_organ_modulus_sets_the_band_where_the_needle_ends(scene: Scene, plans: dict[float, PlanResult]) -> None:
    """The target ROI given 0.5 MPa: the band's moduli at the tip are its, scaled; the gel elsewhere."""
    config = dataclasses.replace(_config(), tissue_moduli_pa=((TARGET, 0.5e6),))
    out = band_shortlist(scene, list(plans[0.19e6].candidates), config)
    (banded,) = [c for c in out if c.tissue_band is not None]
    assert banded.tissue_band is not None
    assert banded.tissue_band.moduli_pa == pytest.approx((0.5e6 / 3, 0.5e6, 1.5e6))
    gel = choose_needles(plans[0.19e6], steered=True)[0].tissue_band
    assert gel is not None and banded.tissue_band.reach_mm != pytest.approx(gel.reach_mm, abs=1e-4)
