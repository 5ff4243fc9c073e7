"""The planning masks: the target (HR-CTV) and the organs at risk as boolean masks on one planning grid."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from reachplan.imaging.types import Grid, Roi, StructureSet
from reachplan.planner.errors import PlanInputError
from reachplan.planner.lookup import applicator_kinds
from reachplan.plugins.applicators import Applicator, applicators_from_structures


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

    Built by :func:`planning_structures` from a structure set.

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


def planning_structures(structures: StructureSet, grid: Grid | None, target_roi: str, oar_names: Sequence[str],
                        applicators: Sequence[Applicator] | None = None) -> PlanningStructures:
    """Return the target and organs at risk (bone and applicators excluded) as masks for dose.

    An applicator (the tandem, ovoids, obturator) may be an obstacle to needles (an organ of the scene) but receives
    no dose limit and is no organ at risk for dose.

    Parameters
    ----------
    structures : StructureSet
        The case's ROIs (contours mm, LPS).
    grid : Grid or None
        The CT's grid; None: a 2 mm grid on the contours' own slices that holds the target and every organ.
    target_roi : str
        The ROI the dwell times are optimised on.
    oar_names : sequence of str
        Normalised names of the organs at risk (those not in the structure set are skipped).
    applicators : sequence of Applicator or None
        The case's applicators (:attr:`Scene.applicators`); None: recognised here with the installed kinds.

    Returns
    -------
    PlanningStructures
        Boolean masks (k, j, i) on the grid.

    Raises
    ------
    PlanInputError
        ``target_roi`` is not in the structure set.
    """
    from reachplan.imaging.meshing import fit_grid, roi_mask

    if target_roi not in structures.names:
        raise PlanInputError(f"no {target_roi} ROI to compute dose on; name it with --target-roi")
    roi = structures.get(target_roi)
    if applicators is None:
        applicators = applicators_from_structures(structures, applicator_kinds())
    parts = {structures.get(a.roi_name).normalized_name for a in applicators if a.roi_name}
    oar_rois = [structures.get(n) for n in oar_names if n in structures.names and n != "Bone" and n not in parts]
    if grid is None:
        union = Roi(0, "planning volume", tuple(c for r in (roi, *oar_rois) for c in r.contours
                                                  if c.geometric_type == "CLOSED_PLANAR"))
        grid = fit_grid(union, None, 2.0)
    oars = tuple(Structure(r.normalized_name, roi_mask(r, grid)) for r in oar_rois)
    return PlanningStructures(grid, Structure(target_roi, roi_mask(roi, grid)), oars)


def gtv_structure(structures: StructureSet, grid: Grid) -> Structure | None:
    """Return the residual GTV at brachytherapy (GTV_res) as a mask on ``grid``, or None when there is none.

    By name (case, spaces and punctuation ignored): a name that starts with ``gtv`` and holds ``res`` (``GTV_res``,
    ``GTV-T_res``) first, else a plain ``GTV`` (``GTV``, ``GTVp``, ``GTV_T``); a GTV at diagnosis (``GTV_init``)
    is not the brachytherapy GTV and is not taken. ROIs without closed contours are skipped.

    Parameters
    ----------
    structures : StructureSet
        The case's ROIs (contours mm, LPS).
    grid : Grid
        The planning grid.

    Returns
    -------
    Structure or None
        Named as the ROI, boolean mask (k, j, i).
    """
    from reachplan.imaging.meshing import roi_mask

    def key(name: str) -> str:
        return "".join(ch for ch in name.casefold() if ch.isalnum())

    closed = [r for r in structures.rois if any(c.geometric_type == "CLOSED_PLANAR" for c in r.contours)]
    ranked = [r for r in closed if key(r.name).startswith("gtv") and "res" in key(r.name)]
    ranked += [r for r in closed if key(r.name) in ("gtv", "gtvp", "gtvt")]
    if not ranked:
        return None
    mask = roi_mask(ranked[0], grid)
    return Structure(ranked[0].name, mask) if mask.any() else None
