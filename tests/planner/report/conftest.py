"""Fixtures of the report's tests: one phantom scene shared by the figure tests (building it takes seconds)."""

from __future__ import annotations

import pytest

from reachplan.imaging.phantom import write_phantom
from reachplan.imaging.rtstruct import read_rtstruct
from reachplan.planner.case.scene import Scene, build_scene

#: The phantom's target the figure tests plan around.
PHANTOM_TARGET = "Target_80_030"


@pytest.fixture(scope="session")
def phantom_scene(tmp_path_factory: pytest.TempPathFactory) -> Scene:
    """The pilot phantom's scene with one target (:data:`PHANTOM_TARGET`)."""
    rs = write_phantom(tmp_path_factory.mktemp("phantom")).rtstruct_path
    return build_scene(read_rtstruct(rs, None), [PHANTOM_TARGET])
