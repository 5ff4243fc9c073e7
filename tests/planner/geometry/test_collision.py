"""FCL clearance and collision against independent computations (trimesh.proximity, analytic spheres)."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from reachplan.planner.errors import PlanInputError
from reachplan.planner.geometry.collision import check_path, make_organ, path_clearance


@pytest.fixture(scope="module")
def bladder() -> trimesh.Trimesh:
    m = trimesh.creation.icosphere(subdivisions=4, radius=1.0)
    m.apply_scale([40.0, 20.0, 25.0])
    m.apply_translation([0.0, -50.0, 105.0])
    return m


def test_needle_through_bladder_collides_and_clear_one_does_not(bladder: trimesh.Trimesh) -> None:
    organ = make_organ("Bladder", bladder)
    through = np.array([[0.0, -50.0, 0.0], [0.0, -50.0, 150.0]])
    clear = np.array([[0.0, 10.0, 0.0], [0.0, 10.0, 150.0]])
    hit = check_path(through, 0.915, (organ,))[0]
    miss = check_path(clear, 0.915, (organ,))[0]
    assert hit.collides and hit.organ == "Bladder" and hit.clearance_mm == 0.0
    # first contact: the bottom of the ellipsoid at z = 80 (minus the capsule's cap, within 1 mm sampling)
    assert hit.contact_s_mm is not None and 78.0 <= hit.contact_s_mm <= 81.0
    assert not miss.collides and miss.contact_s_mm is None
    # the ellipsoid's posterior pole is at y = -30; the needle axis at y = 10, radius 0.915
    assert miss.clearance_mm == pytest.approx(40.0 - 0.915, abs=0.1)


def test_needle_wholly_inside_an_organ_collides(bladder: trimesh.Trimesh) -> None:
    organ = make_organ("Bladder", bladder)
    inside = np.array([[0.0, -50.0, 100.0], [0.0, -50.0, 110.0]])
    assert path_clearance(inside, 0.915, organ).collides


def test_clearance_matches_trimesh_proximity_on_sampled_points(bladder: trimesh.Trimesh) -> None:
    organ = make_organ("Bladder", bladder)
    rng = np.random.default_rng(7)
    pts = rng.uniform([-70, -90, 60], [70, 0, 150], size=(300, 3))
    outside = pts[~bladder.contains(pts)][:60]
    radius = 0.5
    _, dist, _ = trimesh.proximity.closest_point(bladder, outside)
    ours = np.array([path_clearance(p[None, :], radius, organ).clearance_mm for p in outside])
    far = dist > radius + 0.2
    assert far.sum() > 40
    np.testing.assert_allclose(ours[far], dist[far] - radius, atol=0.1)


def test_segment_clearance_is_minimum_over_its_points(bladder: trimesh.Trimesh) -> None:
    organ = make_organ("Bladder", bladder)
    a, b = np.array([45.0, -20.0, 60.0]), np.array([20.0, -10.0, 140.0])
    samples = a + np.outer(np.linspace(0, 1, 2001), b - a)
    _, dist, _ = trimesh.proximity.closest_point(bladder, samples)
    ours = path_clearance(np.stack([a, b]), 1.0, organ).clearance_mm
    assert ours == pytest.approx(dist.min() - 1.0, abs=0.1)


@pytest.mark.parametrize(
    "path",
    [np.zeros((0, 3)), np.array([[0.0, 0.0]]), np.array([[0.0, np.nan, 0.0], [1.0, 1.0, 1.0]])],
)
def test_bad_paths_are_typed_errors(bladder: trimesh.Trimesh, path: np.ndarray) -> None:
    with pytest.raises(PlanInputError):
        check_path(path, 1.0, (make_organ("Bladder", bladder),))


def test_open_mesh_is_rejected() -> None:
    m = trimesh.creation.icosphere()
    m.update_faces(np.arange(len(m.faces)) > 0)
    with pytest.raises(PlanInputError, match="watertight"):
        make_organ("Rectum", m)

