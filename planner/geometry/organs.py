"""Which ROIs of a structure set are the organs at risk a needle is checked against, and which ROI a target is.

ROI names are matched through the synonym table (:mod:`reachplan.imaging.names`: AAPM TG-263 names first, then
clinical variants and other languages). Nothing is dropped silently: every standard organ at risk that is not
found, or is found without closed contours, is named in a note that also lists the ROIs no standard name matched.
"""

from __future__ import annotations

from collections.abc import Collection, Sequence
from dataclasses import dataclass

import numpy as np

from reachplan.imaging.names import DEFAULT_SYNONYMS, name_key
from reachplan.imaging.types import Roi, StructureSet
from reachplan.planner.errors import PlanInputError


def has_closed(roi: Roi) -> bool:
    """Whether ``roi`` has at least one closed planar contour of 3 or more points (something to mesh).

    Parameters
    ----------
    roi : Roi
        The ROI.

    Returns
    -------
    bool
        True when it can be meshed.
    """
    return any(c.geometric_type == "CLOSED_PLANAR" and len(c.points_mm) >= 3 for c in roi.contours)


def _kinds(roi: Roi) -> str:
    if not roi.contours:
        return "no contours"
    if all(c.geometric_type == "CLOSED_PLANAR" for c in roi.contours):
        return "only closed contours of fewer than 3 points"
    return "only " + "/".join(sorted({c.geometric_type for c in roi.contours})) + " contours"


@dataclass(frozen=True)
class OarSelection:
    """The organs at risk found in a structure set.

    Parameters
    ----------
    found : tuple of str
        Normalised names of the organs at risk with closed contours (meshed and checked).
    missing : tuple of str
        Standard organs at risk no ROI maps to.
    skipped : tuple of str
        Present but without closed contours.
    unmapped : tuple of str
        Original names of the ROIs that no standard name matched.
    notes : tuple of str
        One line per problem.
    """

    found: tuple[str, ...]
    missing: tuple[str, ...]
    skipped: tuple[str, ...]
    unmapped: tuple[str, ...]
    notes: tuple[str, ...]


def _ambiguous(structures: StructureSet, name: str) -> list[Roi]:
    key = name.casefold()
    return [r for r in structures.rois if r.normalized_name.casefold() == key]


def check_unique(structures: StructureSet, names: Collection[str] = ()) -> None:
    """Refuse a name in ``names`` (a target or organ) that several ROIs have, or that several ROIs map to.

    ROIs whose names are equal but for case (or equal) and are not used are told apart by ROI number: the reader
    warns about them (:class:`~reachplan.imaging.errors.DuplicateRoiNameWarning`), planning goes on.

    Parameters
    ----------
    structures : StructureSet
        The structure set.
    names : collection of str
        Original or standard (normalised) names used as targets or organs: each must name one ROI at most.

    Raises
    ------
    PlanInputError
        Naming the duplicates.
    """
    used = {n.strip().casefold() for n in names}
    seen: dict[str, list[Roi]] = {}
    for r in structures.rois:
        seen.setdefault(r.name.strip().casefold(), []).append(r)
    dups = [rs for key, rs in seen.items() if len(rs) > 1 and (key in used or any(
        r.normalized_name.casefold() in used for r in rs))]
    if dups:
        listed = "; ".join(f"{rs[0].name!r} (ROI numbers {', '.join(str(r.number) for r in rs)})" for rs in dups)
        raise PlanInputError(f"duplicate ROI names in the structure set, used as a target or organ: {listed}; "
                             "rename them in the TPS and export again")
    for name in names:
        rois = _ambiguous(structures, name)
        if len(rois) > 1:
            listed = ", ".join(repr(r.name) for r in rois)
            raise PlanInputError(f"ROIs {listed} all map to {name}; choose one with --oar {name}=ROI_NAME")


def select_oars(structures: StructureSet, oar_names: Sequence[str],
                standard_names: Collection[str] | None = None, exclude: Collection[str] = ()) -> OarSelection:
    """Find the organs at risk ``oar_names`` (normalised names) in ``structures``.

    Parameters
    ----------
    structures : StructureSet
        The structure set, its ROIs normalised through the synonym table.
    oar_names : sequence of str
        Normalised names of the organs at risk to look for.
    standard_names : collection of str or None
        The names the synonym table maps to (default: the built-in table's); an ROI whose normalised name is not
        among them is listed as unmapped.
    exclude : collection of str
        Original or normalised ROI names not to list as unmapped (the targets).

    Returns
    -------
    OarSelection
        Found, missing, skipped and unmapped names, with notes.

    Raises
    ------
    PlanInputError
        Several ROIs map to one organ at risk (see :func:`check_unique`).
    """
    standards = {s.casefold() for s in (standard_names if standard_names is not None
                                        else DEFAULT_SYNONYMS.standard_names)}
    standards |= {n.casefold() for n in oar_names}
    skip = {n.casefold() for n in exclude}
    check_unique(structures, oar_names)
    found: list[str] = []
    missing: list[str] = []
    skipped: list[str] = []
    notes: list[str] = []
    for name in oar_names:
        rois = _ambiguous(structures, name)
        if not rois:
            missing.append(name)
        elif not has_closed(rois[0]):
            skipped.append(name)
            notes.append(f"organ at risk {name} (ROI {rois[0].name!r}) has {_kinds(rois[0])}: skipped, needles "
                         "are not checked against it")
        else:
            found.append(rois[0].normalized_name)
    unmapped = tuple(r.name for r in structures.rois if r.normalized_name.casefold() not in standards
                     and r.name.casefold() not in skip and r.normalized_name.casefold() not in skip)
    if missing:
        hints = []
        for name in missing:
            stems = {name_key(s)[:4] for s in DEFAULT_SYNONYMS.synonyms_of(name)} | {name_key(name)[:4]}
            maybe = [u for u in unmapped if any(name_key(u).startswith(s) for s in stems if len(s) == 4)]
            if maybe:
                hints.append(f"{name} might be {' or '.join(repr(m) for m in maybe)}")
        notes.append(f"organs at risk not found: {', '.join(missing)}"
                     + (f" ({'; '.join(hints)})" if hints else "")
                     + f"; ROIs no standard name matched: {', '.join(repr(u) for u in unmapped) or 'none'}; "
                     "map one with --oar ORGAN=ROI_NAME or --synonyms FILE")
    return OarSelection(tuple(found), tuple(missing), tuple(skipped), unmapped, tuple(notes))


def roi_points(roi: Roi) -> np.ndarray:
    """Return the points of a target ROI made only of POINT contours.

    Parameters
    ----------
    roi : Roi
        The target ROI.

    Returns
    -------
    (n, 3) float, mm, LPS
        The points of its POINT contours, in contour order.

    Raises
    ------
    PlanInputError
        The ROI has no contours, or open contours only (nothing to aim at).
    """
    pts = [c.points_mm for c in roi.contours if c.geometric_type == "POINT"]
    if not pts:
        raise PlanInputError(f"target ROI {roi.name!r} has {_kinds(roi)}, nothing to aim at; give a contoured "
                             "ROI or a point x,y,z")
    return np.concatenate(pts)
