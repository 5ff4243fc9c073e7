"""Read an RT Structure Set into a :class:`reachplan.imaging.types.StructureSet`.

CLOSED_PLANAR contours become polygons, OPEN_NONPLANAR / OPEN_PLANAR contours (brachy channels,
markers) polylines and POINT contours single points, all in LPS mm. ROI names are normalised through a
:class:`~reachplan.imaging.names.SynonymTable`; the original name is kept. When a volume is given, the Frame of
Reference and the referenced series are checked against it.
"""

from __future__ import annotations

import warnings
from pathlib import Path
from typing import Any

import numpy as np

from reachplan.imaging.contour_checks import encloses_no_area, self_crossings
from reachplan.imaging.dicom_files import parsing, read_dataset
from reachplan.imaging.dicom_io import check_reference
from reachplan.imaging.errors import (
    CorruptFileError,
    DicomQuirkWarning,
    DuplicateRoiNameWarning,
    NoDicomError,
    OutsideImageWarning,
    SelfIntersectingContourWarning,
    SparseContourWarning,
    StructureError,
    ZeroAreaContourWarning,
)
from reachplan.imaging.names import DEFAULT_SYNONYMS, SynonymTable
from reachplan.imaging.types import Contour, PatientStudy, Roi, StructureSet, Volume

RT_STRUCTURE_SET_STORAGE = "1.2.840.10008.5.1.4.1.1.481.3"
GEOMETRIC_TYPES = frozenset({"CLOSED_PLANAR", "OPEN_PLANAR", "OPEN_NONPLANAR", "POINT", "CLOSEDPLANAR_XOR"})


def _contour_points(item: Any, path: Path, roi_label: str) -> np.ndarray:
    """``(n, 3)`` float LPS mm from ContourData, parsed straight from the raw bytes when possible."""
    tag = 0x30060050
    if tag not in item:
        raise StructureError(f"{path}: a contour of ROI {roi_label} has no ContourData; re-export the structure set")
    elem = item.get_item(tag)
    raw = getattr(elem, "value", None)
    try:
        if isinstance(raw, bytes | bytearray):
            text = raw.decode("ascii", errors="strict").strip(" \0")
            values = np.array([float(v) for v in text.split("\\")] if text else [], dtype=float)
        else:
            values = np.array([float(v) for v in np.atleast_1d(item.ContourData)], dtype=float)
    except (ValueError, UnicodeDecodeError):
        raise CorruptFileError(
            f"{path}: ContourData of ROI {roi_label} holds non-numeric values; the file is damaged, re-export it"
        ) from None
    if values.size == 0 or values.size % 3:
        raise StructureError(f"{path}: ContourData of ROI {roi_label} has {values.size} numbers, not a multiple "
                             "of 3 (x, y, z triplets); re-export the structure set")
    if not np.all(np.isfinite(values)):
        raise StructureError(f"{path}: ContourData of ROI {roi_label} holds NaN or infinite coordinates")
    pts = values.reshape(-1, 3)
    n_declared = item.get("NumberOfContourPoints")
    if n_declared is not None and n_declared != "" and int(n_declared) != len(pts):
        warnings.warn(DicomQuirkWarning(
            f"{path}: ROI {roi_label}: NumberOfContourPoints is {int(n_declared)} but ContourData holds "
            f"{len(pts)} points; using ContourData"), stacklevel=4)
    return pts


#: Fewest points a contour of each kind needs to describe anything (a polygon, a polyline, a point).
MIN_POINTS = {"CLOSED_PLANAR": 3, "OPEN_PLANAR": 2, "OPEN_NONPLANAR": 2, "POINT": 1}


def _warn_sparse(path: Path, label: str, contours: list[Contour]) -> None:
    """One :class:`SparseContourWarning` per ROI whose contours have fewer points than their kind needs."""
    sparse = [c for c in contours if len(c.points_mm) < MIN_POINTS.get(c.geometric_type, 1)]
    if sparse:
        counts = sorted({len(c.points_mm) for c in sparse})
        kinds = sorted({c.geometric_type for c in sparse})
        warnings.warn(SparseContourWarning(
            f"{path}: ROI {label}: {len(sparse)} {'/'.join(kinds)} contour(s) with only "
            f"{' or '.join(str(n) for n in counts)} point(s); they enclose nothing and are left out of masks and "
            "volumes: check the contouring"), stacklevel=4)


