"""What a reconstruction writes: ``needles.json`` and an RT Structure Set with the needles as open ROIs.

The structure set holds one BRACHY_CHANNEL ROI per needle found, named ``Needle <hole>``, its centre line as one
OPEN_NONPLANAR contour written tip first (as the planner's exported channels and as Eclipse and Oncentra write
catheters: ``rtplan_conventions.md``), in the image's Frame of Reference and study, referencing the image series.
"""

from __future__ import annotations

import io
from collections.abc import Mapping, Sequence
from datetime import datetime
from typing import Any

import numpy as np

from reachplan.imaging.types import Volume
from reachplan.planner.verify.find import FoundNeedle

RT_STRUCTURE_SET_STORAGE = "1.2.840.10008.5.1.4.1.1.481.3"
#: The Detached Study Management SOP Class every TPS puts in the study reference of a structure set.
DETACHED_STUDY_MANAGEMENT = "1.2.840.10008.3.1.2.3.1"
#: Series number of the reconstruction's structure set (clear of the planner's exports, 901 and 902).
SERIES_NUMBER = 903


def needles_document(found: Sequence[FoundNeedle], about: Mapping[str, object]) -> dict[str, object]:
    """Return ``needles.json``: per needle its hole, centre line from the template plane to the tip, tip, confidence.

    Parameters
    ----------
    found : sequence of FoundNeedle
        The needles found.
    about : mapping of str to object
        What else to record (inputs, template pose, settings, comparisons).

    Returns
    -------
    dict of str to object
        JSON-ready; points mm, LPS, 3 decimals.
    """
    return {
        **about,
        "needles": [{
            "hole_id": f.hole_id,
            "points_mm": np.round(f.points_mm, 3).tolist(),
            "tip_mm": np.round(f.tip_mm, 3).tolist(),
            "length_mm": round(f.length_mm, 2),
            "contrast": round(f.contrast, 1),
            "confidence": round(f.confidence, 3),
            "seconds": round(f.seconds, 3),
            "note": f.note,
        } for f in found],
    }


def _ds(x: float) -> str:
    """Return a decimal string (DS) of at most 16 characters, 3 decimals."""
    s = f"{x:.3f}".rstrip("0").rstrip(".")
    return "0" if s in ("-0", "") else s


def _referenced_frame(volume: Volume, study_uid: str) -> Any:
    """Return the Referenced Frame of Reference item: with the slices, the study -> series -> images chain."""
    from pydicom.dataset import Dataset
    from pydicom.sequence import Sequence as DicomSequence

    ref_for = Dataset()
    ref_for.FrameOfReferenceUID = volume.frame_of_reference_uid
    if volume.slice_uids:
        series = Dataset()
        series.SeriesInstanceUID = volume.series_instance_uid
        images = []
        for cls, uid in volume.slice_uids:
            item = Dataset()
            item.ReferencedSOPClassUID, item.ReferencedSOPInstanceUID = cls, uid
            images.append(item)
        series.ContourImageSequence = DicomSequence(images)
        study = Dataset()
        study.ReferencedSOPClassUID = DETACHED_STUDY_MANAGEMENT
        study.ReferencedSOPInstanceUID = study_uid
        study.RTReferencedSeriesSequence = DicomSequence([series])
        ref_for.RTReferencedStudySequence = DicomSequence([study])
    return ref_for


def _roi_items(found: Sequence[FoundNeedle], for_uid: str) -> tuple[list[Any], list[Any], list[Any]]:
    """Return the Structure Set ROI, ROI Contour and RT ROI Observations items: one BRACHY_CHANNEL per needle."""
    from pydicom.dataset import Dataset
    from pydicom.sequence import Sequence as DicomSequence

    rois, contours, observations = [], [], []
    for number, f in enumerate(found, start=1):
        roi = Dataset()
        roi.ROINumber = number
        roi.ReferencedFrameOfReferenceUID = for_uid
        roi.ROIName = f"Needle {f.hole_id}"[:64]
        roi.ROIGenerationAlgorithm = "AUTOMATIC"
        rois.append(roi)
        c = Dataset()
        c.ContourNumber = 1
        c.ContourGeometricType = "OPEN_NONPLANAR"
        pts = f.points_mm[::-1]  # tip first
        c.NumberOfContourPoints = len(pts)
        c.ContourData = [_ds(float(v)) for v in pts.ravel()]
        rc = Dataset()
        rc.ROIDisplayColor = [255, 255, 0]
        rc.ContourSequence = DicomSequence([c])
        rc.ReferencedROINumber = number
        contours.append(rc)
        ob = Dataset()
        ob.ObservationNumber = number
        ob.ReferencedROINumber = number
        ob.RTROIInterpretedType = "BRACHY_CHANNEL"
        ob.ROIInterpreter = ""
        observations.append(ob)
    return rois, contours, observations


