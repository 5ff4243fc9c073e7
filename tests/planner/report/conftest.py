"""Fixtures of the report's figure tests: a small pelvis of analytic solids, built in a fraction of a second.

Bladder anterior, rectum posterior, pelvic bone on both sides, an HR-CTV around the cervix and one target point,
in front of the default template (template frame = patient frame, needles along +z); LPS mm.
"""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from reachplan.planner.case.config import PlanConfig
from reachplan.planner.case.scene import Scene
from reachplan.planner.geometry.collision import make_organ, with_distance_field
from reachplan.planner.lookup import load_template
from reachplan.planner.steering.candidates import Target

#: The solids' target point (mm, LPS) and its name.
SOLIDS_TARGET = ("Target_solids", (30.0, -10.0, 80.0))


def _solid(kind: str, size: tuple[float, float, float], centre: tuple[float, float, float]) -> trimesh.Trimesh:
    if kind == "box":
        return trimesh.creation.box(extents=size).apply_translation(centre)
    mesh = trimesh.creation.icosphere(subdivisions=3, radius=1.0)
    mesh.apply_scale(size)
    return mesh.apply_translation(centre)


@pytest.fixture(scope="session")
def solids_scene() -> Scene:
    """The analytic pelvis (organs at risk with distance fields, like a planned scene's)."""
    meshes = {
        "Bladder": _solid("ellipsoid", (35.0, 25.0, 25.0), (0.0, -55.0, 70.0)),
        "Rectum": _solid("ellipsoid", (14.0, 14.0, 45.0), (0.0, 55.0, 80.0)),
        "Bone": _solid("box", (12.0, 40.0, 120.0), (70.0, 0.0, 80.0)),
        "HR-CTV": _solid("ellipsoid", (28.0, 20.0, 22.0), (0.0, -5.0, 85.0)),
        "Uterus": _solid("ellipsoid", (30.0, 22.0, 35.0), (0.0, -5.0, 100.0)),
    }
    bone = meshes["Bone"].copy().apply_translation((-140.0, 0.0, 0.0))
    meshes["Bone"] = trimesh.util.concatenate([meshes["Bone"], bone])
    organs = tuple(with_distance_field(make_organ(n, meshes[n]), 5.0) for n in ("Bladder", "Rectum", "Bone"))
    name, point = SOLIDS_TARGET
    return Scene(organs, (Target(name, point),), load_template(PlanConfig().template), np.eye(4), meshes)
