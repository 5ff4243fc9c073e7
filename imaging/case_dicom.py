"""The built-in cases as DICOM: an image series (CT or MR) and an RT Structure Set, with deterministic UIDs.

:func:`reachplan.imaging.phantom.write_phantom` writes what this module encodes: one dataset per image slice
(the painted image of :func:`reachplan.imaging.phantom.phantom_ct_hu`) and the structure set of the spec's
cross-sections, each referencing the slice it is drawn on.
"""

from __future__ import annotations

import hashlib
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from reachplan.imaging.case_spec import PhantomSpec

#: Identity of the phantom's files; changing the geometry must change PHANTOM_VERSION (new UIDs).
PHANTOM_VERSION = "2"
MANUFACTURER = "reachplan"
MODEL_NAME = "reachplan pelvic phantom"
CT_IMAGE_STORAGE = "1.2.840.10008.5.1.4.1.1.2"
MR_IMAGE_STORAGE = "1.2.840.10008.5.1.4.1.1.4"
RT_STRUCTURE_SET_STORAGE = "1.2.840.10008.5.1.4.1.1.481.3"


def _uid(*parts: str, case_id: str = "") -> str:
    """Derive a deterministic UID ``2.25.<128-bit hash>`` (ISO/IEC 9834-8 UUID arc).

    The hash covers the phantom version, the case id (when not empty) and ``parts``.
    """
    case = ["case", case_id] if case_id else []
    digest = hashlib.sha256("\0".join(["reachplan phantom", PHANTOM_VERSION, *case, *parts]).encode()).hexdigest()
    return f"2.25.{int(digest[:32], 16)}"


def _base_dataset(sop_class: str, sop_instance: str, modality: str, series_uid: str,
                  series_number: int, description: str, case_id: str = "",
                  study_description: str = "reachplan synthetic pelvis (gyn ISBT)") -> Any:
    from pydicom.dataset import FileDataset, FileMetaDataset
    from pydicom.uid import PYDICOM_IMPLEMENTATION_UID, UID, ExplicitVRLittleEndian

    meta = FileMetaDataset()
    meta.MediaStorageSOPClassUID = UID(sop_class)
    meta.MediaStorageSOPInstanceUID = UID(sop_instance)
    meta.TransferSyntaxUID = ExplicitVRLittleEndian
    meta.ImplementationClassUID = PYDICOM_IMPLEMENTATION_UID
    ds = FileDataset("", {}, file_meta=meta, preamble=b"\0" * 128)
    ds.SpecificCharacterSet = "ISO_IR 100"
    ds.SOPClassUID = sop_class
    ds.SOPInstanceUID = sop_instance
    ds.StudyDate = ds.SeriesDate = "20260101"
    ds.StudyTime = ds.SeriesTime = "120000"
    ds.AccessionNumber = ""
    ds.Modality = modality
    ds.Manufacturer = MANUFACTURER
    ds.ManufacturerModelName = MODEL_NAME
    ds.SoftwareVersions = f"phantom {PHANTOM_VERSION}"
    ds.ReferringPhysicianName = ""
    ds.StudyDescription = study_description
    ds.SeriesDescription = description
    ds.PatientName = "Phantom^Pelvis"
    ds.PatientID = f"REACHPLAN-PHANTOM-{case_id}" if case_id else "REACHPLAN-PHANTOM"
    ds.PatientBirthDate = ""
    ds.PatientSex = "F"
    ds.StudyInstanceUID = _uid("study", case_id=case_id)
    ds.SeriesInstanceUID = series_uid
    ds.StudyID = "1"
    ds.SeriesNumber = series_number
    return ds


@dataclass(frozen=True)
class ImageRef:
    """What the structure set references of one written image.

    Parameters
    ----------
    SOPClassUID, SOPInstanceUID : str
        The image's SOP Class and SOP Instance UIDs.
    SeriesInstanceUID, StudyInstanceUID : str
        Its series and study.
    FrameOfReferenceUID : str
        Its Frame of Reference.
    """

    SOPClassUID: str
    SOPInstanceUID: str
    SeriesInstanceUID: str
    StudyInstanceUID: str
    FrameOfReferenceUID: str


