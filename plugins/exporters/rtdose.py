"""DICOM RT Dose writer (multi-frame, dose in Gy, unsigned pixels × DoseGridScaling).

Pixels are 16-bit by default (resolution: maximum dose / 65 535) because the dicom3tools validator
``dciodvfy`` (build 20260927) aborts on any 32-bit RT Dose, pydicom's own ``rtdose.dcm`` included;
``bits=32`` gives maximum dose / 4 294 967 295 for readers that need it.

The grid's slice axis must be along the normal of its rows and columns (no shear): RT Dose places
frames by GridFrameOffsetVector along that normal. Writes are atomic and never replace a file that
is not an RT Dose written by reachplan.
"""

from __future__ import annotations

import datetime as _dt
import io
import os
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
import pydicom
from pydicom.dataset import Dataset, FileMetaDataset
from pydicom.uid import UID, ExplicitVRLittleEndian, generate_uid

from reachplan.imaging.errors import OutputExistsError
from reachplan.imaging.files import atomic_write_bytes
from reachplan.imaging.series_geometry import MIN_SPACING_MM
from reachplan.imaging.types import Grid, PatientStudy

RT_DOSE_STORAGE = "1.2.840.10008.5.1.4.1.1.481.2"
RT_PLAN_STORAGE = "1.2.840.10008.5.1.4.1.1.481.5"
MANUFACTURER = "reachplan"


@dataclass(frozen=True)
class DoseContext:
    """Identity the RT Dose carries over from its inputs (all optional except the Frame of Reference).

    Parameters
    ----------
    frame_of_reference_uid : str
        Of the plan or images; required.
    patient_study : PatientStudy
        Of the plan or images; written as given, except an invalid Study Instance UID, replaced by a new one.
    referenced_plan_uid : str
        SOP Instance UID of the RT Plan the dose belongs to; empty: none referenced.
    series_description : str
        Written as Series Description.

    Raises
    ------
    ValueError
        No Frame of Reference UID.
    """

    frame_of_reference_uid: str
    patient_study: PatientStudy = field(default_factory=PatientStudy)
    referenced_plan_uid: str = ""
    series_description: str = "reachplan TG-43 dose"

    def __post_init__(self) -> None:
        if not self.frame_of_reference_uid:
            raise ValueError("an RT Dose needs the Frame of Reference UID of the plan or images")


def _ds(v: float) -> str:
    """Format ``v`` as a DS string of at most 16 characters."""
    s = f"{v:.10g}"
    if len(s) > 16:
        s = f"{v:.8e}"
    return s


def _valid_uid(uid: str) -> bool:
    return bool(uid) and len(uid) <= 64 and all(p.isdigit() and (p == "0" or not p.startswith("0"))
                                                for p in uid.split("."))


#: With a prescription, RT Dose pixels hold doses up to this many times the (total) prescribed dose; voxels
#: above (within a few mm of a dwell, most inside the needle lumen, where the TG-43 dose grows without bound)
#: are stored at that ceiling, so that 16-bit pixels resolve the clinical range (10 x Rx / 65 535, 0.015 % of Rx).
CEILING_TIMES_PRESCRIPTION = 10.0


def rtdose_dataset(dose_gy: np.ndarray, grid: Grid, context: DoseContext, *, bits: int = 16,
                   ceiling_gy: float | None = None) -> Dataset:
    """Build the RT Dose dataset.

    Parameters
    ----------
    dose_gy : (nk, nj, ni) float, Gy
        Dose on ``grid`` (array order: slice, row, column), finite and >= 0.
    grid : Grid
        Where the dose is, LPS mm; rows and columns orthogonal, slices along their normal (no shear).
    context : DoseContext
        Identity carried over.
    bits : {16, 32}
        Bits per pixel.
    ceiling_gy : float, optional
        Doses above it are stored as it (see :data:`CEILING_TIMES_PRESCRIPTION`); None: the maximum dose.

    Returns
    -------
    pydicom.Dataset
        With file meta (Explicit VR Little Endian).

    Raises
    ------
    ValueError
        Other bits, a dose that does not match ``grid`` or is negative or not finite, or a grid RT Dose
        cannot describe (rows and columns not orthogonal, sheared slices).
    """
    if bits not in (16, 32):
        raise ValueError(f"RT Dose pixels are 16 or 32 bits, got {bits}")
    dose = np.asarray(dose_gy, dtype=float)
    if dose.shape != grid.shape:
        raise ValueError(f"dose shape {dose.shape} does not match grid shape {grid.shape}")
    if not np.all(np.isfinite(dose)) or np.any(dose < 0):
        raise ValueError("dose must be finite and >= 0 Gy")
    row_dir, col_dir, along = _frame_axes(grid)
    ds = _identity(context)
    _write_geometry(ds, grid, row_dir, col_dir, along)
    ds.DoseUnits = "GY"
    ds.DoseType = "PHYSICAL"
    ds.DoseSummationType = "PLAN"
    ds.TissueHeterogeneityCorrection = "WATER"
    _write_pixels(ds, dose, bits, ceiling_gy)
    if context.referenced_plan_uid:
        ref = Dataset()
        ref.ReferencedSOPClassUID = RT_PLAN_STORAGE
        ref.ReferencedSOPInstanceUID = context.referenced_plan_uid
        ds.ReferencedRTPlanSequence = [ref]
    return ds