def _warn_degenerate(path: Path, label: str, contours: list[Contour]) -> None:
    """Warn about a ROI's closed contours that enclose no area or cross themselves (one warning of each kind).

    A :class:`ZeroAreaContourWarning` for contours of 3 or more points on a line (left out of masks and volumes),
    a :class:`SelfIntersectingContourWarning` for contours whose edges cross (filled by the even-odd rule).
    """
    closed = [c for c in contours if c.geometric_type == "CLOSED_PLANAR" and len(c.points_mm) >= 3]
    flat = [c for c in closed if encloses_no_area(c.points_mm)]
    if flat:
        warnings.warn(ZeroAreaContourWarning(
            f"{path}: ROI {label}: {len(flat)} closed contour(s) enclose no area (first on the plane through "
            f"{_where(flat[0])}); they are left out of masks and volumes: check the contouring"), stacklevel=4)
    crossed = [(c, n) for c in closed if not encloses_no_area(c.points_mm) and (n := self_crossings(c.points_mm))]
    if crossed:
        warnings.warn(SelfIntersectingContourWarning(
            f"{path}: ROI {label}: {len(crossed)} closed contour(s) cross themselves ({sum(n for _, n in crossed)} "
            f"crossing(s); first on the plane through {_where(crossed[0][0])}); masks and volumes fill them by the "
            "even-odd rule (each lobe once, overlaps left out): check the contouring"), stacklevel=4)


def _where(contour: Contour) -> str:
    """Return the first point of a contour as ``(x, y, z) mm``."""
    return "(" + ", ".join(f"{v:.1f}" for v in contour.points_mm[0]) + ") mm"


#: How far outside the image volume (mm) a contour point may lie (contours are drawn on slice centres and may touch
#: the border), and how far any point may lie before its ROI is reported even when the rest is inside.
OUTSIDE_MARGIN_MM = 5.0
FAR_OUTSIDE_MM = 50.0


def _warn_outside(path: Path, rois: list[Roi], volume: Volume) -> None:
    """Warn about ROIs outside the image volume.

    One :class:`OutsideImageWarning` per ROI that lies wholly more than :data:`OUTSIDE_MARGIN_MM` outside the
    image volume (its voxel centres' box), or reaches more than :data:`FAR_OUTSIDE_MM` beyond it.
    """
    grid = volume.grid
    upper = np.array(grid.shape[::-1], dtype=float) - 1.0  # (i, j, k)
    tol = OUTSIDE_MARGIN_MM / np.asarray(grid.spacing_mm, dtype=float)
    for roi in rois:
        if not roi.contours:
            continue
        pts = np.concatenate([c.points_mm for c in roi.contours])
        ijk = grid.to_index(pts)
        out = np.any((ijk < -tol) | (ijk > upper + tol), axis=1)
        far = float(np.max(np.maximum(-ijk - tol, ijk - upper - tol).clip(min=0) * grid.spacing_mm))
        if out.all() or far + OUTSIDE_MARGIN_MM > FAR_OUTSIDE_MM:
            share = "all" if out.all() else f"{out.mean():.0%} of the"
            warnings.warn(OutsideImageWarning(
                f"{path}: ROI {roi.number} ({roi.name}): {share} contour points lie outside the images (up to "
                f"{far + OUTSIDE_MARGIN_MM:.0f} mm beyond); check that the structure set belongs to these images"),
                stacklevel=4)


def _warn_same_names(path: Path, rois: list[Roi]) -> None:
    """Warn (:class:`DuplicateRoiNameWarning`) about ROIs whose names are equal but for case (or equal).

    Such ROIs are kept and told apart by ROI number (an Oncentra/Vitesse set has channels ``B5.5`` and ``b5.5``);
    only a name used as a target or organ must be unique (the planner refuses it then).
    """
    groups: dict[str, list[Roi]] = {}
    for r in rois:
        groups.setdefault(r.name.strip().casefold(), []).append(r)
    for same in (g for g in groups.values() if len(g) > 1):
        listed = ", ".join(f"{r.name!r} (ROI {r.number})" for r in same)
        how = "the same name" if len({r.name.strip() for r in same}) == 1 else "names that differ only in case"
        warnings.warn(DuplicateRoiNameWarning(
            f"{path.name}: ROIs {listed} have {how}; they are told apart by ROI number (a name used as a target "
            "or organ must be unique: rename one in the TPS)"), stacklevel=4)


def _image_ref(item: Any) -> tuple[str, str]:
    """Return the (SOP Class UID, SOP Instance UID) an image reference item names ("" when missing)."""
    return (str(item.get("ReferencedSOPClassUID", "") or ""), str(item.get("ReferencedSOPInstanceUID", "") or ""))


def _referenced(ds: Any) -> tuple[str, str | None, tuple[tuple[str, str], ...]]:
    """Return a structure set's Frame of Reference UID, referenced series (or None) and that series' images."""
    for_uid = str(ds.get("FrameOfReferenceUID", "") or "")
    series: str | None = None
    images: tuple[tuple[str, str], ...] = ()
    for ref in ds.get("ReferencedFrameOfReferenceSequence", []) or []:
        for_uid = for_uid or str(ref.get("FrameOfReferenceUID", "") or "")
        for study in ref.get("RTReferencedStudySequence", []) or []:
            for s in study.get("RTReferencedSeriesSequence", []) or []:
                if s.get("SeriesInstanceUID") and series is None:
                    series = str(s.SeriesInstanceUID)
                    images = tuple(r for r in (_image_ref(i) for i in s.get("ContourImageSequence", []) or [])
                                   if all(r))
    return for_uid, series, images


