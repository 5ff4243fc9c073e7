"""Dose reference points of a gynaecological implant, placed from the structure set.

* Point A (GEC-ESTRO / ICRU Report 89, 2013, §10.3, the revised Manchester definition): on each side, 20 mm
  cranial along the tandem from the level of the vaginal fornix (the flange or the vaginal applicator's cranial
  surface) and 20 mm lateral, perpendicular to the tandem, in the plane of the tandem and the patient's
  left-right axis. Placed only when a tandem is present (an ROI the ``tandem`` applicator kind recognises, with a
  channel) and the fornix level is known (a ``Flange`` POINT ROI, else the cranial end of the obturator / vaginal
  cylinder: an ROI of the ``obturator`` or ``cylinder`` kind).
* ICRU bladder point (ICRU Report 38, 1985, §2.3; kept by ICRU 89 §10.4): on the anterior-posterior line through
  the centre of the Foley balloon, on the balloon's posterior surface. Placed when a ``Foley`` (or ``Balloon``)
  ROI is present.
* ICRU rectum point (ICRU 38 §2.3): on the anterior-posterior line through the intravaginal applicator at the
  level of its cranial end (the lower end of the intrauterine source), 5 mm posterior to the posterior vaginal
  wall, here the posterior surface of the obturator (vaginal cylinder). Placed when that ROI is present.

Applicator ROIs are recognised by :func:`reachplan.plugins.applicators.applicators_from_structures` (the kinds passed
in, the built-in ones by default), not by their names here.

Positions are mm, DICOM patient coordinates (LPS: +x left, +y posterior, +z cranial).
"""

from __future__ import annotations

import itertools
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from reachplan.imaging.types import Roi, StructureSet
from reachplan.plugins.applicators import BUILTIN_KINDS, ApplicatorKind, applicators_from_structures

POINT_A_CRANIAL_MM = 20.0
POINT_A_LATERAL_MM = 20.0
RECTUM_POINT_DEPTH_MM = 5.0
#: Applicator kinds that stand for the vaginal applicator (fornix level, ICRU rectum point).
VAGINAL_KINDS = ("obturator", "cylinder")
_FOLEY_NAMES = ("foley", "balloon", "foley balloon")


@dataclass(frozen=True, eq=False)
class PlacedPoint:
    """A reference point and how it was placed.

    Parameters
    ----------
    name : str
        The point's name (``Point A left``, ``ICRU bladder``, ...).
    position_mm : (3,) float, mm, LPS
        Where it is.
    how : str
        How it was placed, in words.
    """

    name: str
    position_mm: np.ndarray
    how: str


def _find(structures: StructureSet, names: tuple[str, ...]) -> Roi | None:
    for roi in structures.rois:
        if roi.name.strip().casefold() in names:
            return roi
    return None


def _points(roi: Roi) -> np.ndarray:
    pts = [c.points_mm for c in roi.contours if len(c.points_mm)]
    return np.concatenate(pts) if pts else np.zeros((0, 3))


