"""Read DICOM image series (CT, MR, ...) into a :class:`reachplan.imaging.types.Volume`.

A folder may hold several series and other objects (RT Structure Sets, plans, non-DICOM files). Slices
are sorted along the slice normal (never by file name or InstanceNumber); spacing, orientation and
geometry are checked, and anything that would give a silently wrong volume is a typed error
(:mod:`reachplan.imaging.errors`). Enhanced (multi-frame) CT/MR objects are read frame by frame.
"""

from __future__ import annotations

import os
import struct
import warnings
import zlib
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from pydicom.errors import BytesLengthException

from reachplan.imaging.errors import (
    CorruptFileError,
    ImagingError,
    InvalidValueError,
    NoDicomError,
    ObliqueSliceWarning,
    ReferenceMismatchError,
    SeriesError,
    UnsupportedDataError,
)
from reachplan.imaging.types import Grid, PatientStudy, Volume

MEDIA_STORAGE_DIRECTORY = "1.2.840.10008.1.3.10"  # DICOMDIR

#: Modalities that are never image series, whatever pixel data they carry.
NON_IMAGE_MODALITIES = frozenset({"RTSTRUCT", "RTPLAN", "RTDOSE", "RTRECORD", "REG", "SEG", "SR", "KO", "PR"})

# --------------------------------------------------------------------------------------------------
# Finding and opening files
# --------------------------------------------------------------------------------------------------


def list_files(path: Path) -> list[Path]:
    """List every regular, non-hidden file at ``path`` (itself, or recursively below a folder), sorted.

    Parameters
    ----------
    path : Path
        A file or a folder.

    Returns
    -------
    list of Path
        The files, sorted.

    Raises
    ------
    NoDicomError
        When ``path`` does not exist.
    """
    path = Path(path)
    if path.is_file():
        return [path]
    if not path.is_dir():
        raise NoDicomError(f"{path} does not exist; give a DICOM file or a folder that holds DICOM files")
    out = []
    for root, dirs, files in os.walk(path):
        dirs[:] = sorted(d for d in dirs if not d.startswith("."))
        out += [Path(root) / f for f in sorted(files) if not f.startswith(".")]
    return out


def _looks_like_dicom(path: Path) -> bool:
    """Tell whether the file claims to be DICOM: ``DICM`` magic at byte 128 or a ``.dcm`` name."""
    if path.suffix.lower() in (".dcm", ".dicom"):
        return True
    try:
        with path.open("rb") as fh:
            fh.seek(128)
            return fh.read(4) == b"DICM"
    except OSError:
        return False


def _corrupt(path: Path, what: str) -> CorruptFileError:
    return CorruptFileError(f"{path}: {what}; the file is truncated or damaged: re-export it or remove it")


def _invalid(path: Path, what: str) -> CorruptFileError:
    return CorruptFileError(f"{path}: {what}; the file breaks the DICOM standard: fix or re-export it")


DEFLATED = frozenset({"1.2.840.10008.1.2.1.99", "1.2.840.10008.1.2.8.1"})  # Deflated Explicit VR LE, Deflated Image


def _check_complete(ds: Any, path: Path) -> None:
    """Raise :class:`CorruptFileError` when the last element of ``ds`` runs past the end of the file.

    Deflated files are not checked here: their element offsets count in the inflated stream, and a truncated
    deflate stream already fails while pydicom reads it.
    """
    if str(getattr(getattr(ds, "file_meta", None), "get", lambda *_: "")("TransferSyntaxUID", "")) in DEFLATED:
        return
    size = path.stat().st_size
    tags = list(ds.keys())
    if not tags:
        raise _corrupt(path, "no data elements after the file meta header")
    elem = ds.get_item(tags[-1], keep_deferred=True)
    tell = getattr(elem, "value_tell", None)
    length = getattr(elem, "length", None)
    if tell is not None and length is not None and length != 0xFFFFFFFF and tell + length > size:
        raise _corrupt(path, f"element {elem.tag} needs {tell + length} bytes but the file has {size}")
    if length == 0xFFFFFFFF and getattr(ds, "is_little_endian", True):
        with path.open("rb") as fh:  # an undefined-length sequence must end with its delimiter
            fh.seek(max(0, size - 8))
            if fh.read() != b"\xfe\xff\xdd\xe0\x00\x00\x00\x00":
                raise _corrupt(path, f"sequence {elem.tag} has no end delimiter")


