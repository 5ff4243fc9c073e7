"""Small DICOM objects generated for the imaging tests (no test data files in the repository)."""

from __future__ import annotations

import hashlib
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from pydicom.dataset import Dataset, FileDataset, FileMetaDataset
from pydicom.sequence import Sequence as DicomSequence
from pydicom.uid import UID, ExplicitVRLittleEndian, generate_uid

from reachplan.imaging.phantom import PhantomFiles, write_phantom

CT_STORAGE = "1.2.840.10008.5.1.4.1.1.2"
MR_STORAGE = "1.2.840.10008.5.1.4.1.1.4"
ENHANCED_CT_STORAGE = "1.2.840.10008.5.1.4.1.1.2.1"
RTSTRUCT_STORAGE = "1.2.840.10008.5.1.4.1.1.481.3"


def _uid(*parts: object) -> str:
    return str(generate_uid(prefix="1.2.826.0.1.3680043.10.1.", entropy_srcs=[str(p) for p in parts]))


def _file_dataset(sop_class: str, sop_uid: str, transfer_syntax: str = ExplicitVRLittleEndian) -> FileDataset:
    meta = FileMetaDataset()
    meta.MediaStorageSOPClassUID = UID(sop_class)
    meta.MediaStorageSOPInstanceUID = UID(sop_uid)
    meta.TransferSyntaxUID = UID(transfer_syntax)
    ds = FileDataset("", {}, file_meta=meta, preamble=b"\0" * 128)
    ds.SOPClassUID = sop_class
    ds.SOPInstanceUID = sop_uid
    ds.PatientName = "Test^Case"
    ds.PatientID = "T1"
    ds.StudyInstanceUID = _uid("study")
    return ds


def raw_values(n: int, rows: int, cols: int) -> np.ndarray:
    """Stored values of slice k, row j, column i: ``100 k + 10 j + i`` (int16, (n, rows, cols))."""
    k, j, i = np.meshgrid(np.arange(n), np.arange(rows), np.arange(cols), indexing="ij")
    return (100 * k + 10 * j + i).astype(np.int16)


def write_series(
    folder: Path,
    *,
    n: int = 6,
    rows: int = 10,
    cols: int = 12,
    pixel_spacing: tuple[float, float] = (0.8, 0.7),
    orientation: Sequence[float] = (1, 0, 0, 0, 1, 0),
    origin: Sequence[float] = (-5.0, -4.0, 10.0),
    step: Sequence[float] | None = None,
    slice_spacing: float = 2.0,
    positions: Sequence[Sequence[float]] | None = None,
    modality: str = "CT",
    slope: float | None = 2.0,
    intercept: float | None = -1024.0,
    series_uid: str | None = None,
    for_uid: str | None = None,
    tag: str = "a",
    reverse_names: bool = False,
    edit: Callable[[int, FileDataset], None] | None = None,
) -> list[Path]:
    """Write a small single-frame series; returns the file paths in slice order.

    ``positions`` overrides the regular positions ``origin + k * step`` (``step`` defaults to the slice
    normal times ``slice_spacing``). ``edit(k, ds)`` may change each dataset before it is written.
    """
    folder.mkdir(parents=True, exist_ok=True)
    ori = np.asarray(orientation, dtype=float)
    normal = np.cross(ori[:3], ori[3:])
    st = np.asarray(step, dtype=float) if step is not None else normal * slice_spacing
    pos = np.asarray(positions, dtype=float) if positions is not None else \
        np.asarray(origin, dtype=float) + np.outer(np.arange(n), st)
    values = raw_values(len(pos), rows, cols)
    series_uid = series_uid or _uid("series", tag)
    for_uid = for_uid or _uid("for", tag)
    paths = []
    for k, p in enumerate(pos):
        sop_class = CT_STORAGE if modality == "CT" else MR_STORAGE
        ds = _file_dataset(sop_class, _uid("image", tag, k))
        ds.Modality = modality
        ds.SeriesInstanceUID = series_uid
        ds.FrameOfReferenceUID = for_uid
        ds.SeriesDescription = f"test series {tag}"
        ds.InstanceNumber = len(pos) - k if reverse_names else k + 1
        ds.ImagePositionPatient = [float(x) for x in p]
        ds.ImageOrientationPatient = [float(x) for x in ori]
        ds.PixelSpacing = list(pixel_spacing)
        ds.SliceThickness = slice_spacing
        ds.Rows, ds.Columns = rows, cols
        ds.SamplesPerPixel = 1
        ds.PhotometricInterpretation = "MONOCHROME2"
        ds.BitsAllocated = ds.BitsStored = 16
        ds.HighBit = 15
        ds.PixelRepresentation = 1
        if slope is not None:
            ds.RescaleSlope = slope
        if intercept is not None:
            ds.RescaleIntercept = intercept
        ds.PixelData = values[k].tobytes()
        if edit is not None:
            edit(k, ds)
        name = f"{tag}_{(len(pos) - k) if reverse_names else k + 1:03d}.dcm"
        ds.save_as(folder / name, enforce_file_format=True)
        paths.append(folder / name)
    return paths