def image_files(spec: PhantomSpec, values: np.ndarray) -> Iterator[tuple[str, bytes, ImageRef]]:
    """Return the image slices, (file name, DICOM bytes, reference) each: CT (HU), or MR (T2-weighted-like).

    MR when ``spec.modality == "MR"``. One dataset holds everything the slices share; per slice only the instance
    UID, number, position and pixels are set before it is encoded.

    Parameters
    ----------
    spec : PhantomSpec
        The case: image geometry, modality, case id and description.
    values : (n_slices, matrix, matrix) int16
        The painted image (:func:`reachplan.imaging.phantom.phantom_ct_hu`): HU for CT, signal for MR.

    Yields
    ------
    name : str
        File name, e.g. ``CT.0001.dcm``.
    data : bytes
        The encoded DICOM file.
    ref : ImageRef
        What the structure set references of that slice.
    """
    mr = spec.modality == "MR"
    tag = "mr" if mr else "ct"
    series_uid = _uid(f"{tag} series", case_id=spec.case_id)
    for_uid = _uid("frame of reference", case_id=spec.case_id)
    x0 = spec.first_pixel_xy_mm
    sop = MR_IMAGE_STORAGE if mr else CT_IMAGE_STORAGE
    ds = _base_dataset(sop, _uid(tag, "0", case_id=spec.case_id), spec.modality, series_uid, 1,
                       f"phantom {spec.modality}", spec.case_id, spec.description)
    ds.ImageType = ["DERIVED", "SECONDARY", "AXIAL"] if not mr else ["DERIVED", "SECONDARY", "OTHER"]
    ds.InstanceNumber = 1
    ds.FrameOfReferenceUID = for_uid
    ds.PositionReferenceIndicator = ""
    ds.PatientPosition = "HFS"
    ds.BodyPartExamined = "PELVIS"
    if mr:  # MR Image module (PS3.3 C.8.3.1): a T2-weighted turbo spin echo, described not simulated
        ds.ScanningSequence = "SE"
        ds.SequenceVariant = "SK"
        ds.ScanOptions = ""
        ds.MRAcquisitionType = "2D"
        ds.RepetitionTime = 4000
        ds.EchoTime = 100
        ds.EchoTrainLength = 16
        ds.MagneticFieldStrength = 1.5
        ds.ImagedNucleus = "1H"
        ds.SpacingBetweenSlices = spec.slice_thickness_mm
    else:
        ds.KVP = ""
    ds.AcquisitionNumber = 1
    ds.ImageOrientationPatient = [1, 0, 0, 0, 1, 0]
    ds.SliceThickness = spec.slice_thickness_mm
    ds.PixelSpacing = [spec.pixel_mm, spec.pixel_mm]
    ds.SamplesPerPixel = 1
    ds.PhotometricInterpretation = "MONOCHROME2"
    ds.Rows = ds.Columns = spec.matrix
    ds.BitsAllocated = 16
    ds.BitsStored = 16
    ds.HighBit = 15
    ds.PixelRepresentation = 0 if mr else 1
    if mr:
        ds.WindowCenter = 700
        ds.WindowWidth = 1600
        pixels = np.clip(values, 0, None).astype(np.uint16)
    else:
        ds.RescaleIntercept = 0
        ds.RescaleSlope = 1
        ds.RescaleType = "HU"
        ds.WindowCenter = 40
        ds.WindowWidth = 400
        pixels = values
    for k, z in enumerate(spec.slice_z_mm):
        uid = _uid(tag, str(k), case_id=spec.case_id)
        ds.file_meta.MediaStorageSOPInstanceUID = uid
        ds.SOPInstanceUID = uid
        ds.InstanceNumber = k + 1
        ds.ImagePositionPatient = [f"{x0:.3f}", f"{x0:.3f}", f"{z:.3f}"]
        ds.SliceLocation = f"{z:.3f}"
        ds.PixelData = pixels[k].tobytes()
        yield (f"{spec.modality}.{k + 1:04d}.dcm", encode(ds),
               ImageRef(sop, uid, series_uid, ds.StudyInstanceUID, for_uid))