def _axis(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Centre and unit principal axis of ``points`` (n, 3), oriented cranially (+z)."""
    centre = points.mean(axis=0)
    _, _, vt = np.linalg.svd(points - centre, full_matrices=False)
    u = vt[0] / np.linalg.norm(vt[0])
    return centre, (u if u[2] >= 0 else -u)


def point_a(tandem_points_mm: np.ndarray, fornix_mm: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Point A left and right (ICRU 89) from the tandem and the vaginal fornix (flange) level.

    Parameters
    ----------
    tandem_points_mm : (n, 3) float, mm, LPS
        Points of the tandem (its channel line or contours); its principal axis is the tandem axis.
    fornix_mm : (3,) float, mm, LPS
        A point at the level of the vaginal fornix (flange); projected on the tandem axis.

    Returns
    -------
    left, right : (3,) float, mm, LPS

    Raises
    ------
    ValueError
        Fewer than two tandem points, or a tandem along the left-right axis (no lateral direction).
    """
    pts = np.asarray(tandem_points_mm, dtype=float).reshape(-1, 3)
    if len(pts) < 2:
        raise ValueError("the tandem needs at least two points to give its axis")
    centre, u = _axis(pts)
    flange = centre + float((np.asarray(fornix_mm, dtype=float) - centre) @ u) * u
    left = np.array([1.0, 0.0, 0.0]) - u[0] * u  # patient left (+x) perpendicular to the tandem
    if np.linalg.norm(left) < 1e-6:
        raise ValueError("the tandem lies along the left-right axis; Point A is undefined")
    left /= np.linalg.norm(left)
    base = flange + POINT_A_CRANIAL_MM * u
    return base + POINT_A_LATERAL_MM * left, base - POINT_A_LATERAL_MM * left


def _slice_nearest(roi: Roi, z_mm: float) -> np.ndarray | None:
    closed = [c.points_mm for c in roi.contours if c.geometric_type == "CLOSED_PLANAR" and len(c.points_mm) >= 3]
    if not closed:
        return None
    return min(closed, key=lambda c: abs(float(c[:, 2].mean()) - z_mm))


def _posterior_on_ap_line(contour: np.ndarray, x_mm: float) -> float:
    """Y (mm) of the posterior crossing of the line x = ``x_mm`` with a closed planar contour."""
    pts = np.vstack([contour, contour[:1]])
    ys = []
    for a, b in itertools.pairwise(pts):
        if (a[0] - x_mm) * (b[0] - x_mm) <= 0 and a[0] != b[0]:
            t = (x_mm - a[0]) / (b[0] - a[0])
            ys.append(a[1] + t * (b[1] - a[1]))
    return float(max(ys)) if ys else float(contour[:, 1].max())


def icru_bladder_point(foley: Roi) -> np.ndarray | None:
    """ICRU 38 bladder point: posterior surface of the Foley balloon on the AP line through its centre.

    Parameters
    ----------
    foley : Roi
        The Foley balloon's ROI, closed contours in LPS mm.

    Returns
    -------
    (3,) float, mm, LPS, or None
        The point; None when the balloon has too few contour points.
    """
    pts = _points(foley)
    if len(pts) < 3:
        return None
    c = pts.mean(axis=0)
    contour = _slice_nearest(foley, float(c[2]))
    if contour is None:
        return None
    return np.array([c[0], _posterior_on_ap_line(contour, float(c[0])), float(contour[:, 2].mean())])


def icru_rectum_point(obturator: Roi) -> np.ndarray | None:
    """ICRU 38 rectum point: 5 mm posterior to the vaginal cylinder's posterior surface at its cranial end.

    The level is the last closed contour below the cranial end (the cylinder's wall, not its dome).

    Parameters
    ----------
    obturator : Roi
        The vaginal cylinder's (obturator's) ROI, closed contours in LPS mm.

    Returns
    -------
    (3,) float, mm, LPS, or None
        The point; None without a closed contour.
    """
    closed = [c.points_mm for c in obturator.contours if c.geometric_type == "CLOSED_PLANAR" and len(c.points_mm) >= 3]
    if not closed:
        return None
    top = max(closed, key=lambda c: float(c[:, 2].mean()))
    x = float(top[:, 0].mean())
    y = _posterior_on_ap_line(top, x) + RECTUM_POINT_DEPTH_MM
    return np.array([x, y, float(top[:, 2].mean())])


def place_reference_points(structures: StructureSet, kinds: Mapping[str, ApplicatorKind] = BUILTIN_KINDS,
                           assign: Mapping[str, str] | None = None,
                           ) -> tuple[tuple[PlacedPoint, ...], tuple[str, ...]]:
    """Point A left/right, the ICRU bladder and rectum points, where the structure set allows.

    Parameters
    ----------
    structures : StructureSet
        The case's ROIs (mm, LPS).
    kinds : mapping of str to ApplicatorKind
        The applicator kinds that recognise the tandem and the obturator / cylinder (default: the built-in ones).
    assign : mapping of str to str, optional
        ROI name -> applicator kind name, overriding recognition (``--applicator KIND=ROI``).

    Returns
    -------
    points : tuple of PlacedPoint
        Positions (3,) float, mm, LPS.
    notes : tuple of str
        One line per point that could not be placed, saying what is missing.
    """
    out: list[PlacedPoint] = []
    notes: list[str] = []
    applicators = applicators_from_structures(structures, kinds, assign)
    by_number = {r.number: r for r in structures.rois}
    tandem = next((by_number[a.roi_number] for a in applicators
                   if a.kind == "tandem" and a.channels and a.roi_number is not None), None)
    obturator = next((by_number[a.roi_number] for a in applicators
                      if a.kind in VAGINAL_KINDS and a.roi_number is not None), None)
    flange = _find(structures, ("flange", "fornix"))
    if tandem is None:
        notes.append("no tandem ROI: Point A (ICRU 89) not placed")
    else:
        fornix: np.ndarray | None = None
        if flange is not None and len(_points(flange)):
            fornix = _points(flange).mean(axis=0)
        elif obturator is not None and len(_points(obturator)):
            o = _points(obturator)
            fornix = o[np.argmax(o[:, 2])]
        if fornix is None:
            notes.append("no Flange point or Obturator ROI for the vaginal fornix level: Point A not placed")
        else:
            left, right = point_a(_points(tandem), fornix)  # all its points: the channel's axis, as drawn
            out += [PlacedPoint("Point A left", left, "ICRU 89 (tandem + fornix level)"),
                    PlacedPoint("Point A right", right, "ICRU 89 (tandem + fornix level)")]
    foley = _find(structures, _FOLEY_NAMES)
    bladder = icru_bladder_point(foley) if foley is not None else None
    if bladder is None:
        notes.append("no Foley balloon ROI: ICRU bladder point not placed")
    else:
        out.append(PlacedPoint("ICRU bladder", bladder, "ICRU 38 (Foley balloon)"))
    rectum = icru_rectum_point(obturator) if obturator is not None else None
    if rectum is None:
        notes.append("no Obturator (vaginal cylinder) ROI: ICRU rectum point not placed")
    else:
        out.append(PlacedPoint("ICRU rectum", rectum, "ICRU 38 (5 mm behind the vaginal cylinder)"))
    return tuple(out), tuple(notes)