def _frame_axes(grid: Grid) -> tuple[np.ndarray, np.ndarray, float]:
    """Return the row and column directions of ``grid`` and its slice step along their normal.

    Returns
    -------
    row_dir, col_dir : (3,) float, LPS
        Unit directions of increasing column and row index.
    along : float, mm
        Slice step along ``row_dir x col_dir`` (negative when the slices run against it).

    Raises
    ------
    ValueError
        Rows and columns not orthogonal, or slices not stacked along their normal (sheared grid).
    """
    a = grid.patient_from_index
    sp = grid.spacing_mm
    row_dir, col_dir = a[:3, 0] / sp[0], a[:3, 1] / sp[1]
    if abs(float(row_dir @ col_dir)) > 1e-6:
        raise ValueError("RT Dose needs orthogonal row and column directions")
    normal = np.cross(row_dir, col_dir)
    step = a[:3, 2]
    along = float(step @ normal)
    if np.linalg.norm(step - along * normal) > 1e-6 * max(1.0, abs(along)):
        raise ValueError("RT Dose frames must be stacked along the image normal (sheared grid)")
    return row_dir, col_dir, along


def _identity(context: DoseContext) -> Dataset:
    """Start the RT Dose dataset: file meta, new SOP and series UIDs, dates, patient and study, Frame of Reference.

    An invalid Study Instance UID in ``context.patient_study`` is replaced by a new one.
    """
    now = _dt.datetime.now()
    meta = FileMetaDataset()
    meta.MediaStorageSOPClassUID = UID(RT_DOSE_STORAGE)
    meta.MediaStorageSOPInstanceUID = generate_uid()
    meta.TransferSyntaxUID = ExplicitVRLittleEndian
    ds = Dataset()
    ds.file_meta = meta
    ds.SpecificCharacterSet = "ISO_IR 100"
    ds.SOPClassUID = RT_DOSE_STORAGE
    ds.SOPInstanceUID = meta.MediaStorageSOPInstanceUID
    ds.InstanceCreationDate = now.strftime("%Y%m%d")
    ds.InstanceCreationTime = now.strftime("%H%M%S")
    ds.ContentDate = now.strftime("%Y%m%d")
    ds.ContentTime = now.strftime("%H%M%S")
    ds.AccessionNumber = ""
    ds.Modality = "RTDOSE"
    ds.Manufacturer = MANUFACTURER
    ds.ReferringPhysicianName = ""
    ds.SeriesDescription = context.series_description
    ds.OperatorsName = ""
    study = context.patient_study
    if not _valid_uid(study.study_instance_uid):
        study = replace(study, study_instance_uid=generate_uid())
    study.write(ds)
    ds.PatientBirthDate = ""
    ds.PatientSex = ""
    ds.SeriesInstanceUID = generate_uid()
    ds.SeriesNumber = 903  # after the RT Structure Set (901) and RT Plan (902) of an export
    ds.InstanceNumber = 1
    ds.FrameOfReferenceUID = context.frame_of_reference_uid
    ds.PositionReferenceIndicator = ""
    return ds