def write_enhanced_ct(path: Path, *, n: int = 6, rows: int = 10, cols: int = 12, slope: float = 2.0,
                      intercept: float = -1024.0, tag: str = "mf") -> Path:
    """One Enhanced CT object holding the same geometry and values as :func:`write_series` defaults,
    with its frames stored in reverse slice order."""
    ds = _file_dataset(ENHANCED_CT_STORAGE, _uid("enhanced", tag))
    ds.Modality = "CT"
    ds.SeriesInstanceUID = _uid("series", tag)
    ds.FrameOfReferenceUID = _uid("for", tag)
    ds.Rows, ds.Columns = rows, cols
    ds.NumberOfFrames = n
    ds.SamplesPerPixel = 1
    ds.PhotometricInterpretation = "MONOCHROME2"
    ds.BitsAllocated = ds.BitsStored = 16
    ds.HighBit = 15
    ds.PixelRepresentation = 1
    shared = Dataset()
    meas, orient, trans = Dataset(), Dataset(), Dataset()
    meas.PixelSpacing = [0.8, 0.7]
    meas.SliceThickness = 2.0
    orient.ImageOrientationPatient = [1, 0, 0, 0, 1, 0]
    trans.RescaleSlope, trans.RescaleIntercept, trans.RescaleType = slope, intercept, "HU"
    shared.PixelMeasuresSequence = DicomSequence([meas])
    shared.PlaneOrientationSequence = DicomSequence([orient])
    shared.PixelValueTransformationSequence = DicomSequence([trans])
    ds.SharedFunctionalGroupsSequence = DicomSequence([shared])
    values = raw_values(n, rows, cols)
    frames = []
    for k in reversed(range(n)):
        item, pos = Dataset(), Dataset()
        pos.ImagePositionPatient = [-5.0, -4.0, 10.0 + 2.0 * k]
        item.PlanePositionSequence = DicomSequence([pos])
        frames.append(item)
    ds.PerFrameFunctionalGroupsSequence = DicomSequence(frames)
    ds.PixelData = values[::-1].tobytes()
    ds.save_as(path, enforce_file_format=True)
    return path