def read_dataset(
    path: Path, *, header_only: bool = False, required: bool = False, defer_size: int | None = None
) -> Any:
    """Read one DICOM file with pydicom.

    Returns ``None`` for a file that does not claim to be DICOM (no ``DICM`` magic, no ``.dcm`` name) and
    cannot be read as DICOM. A file that claims to be DICOM but cannot be read is an error.

    Parameters
    ----------
    path : Path
        The file.
    header_only : bool
        Stop before the pixel data (no completeness check).
    required : bool
        A file that is not DICOM at all is an error too (:class:`NoDicomError`).
    defer_size : int, optional
        Values longer than this many bytes are read from the file only when used.

    Returns
    -------
    pydicom.Dataset or None

    Raises
    ------
    CorruptFileError
        The file claims to be DICOM (or is parsed as such) but is truncated or cannot be parsed.
    NoDicomError
        With ``required``: the file is not DICOM.
    """
    from pydicom import dcmread
    from pydicom.errors import InvalidDicomError

    claims = _looks_like_dicom(path)
    try:
        ds = dcmread(path, stop_before_pixels=header_only, defer_size=defer_size)
    except InvalidDicomError:
        if not claims:
            if required:
                raise NoDicomError(f"{path} is not a DICOM file; give a DICOM file or folder") from None
            return None
        try:  # a DICOM dataset without preamble / file meta is still readable
            ds = dcmread(path, stop_before_pixels=header_only, defer_size=defer_size, force=True)
        except Exception as exc:
            raise _corrupt(path, f"cannot be parsed as DICOM ({type(exc).__name__})") from None
        if "SOPClassUID" not in ds:
            raise _corrupt(path, "has no DICOM preamble and no SOP Class UID") from None
    except PARSE_ERRORS as exc:
        raise _corrupt(path, f"cannot be parsed as DICOM ({type(exc).__name__}: {_one_line(exc)})") from None
    if not header_only:
        _check_complete(ds, path)
    with parsing(path):
        media_class = str(getattr(getattr(ds, "file_meta", None), "MediaStorageSOPClassUID", "") or "")
        if "SOPClassUID" not in ds and "Modality" not in ds and media_class != MEDIA_STORAGE_DIRECTORY:
            raise _corrupt(path, "has neither SOP Class UID nor Modality")
        _ = ds.get("Modality"), ds.get("SOPClassUID")  # the values every caller looks at first
    return ds


#: What pydicom raises on damaged bytes, when a file is read or when its values are first used.
PARSE_ERRORS: tuple[type[Exception], ...] = (
    OSError, EOFError, ValueError, KeyError, TypeError, IndexError, AttributeError, OverflowError, struct.error,
    NotImplementedError, RuntimeError, BytesLengthException, zlib.error, MemoryError,
)


@contextmanager
def parsing(path: Path) -> Iterator[None]:
    """Turn pydicom's errors on damaged values met while using a dataset into :class:`CorruptFileError`."""
    try:
        yield
    except ImagingError:
        raise
    except PARSE_ERRORS as exc:
        raise _corrupt(path, f"a value cannot be parsed ({type(exc).__name__}: {_one_line(exc)})") from None


def _one_line(exc: BaseException, limit: int = 160) -> str:
    """Return ``exc``'s message on one line, without the traceback pydicom embeds in nested errors.

    The chain of "With tag X got exception:" prefixes is kept as the path of tags to the damaged element.
    """
    text = " ".join(str(exc).split("Traceback (most recent call last)")[0].split())
    return text if len(text) <= limit else text[: limit - 3] + "..."


one_line = _one_line


# --------------------------------------------------------------------------------------------------
# Frames and series
# --------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class _Frame:
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


@dataclass(frozen=True)
class SeriesSummary:
    """What a folder holds for one image series (no pixel data read).

    Parameters
    ----------
    series_instance_uid, modality, description, frame_of_reference_uid : str
        From the first object of the series (empty when not given).
    n_frames : int
        Image frames over all the series' objects.
    rows, columns : int
        Image size of the first object, pixels.
    paths : tuple of Path
        The series' files, in scan order.
    """

    series_instance_uid: str
    modality: str
    description: str
    frame_of_reference_uid: str
    n_frames: int
    rows: int
    columns: int
    paths: tuple[Path, ...]


