"""Numbers, lists and points on the command line, and where target points lie.

* :class:`NumbersParser`: an :class:`argparse.ArgumentParser` that reads a value starting with a minus sign and a
  digit (``-20,0,90``, ``-1.5e2``) as a value, not as an option, so ``--targets -20,0,90`` works like
  ``--targets=-20,0,90`` (argparse itself takes only ``-20`` or ``-1.5`` alone for a number).
* :func:`comma_items`: a comma-separated list; an empty item (``1,,2``) is an error, never dropped.
* :func:`parse_point`: three finite numbers ``x,y,z`` (mm, LPS).
* :func:`check_targets_inside`: target points must lie inside the image volume and the body contour, checked before
  any planning (a point far outside would be planned for minutes and end with every result null).
"""

from __future__ import annotations

import argparse
import math
import re
from collections.abc import Sequence
from typing import TYPE_CHECKING, Any

from reachplan.planner.errors import PlanInputError

if TYPE_CHECKING:  # numpy and the imaging floor are imported when used: start-up of every command stays light
    import numpy as np

    from reachplan.imaging.types import StructureSet, Volume
    from reachplan.planner.steering.candidates import Target

_NUMBER = r"[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?"
#: A negative number, or a comma-separated list of numbers whose first is negative: a value, not an option.
NEGATIVE_VALUE = re.compile(rf"^-(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?(?:,\s*{_NUMBER})*,?$")
#: How far (mm) beyond the box holding every contour a point may lie when there are neither images nor a body.
NO_BODY_MARGIN_MM = 50.0


class NumbersParser(argparse.ArgumentParser):
    """An argument parser that takes ``-20,0,90`` (a negative number first) as a value, not an option.

    argparse treats an argument that starts with ``-`` as an option unless it looks like a negative number
    (``-20``, ``-1.5``), so a point whose first coordinate is negative (the patient's right) was refused after
    ``--targets``. Sub-parsers are made of the same class (argparse uses the parent's class), so every command
    reads such values.

    Parameters
    ----------
    *args, **kwargs
        As for :class:`argparse.ArgumentParser`.
    """

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self._negative_number_matcher = NEGATIVE_VALUE


def comma_items(text: str, option: str, error: type[Exception] = PlanInputError) -> list[str]:
    """Split a comma-separated list; an empty item is an error (``1,,2`` is not ``1,2``).

    Parameters
    ----------
    text : str
        The option's value.
    option : str
        The option's name, for the message.
    error : type
        The typed error to raise (a :class:`~reachplan.ReachplanError`).

    Returns
    -------
    list of str
        The items, spaces around them removed.

    Raises
    ------
    ReachplanError
        ``error``, when an item is empty (or the whole list is).
    """
    items = [t.strip() for t in text.split(",")]
    empty = [k + 1 for k, t in enumerate(items) if not t]
    if empty:
        raise error(f"{option} {text!r}: item {empty[0]} of {len(items)} is empty; give comma-separated values "
                    "without empty items (e.g. 1,2,3)")
    return items


def parse_point(spec: str, what: str) -> tuple[float, float, float]:
    """Read three finite numbers ``x,y,z`` (mm, LPS).

    Parameters
    ----------
    spec : str
        The value as given.
    what : str
        What it is, for the message (e.g. ``"--template-origin"``).

    Returns
    -------
    (float, float, float)
        The point, mm.

    Raises
    ------
    PlanInputError
        Not three finite numbers, or an empty item.
    """
    parts = comma_items(spec, what)
    try:
        values = tuple(float(p) for p in parts)
    except ValueError:
        values = ()
    if len(values) != 3 or not all(math.isfinite(v) for v in values):
        raise PlanInputError(f"{what} {spec!r}: give three finite numbers 'x,y,z' in mm")
    return values[0], values[1], values[2]


class TargetOutsideError(PlanInputError):
    """A target point lies outside the image volume or the body contour (``--allow-outside-body`` accepts it)."""


def _outside_volume(volume: Volume, p: np.ndarray) -> str | None:
    import numpy as np

    grid = volume.grid
    ijk = grid.to_index(p[None])[0]
    upper = np.array(grid.shape[::-1], dtype=float) - 0.5
    clipped = np.clip(ijk, -0.5, upper)
    if np.array_equal(clipped, ijk):
        return None
    gap = float(np.linalg.norm(grid.to_patient(clipped[None])[0] - p))
    lo, hi = grid.to_patient(np.array([[-0.5, -0.5, -0.5]]))[0], grid.to_patient(upper[None])[0]
    box = ", ".join(f"{a} {min(x, y):.0f} to {max(x, y):.0f}" for a, x, y in zip("xyz", lo, hi, strict=True))
    return f"{gap:.0f} mm outside the image volume ({box} mm)"


def _outside_body(structures: StructureSet, volume: Volume | None, p: np.ndarray) -> str | None:
    import numpy as np

    from reachplan.imaging.errors import StructureError
    from reachplan.imaging.meshing import roi_contains

    body = [r for r in structures.rois if r.normalized_name == "Body" or r.interpreted_type.upper() == "EXTERNAL"]
    closed = [r for r in body if any(c.geometric_type == "CLOSED_PLANAR" for c in r.contours)]
    if closed:
        spacing = float(volume.grid.spacing_mm[2]) if volume is not None else None
        try:
            if not roi_contains(closed[0], p[None], spacing)[0]:
                return f"outside the body contour (ROI {closed[0].name!r})"
            return None
        except StructureError:
            pass  # contours that do not stack: fall back to the box of every contour
    if volume is not None:
        return None
    pts = [c.points_mm for r in structures.rois for c in r.contours if len(c.points_mm)]
    if not pts:
        return None
    allpts = np.concatenate(pts)
    lo, hi = allpts.min(axis=0) - NO_BODY_MARGIN_MM, allpts.max(axis=0) + NO_BODY_MARGIN_MM
    if np.all((p >= lo) & (p <= hi)):
        return None
    gap = float(np.linalg.norm(p - np.clip(p, lo, hi)))
    return f"{gap + NO_BODY_MARGIN_MM:.0f} mm beyond every contour of the structure set (no images, no body contour)"


def check_targets_inside(targets: Sequence[Target], volume: Volume | None, structures: StructureSet,
                         allow_outside_body: bool = False) -> None:
    """Check, before any planning, that every target point lies inside the images and the body.

    Inside the image volume (when images are given) and inside the body contour (a ROI named Body or External, or of
    type EXTERNAL); with neither images nor a body, within :data:`NO_BODY_MARGIN_MM` of the box holding every
    contour.

    Parameters
    ----------
    targets : sequence of Target
        The target points given on the command line (mm, LPS).
    volume : Volume or None
        The image series, if given.
    structures : StructureSet
        The structure set.
    allow_outside_body : bool
        Accept such points (``--allow-outside-body``).

    Raises
    ------
    TargetOutsideError
        A point outside, named with where it lies and how far.
    """
    import numpy as np

    if allow_outside_body:
        return
    for t in targets:
        p = np.asarray(t.position_mm, dtype=float)
        where = (_outside_volume(volume, p) if volume is not None else None) or _outside_body(structures, volume, p)
        if where is not None:
            xyz = ",".join(f"{v:g}" for v in t.position_mm)
            raise TargetOutsideError(
                f"target {t.name} ({xyz} mm) lies {where}; give a point inside the patient (mm, DICOM patient "
                "coordinates LPS: +x left, +y posterior, +z superior) or pass --allow-outside-body")
