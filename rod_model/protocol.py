"""The one interface every rod model implements, and what a model can represent.

Built-in models and third-party ones register as plugins of kind ``rod_models`` (entry-point group
``reachplan.rod_models``); the object an entry point names is an instance implementing :class:`RodModel`.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass
from typing import Protocol, runtime_checkable

import numpy as np

from reachplan.rod_model.design import Loads, RodDesign
from reachplan.rod_model.errors import TensionAboveLimitWarning, UnsupportedLoadError
from reachplan.rod_model.result import FailedSolve, RodBatch, RodPath


@dataclass(frozen=True)
class Capabilities:
    """What a model can represent.

    Parameters
    ----------
    planar_only : bool
        Only shapes in one plane (one pulled tendon direction, loads in that plane).
    twist : bool
        Relative twist of stylet and needle.
    several_tendons : bool
        Several tendons pulled at once, in different directions.
    external_load : bool
        Tip force/moment and distributed loads.
    large_deflection : bool
        Geometrically exact (no small-angle assumption).
    friction : bool
        Capstan friction of the tendons and Coulomb friction in the joints (the design's coefficients).
    """

    planar_only: bool
    twist: bool
    several_tendons: bool
    external_load: bool
    large_deflection: bool
    friction: bool = False


@runtime_checkable
class RodModel(Protocol):
    """A rod model: maps a design and loads to a shape.

    ``solve`` returns a :class:`RodPath`, or a :class:`FailedSolve` when the model could not converge (never a
    plausible wrong shape); it raises :class:`reachplan.rod_model.errors.UnsupportedLoadError` for loads outside its
    ``capabilities``. ``solve_batch`` solves many free-space tensions of tendon 0 at once.
    """

    @property
    def name(self) -> str:
        """Plugin name (``two_tube_cosserat``, ...)."""

    @property
    def capabilities(self) -> Capabilities:
        """What the model can represent."""

    def solve(self, design: RodDesign, loads: Loads) -> RodPath | FailedSolve:
        """Solve the shape of ``design`` under ``loads``.

        Parameters
        ----------
        design : RodDesign
            The stylet in its needle.
        loads : Loads
            One tension per tendon (N), roll, and external loads in the needle's base frame.

        Returns
        -------
        RodPath or FailedSolve
            Positions in mm in the needle frame; a falsy :class:`FailedSolve` with its reason when the solver
            does not converge.

        Raises
        ------
        UnsupportedLoadError
            Loads the model cannot represent (see :func:`check_loads`).
        """
        ...

    def solve_batch(self, design: RodDesign, tensions_n: np.ndarray, roll_deg: float = 0.0) -> RodBatch:
        """Solve many free-space pulls of tendon 0 at once.

        Parameters
        ----------
        design : RodDesign
            The stylet in its needle.
        tensions_n : (b,) float, N
            Tension on tendon 0 of each solve, ≥ 0.
        roll_deg : float
            Roll of the stylet, degrees, shared by all solves.

        Returns
        -------
        RodBatch
            Tip positions (mm, needle frame) and section curvatures; failed solves are marked in ``converged``.
        """
        ...


def check_rod_model(obj: object) -> None:
    """Check that ``obj`` implements :class:`RodModel` (the registry's check).

    Raises
    ------
    TypeError
        A missing member, a name that is not a str or capabilities that are not :class:`Capabilities`.
    """
    if not isinstance(obj, RodModel):
        raise TypeError(f"{obj!r} does not implement rod_model.protocol.RodModel (name, capabilities, solve, "
                        "solve_batch)")
    if not isinstance(obj.capabilities, Capabilities) or not isinstance(obj.name, str):
        raise TypeError(f"{obj!r}: name must be a str and capabilities a rod_model.protocol.Capabilities")


def check_loads(name: str, caps: Capabilities, design: RodDesign, loads: Loads) -> None:
    """Check that ``loads`` fit ``design`` and the capabilities ``caps`` of the model called ``name``.

    Warns (:class:`TensionAboveLimitWarning`) when a tension exceeds the design's ``max_tension_n``.

    Raises
    ------
    UnsupportedLoadError
        Not one tension per tendon, external loads the model cannot represent, or several pulled tendons for
        a model that takes one.
    """
    if len(loads.tensions_n) != design.n_tendons:
        raise UnsupportedLoadError(f"{len(loads.tensions_n)} tensions given for a design with {design.n_tendons} "
                                   "tendons; give one tension per tendon")
    if loads.has_external and not caps.external_load:
        raise UnsupportedLoadError(f"model {name} cannot represent external loads; use cosserat_rod or "
                                   "two_tube_cosserat")
    if design.has_friction and not caps.friction:
        raise UnsupportedLoadError(f"model {name} has no friction but {design.name} has friction coefficients; use "
                                   "cosserat_rod or two_tube_cosserat, or set the coefficients to 0")
    if max(loads.tensions_n) > design.max_tension_n:
        warnings.warn(f"tension {max(loads.tensions_n):g} N exceeds {design.name}'s limit of "
                      f"{design.max_tension_n:g} N; the stylet is not built for it", TensionAboveLimitWarning,
                      stacklevel=3)
    if not caps.several_tendons and sum(t > 0 for t in loads.tensions_n) > 1:
        raise UnsupportedLoadError(f"model {name} represents one pulled tendon at a time; use "
                                   "cosserat_rod or two_tube_cosserat")
