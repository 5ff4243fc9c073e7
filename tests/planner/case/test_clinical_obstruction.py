"""The property the clinical case exists for: a straight needle that reaches the anterior uterine body collides
with an organ at risk (reported with organ and depth), and a steered needle reaches the same point 2 mm clear of
every organ from a hole at least as medial as any straight needle that reaches it cleanly.

Since the cohort's anatomy varies (issue 30: bladder filling and position, uterine version and flexion, tumour
size), that holds for the seeds of :data:`BLOCKED` (the demo's seed 0 among them), not for every seed: an emptier
bladder or a retroverted uterus leaves a straight path open, a bladder pressed against the body leaves no path 2 mm
clear. For every seed 0-9 each straight needle that collides is reported with its organ and depth.

To keep the run time reasonable the case is not written as DICOM: its contours are cut in memory (the ones
the writer would write) below z = 140 mm (every needle here stays below 115 mm, so organ parts above are more
than 25 mm from any path and cannot change a collision), and only the ``corpus_ant`` target is planned, at
the screening stage (no reference re-solve, no robustness check).
"""

from __future__ import annotations

import dataclasses

import pytest

from reachplan.imaging.clinical import clinical_case, image_grid, structure_set
from reachplan.planner.case.config import DEFAULT_OARS, PlanConfig
from reachplan.planner.case.scene import build_scene
from reachplan.planner.case.search import plan
from reachplan.planner.steering.candidates import Target

ROIS = ("Bladder", "Rectum", "Colon_Sigmoid", "Bowel_Small", "Bone_Pelvic", "Tandem", "Obturator")


#: Seeds (of 0-9) whose anterior uterine body no straight needle reaches without a collision, and a steered one does.
BLOCKED = (0, 2, 4, 6, 7, 8)


@pytest.mark.parametrize("seed", range(10))
def test_straight_needles_collide_where_a_steered_one_reaches_cleanly(seed: int) -> None:
    case = clinical_case(seed)
    spec = dataclasses.replace(case.spec, z_range_mm=(-20.0, 140.0))
    config = PlanConfig(oar_names=(*DEFAULT_OARS, "Tandem"), refine_top=0, robust_top=0)
    point = dict(case.targets)["corpus_ant"]
    scene = build_scene(structure_set(spec, ROIS), [], [Target("corpus_ant", point)], grid=image_grid(spec),
                        config=config)
    result = plan(scene, config)
    cands = result.ranking["corpus_ant"]
    straight = [c for c in cands if not c.steered and c.reaches]
    blocked = [c for c in straight if c.collides]
    assert blocked or seed not in BLOCKED, f"seed {seed}: no straight needle to the anterior uterine body collides"
    for c in blocked:
        assert c.closest_organ in {"Bladder", "Sigmoid", "Bowel"}, c.reason
        assert c.contact_depth_mm is not None and 0 < c.contact_depth_mm < c.insertion_depth_mm
        assert f"collides with {c.closest_organ} at depth" in c.reason
        j = c.to_json()
        assert j["reaches"] and j["collides"] and j["contact_depth_mm"] == round(c.contact_depth_mm, 1)
    if seed not in BLOCKED:
        return
    clean_straight = [c.hole_distance_mm for c in straight if c.feasible and c.clearance_mm >= 2.0]
    steered = [c for c in cands if c.steered and c.feasible and c.clearance_mm >= 2.0]
    assert steered, f"seed {seed}: no steered needle reaches the anterior uterine body 2 mm clear"
    best = min(steered, key=lambda c: c.hole_distance_mm)
    assert best.reach_error_mm <= config.reach_tolerance_mm
    assert all(best.hole_distance_mm <= d for d in clean_straight)
    assert best.hole_distance_mm < min(c.hole_distance_mm for c in blocked)  # from a more medial hole
