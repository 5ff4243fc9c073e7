"""Template layouts and their pose in the patient."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from reachplan.planner.errors import PlanInputError
from reachplan.planner.geometry.template import check_rigid, hole_frames
from reachplan.planner.lookup import load_template
from reachplan.plugins.templates import TemplateFileError, load_template_csv


def test_builtin_layout_has_the_published_rings() -> None:
    t = load_template("needlefinder_syed_63")
    assert len(t.holes) == 63 and len(t.needle_holes) == 62
    radii = np.array(sorted(round(h.distance_mm) for h in t.needle_holes))
    # rings of the reference: 6 at ~10.6 mm, 12 at 20, 18 at 30, 10 at 40, 8 at 50, 8 corner holes at 47-49
    assert (radii == 11).sum() == 6 and (radii == 20).sum() == 12 and (radii == 30).sum() == 18
    assert (radii == 40).sum() == 10 and (radii == 50).sum() == 8 and ((radii >= 47) & (radii <= 49)).sum() == 8


def test_hole_frames_follow_the_pose() -> None:
    t = load_template("needlefinder_syed_63")
    pose = np.eye(4)
    pose[:3, :3] = [[0, -1, 0], [1, 0, 0], [0, 0, 1]]  # 90 degrees about z
    pose[:3, 3] = [5.0, -3.0, 10.0]
    entry, direction = hole_frames(t, pose)
    xy = np.array([h.xy_mm for h in t.needle_holes])
    np.testing.assert_allclose(entry, np.column_stack([-xy[:, 1] + 5.0, xy[:, 0] - 3.0, np.full(len(xy), 10.0)]))
    np.testing.assert_allclose(direction, np.tile([0.0, 0.0, 1.0], (len(xy), 1)))


def test_bad_pose_and_layout_are_typed_errors(tmp_path: Path) -> None:
    with pytest.raises(PlanInputError, match="rigid"):
        check_rigid(np.diag([2.0, 1.0, 1.0, 1.0]))
    bad = tmp_path / "t.csv"
    bad.write_text("hole_id,x_mm\nA,1\n")
    with pytest.raises(TemplateFileError, match="missing column"):
        load_template_csv(bad)


def test_template_pose_from_the_phantom_obturator_matches_the_phantom(tmp_path) -> None:  # type: ignore[no-untyped-def]
    from reachplan.imaging.phantom import phantom_spec, write_phantom
    from reachplan.imaging.rtstruct import read_rtstruct
    from reachplan.planner.geometry.template import pose_from_obturator

    ss = read_rtstruct(write_phantom(tmp_path / "p").rtstruct_path)
    np.testing.assert_allclose(pose_from_obturator(ss.get("Obturator")), phantom_spec().patient_from_template,
                               atol=0.05)


def _check_frame(m: np.ndarray, origin: np.ndarray, axis: np.ndarray) -> None:
    r = m[:3, :3]
    np.testing.assert_allclose(r.T @ r, np.eye(3), atol=1e-12)
    assert np.linalg.det(r) == pytest.approx(1.0)
    np.testing.assert_allclose(m[:3, 2], axis / np.linalg.norm(axis), atol=1e-12)
    np.testing.assert_allclose(m[:3, 3], origin, atol=1e-12)


def test_pose_from_axis_is_rigid_and_keeps_the_patients_left_on_template_x() -> None:
    from reachplan.planner.geometry.template import pose_from_axis

    np.testing.assert_allclose(pose_from_axis((0, 0, 0), (0, 0, 5)), np.eye(4), atol=1e-12)
    rng = np.random.default_rng(3)
    for _ in range(50):
        origin, axis = rng.normal(size=3) * 50, rng.normal(size=3)
        m = pose_from_axis(origin, axis)
        _check_frame(m, origin, axis)
        z = axis / np.linalg.norm(axis)
        if abs(z[0]) < np.cos(np.radians(10)):
            # template +x is the patient's left projected on the template plane
            left = np.array([1.0, 0, 0]) - z[0] * z
            np.testing.assert_allclose(m[:3, 0], left / np.linalg.norm(left), atol=1e-12)
    # an axis along left-right: template +y is the patient's posterior
    m = pose_from_axis((1, 2, 3), (-1, 0, 0))
    _check_frame(m, np.array([1.0, 2, 3]), np.array([-1.0, 0, 0]))
    np.testing.assert_allclose(m[:3, 1], [0, 1, 0], atol=1e-12)
    for bad in [((0, 0, 0), (0, 0, 0)), ((0, np.nan, 0), (0, 0, 1)), ((0, 0), (0, 0, 1))]:
        with pytest.raises(PlanInputError):
            pose_from_axis(*bad)


def test_pose_from_a_straight_obturator_channel_and_a_bent_tandem() -> None:
    from reachplan.planner.geometry.template import pose_from_channel

    d = np.array([0.0, -0.4, 1.0]) / np.linalg.norm([0.0, -0.4, 1.0])  # insertion direction
    tip = np.array([3.0, -20.0, 40.0])
    obturator = tip - np.outer(np.linspace(0, 120, 25), d)  # tip first
    m = pose_from_channel(obturator, np.zeros((0, 3)), tandem=False, depth_mm=60.0)
    _check_frame(m, tip - 60.0 * d, d)
    # a tandem: straight through the vagina and cervix along d up to the os, then bent 30 degrees forward in
    # the uterus; loaded from the os (last dwell) to the tip
    os_ = np.array([0.0, 10.0, -20.0])
    bend = np.array([0.0, -np.sin(np.radians(30)), np.cos(np.radians(30))])
    uterine = os_ + np.outer(np.linspace(60, 0, 13), bend)  # tip ... os
    vaginal = os_ - np.outer(np.linspace(5, 150, 30), d)
    path = np.vstack([uterine, vaginal])
    dwells = uterine[::2]
    m = pose_from_channel(path, dwells, tandem=True, depth_mm=55.0)
    _check_frame(m, os_ - 55.0 * d, d)
    with pytest.raises(PlanInputError, match="shorter than 1 mm"):
        pose_from_channel(np.zeros((3, 3)), dwells, tandem=True)
