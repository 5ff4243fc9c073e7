"""Errors raised by the planner (expected per-candidate failures are results, not errors)."""

from __future__ import annotations

from reachplan import ReachplanError


class PlannerError(ReachplanError):
    """Base of the planner errors."""


class PlanInputError(PlannerError):
    """A plan's inputs are inconsistent or incomplete (missing organ, unknown target, bad pose...)."""


class ProtocolError(PlanInputError):
    """A protocol file or name (``--protocol``) cannot be read as aims: unknown name, bad file, bad key or value."""


class ProtocolWarning(UserWarning):
    """The protocol's aims were applied where they may not fit (see the subclasses)."""


class ProtocolSiteWarning(ProtocolWarning):
    """The structure set's target is not the protocol's site's (e.g. a prostate with the cervix protocol)."""


class SmallOrganWarning(ProtocolWarning):
    """An organ at risk is smaller than 2 cm³: its D2cm³ is not applicable (a smaller volume's dose is reported)."""


class StudyError(PlanInputError):
    """A design study cannot run or resume as asked (output folder, cases, scheduler, missing results)."""
