"""Errors raised by the planner (expected per-candidate failures are results, not errors)."""

from __future__ import annotations

from reachplan import ReachplanError


class PlannerError(ReachplanError):
    """Base of the planner errors."""


class PlanInputError(PlannerError):
    """A plan's inputs are inconsistent or incomplete (missing organ, unknown target, bad pose...)."""


class StudyError(PlanInputError):
    """A design study cannot run or resume as asked (output folder, cases, scheduler, missing results)."""