def write_rtstruct(
    path: Path,
    rois: Sequence[tuple[str, Sequence[np.ndarray], str]],
    *,
    series_uid: str | None,
    for_uid: str,
    image_uids: Sequence[str] = (),
    edit: Callable[[FileDataset], None] | None = None,
) -> Path:
    """An RT Structure Set with ``rois`` = ``[(name, [points (n, 3) ...], geometric_type), ...]``."""
    ds = _file_dataset(RTSTRUCT_STORAGE, _uid("rtstruct", path.name))
    ds.Modality = "RTSTRUCT"
    ds.SeriesInstanceUID = _uid("rs series", path.name)
    ds.StructureSetLabel = "TEST"
    ref = Dataset()
    ref.FrameOfReferenceUID = for_uid
    if series_uid is not None:
        study, series = Dataset(), Dataset()
        series.SeriesInstanceUID = series_uid
        images = []
        for uid in image_uids:
            r = Dataset()
            r.ReferencedSOPClassUID = CT_STORAGE
            r.ReferencedSOPInstanceUID = uid
            images.append(r)
        series.ContourImageSequence = DicomSequence(images)
        study.RTReferencedSeriesSequence = DicomSequence([series])
        ref.RTReferencedStudySequence = DicomSequence([study])
    ds.ReferencedFrameOfReferenceSequence = DicomSequence([ref])
    ss_rois, contours, observations = [], [], []
    for number, (name, polys, gtype) in enumerate(rois, start=1):
        r = Dataset()
        r.ROINumber = number
        r.ROIName = name
        r.ReferencedFrameOfReferenceUID = for_uid
        ss_rois.append(r)
        rc = Dataset()
        rc.ReferencedROINumber = number
        rc.ROIDisplayColor = [255, 0, 0]
        items = []
        for pts in polys:
            c = Dataset()
            c.ContourGeometricType = gtype
            c.NumberOfContourPoints = len(pts)
            c.ContourData = [f"{v:.4f}" for v in np.asarray(pts, dtype=float).ravel()]
            items.append(c)
        rc.ContourSequence = DicomSequence(items)
        contours.append(rc)
        o = Dataset()
        o.ObservationNumber = number
        o.ReferencedROINumber = number
        o.RTROIInterpretedType = "ORGAN"
        observations.append(o)
    ds.StructureSetROISequence = DicomSequence(ss_rois)
    ds.ROIContourSequence = DicomSequence(contours)
    ds.RTROIObservationsSequence = DicomSequence(observations)
    if edit is not None:
        edit(ds)
    ds.save_as(path, enforce_file_format=True)
    return path


def square(half: float, z: float, cx: float = 0.0, cy: float = 0.0) -> np.ndarray:
    """(4, 3) corners of an axial square of side ``2 half`` centred on (cx, cy) at height z."""
    return np.array([[cx - half, cy - half, z], [cx + half, cy - half, z],
                     [cx + half, cy + half, z], [cx - half, cy + half, z]])


def circle(r: float, z: float, n: int = 200, cx: float = 0.0, cy: float = 0.0) -> np.ndarray:
    t = np.linspace(0, 2 * np.pi, n, endpoint=False)
    return np.column_stack([cx + r * np.cos(t), cy + r * np.sin(t), np.full(n, z)])


def folder_hashes(folder: Path) -> dict[str, str]:
    """sha256 of every file below ``folder`` (or of ``folder`` itself when it is a file)."""
    files = [folder] if folder.is_file() else sorted(p for p in folder.rglob("*") if p.is_file())
    return {str(p): hashlib.sha256(p.read_bytes()).hexdigest() for p in files}


class Factory:
    """The generators above, handed to tests through the ``dicom`` fixture."""

    write_series = staticmethod(write_series)
    write_enhanced_ct = staticmethod(write_enhanced_ct)
    write_rtstruct = staticmethod(write_rtstruct)
    raw_values = staticmethod(raw_values)
    square = staticmethod(square)
    circle = staticmethod(circle)
    hashes = staticmethod(folder_hashes)
    uid = staticmethod(_uid)


@pytest.fixture(scope="session")
def dicom() -> Any:
    return Factory


@pytest.fixture(scope="session")
def phantom_files(tmp_path_factory: pytest.TempPathFactory) -> PhantomFiles:
    """The built-in phantom written once per test session (treat as read-only)."""
    return write_phantom(tmp_path_factory.mktemp("phantom"))
