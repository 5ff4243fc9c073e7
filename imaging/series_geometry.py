"""The geometry of an image series: each frame's position, orientation and spacing, and the regular grid they form.

Slices are sorted along the slice normal (never by file name or InstanceNumber); spacing, orientation and
positions are checked, and anything that would give a silently wrong volume is a
:class:`~reachplan.imaging.errors.SeriesError`. Enhanced (multi-frame) objects give one frame per functional group.
"""

from __future__ import annotations

import warnings
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from reachplan.imaging.dicom_files import corrupt_error, invalid_error
from reachplan.imaging.errors import InvalidValueError, ObliqueSliceWarning, SeriesError, UnsupportedDataError
from reachplan.imaging.types import Grid


@dataclass(frozen=True)
class Frame:
    """One image frame of a series and its geometry, as the header gives it (no pixel data).

    Parameters
    ----------
    path : Path
        The file holding the frame.
    frame : int or None
        Index into a multi-frame object; None for a single-frame file.
    position : (3,) float, mm, LPS
        ImagePositionPatient.
    orientation : (6,) float
        ImageOrientationPatient (row and column direction cosines).
    spacing : (float, float), mm
        PixelSpacing (row spacing, column spacing).
    rows, columns : int
        Image size, pixels.
    slope, intercept : float
        Rescale from stored values to output values (HU for CT).
    thickness : float, optional, mm
        SliceThickness, used only for a single-slice series.
    """

    path: Path
    frame: int | None  # index into a multi-frame object; None = single-frame file
    position: np.ndarray  # (3,) ImagePositionPatient, LPS mm
    orientation: np.ndarray  # (6,) ImageOrientationPatient
    spacing: tuple[float, float]  # PixelSpacing (row spacing, column spacing), mm
    rows: int
    columns: int
    slope: float
    intercept: float
    thickness: float | None = None  # SliceThickness, used only for a single-slice series



def _floats(ds: Any, keyword: str, n: int, path: Path) -> np.ndarray:
    value = ds.get(keyword)
    if value is None or value == "":
        raise invalid_error(path, f"required attribute {keyword} is missing")
    try:
        v = np.array([float(x) for x in value] if n > 1 and not isinstance(value, str | bytes) else
                     [float(value)], dtype=float)
    except (TypeError, ValueError):
        raise invalid_error(path, f"{keyword} is not numeric ({value!r})") from None
    if v.shape != (n,) or not np.all(np.isfinite(v)):
        raise invalid_error(path, f"{keyword} must hold {n} finite numbers, got {value!r}")
    return v


def rescale(ds: Any, path: Path) -> tuple[float, float]:
    """Return the rescale ``(slope, intercept)`` of a dataset or functional group (``(1, 0)`` when absent).

    Parameters
    ----------
    ds : pydicom.Dataset
        A dataset, or one functional group's Pixel Value Transformation item.
    path : Path
        Its file (named in the messages).

    Returns
    -------
    (float, float)
        RescaleSlope and RescaleIntercept: output value (HU for CT) = slope * stored + intercept.

    Raises
    ------
    InvalidValueError
        A zero slope, or a slope beyond 1e6 or an intercept beyond 1e7.
    CorruptFileError
        A value that is not a finite number.
    """
    slope = float(_floats(ds, "RescaleSlope", 1, path)[0]) if ds.get("RescaleSlope") is not None else 1.0
    intercept = float(_floats(ds, "RescaleIntercept", 1, path)[0]) if ds.get("RescaleIntercept") is not None \
        else 0.0
    if slope == 0 or abs(slope) > 1e6 or abs(intercept) > 1e7:
        raise InvalidValueError(f"{path}: RescaleSlope is {slope:g} and RescaleIntercept {intercept:g}; the slope must "
                                "be non-zero within 1e6 and the intercept within 1e7: fix the header or re-export")
    return slope, intercept