def _write_geometry(ds: Dataset, grid: Grid, row_dir: np.ndarray, col_dir: np.ndarray, along: float) -> None:
    """Set the image plane and multi-frame attributes of ``ds`` for ``grid`` (frames at GridFrameOffsetVector).

    Parameters
    ----------
    ds : pydicom.Dataset
        The RT Dose, changed in place.
    grid : Grid
        Where the dose is, LPS mm.
    row_dir, col_dir : (3,) float, LPS
        Its row and column directions (:func:`_frame_axes`).
    along : float, mm
        Its slice step along their normal.
    """
    a = grid.patient_from_index
    sp = grid.spacing_mm
    ds.ImagePositionPatient = [_ds(x) for x in a[:3, 3]]
    ds.ImageOrientationPatient = [_ds(x) for x in np.concatenate([row_dir, col_dir])]
    ds.PixelSpacing = [_ds(sp[1]), _ds(sp[0])]  # row spacing (between rows), column spacing
    ds.SliceThickness = _ds(abs(along)) if grid.shape[0] > 1 else ""
    ds.SamplesPerPixel = 1
    ds.PhotometricInterpretation = "MONOCHROME2"
    nk, nj, ni = grid.shape
    ds.NumberOfFrames = nk
    ds.FrameIncrementPointer = pydicom.tag.Tag(0x3004, 0x000C)
    ds.Rows = nj
    ds.Columns = ni
    ds.GridFrameOffsetVector = [_ds(along * k) for k in range(nk)]


def _write_pixels(ds: Dataset, dose: np.ndarray, bits: int, ceiling_gy: float | None) -> None:
    """Store ``dose`` (Gy, capped at ``ceiling_gy``) as unsigned ``bits``-bit pixels times DoseGridScaling.

    The scaling is rounded up so that the peak stays representable, and the pixels are computed with the scaling
    a reader will parse.

    Raises
    ------
    ValueError
        A ceiling that is not a positive number of Gy.
    """
    top = 2**bits - 1
    ds.BitsAllocated = bits
    ds.BitsStored = bits
    ds.HighBit = bits - 1
    ds.PixelRepresentation = 0
    if ceiling_gy is not None:
        if not (np.isfinite(ceiling_gy) and ceiling_gy > 0):
            raise ValueError(f"the dose ceiling must be a positive number of Gy, got {ceiling_gy}")
        dose = np.minimum(dose, ceiling_gy)
    peak = float(dose.max())
    scaling = peak / top if peak > 0 else 1.0
    ds.DoseGridScaling = _ds(scaling * (1 + 1e-9))  # rounded up: the peak stays representable
    scaling = float(ds.DoseGridScaling)  # the value a reader will use
    pixels = np.clip(np.rint(dose / scaling), 0, top).astype("<u2" if bits == 16 else "<u4")
    ds.PixelData = pixels.tobytes()
    ds["PixelData"].VR = "OW"


def _is_ours(path: Path) -> bool:
    try:
        old = pydicom.dcmread(path, stop_before_pixels=True)
    except Exception:
        return False
    return str(old.get("Modality", "")) == "RTDOSE" and str(old.get("Manufacturer", "")) == MANUFACTURER


def write_rtdose(
    path: str | os.PathLike[str], dose_gy: np.ndarray, grid: Grid, context: DoseContext, *, bits: int = 16,
    ceiling_gy: float | None = None,
) -> Path:
    """Write an RT Dose file atomically.

    Parameters
    ----------
    path : path-like
        Output file. An existing file is replaced only if it is an RT Dose written by reachplan.
    dose_gy : (nk, nj, ni) float, Gy
        Dose on ``grid`` (see :func:`rtdose_dataset`).
    grid : Grid
        Where the dose is, LPS mm.
    context : DoseContext
        Identity carried over.
    bits : {16, 32}
        Bits per pixel (see the module docstring).
    ceiling_gy : float, optional
        See :func:`rtdose_dataset`.

    Returns
    -------
    Path
        The written file.

    Raises
    ------
    OutputExistsError
        ``path`` holds another file.
    ValueError
        As for :func:`rtdose_dataset`.
    """
    out = Path(path)
    if out.exists() and not _is_ours(out):
        raise OutputExistsError(f"{out} exists and is not an RT Dose written by reachplan; choose another --out")
    ds = rtdose_dataset(dose_gy, grid, context, bits=bits, ceiling_gy=ceiling_gy)
    buf = io.BytesIO()
    ds.save_as(buf, enforce_file_format=True)
    atomic_write_bytes(out, buf.getvalue())
    return out