def _floats(ds: Any, keyword: str, n: int, path: Path) -> np.ndarray:
    value = ds.get(keyword)
    if value is None or value == "":
        raise _invalid(path, f"required attribute {keyword} is missing")
    try:
        v = np.array([float(x) for x in value] if n > 1 and not isinstance(value, str | bytes) else
                     [float(value)], dtype=float)
    except (TypeError, ValueError):
        raise _invalid(path, f"{keyword} is not numeric ({value!r})") from None
    if v.shape != (n,) or not np.all(np.isfinite(v)):
        raise _invalid(path, f"{keyword} must hold {n} finite numbers, got {value!r}")
    return v


def _rescale(ds: Any, path: Path) -> tuple[float, float]:
    slope = float(_floats(ds, "RescaleSlope", 1, path)[0]) if ds.get("RescaleSlope") is not None else 1.0
    intercept = float(_floats(ds, "RescaleIntercept", 1, path)[0]) if ds.get("RescaleIntercept") is not None \
        else 0.0
    if slope == 0 or abs(slope) > 1e6 or abs(intercept) > 1e7:
        raise InvalidValueError(f"{path}: RescaleSlope is {slope:g} and RescaleIntercept {intercept:g}; the slope must "
                                "be non-zero within 1e6 and the intercept within 1e7: fix the header or re-export")
    return slope, intercept


def _frames_of(ds: Any, path: Path) -> list[_Frame]:
    """Return the image frames of one object with their geometry."""
    rows, cols = int(ds.get("Rows", 0) or 0), int(ds.get("Columns", 0) or 0)
    if rows < 1 or cols < 1:
        raise _invalid(path, f"image has {rows} rows and {cols} columns")
    n_frames = int(ds.get("NumberOfFrames", 1) or 1)
    if "PerFrameFunctionalGroupsSequence" not in ds:
        if n_frames != 1:
            raise UnsupportedDataError(
                f"{path}: multi-frame object without per-frame functional groups (no plane positions); "
                "convert it to single-frame slices"
            )
        slope, intercept = _rescale(ds, path)
        ps = _floats(ds, "PixelSpacing", 2, path)
        thickness = ds.get("SliceThickness")
        try:
            thick = float(thickness) if thickness not in (None, "") and 0 < float(thickness) <= 1e3 else None
        except (TypeError, ValueError):
            thick = None
        return [_Frame(path, None, _floats(ds, "ImagePositionPatient", 3, path),
                       _floats(ds, "ImageOrientationPatient", 6, path), (ps[0], ps[1]), rows, cols, slope, intercept,
                       thick)]
    shared = ds.SharedFunctionalGroupsSequence[0] if "SharedFunctionalGroupsSequence" in ds else None
    per_frame = ds.PerFrameFunctionalGroupsSequence
    if len(per_frame) != n_frames:
        raise _corrupt(path, f"NumberOfFrames is {n_frames} but there are {len(per_frame)} per-frame groups")

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
            raise _corrupt(path, f"frame {f + 1} lacks plane position, orientation or pixel measures")
        slope, intercept = _rescale(trans, path) if trans is not None else _rescale(ds, path)
        ps = _floats(meas, "PixelSpacing", 2, path)
        out.append(_Frame(path, f, _floats(pos, "ImagePositionPatient", 3, path),
                          _floats(ori, "ImageOrientationPatient", 6, path), (ps[0], ps[1]), rows, cols,
                          slope, intercept))
    return out


def _is_image(ds: Any) -> bool:
    modality = str(ds.get("Modality", "")).upper()
    return modality not in NON_IMAGE_MODALITIES and "Rows" in ds and "Columns" in ds


_SUMMARY_KEYWORDS = ("SeriesInstanceUID", "FrameOfReferenceUID", "SeriesDescription", "NumberOfFrames", "Rows",
                     "Columns", "StudyInstanceUID", "PatientID", "PatientName")


