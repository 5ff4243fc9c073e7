"""Organ distance fields: error bound against closed forms, and the screen leaves the phantom ranking unchanged."""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np
import pytest
import trimesh

from reachplan.planner.geometry.collision import check_path, make_organ, path_clearance, with_distance_field
from reachplan.planner.geometry.distance_field import DistanceField


def test_field_within_its_error_bound_of_a_sphere() -> None:
    radius = 20.0
    mesh = trimesh.creation.icosphere(subdivisions=4, radius=radius)
    f = DistanceField.from_mesh(mesh, pitch_mm=1.0, confirm_within_mm=6.0)
    rng = np.random.default_rng(3)
    u = rng.normal(size=(50_000, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    r = rng.uniform(radius, radius + f.reach_mm - 1.0, len(u))
    got = f.sample(u * r[:, None])
    exact = r - radius  # the icosphere's facets lie within 0.05 mm of the sphere at this subdivision
    assert np.max(np.abs(got - exact)) <= f.error_mm + 0.05
    assert f.sample(np.array([[0.0, 0.0, radius + f.reach_mm + 5.0]]))[0] == pytest.approx(f.reach_mm)


def test_path_lower_bound_never_above_fcl() -> None:
    mesh = trimesh.creation.box((30.0, 20.0, 40.0))
    organ = with_distance_field(make_organ("Box", mesh), confirm_within_mm=3.0)
    assert organ.field is not None
    rng = np.random.default_rng(5)
    for _ in range(40):
        a, b = rng.uniform(-45, 45, (2, 3))
        path = np.linspace(a, b, 7)
        est, lower, upper = organ.field.path_clearance(path, 1.0)
        exact = path_clearance(path, 1.0, organ)
        assert lower <= exact.clearance_mm + 1e-9
        assert exact.collides or exact.clearance_mm <= upper + 1e-9
        if exact.clearance_mm + 1.0 < organ.field.reach_mm - organ.field.error_mm and not exact.collides:
            assert abs(est - exact.clearance_mm) <= organ.field.error_mm + 0.5 * organ.field.pitch_mm
        got = check_path(path, 1.0, (organ,))[0]  # screened or exact: never a missed collision
        assert got.collides == exact.collides
        if got.clearance_mm <= organ.field.confirm_within_mm:
            assert got.clearance_mm == exact.clearance_mm


def test_exact_clearance_measures_only_the_segments_that_can_matter_and_is_unchanged() -> None:
    """Segment pruning by the field: the same clearance, collision and first contact as every capsule measured."""
    import reachplan.planner.geometry.collision as collision

    mesh = trimesh.creation.icosphere(subdivisions=4, radius=15.0)
    plain = make_organ("Ball", mesh)
    screened = with_distance_field(plain)
    assert screened.field is not None
    rng = np.random.default_rng(11)
    made: list[int] = []
    capsule = collision._capsule
    pruned_any = False
    for n in range(60):
        a, b = rng.uniform(-40, 40, (2, 3))
        bend = rng.normal(scale=8.0, size=3)
        t = np.linspace(0.0, 1.0, 25)[:, None]
        path = a + t * (b - a) + 4 * t * (1 - t) * bend  # a curved needle, 24 segments
        if n % 5 == 0:
            path = np.vstack([path[:3], path[2:3], path[3:]])  # a repeated point: a zero-length segment
        exact = path_clearance(path, 0.9, plain)
        collision._capsule = lambda *args: (made.append(1), capsule(*args))[1]
        try:
            got = path_clearance(path, 0.9, screened)
        finally:
            collision._capsule = capsule
        assert got.collides == exact.collides
        assert got.clearance_mm == pytest.approx(exact.clearance_mm, abs=1e-12)
        assert got.contact_s_mm == exact.contact_s_mm
        pruned_any |= len(made) < 24
        made.clear()
    assert pruned_any  # the field spared FCL queries


def test_phantom_plan_same_with_and_without_screen(tmp_path: Path) -> None:
    from reachplan.imaging.phantom import write_phantom
    from reachplan.imaging.rtstruct import read_rtstruct
    from reachplan.planner.case.config import PlanConfig
    from reachplan.planner.case.scene import build_scene
    from reachplan.planner.case.search import plan

    files = write_phantom(tmp_path / "phantom")
    structures = read_rtstruct(files.rtstruct_path, None)
    cfg = PlanConfig(refine_top=0, robust_top=0)
    scene = build_scene(structures, config=cfg)
    assert all(o.field is not None for o in scene.organs)
    bare = dataclasses.replace(scene, organs=tuple(dataclasses.replace(o, field=None) for o in scene.organs))
    exact = plan(bare, cfg)
    # an infinite band (FCL only for the organs that can be the nearest) leaves every number of the plan as FCL
    # alone gives it (ranking, clearances, Pareto flags)
    exact_screen = dataclasses.replace(scene, organs=tuple(with_distance_field(o) for o in bare.organs))
    assert plan(exact_screen, cfg).to_json() == exact.to_json()
    # the planner's banded screen (estimates beyond the clearance cap + 1 mm) keeps the ranking and every
    # clearance within the cap
    cap = cfg.weights.clearance_cap_mm
    banded = plan(scene, cfg)
    assert banded.ranking.keys() == exact.ranking.keys()
    for target, ranked in exact.ranking.items():
        other = banded.ranking[target]
        assert [(c.hole_id, c.steered, c.reason) for c in other] == [(c.hole_id, c.steered, c.reason) for c in ranked]
        for a, b in zip(ranked, other, strict=True):
            if math.isfinite(a.clearance_mm) and a.clearance_mm <= cap:
                assert b.clearance_mm == a.clearance_mm
            else:
                assert not (math.isfinite(b.clearance_mm) and b.clearance_mm <= cap)


def test_organ_containment_by_ray_parity_agrees_with_trimesh_on_a_torus() -> None:
    # a torus: points in its hole are outside, though inside its bounding box
    mesh = trimesh.creation.torus(major_radius=30.0, minor_radius=10.0, major_sections=48, minor_sections=24)
    organ = make_organ("Bowel", mesh)
    rng = np.random.default_rng(7)
    pts = rng.uniform(-45.0, 45.0, (600, 3)) * np.array([1.0, 1.0, 0.4])
    got = np.array([organ.contains(p) for p in pts])
    assert 50 < got.sum() < 550
    assert np.array_equal(got, mesh.contains(pts))
    assert not organ.contains(np.zeros(3)) and organ.contains(np.array([30.0, 0.0, 0.0]))


@pytest.mark.parametrize(("shape", "pitch_mm"), [((30, 41, 52), 1.0), ((23, 17, 35), 1.85), ((6, 1, 9), 1.19)])
def test_compiled_distance_transform_equals_scipys_exact_edt(shape: tuple[int, int, int], pitch_mm: float) -> None:
    from scipy import ndimage

    from reachplan.planner.geometry.distance_field import _edt

    seeds = np.random.default_rng(11).random(shape) < 0.003
    seeds[-1, 0, -1] = True
    got = np.empty(shape)
    _edt(seeds, np.ones(3), pitch_mm, 15.0, got)  # as a field builds it: whole voxels, scaled
    want = np.minimum(ndimage.distance_transform_edt(~seeds, sampling=pitch_mm), 15.0).astype(np.float32)
    assert np.array_equal(got.astype(np.float32), want) and got.max() > 5.0


@pytest.mark.parametrize("spacing_mm", [(2.5, 0.98, 0.98), (1.0, 3.0, 0.5)])
def test_anisotropic_distance_transform_equals_scipys(spacing_mm: tuple[float, float, float]) -> None:
    """The implant's organ map: a CT grid's voxels (slice thickness apart from the pixel), no clipping."""
    from scipy import ndimage

    from reachplan.planner.geometry.distance_field import distance_transform

    seeds = np.random.default_rng(4).random((19, 47, 33)) < 0.002
    seeds[0, 0, 0] = True
    got = distance_transform(seeds, spacing_mm)
    want = ndimage.distance_transform_edt(~seeds, sampling=spacing_mm)
    np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-12)
    assert np.all(np.isinf(distance_transform(np.zeros((3, 4, 5), bool), spacing_mm)))
