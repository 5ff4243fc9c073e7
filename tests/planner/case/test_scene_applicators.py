"""The scene says why an applicator gives no channel (its notes join the scene's, which plan.json and the terminal
show as warnings)."""

from __future__ import annotations

import numpy as np

from reachplan.imaging.types import Contour, Roi, StructureSet
from reachplan.planner.case.scene import build_scene
from reachplan.planner.steering.candidates import Target


def _tube(number: int, name: str, z0: float, z1: float, radius: float, y: float = 0.0) -> Roi:
    t = np.linspace(0.0, 2 * np.pi, 24, endpoint=False)
    ring = np.column_stack([radius * np.cos(t), y + radius * np.sin(t), np.zeros(24)])
    return Roi(number, name, tuple(Contour(ring + np.array([0.0, 0.0, z])) for z in np.arange(z0, z1 + 1e-9, 2.5)))


def test_a_tandem_drawn_as_one_point_is_named_in_the_scene_notes() -> None:
    rois = (_tube(1, "Obturator", -20.0, 60.0, 15.0), _tube(2, "Bladder", 40.0, 80.0, 10.0, y=-40.0),
            Roi(3, "Tandem", (Contour(np.array([[0.0, 0.0, 70.0]]), "POINT"),)))
    scene = build_scene(StructureSet(rois, "1.2.3"), [], [Target("p", np.array([0.0, 0.0, 90.0]))])
    (tandem,) = [a for a in scene.applicators if a.kind == "tandem"]
    assert tandem.channels == () and not tandem.loadable
    assert any("'Tandem' is drawn as a single point: no centre line" in n for n in scene.notes)