@dataclass(frozen=True)
class FolderScan:
    """Headers of every DICOM object below a path (pixel data not read).

    Parameters
    ----------
    images : tuple of (pydicom.Dataset, Path)
        Image objects (CT, MR, ...; see :data:`NON_IMAGE_MODALITIES`), with their file.
    others : tuple of (pydicom.Dataset, Path)
        The other DICOM objects (structure sets, plans, DICOMDIR, ...).
    n_non_dicom : int
        Files that are not DICOM.
    """

    images: tuple[tuple[Any, Path], ...]
    others: tuple[tuple[Any, Path], ...]
    n_non_dicom: int

    def series(self) -> tuple[SeriesSummary, ...]:
        """One summary per SeriesInstanceUID of the image objects, in order of first appearance."""
        groups: dict[str, list[tuple[Any, Path]]] = {}
        for ds, path in self.images:
            groups.setdefault(str(ds.get("SeriesInstanceUID", "")), []).append((ds, path))
        out = []
        for uid, items in groups.items():
            ds0 = items[0][0]
            out.append(SeriesSummary(
                series_instance_uid=uid, modality=str(ds0.get("Modality", "")),
                description=str(ds0.get("SeriesDescription", "")),
                frame_of_reference_uid=str(ds0.get("FrameOfReferenceUID", "")),
                n_frames=sum(int(d.get("NumberOfFrames", 1) or 1) for d, _ in items),
                rows=int(ds0.get("Rows", 0)), columns=int(ds0.get("Columns", 0)),
                paths=tuple(p for _, p in items)))
        return tuple(out)


def scan(path: Path) -> FolderScan:
    """Read the headers of every file at ``path`` (a file or a folder, recursively).

    Values over 1 KiB (pixel data, long contour lists) stay on disk until used. Every DICOM file is checked to
    be complete.

    Parameters
    ----------
    path : Path
        What to scan: one file, or a folder and everything below it.

    Returns
    -------
    FolderScan
        The headers found, by series and object.

    Raises
    ------
    NoDicomError
        ``path`` does not exist.
    CorruptFileError
        A file that claims to be DICOM cannot be read.
    """
    images, others, n_non = [], [], 0
    for p in list_files(Path(path)):
        ds = read_dataset(p, defer_size=1024)
        if ds is None:
            n_non += 1
            continue
        with parsing(p):
            image = _is_image(ds)
            if image:  # parse now what the series summaries and the volume use, so damage shows here
                for keyword in _SUMMARY_KEYWORDS:
                    ds.get(keyword)
                for keyword in ("Rows", "Columns", "NumberOfFrames"):
                    int(ds.get(keyword, 1) or 1)
        if image:
            images.append((ds, p))
        else:
            others.append((ds, p))
    return FolderScan(tuple(images), tuple(others), n_non)


def _describe(s: SeriesSummary) -> str:
    return f"{s.series_instance_uid} ({s.modality}, {s.n_frames} images, {s.description or 'no description'})"


def select_series(
    found: FolderScan, folder: Path, series_uid: str | None = None, modality: str | None = None
) -> SeriesSummary:
    """Pick the one image series of a scan matching ``series_uid`` and ``modality`` (None matches any).

    Parameters
    ----------
    found : FolderScan
        What :func:`scan` found.
    folder : Path
        Where it was found (for the messages).
    series_uid : str, optional
        SeriesInstanceUID to pick.
    modality : str, optional
        ``"CT"``, ``"MR"``, ... (case-insensitive).

    Returns
    -------
    SeriesSummary
        The matching series.

    Raises
    ------
    NoDicomError
        No image series matches; the message lists what the folder holds.
    SeriesError
        More than one series matches.
    """
    all_series = found.series()
    chosen = [s for s in all_series
              if (series_uid is None or s.series_instance_uid == series_uid)
              and (modality is None or s.modality.upper() == modality.upper())]
    if not chosen:
        what = " ".join(x for x in (modality, "image series", f"with SeriesInstanceUID {series_uid}"
                                    if series_uid else "") if x)
        if all_series:
            have = "; ".join(_describe(s) for s in all_series)
            raise NoDicomError(f"no {what} in {folder}; it holds: {have}")
        raise NoDicomError(
            f"no {what} in {folder} ({len(found.others)} non-image DICOM objects, {found.n_non_dicom} other "
            "files); give the folder of a CT or MR series"
        )
    if len(chosen) > 1:
        have = "; ".join(_describe(s) for s in chosen)
        raise SeriesError(f"{folder} holds {len(chosen)} image series: {have}; choose one with series_uid")
    return chosen[0]


# --------------------------------------------------------------------------------------------------
# Geometry
# --------------------------------------------------------------------------------------------------


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


