"""The slice along a needle (issue 29, item 2): its geometry against closed forms, its clearance against FCL."""

from __future__ import annotations

from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest
import trimesh

from reachplan.planner.case.scene import Scene
from reachplan.planner.geometry.collision import path_clearance
from reachplan.planner.report import reformat
from reachplan.planner.report.legibility import small_texts, text_overlaps

RADIUS_MM = 0.65


def _sphere(centre: tuple[float, float, float], radius_mm: float) -> trimesh.Trimesh:
    return trimesh.creation.icosphere(subdivisions=4, radius=radius_mm).apply_translation(centre)


def _arc(rho_mm: float, length_mm: float, n: int = 200) -> np.ndarray:
    """A needle bent in the y-z plane: a circular arc of radius ``rho_mm`` from the origin, leaving along +z."""
    phi = np.linspace(0.0, length_mm / rho_mm, n)
    return np.column_stack([np.zeros(n), rho_mm * (1 - np.cos(phi)), rho_mm * np.sin(phi)])


def test_closest_approach_of_a_straight_needle_to_a_sphere() -> None:
    path = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 100.0]])
    near, far = _sphere((0.0, 20.0, 60.0), 10.0), _sphere((50.0, 0.0, 50.0), 10.0)
    c = reformat.closest_approach(path, {"near": near, "far": far}, RADIUS_MM)
    assert c is not None and c.organ == "near"
    assert c.clearance_mm == pytest.approx(20.0 - 10.0 - RADIUS_MM, abs=0.02)  # a polyhedron inside the sphere
    assert c.s_mm == pytest.approx(60.0, abs=reformat.SEARCH_STEP_MM)
    assert np.allclose(c.organ_point_mm, [0.0, 10.0, 60.0], atol=0.1)


@pytest.mark.parametrize("path", [np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 100.0]]), _arc(150.0, 100.0)],
                         ids=["straight", "arc"])
def test_the_sections_lie_on_the_organ_and_map_back_to_it(path: np.ndarray) -> None:
    """Every outline point (s, t) maps back to p(s) + t e(s) on the sphere's surface, in both panels."""
    centre = reformat.resample(path, np.array([60.0]))[0] + np.array([0.0, 5.0, 0.0])
    sphere = _sphere(tuple(centre), 8.0)
    length = reformat.arc_length(path)[-1]
    s = np.unique(np.append(np.arange(0.0, length, reformat.STEP_MM), length))
    e1 = reformat.lateral_directions(path, s, np.array([0.0, 1.0, 0.0]))
    e2 = np.cross(reformat._tangents(path, s), e1)
    for e, cut in zip((e1, e2), reformat.curved_section(sphere, path, s, (e1, e2)), strict=True):
        pts = cut[np.isfinite(cut[:, 0])]
        assert len(pts) > 50
        back = reformat.resample(path, pts[:, 0]) + pts[:, 1:2] * np.array(
            [np.interp(pts[:, 0], s, e[:, i]) for i in range(3)]).T
        r = np.linalg.norm(back - centre, axis=1)
        assert np.allclose(r, 8.0, atol=0.1), (r.min(), r.max())
    if len(path) == 2:  # straight: the panel turned toward the sphere is a plane through its centre (closed form)
        (cut,) = reformat.curved_section(sphere, path, s, (e1,))
        assert np.nanmax(cut[:, 1]) == pytest.approx(5.0 + 8.0, abs=0.15)
        assert np.nanmin(cut[:, 0]) == pytest.approx(60.0 - 8.0, abs=0.15)


def test_clearance_annotated_is_fcls_and_the_figure_is_legible(solids_scene: Scene) -> None:
    scene = solids_scene
    hole = next(h for h in scene.template.holes if h.hole_id == "Cd")
    m = scene.patient_from_template
    base = m[:3, :3] @ np.array([*hole.xy_mm, 0.0]) + m[:3, 3]
    path = base + np.linspace(0.0, 85.0, 30)[:, None] * m[:3, 2]
    dwells = path[-1] - np.arange(6)[:, None] * 2.5 * m[:3, 2]
    needle: Any = SimpleNamespace(hole_id="Cd", path_mm=path, dwell_positions_mm=dwells,
                                  dwell_times_s=np.array([5.0, 9.0, 12.0, 12.0, 9.0, 5.0]), schedule=None)
    fig, closest = reformat.needle_reformat_figure(scene, needle, RADIUS_MM)
    # FCL on every organ the distance fields cannot rule out (their bounds are proven, so none is missed)
    bounds = {o.name: o.field.path_clearance(path, RADIUS_MM)[1:] if o.field is not None else (0.0, np.inf)
              for o in scene.organs}
    cutoff = min(hi for _, hi in bounds.values())
    fcl = min((path_clearance(path, RADIUS_MM, o) for o in scene.organs if bounds[o.name][0] <= cutoff),
              key=lambda c: c.clearance_mm)
    assert closest is not None and closest.organ == fcl.organ
    assert closest.clearance_mm == pytest.approx(fcl.clearance_mm, abs=0.05)  # trimesh point-to-mesh vs FCL
    top = next(a for a in fig.axes if a.get_gid() == "toward-organ")
    (arrow,) = [t for t in top.texts if t.get_gid() == "clearance"]
    (x0, y0), (x1, y1) = arrow.xyann, arrow.xy
    assert x0 == pytest.approx(closest.s_mm) and y0 == 0.0
    # centreline to organ at its true length in the panel (across the needle, or slanting ahead at the tip)
    assert np.hypot(x1 - x0, y1) == pytest.approx(closest.clearance_mm + RADIUS_MM, abs=1e-6)
    assert x1 == pytest.approx(x0, abs=1e-6) or closest.s_mm == pytest.approx(reformat.arc_length(path)[-1])
    bars = next(a for a in fig.axes if a.get_gid() == "dwell-times").patches
    assert sorted(b.get_height() for b in bars) == sorted(needle.dwell_times_s)
    assert {str(ln.get_gid()) for a in fig.axes for ln in a.lines} >= {"needle:Cd", f"organ:{closest.organ}"}
    assert small_texts(fig) == [] and text_overlaps(fig) == []