def frames_of(ds: Any, path: Path) -> list[Frame]:
    """Return the image frames of one object with their geometry (one per functional group when multi-frame).

    Parameters
    ----------
    ds : pydicom.Dataset
        The image object's header.
    path : Path
        Its file.

    Returns
    -------
    list of Frame
        One frame for a single-frame file; one per item of the Per-Frame Functional Groups Sequence otherwise.

    Raises
    ------
    UnsupportedDataError
        A multi-frame object without per-frame functional groups.
    CorruptFileError
        Missing or non-numeric geometry, or per-frame groups that do not match NumberOfFrames.
    """
    rows, cols = int(ds.get("Rows", 0) or 0), int(ds.get("Columns", 0) or 0)
    if rows < 1 or cols < 1:
        raise invalid_error(path, f"image has {rows} rows and {cols} columns")
    n_frames = int(ds.get("NumberOfFrames", 1) or 1)
    if "PerFrameFunctionalGroupsSequence" not in ds:
        if n_frames != 1:
            raise UnsupportedDataError(
                f"{path}: multi-frame object without per-frame functional groups (no plane positions); "
                "convert it to single-frame slices"
            )
        slope, intercept = rescale(ds, path)
        ps = _floats(ds, "PixelSpacing", 2, path)
        thickness = ds.get("SliceThickness")
        try:
            thick = float(thickness) if thickness not in (None, "") and 0 < float(thickness) <= 1e3 else None
        except (TypeError, ValueError):
            thick = None
        return [Frame(path, None, _floats(ds, "ImagePositionPatient", 3, path),
                       _floats(ds, "ImageOrientationPatient", 6, path), (ps[0], ps[1]), rows, cols, slope, intercept,
                       thick)]
    shared = ds.SharedFunctionalGroupsSequence[0] if "SharedFunctionalGroupsSequence" in ds else None
    per_frame = ds.PerFrameFunctionalGroupsSequence
    if len(per_frame) != n_frames:
        raise corrupt_error(path, f"NumberOfFrames is {n_frames} but there are {len(per_frame)} per-frame groups")

    def macro(item: Any, seq: str) -> Any:
        for group in (item, shared):
            if group is not None and seq in group and len(group[seq].value):
                return group[seq][0]
        return None

    out = []
    for f, item in enumerate(per_frame):
        pos, ori, meas, trans = (macro(item, s) for s in (
            "PlanePositionSequence", "PlaneOrientationSequence", "PixelMeasuresSequence",
            "PixelValueTransformationSequence"))
        if pos is None or ori is None or meas is None:
            raise corrupt_error(path, f"frame {f + 1} lacks plane position, orientation or pixel measures")
        slope, intercept = rescale(trans, path) if trans is not None else rescale(ds, path)
        ps = _floats(meas, "PixelSpacing", 2, path)
        out.append(Frame(path, f, _floats(pos, "ImagePositionPatient", 3, path),
                          _floats(ori, "ImageOrientationPatient", 6, path), (ps[0], ps[1]), rows, cols,
                          slope, intercept))
    return out



#: Smallest pixel and slice spacing accepted, mm: 10 µm, below any CT or MR voxel (micro-CT reaches a few µm, but
#: not of a patient); a smaller one is a damaged header (a PixelSpacing of 1e-320 would make the affine singular).
MIN_SPACING_MM = 0.01
#: Largest pixel and slice spacing accepted, mm.
MAX_SPACING_MM = 1e3


@dataclass(frozen=True)
class SeriesTolerance:
    """How strictly a series must be regular.

    Parameters
    ----------
    spacing : float
        Relative tolerance on slice-to-slice spacing (and on positions along the slice axis), in (0, 0.5).
    orientation : float
        Absolute tolerance on ImageOrientationPatient components (direction cosines), in (0, 0.1).
    allow_gantry_tilt : bool
        Accept slices whose positions step sideways (gantry tilt) with an
        :class:`~reachplan.imaging.errors.ObliqueSliceWarning`; the affine then carries the shear exactly.

    Raises
    ------
    ValueError
        A tolerance out of its range.
    """

    spacing: float = 0.01
    orientation: float = 1e-4
    allow_gantry_tilt: bool = False

    def __post_init__(self) -> None:
        if not (0 < self.spacing < 0.5 and 0 < self.orientation < 0.1):
            raise ValueError("SeriesTolerance needs 0 < spacing < 0.5 and 0 < orientation < 0.1")


