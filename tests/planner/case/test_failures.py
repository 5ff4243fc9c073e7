"""A model that fails for one candidate marks that candidate (its reason, not feasible); the plan goes on.

Stub insertion models are injected through ``plan(..., models=PlanModels(...))``: each fails on its first call
only (the first candidate it is asked about), in one of the ways a real solve fails.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
import pytest
import trimesh

from reachplan.planner.case.config import PlanConfig, PlanModels
from reachplan.planner.case.result import PlanResult
from reachplan.planner.case.scene import Scene
from reachplan.planner.case.search import plan
from reachplan.planner.errors import PlanInputError
from reachplan.planner.geometry.collision import make_organ
from reachplan.planner.lookup import load_template
from reachplan.planner.steering.candidates import Candidate, Target
from reachplan.planner.steering.insertion import FailedInsertion
from reachplan.planner.steering.kinematic import KinematicInsertion
from reachplan.planner.steering.schedule import TensionSchedule
from reachplan.planner.steering.tissue_rod import PLANNER_REFERENCE, TissueRodInsertion
from reachplan.rod_model.cosserat import TwoTubeCosserat
from reachplan.rod_model.design import RodDesign
from reachplan.rod_model.errors import RodModelError

FAILURES = {
    "failed": "at depth 12.0 mm: stub multiple shooting did not converge",
    "not_finite": "the predicted shape is not finite",
    "rod_model": "stub rod model did not converge",
}


def _fail(kind: str, model: TissueRodInsertion) -> np.ndarray | FailedInsertion:
    if kind == "failed":
        return FailedInsertion(model.info, FAILURES["failed"])
    if kind == "rod_model":
        raise RodModelError("stub rod model did not converge")
    return np.full((5, 3), np.nan)  # a shape out of range


@dataclass(frozen=True)
class ReferenceFailingOnce(TissueRodInsertion):
    """The planner's reference model, failing (``kind``) on its first solve."""

    rod_model: TwoTubeCosserat = PLANNER_REFERENCE.rod_model
    kind: str = "failed"
    calls: list[int] = field(default_factory=list, compare=False, hash=False)

    def insert_one(self, design: RodDesign, schedule: TensionSchedule, depth_mm: float,
                   modulus_profile: tuple[np.ndarray, np.ndarray] | None = None) -> np.ndarray | FailedInsertion:
        self.calls.append(1)
        if len(self.calls) == 1:
            return _fail(self.kind, self)
        return super().insert_one(design, schedule, depth_mm, modulus_profile)


@dataclass(frozen=True)
class RobustnessFailingOnce(KinematicInsertion):
    """The robustness model, raising on its first call."""

    calls: list[int] = field(default_factory=list, compare=False, hash=False)

    def insert_array(self, design: RodDesign, schedules: Sequence[TensionSchedule], depth_mm: float) -> np.ndarray:
        self.calls.append(1)
        if len(self.calls) == 1:
            raise PlanInputError("stub: a schedule exceeds the maximum tension")
        return super().insert_array(design, schedules, depth_mm)


def _planted_plan(models: PlanModels, **config: int) -> PlanResult:
    """Target above hole Df (40, 0) whose straight path a sphere blocks: only steered routes are feasible."""
    sphere = trimesh.creation.icosphere(subdivisions=3, radius=5.0)
    sphere.apply_translation((40.0, 0.0, 50.0))
    scene = Scene((make_organ("Organ0", sphere),), (Target("T", (40.0, 0.0, 110.0)),),
                  load_template("needlefinder_syed_63"), np.eye(4))
    return plan(scene, PlanConfig(**config), models=models)  # type: ignore[arg-type]


def _failed(result: PlanResult) -> list[Candidate]:
    return [c for c in result.candidates if c.failed]


@pytest.mark.parametrize("kind", sorted(FAILURES))
def test_a_failed_reference_resolve_marks_that_candidate_and_the_plan_goes_on(kind: str) -> None:
    reference = ReferenceFailingOnce(kind=kind)
    result = _planted_plan(PlanModels(reference=reference), robust_top=0)
    # the reference's solves are memoised: the mirror image of the failed candidate (the same schedule and depth
    # from the hole mirrored about the target's plane) fails with it
    bad, *mirrors = _failed(result)
    assert len(mirrors) <= 1 and all(m.reason == bad.reason and m.peak_tension_n == bad.peak_tension_n
                                     for m in mirrors)
    assert not bad.feasible and bad.steered and bad.reaches  # it did reach on the screening model's numbers
    assert f"re-solve ({reference.info.label}) failed" in bad.reason and FAILURES[kind] in bad.reason
    assert bad.model.insertion == "kinematic"  # its numbers are the screening model's, and it says so
    doc = bad.to_json()
    assert doc["feasible"] is False and doc["reason"] == bad.reason and doc["model"] == bad.model.label
    ranked = result.ranking["T"]
    best = ranked[0]
    assert best.feasible and best.steered and best.hole_id not in {c.hole_id for c in (bad, *mirrors)}
    assert best.model == reference.info  # the next candidate was re-solved by the reference instead
    feasible = [i for i, c in enumerate(ranked) if c.feasible]
    assert len(feasible) >= 2 and ranked.index(bad) > max(feasible)  # ranked after every feasible one


def test_a_failed_robustness_assessment_marks_that_candidate_and_the_others_are_assessed() -> None:
    robustness = RobustnessFailingOnce()
    result = _planted_plan(PlanModels(robustness=robustness), robust_top=2, refine_top=1)
    (bad,) = _failed(result)
    assert not bad.feasible and "robustness (kinematic+planar_beam) failed: stub" in bad.reason
    assert np.isnan(bad.worst_reach_mm)
    assessed = [c for c in result.ranking["T"] if np.isfinite(c.worst_reach_mm)]
    assert assessed and all(c.feasible and c.steered and c.hole_id != bad.hole_id for c in assessed)
    assert len(robustness.calls) == 1 + len(assessed)
