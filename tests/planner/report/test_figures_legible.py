"""Legible report figures, read from the figures' own data: font sizes, overlapping labels, colours, windowing.

Issue 29, item 6: labels of at least 9 pt at display size, a distinct organ palette, hole labels never under the
orientation letters, a colour bar and organ names on the workspace figure, MR windowing from the image itself.
"""

from __future__ import annotations

import dataclasses
import itertools
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest
from matplotlib.colors import to_rgb
from skimage.color import deltaE_ciede2000, rgb2lab

from reachplan.imaging.types import Grid, Volume
from reachplan.planner.case.config import PlanConfig
from reachplan.planner.case.scene import Scene
from reachplan.planner.report import charts, figures
from reachplan.planner.report.legibility import small_texts, text_overlaps
from reachplan.planner.report.workspace import workspace_map_figure

TARGET = "Target_solids"  # the target of the solids_scene fixture (conftest.py)


@pytest.fixture(scope="module")
def scene(solids_scene: Scene) -> Scene:
    return solids_scene


def _needle(scene: Scene, hole_id: str, steered: bool) -> Any:
    """A candidate from a hole straight along the template axis to the target's depth (a stand-in for a plan's)."""
    hole = next(h for h in scene.template.holes if h.hole_id == hole_id)
    m = scene.patient_from_template
    base = m[:3, :3] @ np.array([*hole.xy_mm, 0.0]) + m[:3, 3]
    depth = float((np.asarray(scene.targets[0].position_mm) - base) @ m[:3, 2])
    path = base + np.linspace(0.0, depth, 20)[:, None] * m[:3, 2]
    return SimpleNamespace(target=TARGET, hole_id=hole_id, path_mm=path, steered=steered)


def _legible(fig: object) -> None:
    assert small_texts(fig) == []  # type: ignore[arg-type]
    assert text_overlaps(fig) == []  # type: ignore[arg-type]
    width_px = fig.get_size_inches()[0] * figures.DISPLAY_DPI  # type: ignore[attr-defined]
    assert width_px <= figures.MAX_DISPLAY_WIDTH_PX  # shown at its own size: a point is a point on the screen


def test_the_organ_palette_is_distinct_from_itself_and_from_the_needles() -> None:
    colours = {**figures.ORGAN_COLOURS, "target": figures.TARGET_COLOUR, "straight": figures.STRAIGHT_COLOUR,
               "steered": figures.STEERED_COLOUR}
    lab = {n: rgb2lab(np.array([[to_rgb(c)]]))[0, 0] for n, c in colours.items()}
    worst = min((float(deltaE_ciede2000(lab[a], lab[b])), a, b) for a, b in itertools.combinations(colours, 2))
    assert worst[0] >= 20.0, worst  # CIEDE2000: 20 is a plainly different colour, 2 just noticeable
    assert figures.organ_colour("rectum") == figures.ORGAN_COLOURS["Rectum"]
    assert figures.organ_colour("GTV_res") == figures.ORGAN_COLOURS["GTV"]
    assert figures.organ_colour("Target_x") == figures.TARGET_COLOUR
    assert figures.organ_colour("Femur_L") == figures.OTHER_COLOUR


def test_the_template_map_fills_exactly_the_implants_holes_and_no_label_hides_another(scene: Scene) -> None:
    holes = {h.hole_id: h.xy_mm for h in scene.template.holes}
    # holes at the four edges, next to the orientation letters (Ce under A before), one steered
    implant = [("Ce", False), ("Cn", True), ("Ea", False), ("Ed", True)]
    fig = figures.template_map_figure(scene, implant)
    ax = fig.axes[0]
    for kind, steered in (("straight", False), ("steered", True)):
        (marks,) = [c for c in ax.collections if c.get_gid() == f"implant:{kind}"]
        want = sorted(tuple(holes[h]) for h, s in implant if s == steered)
        assert sorted(map(tuple, np.round(marks.get_offsets(), 6))) == sorted(map(tuple, np.round(want, 6)))
    bold = {t.get_text() for t in ax.texts if str(t.get_gid()).startswith("hole:") and t.get_fontweight() == "bold"}
    assert bold == {h for h, _ in implant}
    assert not [c for c in ax.collections if str(c.get_gid()).startswith("implant:") and c.get_gid() not in
                ("implant:straight", "implant:steered")]
    _legible(fig)


