"""The planning masks: the target (HR-CTV) and the organs at risk as boolean masks on one planning grid."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from reachplan.imaging.types import Grid


@dataclass(frozen=True, eq=False)
class Structure:
    """A structure as a mask on the planning grid.

    Parameters
    ----------
    name : str
        The structure's name (organ names select their D2cm³ limit, see :class:`reachplan.planner.dose.aims.Aims`).
    mask : (nk, nj, ni) bool
        True inside, on :attr:`PlanningStructures.grid` (voxel index order k, j, i).

    Raises
    ------
    ValueError
        The mask is not 3-D.
    """

    name: str
    mask: np.ndarray

    def __post_init__(self) -> None:
        m = np.asarray(self.mask, dtype=bool)
        if m.ndim != 3:
            raise ValueError(f"structure {self.name}: mask must be 3-D (nk, nj, ni), got {m.shape}")
        m.setflags(write=False)
        object.__setattr__(self, "mask", m)


@dataclass(frozen=True, eq=False)
class PlanningStructures:
    """The target (HR-CTV) and organs at risk on one grid.

    Parameters
    ----------
    grid : Grid
        The planning grid (voxel centres in mm, LPS).
    target : Structure
        The HR-CTV; must not be empty.
    oars : tuple of Structure
        The organs at risk, each on ``grid``.

    Raises
    ------
    ValueError
        A mask is not on ``grid``, or the target is empty.
    """

    grid: Grid
    target: Structure
    oars: tuple[Structure, ...] = ()

    def __post_init__(self) -> None:
        object.__setattr__(self, "oars", tuple(self.oars))
        for s in (self.target, *self.oars):
            if s.mask.shape != self.grid.shape:
                raise ValueError(f"structure {s.name}: mask {s.mask.shape} is not on the grid {self.grid.shape}")
        if not self.target.mask.any():
            raise ValueError(f"target {self.target.name} is empty")
