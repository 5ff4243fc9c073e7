"""run_case as a library call: the chain plan and demo share, on the clinical case's contours (no DICOM, no files).

The case is cut in memory below z = 140 mm and one target is planned at the screening stage, as in
tests/planner/case/test_clinical_obstruction.py, so that the chain itself is what is tested: the applicators are
recognised once (the tandem becomes an obstacle without being named as an organ), the ranking is the steering
search's, the computed part of plan.json holds what the writers need, and bad input is refused before any work.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from reachplan import ReachplanError
from reachplan.imaging.clinical import clinical_case, structure_set
from reachplan.imaging.types import Contour, Roi, StructureSet
from reachplan.planner.case.config import PlanConfig
from reachplan.planner.case.scene import build_scene
from reachplan.planner.case.search import plan
from reachplan.planner.errors import PlanInputError
from reachplan.planner.run.case import CaseConfig, CaseInput, run_case
from reachplan.planner.steering.candidates import Target

#: no bowel: cut at 140 mm it lies on one plane, which the contours alone (no CT grid here) cannot give a thickness
ROIS = ("Bladder", "Rectum", "Colon_Sigmoid", "Bone_Pelvic", "Tandem", "Obturator")


@pytest.fixture(scope="module")
def case() -> tuple[CaseInput, CaseConfig]:
    clinical = clinical_case(0)
    spec = dataclasses.replace(clinical.spec, z_range_mm=(-20.0, 140.0))
    point = dict(clinical.targets)["corpus_ant"]
    config = CaseConfig(plan=PlanConfig(refine_top=0, robust_top=0), target_names=(),
                        target_points=(Target("corpus_ant", point),), export=False)
    return CaseInput(structure_set(spec, ROIS), None, (), "clinical seed 0"), config


def test_run_case_chains_the_scene_and_the_steering_search(case: tuple[CaseInput, CaseConfig]) -> None:
    inputs, config = case
    seen = []
    result = run_case(inputs, config, on_scene=seen.append)
    assert len(seen) == 1 and seen[0] is result.scene
    # the tandem is recognised as an applicator and, being an obstacle, joins the organs: nobody named it
    assert "Tandem" not in config.plan.oar_names
    assert sorted(a.kind for a in result.scene.applicators) == ["obturator", "tandem"]
    assert "Tandem" in [o.name for o in result.scene.organs]
    assert result.config.plan.oar_names == tuple(o.name for o in result.scene.organs)
    # the same ranking as the steering search called directly on the same scene
    direct = plan(build_scene(inputs.structures, [], config.target_points, config=config.plan), config.plan)
    assert [(c.hole_id, c.steered) for c in result.result.ranking["corpus_ant"]] == \
        [(c.hole_id, c.steered) for c in direct.ranking["corpus_ant"]]
    assert result.delivery is None and result.comparison is None and "ranked only" in result.comparison_note
    doc = result.to_json()
    assert set(doc) >= {"config", "targets", "warnings", "blocked_straight"}
    assert "delivery" not in doc and set(result.timings) == {"scene_s", "plan_s", "plan_cpu_s"}
    blocked = result.result.blocked_straight()
    assert doc["blocked_straight"] == [b.to_json() for b in blocked]
    assert blocked and all(b.straight.collides and b.straight.reaches for b in blocked)


def test_run_case_refuses_a_dose_target_without_closed_contours(case: tuple[CaseInput, CaseConfig]) -> None:
    inputs, config = case
    with pytest.raises(ReachplanError, match="no ROI named 'HR-CTV'"):
        run_case(inputs, dataclasses.replace(config, export=True))  # HR-CTV is not among the ROIs cut here
    point = Roi(99, "HR-CTV", (Contour(np.zeros((1, 3)), "POINT"),))
    with pytest.raises(PlanInputError, match="no closed contours"):
        run_case(dataclasses.replace(inputs, structures=StructureSet((*inputs.structures.rois, point), "1.2.3")),
                 dataclasses.replace(config, export=True))



@pytest.mark.parametrize(("builtin", "given", "expect"), [(False, None, 0.0), (True, None, 2.5), (False, 1.5, 1.5)])
def test_dwell_margin_is_zero_on_real_structure_sets(case: tuple[CaseInput, CaseConfig], builtin: bool,
                                                     given: float | None, expect: float) -> None:
    """Issue 27: dwells in the target as drawn on a real structure set; the built-in case keeps its margin."""
    from reachplan.planner.implant.settings import ImplantSettings
    from reachplan.planner.run.case import implant_settings

    inputs, config = case
    got = implant_settings(dataclasses.replace(inputs, builtin=builtin),
                           dataclasses.replace(config, dwell_margin_mm=given))
    assert got.dwell_margin_mm == expect
    assert dataclasses.replace(got, dwell_margin_mm=ImplantSettings().dwell_margin_mm) == ImplantSettings()