def read_rtdose_grid(path: str | os.PathLike[str]) -> tuple[np.ndarray, Grid]:
    """Read an RT Dose and its grid; used for ``--like`` and round trips.

    Parameters
    ----------
    path : path-like
        The RD file.

    Returns
    -------
    dose_gy : (nk, nj, ni) float64, Gy
        Pixel values times Dose Grid Scaling, indexed ``[k, j, i]``.
    grid : Grid
        ``patient_from_index`` to LPS mm.

    Raises
    ------
    NoDicomError
        No such file, or not an RT Dose.
    CorruptFileError
        Unreadable, incomplete geometry, or frames that are not evenly spaced (or absolute offsets on a
        non-axial grid).
    """
    from reachplan.imaging.dicom_files import one_line
    from reachplan.imaging.errors import CorruptFileError, NoDicomError

    p = Path(path)
    try:
        ds = pydicom.dcmread(p)
    except FileNotFoundError:
        raise NoDicomError(f"{p}: no such file; pass an RT Dose (RD) file") from None
    except Exception as exc:
        raise CorruptFileError(f"{p}: not readable as DICOM ({type(exc).__name__}: {one_line(exc)})") from None
    try:
        return _dose_and_grid(ds, p)
    except CorruptFileError:
        raise
    except (AttributeError, ValueError, TypeError, IndexError, KeyError, OverflowError, NotImplementedError,
            RuntimeError, MemoryError, EOFError, OSError) as exc:
        raise CorruptFileError(f"{p}: RT Dose cannot be read ({type(exc).__name__}: {one_line(exc)}); re-export it") \
            from None


def _dose_and_grid(ds: Any, p: Path) -> tuple[np.ndarray, Grid]:
    from reachplan.imaging.dicom_files import one_line
    from reachplan.imaging.errors import CorruptFileError, NoDicomError

    if str(ds.get("Modality", "")) != "RTDOSE":
        raise NoDicomError(f"{p}: is not an RT Dose (Modality {ds.get('Modality', '')!r}); pass an RD file")
    try:
        pos = np.array([float(x) for x in ds.ImagePositionPatient])
        iop = np.array([float(x) for x in ds.ImageOrientationPatient])
        row_sp, col_sp = (float(x) for x in ds.PixelSpacing)
        nk = int(ds.get("NumberOfFrames", 1) or 1)
        offsets = np.array([float(x) for x in ds.get("GridFrameOffsetVector", [0.0])], dtype=float)
        rows, cols = int(ds.Rows), int(ds.Columns)
    except (AttributeError, ValueError, TypeError) as exc:
        raise CorruptFileError(f"{p}: RT Dose geometry is incomplete ({one_line(exc)})") from None
    if len(offsets) != nk:
        raise CorruptFileError(f"{p}: GridFrameOffsetVector has {len(offsets)} values for {nk} frames")
    normal = np.cross(iop[:3], iop[3:])
    if abs(offsets[0]) > 1e-6:  # "absolute" offsets (PS3.3 C.8.8.3.2): patient z of each plane, axial only
        if abs(abs(normal[2]) - 1.0) > 1e-6:
            raise CorruptFileError(f"{p}: absolute GridFrameOffsetVector on a non-axial RT Dose grid")
        offsets = (offsets - offsets[0]) * np.sign(normal[2])
    steps = np.diff(offsets)
    if nk > 1 and (np.ptp(steps) > 1e-3 * max(1.0, abs(steps).max()) or np.any(steps == 0)):
        raise CorruptFileError(f"{p}: RT Dose frames are not evenly spaced; cannot use it as a grid")
    step = float(steps[0]) if nk > 1 else 1.0
    if not (np.all(np.isfinite(pos)) and np.all(np.isfinite(iop)) and len(iop) == 6 and len(pos) == 3
            and MIN_SPACING_MM <= row_sp <= 1e3 and MIN_SPACING_MM <= col_sp <= 1e3
            and MIN_SPACING_MM <= abs(step) <= 1e3 and rows > 0 and cols > 0 and nk > 0
            and np.all(np.isfinite(offsets)) and abs(np.linalg.norm(normal) - 1.0) < 1e-3):
        raise CorruptFileError(f"{p}: RT Dose geometry is not finite and positive (position, orientation, spacing of "
                               f"{MIN_SPACING_MM:g} to 1000 mm, frame offsets); re-export it")
    affine = np.eye(4)
    affine[:3, 0] = iop[:3] * col_sp
    affine[:3, 1] = iop[3:] * row_sp
    affine[:3, 2] = normal * step
    affine[:3, 3] = pos + normal * offsets[0]
    grid = Grid((nk, rows, cols), affine)
    scaling = float(ds.get("DoseGridScaling", 1.0))
    dose = np.asarray(ds.pixel_array, dtype=float).reshape(grid.shape) * scaling
    return dose, grid