def read_rtstruct(
    path: Path, volume: Volume | None = None, *, synonyms: SynonymTable | None = None
) -> StructureSet:
    """Read an RT Structure Set.

    Parameters
    ----------
    path : Path
        The RT Structure Set file.
    volume : Volume, optional
        The images it was drawn on; when given, its Frame of Reference and referenced series must match.
    synonyms : SynonymTable, optional
        ROI name table (default :data:`reachplan.imaging.names.DEFAULT_SYNONYMS`).

    Returns
    -------
    StructureSet
        ROIs in file order; contour points ``(n, 3)`` float, mm, LPS.

    Raises
    ------
    NoDicomError
        Not DICOM, or DICOM but not an RT Structure Set.
    CorruptFileError
        Truncated or unparsable.
    StructureError
        Broken structure (no ROI list, contours of an undeclared ROI, bad ContourData).
    ReferenceMismatchError
        ``volume`` is another series or Frame of Reference.
    """
    path = Path(path)
    if not path.is_file():
        raise NoDicomError(f"{path} is not a file; give the RT Structure Set file (RS*.dcm)")
    ds = read_dataset(path, required=True)
    with parsing(path):
        return _structure_set(ds, path, volume, synonyms)


def _structure_set(ds: Any, path: Path, volume: Volume | None, synonyms: SynonymTable | None) -> StructureSet:
    sop_class = str(ds.get("SOPClassUID", ""))
    if str(ds.get("Modality", "")).upper() != "RTSTRUCT" and sop_class != RT_STRUCTURE_SET_STORAGE:
        raise NoDicomError(f"{path} is a {ds.get('Modality', 'DICOM')} object, not an RT Structure Set")
    table = synonyms or DEFAULT_SYNONYMS
    if "StructureSetROISequence" not in ds:
        raise StructureError(f"{path}: no StructureSetROISequence (the list of ROIs); re-export the structure set")
    declared: dict[int, Any] = {}
    for item in ds.StructureSetROISequence:
        if item.get("ROINumber") in (None, ""):
            raise StructureError(f"{path}: a StructureSetROISequence item has no ROINumber")
        number = int(item.ROINumber)
        if number in declared:
            raise StructureError(f"{path}: ROI number {number} is declared twice")
        declared[number] = item
    types = {int(o.ReferencedROINumber): str(o.get("RTROIInterpretedType", "") or "")
             for o in ds.get("RTROIObservationsSequence", []) or [] if o.get("ReferencedROINumber") not in (None, "")}
    contours: dict[int, list[Contour]] = {n: [] for n in declared}
    colors: dict[int, tuple[int, int, int]] = {}
    for rc in ds.get("ROIContourSequence", []) or []:
        if rc.get("ReferencedROINumber") in (None, ""):
            raise StructureError(f"{path}: a ROIContourSequence item has no ReferencedROINumber")
        number = int(rc.ReferencedROINumber)
        if number not in declared:
            raise StructureError(f"{path}: contours reference ROI number {number}, which the structure set does "
                                 "not declare; the file is inconsistent, re-export it")
        label = f"{number} ({declared[number].get('ROIName', '')})"
        color = rc.get("ROIDisplayColor")
        if color is not None and len(color) == 3:
            colors[number] = (int(color[0]), int(color[1]), int(color[2]))
        for item in rc.get("ContourSequence", []) or []:
            gtype = str(item.get("ContourGeometricType", "") or "").upper()
            if gtype not in GEOMETRIC_TYPES:
                raise StructureError(f"{path}: ROI {label} has a contour of unknown type {gtype or 'none'!r}")
            pts = _contour_points(item, path, label)
            if gtype == "CLOSEDPLANAR_XOR":  # DICOM 2020+: XOR-combined closed planar contours
                gtype = "CLOSED_PLANAR"
            refs = item.get("ContourImageSequence", []) or []
            image = _image_ref(refs[0]) if len(refs) == 1 else ("", "")
            contours[number].append(Contour(pts, gtype, image if all(image) else ("", "")))
        _warn_sparse(path, label, contours[number])
        _warn_degenerate(path, label, contours[number])
    rois = []
    for number, item in declared.items():
        name = str(item.get("ROIName", "") or f"ROI_{number}")
        rois.append(Roi(number=number, name=name, contours=tuple(contours[number]),
                        normalized_name=table.normalize(name), interpreted_type=types.get(number, ""),
                        color=colors.get(number)))
    _warn_same_names(path, rois)
    for_uid, series_uid, images = _referenced(ds)
    if volume is not None:
        check_reference(volume, for_uid, series_uid, f"RT Structure Set {path}")
        _warn_outside(path, rois, volume)
    return StructureSet(
        rois=tuple(rois), frame_of_reference_uid=for_uid, referenced_series_uid=series_uid,
        sop_instance_uid=str(ds.get("SOPInstanceUID", "")), label=str(ds.get("StructureSetLabel", "")),
        patient_study=PatientStudy.read(ds),
        referenced_images=images,
    )