def rtstruct_dataset(spec: PhantomSpec, ct: list[ImageRef]) -> Any:
    """Build the RT Structure Set of a case: every structure's axial cross-sections, one contour per polygon.

    Parameters
    ----------
    spec : PhantomSpec
        The case; its structures are written in order, numbered from 1.
    ct : list of ImageRef
        The written image slices, in slice order (``ct[k]`` is slice ``k``); each contour references its slice.

    Returns
    -------
    pydicom.dataset.FileDataset
        The structure set, ready to encode (contour points in LPS mm, 3 decimals).
    """
    from pydicom.dataset import Dataset
    from pydicom.sequence import Sequence

    first = ct[0]
    ds = _base_dataset(RT_STRUCTURE_SET_STORAGE, _uid("rtstruct", case_id=spec.case_id), "RTSTRUCT",
                       _uid("rtstruct series", case_id=spec.case_id), 2, "phantom structures", spec.case_id)
    ds.InstanceNumber = 1
    ds.OperatorsName = ""
    ds.FrameOfReferenceUID = first.FrameOfReferenceUID
    ds.PositionReferenceIndicator = ""
    ds.StructureSetLabel = "PHANTOM"
    ds.StructureSetName = "reachplan phantom"
    ds.StructureSetDate = "20260101"
    ds.StructureSetTime = "120000"

    def image_ref(img: ImageRef) -> Dataset:
        r = Dataset()
        r.ReferencedSOPClassUID = img.SOPClassUID
        r.ReferencedSOPInstanceUID = img.SOPInstanceUID
        return r

    series = Dataset()
    series.SeriesInstanceUID = first.SeriesInstanceUID
    series.ContourImageSequence = Sequence([image_ref(img) for img in ct])
    study = Dataset()
    study.ReferencedSOPClassUID = "1.2.840.10008.3.1.2.3.1"  # Detached Study Management (retired, as TPSs write)
    study.ReferencedSOPInstanceUID = first.StudyInstanceUID
    study.RTReferencedSeriesSequence = Sequence([series])
    for_ref = Dataset()
    for_ref.FrameOfReferenceUID = first.FrameOfReferenceUID
    for_ref.RTReferencedStudySequence = Sequence([study])
    ds.ReferencedFrameOfReferenceSequence = Sequence([for_ref])

    rois, contours, observations = [], [], []
    z_all = spec.slice_z_mm
    for number, s in enumerate(spec.structures, start=1):
        roi = Dataset()
        roi.ROINumber = number
        roi.ReferencedFrameOfReferenceUID = first.FrameOfReferenceUID
        roi.ROIName = s.name
        roi.ROIGenerationAlgorithm = "AUTOMATIC"
        rois.append(roi)
        items = []
        for k, z in enumerate(z_all):
            for poly in s.cross_section(float(z)):
                c = Dataset()
                c.ContourImageSequence = Sequence([image_ref(ct[k])])
                c.ContourGeometricType = "CLOSED_PLANAR"
                c.NumberOfContourPoints = len(poly)
                pts = np.column_stack([poly, np.full(len(poly), z)])
                c[0x30060050] = _raw_ds(0x30060050, pts.ravel())  # ContourData
                c.set_original_encoding(False, True, "iso8859")  # lets pydicom write the raw bytes as they are
                items.append(c)
        rc = Dataset()
        rc.ROIDisplayColor = list(s.color)
        rc.ReferencedROINumber = number
        rc.ContourSequence = Sequence(items)
        contours.append(rc)
        obs = Dataset()
        obs.ObservationNumber = number
        obs.ReferencedROINumber = number
        obs.RTROIInterpretedType = s.interpreted_type
        obs.ROIInterpreter = ""
        observations.append(obs)
    ds.StructureSetROISequence = Sequence(rois)
    ds.ROIContourSequence = Sequence(contours)
    ds.RTROIObservationsSequence = Sequence(observations)
    return ds


def _raw_ds(tag: int, values: np.ndarray) -> Any:
    """Build a DS element holding ``values`` (3 decimals) as raw bytes (pydicom's per-value checks are slow)."""
    from pydicom.dataelem import RawDataElement
    from pydicom.tag import Tag

    text = "\\".join([f"{v:.3f}" for v in values.tolist()]).encode("ascii")  # Python floats: 5x faster
    if len(text) % 2:
        text += b" "
    return RawDataElement(Tag(tag), "DS", len(text), text, 0, False, True)


def is_case_file(path: Path) -> bool:
    """Tell whether ``path`` is a DICOM file of a built-in case written by reachplan (any version).

    Parameters
    ----------
    path : Path
        Any file (DICOM or not).

    Returns
    -------
    bool
        True when its Manufacturer and Manufacturer's Model Name are this package's; False for any other or
        unreadable file.
    """
    from pydicom import dcmread

    try:
        ds = dcmread(path, stop_before_pixels=True, specific_tags=["Manufacturer", "ManufacturerModelName"])
    except Exception:  # any unreadable file is not ours
        return False
    return ds.get("Manufacturer") == MANUFACTURER and ds.get("ManufacturerModelName") == MODEL_NAME


def encode(ds: Any) -> bytes:
    """Return the DICOM file of a dataset as bytes.

    Parameters
    ----------
    ds : pydicom.Dataset
        A complete dataset with its file meta information.

    Returns
    -------
    bytes
        The DICOM file (preamble, meta and dataset).
    """
    import io

    buf = io.BytesIO()
    ds.save_as(buf, enforce_file_format=True)
    return buf.getvalue()