def assemble_geometry(frames: Sequence[Frame], tol: SeriesTolerance, label: str) -> tuple[Grid, list[int]]:
    """Check that ``frames`` form one regular volume; return its grid and the frames' order along k.

    Parameters
    ----------
    frames : sequence of Frame
        The frames of one series with their geometry (positions and orientations in LPS mm).
    tol : SeriesTolerance
        How regular the frames must be.
    label : str
        Names the series in messages.

    Returns
    -------
    grid : Grid
        Shape ``(n_frames, rows, columns)``; ``patient_from_index`` in LPS mm, sheared when gantry tilt is
        allowed.
    order : list of int
        ``order[k]`` is the index into ``frames`` of slice ``k`` (sorted along the slice normal).

    Raises
    ------
    SeriesError
        Different image sizes, pixel spacings or orientations, duplicate or missing slices, irregular
        spacing, slices not on a line, gantry tilt (unless allowed).
    """
    sizes = {(f.rows, f.columns) for f in frames}
    if len(sizes) > 1:
        raise SeriesError(f"{label}: slices have different sizes {sorted(sizes)}; it is not one volume")
    ori = np.array([f.orientation for f in frames])
    if np.abs(ori - ori[0]).max() > tol.orientation:
        raise SeriesError(f"{label}: slices have different orientations (ImageOrientationPatient); "
                          "select one stack or reslice it")
    row, col = ori[0, :3], ori[0, 3:]
    if abs(np.linalg.norm(row) - 1) > 1e-3 or abs(np.linalg.norm(col) - 1) > 1e-3 or abs(row @ col) > 1e-3:
        raise SeriesError(f"{label}: ImageOrientationPatient {ori[0].tolist()} is not two orthogonal unit vectors")
    row, col = row / np.linalg.norm(row), col / np.linalg.norm(col)
    spacing = np.array([f.spacing for f in frames])
    if np.any(spacing < MIN_SPACING_MM) or np.any(spacing > MAX_SPACING_MM) or \
            np.abs(spacing - spacing[0]).max() > 1e-4 * spacing[0].max():
        raise SeriesError(f"{label}: PixelSpacing {spacing[0].tolist()} mm is not between {MIN_SPACING_MM:g} and "
                          f"{MAX_SPACING_MM:g} mm or differs between slices; fix the header or re-export the series")
    pos = np.array([f.position for f in frames])
    if np.abs(pos).max() > 1e6:
        raise SeriesError(f"{label}: ImagePositionPatient beyond 1 km ({np.abs(pos).max():g} mm); fix the header "
                          "or re-export the series")
    normal = np.cross(row, col)
    d = pos @ normal
    order = [int(i) for i in np.argsort(d, kind="stable")]
    d_sorted, pos_sorted = d[order], pos[order]
    if len(frames) == 1:
        step = normal * (frames[0].thickness or 1.0)
    else:
        diffs = np.diff(d_sorted)
        scale = max(float(np.median(diffs)), 1e-9)
        dup = int(np.sum(diffs < tol.spacing * max(scale, 1e-3)))
        if dup or scale < 1e-6:
            raise SeriesError(f"{label}: {max(dup, 1)} duplicate slice position(s) along the slice normal; "
                              "remove the duplicate images or pick one acquisition")
        if np.abs(diffs - scale).max() > tol.spacing * scale:
            ratio = diffs / scale
            gaps = np.flatnonzero(np.abs(ratio - np.round(ratio)) < tol.spacing * 5 * np.round(ratio))
            gaps = gaps[np.round(ratio[gaps]) >= 2]
            if len(gaps):
                k = int(gaps[0])
                raise SeriesError(f"{label}: missing slice(s) between positions {d_sorted[k]:.2f} and "
                                  f"{d_sorted[k + 1]:.2f} mm (spacing {scale:.3g} mm); re-export the complete series")
            raise SeriesError(f"{label}: irregular slice spacing ({diffs.min():.3g} to {diffs.max():.3g} mm); "
                              "resample the series to a regular grid")
        step = (pos_sorted[-1] - pos_sorted[0]) / (len(frames) - 1)
        line = pos_sorted[0] + np.outer(np.arange(len(frames)), step)
        if np.linalg.norm(pos_sorted - line, axis=1).max() > tol.spacing * scale:
            raise SeriesError(f"{label}: slice positions do not lie on a straight line; re-export the series")
        sideways = np.linalg.norm(step - (step @ normal) * normal)
        if sideways > tol.spacing * scale:
            angle = np.degrees(np.arctan2(sideways, step @ normal))
            if not tol.allow_gantry_tilt:
                raise SeriesError(f"{label}: slices are sheared by {angle:.1f} degrees (gantry tilt); "
                                  "resample it or read with SeriesTolerance(allow_gantry_tilt=True)")
            warnings.warn(ObliqueSliceWarning(
                f"{label}: gantry tilt of {angle:.1f} degrees; the volume's affine is sheared accordingly"),
                stacklevel=3)
    m = np.eye(4)
    m[:3, 0] = row * spacing[0][1]
    m[:3, 1] = col * spacing[0][0]
    m[:3, 2] = step
    m[:3, 3] = pos_sorted[0]
    slice_mm = float(np.linalg.norm(step))
    if not np.all(np.isfinite(m)) or not MIN_SPACING_MM <= slice_mm <= MAX_SPACING_MM:
        raise SeriesError(f"{label}: the slice spacing is {slice_mm:g} mm (allowed {MIN_SPACING_MM:g} to "
                          f"{MAX_SPACING_MM:g} mm); fix the positions or SliceThickness, or re-export the series")
    rows, columns = frames[0].rows, frames[0].columns
    return Grid((len(frames), rows, columns), m), order
