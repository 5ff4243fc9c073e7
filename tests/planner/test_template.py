"""Template layouts and their pose in the patient."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from reachplan.planner.errors import PlanInputError
from reachplan.planner.geometry.template import check_rigid, hole_frames
from reachplan.planner.pipeline import load_template
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