def assemble_geometry(frames: Sequence[_Frame], tol: SeriesTolerance, label: str) -> tuple[Grid, list[int]]:
    """Check that ``frames`` form one regular volume; return its grid and the frames' order along k.

    Parameters
    ----------
    frames : sequence of _Frame
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
    if np.any(spacing <= 0) or np.any(spacing > 1e3) or np.abs(spacing - spacing[0]).max() > 1e-4 * spacing[0].max():
        raise SeriesError(f"{label}: PixelSpacing {spacing[0].tolist()} mm is not positive (up to 1000 mm) or differs "
                          "between slices; fix the header or re-export the series")
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
    if not np.all(np.isfinite(m)) or not 1e-3 <= slice_mm <= 1e3:
        raise SeriesError(f"{label}: the slice spacing is {slice_mm:g} mm (allowed 0.001 to 1000 mm); fix the "
                          "positions or SliceThickness, or re-export the series")
    rows, columns = frames[0].rows, frames[0].columns
    return Grid((len(frames), rows, columns), m), order


# --------------------------------------------------------------------------------------------------
# Pixel data
# --------------------------------------------------------------------------------------------------


_NATIVE_LE = frozenset({"1.2.840.10008.1.2", "1.2.840.10008.1.2.1"})


def _native_pixels(ds: Any, path: Path) -> np.ndarray | None:
    """Uncompressed little-endian single-frame grey pixels straight from the bytes; None when not that simple."""
    meta = getattr(ds, "file_meta", None)
    if meta is None or str(meta.get("TransferSyntaxUID", "")) not in _NATIVE_LE:
        return None
    try:
        bits, stored = int(ds.BitsAllocated), int(ds.BitsStored)
        rows, cols, signed = int(ds.Rows), int(ds.Columns), int(ds.PixelRepresentation) == 1
        spp, frames = int(ds.get("SamplesPerPixel", 1)), int(ds.get("NumberOfFrames", 1) or 1)
    except (AttributeError, TypeError, ValueError):
        return None
    if bits not in (8, 16, 32) or stored != bits or spp != 1 or frames != 1 or "PixelData" not in ds:
        return None
    dtype = np.dtype(f"<{'i' if signed else 'u'}{bits // 8}")
    n = rows * cols
    elem = ds.get_item(0x7FE00010, keep_deferred=True)
    if getattr(elem, "value", b"") is None and getattr(elem, "length", 0) >= n * dtype.itemsize:
        # deferred: read the pixels from the file without keeping a copy in the dataset
        arr = np.fromfile(path, dtype=dtype, count=n, offset=int(elem.value_tell))
        return arr.reshape(rows, cols) if arr.size == n else None
    data = ds.PixelData
    if len(data) < n * dtype.itemsize:
        return None  # let pydicom explain what is wrong
    return np.frombuffer(data, dtype=dtype, count=n).reshape(rows, cols)


_NATIVE = _NATIVE_LE | {"1.2.840.10008.1.2.2", "1.2.840.10008.1.2.1.99"}  # + big endian, deflated


def _check_pixel_length(ds: Any, path: Path) -> None:
    """Check that the pixel description is coherent and fits the pixel data.

    BitsAllocated 1, 8, 16, 32 or 64; BitsStored <= BitsAllocated; HighBit = BitsStored - 1; and, for
    uncompressed pixel data, its length must be Rows x Columns x frames x samples x BitsAllocated / 8 (plus at
    most one padding byte): a BitsAllocated of 8 on 16-bit data would otherwise give a garbled volume.

    Raises
    ------
    InvalidValueError
    """
    with parsing(path):
        bits = int(ds.get("BitsAllocated", 16) or 16)
        stored = int(ds.get("BitsStored", bits) or bits)
        high = ds.get("HighBit")
        high = stored - 1 if high in (None, "") else int(high)
        rows, cols = int(ds.Rows), int(ds.Columns)
        n = rows * cols * int(ds.get("NumberOfFrames", 1) or 1) * int(ds.get("SamplesPerPixel", 1) or 1)
    if bits not in (1, 8, 16, 32, 64) or not (1 <= stored <= bits) or high != stored - 1:
        raise InvalidValueError(
            f"{path}: BitsAllocated {bits}, BitsStored {stored}, HighBit {high} do not describe valid pixels "
            "(BitsStored <= BitsAllocated, HighBit = BitsStored - 1); fix the header or re-export the image")
    meta = getattr(ds, "file_meta", None)
    if meta is None or str(meta.get("TransferSyntaxUID", "")) not in _NATIVE:
        return
    with parsing(path):
        elem = ds.get_item(0x7FE00010, keep_deferred=True) if 0x7FE00010 in ds else None
        if elem is None:
            raise _invalid(path, "the image has no Pixel Data")
        length = getattr(elem, "length", None)
        if length is None or (length == 0xFFFFFFFF and getattr(elem, "value", None) is not None):
            length = len(elem.value or b"")
    need = (n * bits + 7) // 8
    if length != 0xFFFFFFFF and length not in (need, need + 1):
        raise InvalidValueError(
            f"{path}: pixel data (7FE0,0010) has {length} bytes but Rows {rows} x Columns {cols} x frames x samples at "
            f"BitsAllocated {bits} need {need}; the header does not describe the pixels (damaged or mis-edited "
            "BitsAllocated, Rows or Columns): re-export the image")


def _sitk_pixels(ds: Any, path: Path) -> np.ndarray | None:
    """Decode a single-frame image with SimpleITK (GDCM) into stored values; None when it cannot.

    GDCM applies the rescale slope and intercept; they are undone here so that every decoder returns stored
    values and the rescale is applied in one place.
    """
    if int(ds.get("NumberOfFrames", 1) or 1) != 1:
        return None
    try:
        import SimpleITK as sitk

        reader = sitk.ImageFileReader()
        reader.SetImageIO("GDCMImageIO")
        reader.SetFileName(str(path))
        arr = sitk.GetArrayFromImage(reader.Execute())
    except (ImportError, RuntimeError):
        return None
    arr = arr.reshape(arr.shape[-2:]) if arr.ndim == 3 and arr.shape[0] == 1 else arr
    if arr.ndim != 2:
        return None
    slope, intercept = _rescale(ds, path)
    if slope != 1 or intercept != 0:
        arr = np.rint((arr.astype(np.float64) - intercept) / slope)
    return arr


def _pixels(ds: Any, path: Path) -> np.ndarray:
    fast = _native_pixels(ds, path)
    if fast is not None:
        return fast
    try:
        arr = ds.pixel_array
    except (NotImplementedError, RuntimeError) as exc:
        arr = _sitk_pixels(ds, path)  # GDCM inside SimpleITK decodes JPEG lossless, JPEG-LS, ...
        if arr is None:
            ts = getattr(getattr(ds, "file_meta", None), "TransferSyntaxUID", "unknown")
            raise UnsupportedDataError(
                f"{path}: neither pydicom nor SimpleITK can decode pixel data with transfer syntax {ts} "
                f"({_one_line(exc, 80)}); install a pydicom decoder plugin (e.g. pylibjpeg) or decompress the series"
            ) from None
    except (ValueError, AttributeError, KeyError, TypeError, EOFError, OSError) as exc:
        raise _corrupt(path, f"pixel data cannot be read ({_one_line(exc, 100)})") from None
    if arr.ndim not in (2, 3) or np.iscomplexobj(arr):
        raise UnsupportedDataError(f"{path}: pixel data of shape {arr.shape} is not a grey-level image")
    return arr


def read_series(
    folder: Path,
    series_uid: str | None = None,
    modality: str | None = None,
    tolerance: SeriesTolerance | None = None,
) -> Volume:
    """Read one CT/MR image series into a :class:`~reachplan.imaging.types.Volume`.

    Parameters
    ----------
    folder : Path
        A folder (searched recursively) or a single (multi-frame) file.
    series_uid : str, optional
        SeriesInstanceUID to pick when the folder holds several series.
    modality : str, optional
        ``"CT"``, ``"MR"``, ... to pick by modality.
    tolerance : SeriesTolerance, optional
        Regularity checks (default :class:`SeriesTolerance`).

    Returns
    -------
    Volume
        ``array`` (nk, nj, ni) float32 (CT in HU: rescale slope and intercept applied per slice),
        ``grid.patient_from_index`` in LPS mm.

    Raises
    ------
    NoDicomError
        No file, or no (single) matching image series.
    CorruptFileError
        A file is truncated or breaks the standard.
    SeriesError
        The slices do not form one regular volume, or several series match.
    UnsupportedDataError
        Pixel data that cannot be decoded, or a volume too large for memory.
    """
    folder = Path(folder)
    found = scan(folder)
    return load_series(found, select_series(found, folder, series_uid, modality), tolerance, folder)


def load_series(
    found: FolderScan, chosen: SeriesSummary, tolerance: SeriesTolerance | None = None, folder: Path | None = None
) -> Volume:
    """Read the pixel data of one series of a :func:`scan` into a volume.

    Slices in order along the slice normal; CT values rescaled (slope, intercept) to Hounsfield units.

    Parameters
    ----------
    found : FolderScan
        The folder's headers, as :func:`scan` read them.
    chosen : SeriesSummary
        The series to read (from :func:`select_series` or :meth:`FolderScan.series`).
    tolerance : SeriesTolerance, optional
        Regularity checks (default :class:`SeriesTolerance`).
    folder : Path, optional
        Where the series was found (for the messages).

    Returns
    -------
    Volume
        As for :func:`read_series`.

    Raises
    ------
    CorruptFileError, SeriesError, UnsupportedDataError
        As for :func:`read_series`.
    """
    tol = tolerance or SeriesTolerance()
    where = folder if folder is not None else (chosen.paths[0].parent if chosen.paths else Path("."))
    label = f"series {chosen.series_instance_uid} in {where}"
    wanted = set(chosen.paths)
    headers = [(ds, p) for ds, p in found.images if p in wanted]
    uids = {str(ds.get("FrameOfReferenceUID", "")) for ds, _ in headers}
    if len(uids) > 1:
        raise SeriesError(f"{label}: images have {len(uids)} different Frame of Reference UIDs")
    frames = []
    for ds, p in headers:
        with parsing(p):
            frames += _frames_of(ds, p)
    grid, order = assemble_geometry(frames, tol, label)
    for ds, p in headers:
        _check_pixel_length(ds, p)
    try:
        out = np.empty(grid.shape, dtype=np.float32)
    except MemoryError:
        raise UnsupportedDataError(f"{label}: a volume of {grid.shape} voxels does not fit in memory") from None
    slot = {(frames[i].path, frames[i].frame): k for k, i in enumerate(order)}
    by_path: dict[Path, list[_Frame]] = {}
    for f in frames:
        by_path.setdefault(f.path, []).append(f)
    for ds, path in headers:
        with parsing(path):
            arr = _pixels(ds, path)
        mine = by_path[path]
        if arr.ndim == 2:
            arr = arr[None]
        if arr.shape[0] != len(mine) or arr.shape[1:] != grid.shape[1:]:
            raise _corrupt(path, f"pixel data has shape {arr.shape}, expected {len(mine)} x {grid.shape[1:]}")
        for f in mine:
            k = slot[(f.path, f.frame)]
            np.multiply(arr[f.frame or 0], np.float32(f.slope), out=out[k], casting="unsafe")
            if f.intercept:
                out[k] += np.float32(f.intercept)
    sop = {p: (str(ds.get("SOPClassUID", "")), str(ds.get("SOPInstanceUID", ""))) for ds, p in headers}
    slice_uids = [("", "")] * len(order)
    for (path, frame), k in slot.items():
        slice_uids[k] = sop[path] if frame is None else ("", "")  # multi-frame: no per-slice instance
    return Volume(
        array=out, grid=grid, modality=chosen.modality, series_instance_uid=chosen.series_instance_uid,
        frame_of_reference_uid=chosen.frame_of_reference_uid,
        patient_study=PatientStudy.read(headers[0][0]),
        slice_uids=tuple(slice_uids) if all(all(u) for u in slice_uids) else (),
    )


def check_reference(volume: Volume, frame_of_reference_uid: str | None, series_uid: str | None, what: str) -> None:
    """Check that an object drawn on images refers to ``volume``.

    Parameters
    ----------
    volume : Volume
        The images at hand.
    frame_of_reference_uid : str or None
        The Frame of Reference the object refers to; empty or None is not checked.
    series_uid : str or None
        The series it refers to; empty or None is not checked.
    what : str
        Names the object in the message.

    Raises
    ------
    ReferenceMismatchError
        The object refers to another Frame of Reference or series than ``volume``.
    """
    if frame_of_reference_uid and volume.frame_of_reference_uid and \
            frame_of_reference_uid != volume.frame_of_reference_uid:
        raise ReferenceMismatchError(
            f"{what} is in Frame of Reference {frame_of_reference_uid} but the image series is in "
            f"{volume.frame_of_reference_uid}; give the images it was drawn on"
        )
    if series_uid and series_uid != volume.series_instance_uid:
        raise ReferenceMismatchError(
            f"{what} references series {series_uid} but the image series is {volume.series_instance_uid}; "
            "give the images it was drawn on, or read it without images"
        )
