"""Errors raised by :mod:`reachplan.rod_model`.

A solve that does not converge is *not* an error: it is a :class:`reachplan.rod_model.result.FailedSolve`.
These errors are for requests that cannot be served at all.
"""

from __future__ import annotations

from reachplan import ReachplanError


class RodModelError(ReachplanError):
    """Base of the rod-model errors."""


class UnknownPresetError(RodModelError):
    """A design preset name is not known."""


class UnsupportedLoadError(RodModelError):
    """A model was asked for a load case it cannot represent (see its ``capabilities``)."""


class NoModelWithinToleranceError(RodModelError):
    """The model selector found no model whose measured error is within the tolerance asked for."""


class TensionAboveLimitWarning(UserWarning):
    """A tendon tension above the design's ``max_tension_n`` was solved.

    The API warns; ``reachplan rod`` refuses unless ``--allow-over-limit``.
    """