def needles_rtstruct(found: Sequence[FoundNeedle], volume: Volume, label: str = "NEEDLES",
                     now: datetime | None = None) -> bytes:
    """Encode the RT Structure Set of the needles found (module docstring).

    Parameters
    ----------
    found : sequence of FoundNeedle
        The needles (at least one).
    volume : Volume
        The image they were found in: patient, study, Frame of Reference and the slices referenced.
    label : str
        Structure Set Label (<= 16 characters).
    now : datetime, optional
        Creation date and time; None: now.

    Returns
    -------
    bytes
        The DICOM file (implicit VR little endian).
    """
    import pydicom
    from pydicom.dataset import Dataset, FileMetaDataset
    from pydicom.sequence import Sequence as DicomSequence
    from pydicom.uid import ImplicitVRLittleEndian, generate_uid

    from reachplan import __version__

    now = (now or datetime.now()).replace(microsecond=0)
    ds = Dataset()
    ds.SpecificCharacterSet = "ISO_IR 192"
    ds.SOPClassUID = RT_STRUCTURE_SET_STORAGE
    ds.SOPInstanceUID = generate_uid()
    ds.InstanceCreationDate, ds.InstanceCreationTime = now.strftime("%Y%m%d"), now.strftime("%H%M%S")
    volume.patient_study.write(ds)
    ds.StudyID = ds.StudyID or "1"
    ds.StudyDate = ds.StudyDate or now.strftime("%Y%m%d")
    ds.StudyTime = ds.StudyTime or now.strftime("%H%M%S")
    ds.StudyInstanceUID = ds.StudyInstanceUID or generate_uid()
    ds.PatientBirthDate, ds.PatientSex, ds.AccessionNumber, ds.ReferringPhysicianName = "", "", "", ""
    ds.Modality = "RTSTRUCT"
    ds.Manufacturer = ds.ManufacturerModelName = "reachplan"
    ds.SoftwareVersions = __version__
    ds.SeriesDescription = "reachplan needles found"
    ds.SeriesInstanceUID = generate_uid()
    ds.SeriesNumber = SERIES_NUMBER
    ds.InstanceNumber = 1
    ds.OperatorsName = ""
    ds.FrameOfReferenceUID = volume.frame_of_reference_uid
    ds.PositionReferenceIndicator = ""
    ds.StructureSetLabel = label[:16]
    ds.StructureSetDate, ds.StructureSetTime = now.strftime("%Y%m%d"), now.strftime("%H%M%S")
    ref_for = _referenced_frame(volume, ds.StudyInstanceUID)
    ds.ReferencedFrameOfReferenceSequence = DicomSequence([ref_for])
    rois, contours, observations = _roi_items(found, volume.frame_of_reference_uid)
    ds.StructureSetROISequence = DicomSequence(rois)
    ds.ROIContourSequence = DicomSequence(contours)
    ds.RTROIObservationsSequence = DicomSequence(observations)
    ds.ApprovalStatus = "UNAPPROVED"
    meta = FileMetaDataset()
    meta.MediaStorageSOPClassUID = ds.SOPClassUID
    meta.MediaStorageSOPInstanceUID = ds.SOPInstanceUID
    meta.TransferSyntaxUID = ImplicitVRLittleEndian
    ds.file_meta = meta
    buf = io.BytesIO()
    pydicom.dcmwrite(buf, ds, enforce_file_format=True)
    return buf.getvalue()