def test_slices_overview_and_workspace_are_legible(scene: Scene) -> None:
    straight, steered = _needle(scene, "Ab", False), _needle(scene, "Ac", True)
    _legible(figures.slice_figure(scene, TARGET, straight, steered))
    _legible(figures.overview_figure(scene, [straight, steered]))
    ws = workspace_map_figure(scene, PlanConfig())
    _legible(ws)
    (bar,) = [a for a in ws.axes if a.get_label() == "<colorbar>"]
    assert "distance from the template centre" in bar.get_ylabel()
    named = {t.get_text() for t in ws.legends[0].get_texts()}
    outlined = {str(ln.get_gid()).removeprefix("organ:") for ln in ws.axes[0].lines
                if str(ln.get_gid()).startswith("organ:")}
    assert outlined - {t.name for t in scene.targets} <= named and "Bladder" in named


def test_a_needle_is_drawn_solid_only_near_the_slice(scene: Scene) -> None:
    """A needle off the slice is drawn faint: a needle in front of an organ no longer seems to cross it."""
    needle = _needle(scene, "Ab", False)
    fig = figures.slice_figure(scene, TARGET, needle, None)
    for ax in fig.axes:
        (solid,) = [ln for ln in ax.lines if ln.get_gid() == "needle:Ab"]
        normal = {"axial": 2, "sagittal": 0, "coronal": 1}[ax.get_gid()]
        value = np.asarray(scene.targets[0].position_mm)[normal]
        far = np.abs(needle.path_mm[:, normal] - value) > figures.IN_PLANE_MM
        assert np.all(np.isnan(solid.get_xdata()[far])) and np.all(np.isfinite(solid.get_xdata()[~far]))


def _mr(scene: Scene) -> Volume:
    """An MR-like volume: organ signal near 800, a bright rim at 3000, background 0 (arbitrary units)."""
    rng = np.random.default_rng(0)
    shape = (40, 80, 80)
    a = rng.normal(800.0, 60.0, shape).astype(np.float32)
    a[:, :4, :] = 3000.0
    a[:2] = 0.0
    affine = np.diag([3.0, 3.0, 5.0, 1.0])
    affine[:3, 3] = (-120.0, -120.0, -50.0)
    return Volume(a, Grid(shape, affine), "MR", "1.2.3", "1.2.4")


def test_mr_is_windowed_from_its_own_intensities_and_ct_in_hounsfield_units(scene: Scene) -> None:
    mr = _mr(scene)
    lo, hi = figures.display_window(mr)
    assert lo == pytest.approx(np.percentile(mr.array, 1.0), abs=50.0)
    assert hi == pytest.approx(np.percentile(mr.array, 99.5), abs=50.0)
    fig = figures.overview_figure(scene, [], mr)
    (image,) = [im for im in fig.axes[0].images if im.get_gid() == "image"]
    assert image.get_clim() == (lo, hi)
    organ = mr.array[2:, 4:, :]
    assert np.mean(organ >= hi) < 0.01  # the organs are not saturated (a CT window of 300 would whiten them all)
    ct = dataclasses.replace(mr, modality="CT")
    assert figures.display_window(ct) == figures.CT_WINDOW_HU


def test_charts_are_legible() -> None:
    from reachplan.planner.dose.aims import Aims
    from reachplan.planner.dose.coverage import cumulative_dvh

    rng = np.random.default_rng(1)
    dvhs = (("HR-CTV", cumulative_dvh(rng.gamma(9.0, 1.0, 2000), 0.01)),
            *((o, cumulative_dvh(rng.exponential(1.5, 2000), 0.03)) for o in ("Bladder", "Rectum", "Sigmoid")))
    _legible(charts.dvh_aims_figure(dvhs, Aims()))
    points = tuple(SimpleNamespace(n_needles=n, hrctv_d90_eqd2_gy=80.0 + 2 * n, aims_met=n > 2) for n in range(5))
    plan = SimpleNamespace(dvhs=dvhs, n_needles=3, target=SimpleNamespace(d90_eqd2_gy=86.0))
    arms = [SimpleNamespace(name=name, plan=plan, pareto=points) for name in ("straight", "steered")]
    _legible(charts.implant_dvh_figure(arms, Aims()))
    _legible(charts.pareto_figure(arms, Aims().target_d90_eqd2_gy))
