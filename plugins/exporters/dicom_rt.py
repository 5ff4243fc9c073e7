"""DICOM RT export of a plan: an RT Plan (brachy, HDR, interstitial), an RT Structure Set and an RT Dose.

Mirrors what Varian BrachyVision and Oncentra/Vitesse write (reference/rtplan_conventions.md, with the DICOM
types and the genuine exports it was read from):

* RT Structure Set: the patient's ROIs as read (numbers, names, colours, contours kept) plus one ROI per
  needle of interpreted type ``BRACHY_CHANNEL`` holding one ``OPEN_NONPLANAR`` contour, the needle path
  written tip first. With the input CT the reference chain Frame of Reference → study → series → every slice,
  and each planar contour references its slice (§8).
* RT Plan: the prescription in Eclipse's layout by default (Brachy Application Setup Dose = dose per fraction,
  specified at the plan's specification point; each reference point a COORDINATES item; no Target Prescription
  Dose (300A,0026) in the Dose Reference Sequence; ``rtplan_style="vitesse"`` adds the target as SITE/TARGET with
  it, as Oncentra/Vitesse writes; Number of Fractions Planned) (§2-3); one Application Setup of the template's
  type with one Channel per needle, linked to its ROI by Referenced ROI Number; Brachy Control Points in pairs
  per dwell (same position; the cumulative time weight rises across the pair by the dwell time), ordered from the
  tip, each with every dose reference's Cumulative
  Dose Reference Coefficient (the channel's share of the setup dose so far: planned dose per fraction at a point
  = Σ over channels of the last coefficient × setup dose, §4) and, on curved needles, Control Point Orientation
  toward the tip (§7); Control Point Relative Position = arc distance from the tip (the channel's end: the first
  dwell is written at the source-tip offset it is given at); dwell times to 1 ms; Channel Length, Channel
  Effective Length and Source Applicator Length = the afterloader's length, Treatment Machine Name from
  :class:`~reachplan.plugins.exporters.base.Afterloader` (§5-6); one Source from the plan's
  :class:`SourceSpec`, its strength dated as the spec says (the planner dates it to the plan day at midnight, as
  Eclipse does, §5).
* RT Dose (when the plan carries its dose): the planned dose of all fractions, referencing the plan (§9).
* All files share one Study (the input CT's, with its date, time and ID) and Frame of Reference, carry the input
  patient identity, get new SOP Instance and Series UIDs, and the plan references the structure set. Approval
  status is ``UNAPPROVED``: this is a pre-plan.

Written with Implicit VR Little Endian (as BrachyVision does: contour data can exceed the 64 kB value
length of explicit-VR DS).
"""

from __future__ import annotations

import io
import weakref
from collections.abc import Callable
from dataclasses import dataclass
from datetime import datetime
from decimal import Decimal
from functools import partial
from importlib import metadata
from pathlib import Path

import numpy as np
import pydicom
from pydicom.dataelem import RawDataElement
from pydicom.dataset import Dataset, FileMetaDataset
from pydicom.sequence import Sequence
from pydicom.tag import Tag
from pydicom.uid import ImplicitVRLittleEndian, generate_uid

from reachplan._arrays import arc_length_mm
from reachplan.imaging.files import atomic_write_bytes
from reachplan.imaging.types import Contour, PatientStudy, Roi
from reachplan.plugins.exporters import base
from reachplan.plugins.exporters.base import ExportError, ExportOptions, ExportPlan, NeedleExport, project_on_path
from reachplan.plugins.exporters.rtdose import CEILING_TIMES_PRESCRIPTION, DoseContext, rtdose_dataset

RT_PLAN_STORAGE = "1.2.840.10008.5.1.4.1.1.481.5"
RT_STRUCTURE_SET_STORAGE = "1.2.840.10008.5.1.4.1.1.481.3"
#: Referenced SOP Class of the RT Referenced Study item (Detached Study Management, as Oncentra/Vitesse
#: writes; rtplan_conventions.md §8).
DETACHED_STUDY_MANAGEMENT = "1.2.840.10008.3.1.2.3.1"
#: Implementation Class UID of reachplan's writer (derived from a fixed name, so stable across runs).
IMPLEMENTATION_CLASS_UID = generate_uid(entropy_srcs=["reachplan DICOM RT exporter"])
CHANNEL_COLOR = (255, 255, 0)
#: Series Number of each exported object (RT Dose: rtdose.py writes its own).
SERIES_NUMBERS = {"RTSTRUCT": 901, "RTPLAN": 902}
_INTERPRETED_TYPE_CHARS = set("ABCDEFGHIJKLMNOPQRSTUVWXYZ0123456789_ ")


def _version() -> str:
    try:
        return metadata.version("reachplan")
    except metadata.PackageNotFoundError:
        return "unknown"


def _ds(x: float, decimals: int = 4) -> str:
    """Format ``x`` as a decimal string (DS, <= 16 characters) with at most ``decimals`` decimals."""
    s = f"{x:.{decimals}f}".rstrip("0").rstrip(".")
    s = "0" if s in ("-0", "") else s
    if len(s) > 16:
        raise ExportError(f"value {x} does not fit a DICOM decimal string; coordinates must be in mm")
    return s


#: ContourData elements already written, by the id of their points array (kept while the array lives).
_WRITTEN: dict[int, tuple[weakref.ref[np.ndarray], RawDataElement]] = {}


def _contour_data(points_mm: np.ndarray) -> RawDataElement:
    """ContourData (3006,0050) of ``points_mm`` ((n, 3) float, mm, LPS), each value as :func:`_ds` writes it.

    As raw bytes (implicit VR little endian, the files' transfer syntax): pydicom's check of each of a structure
    set's half a million values took seconds. A contour array written before (the same structure set exported with
    the plan and with each arm's implant) gives the same element again.
    """
    seen = _WRITTEN.get(id(points_mm))
    if seen is not None and seen[0]() is points_mm:
        return seen[1]
    element = _format_contour(points_mm)
    if isinstance(points_mm, np.ndarray):
        key = id(points_mm)
        _WRITTEN[key] = (weakref.ref(points_mm, partial(_forget, key)), element)
    return element


def _forget(key: int, _ref: object) -> None:
    """Drop the element of a points array that no longer exists."""
    _WRITTEN.pop(key, None)


def _format_contour(points_mm: np.ndarray) -> RawDataElement:
    """Format the ContourData element of :func:`_contour_data`."""
    text = "\\".join(_ds(x) for x in np.asarray(points_mm, dtype=float).ravel()).encode("ascii")
    if len(text) % 2:
        text += b" "
    return RawDataElement(Tag(0x30060050), "DS", len(text), text, 0, True, True)


def _dsd(x: Decimal) -> str:
    s = format(x.normalize(), "f")
    if len(s) > 16:
        raise ExportError(f"value {s} does not fit a DICOM decimal string (16 characters)")
    return s


def new_uid(prefix: str | None = None) -> str:
    """Generate a new UID under ``prefix`` (default: pydicom's registered root ``1.2.826.0.1.3680043.8.498.``)."""
    return str(generate_uid() if prefix is None else generate_uid(prefix=prefix))


def _date(t: datetime) -> str:
    return t.strftime("%Y%m%d")


def _time(t: datetime) -> str:
    return t.strftime("%H%M%S")


@dataclass(frozen=True)
class Identity:
    """Patient, study and Frame of Reference identity shared by every file of an export.

    Parameters
    ----------
    patient_study : PatientStudy
        As written to every file: the input images' study (else the structure set's); a study of our own has the
        export's date and time and ID "1".
    frame_of_reference_uid : str
        As written to every file.
    generated : tuple of str
        What the input did not give and was generated (placeholders), e.g.
        ``("Study Instance UID", "Frame of Reference UID")``.
    """

    patient_study: PatientStudy
    frame_of_reference_uid: str
    generated: tuple[str, ...] = ()


def plan_identity(plan: ExportPlan, uid_prefix: str | None = None) -> Identity:
    """Take the identity of the input CT (else of the input structure set); generate what is missing.

    Raises
    ------
    ExportError
        When the volume and the structure set belong to different Frames of Reference, studies or patients.
    """
    v, s = plan.volume, plan.structure_set
    vs = v.patient_study if v else PatientStudy()
    ss = s.patient_study if s else PatientStudy()
    pairs = {
        "Frame of Reference UID": (v.frame_of_reference_uid if v else "", s.frame_of_reference_uid if s else ""),
        "Study Instance UID": (vs.study_instance_uid, ss.study_instance_uid),
        "Patient ID": (vs.patient_id, ss.patient_id),
    }
    for what, (a, b) in pairs.items():
        if a and b and a != b:
            raise ExportError(f"the input volume and structure set differ in {what} ({a} vs {b}); "
                              "export with the structure set drawn on that volume")
    given = {what: a or b for what, (a, b) in pairs.items()}
    generated = tuple(what for what in ("Study Instance UID", "Frame of Reference UID") if not given[what])
    study = [x for x in (vs, ss) if x.study_instance_uid == given["Study Instance UID"]
             and x.study_date]  # the CT's study attributes, else the input structure set's
    now = plan.plan_datetime or datetime.now()
    return Identity(
        patient_study=PatientStudy(
            patient_id=given["Patient ID"],
            patient_name=vs.patient_name or ss.patient_name,
            study_instance_uid=given["Study Instance UID"] or new_uid(uid_prefix),
            study_date=study[0].study_date if study else _date(now),
            study_time=study[0].study_time if study else _time(now),
            study_id=(study[0].study_id if study else "") or "1"),
        frame_of_reference_uid=given["Frame of Reference UID"] or new_uid(uid_prefix),
        generated=generated + (() if given["Patient ID"] else ("Patient ID (left empty)",)),
    )


def _common(ds: Dataset, ident: Identity, sop_class: str, sop_uid: str, modality: str, now: datetime,
            series_uid: str) -> None:
    ds.SpecificCharacterSet = "ISO_IR 192"
    ds.InstanceCreationDate = _date(now)
    ds.InstanceCreationTime = _time(now)
    ds.SOPClassUID = sop_class
    ds.SOPInstanceUID = sop_uid
    # the study of the images (dciodvfy warns about empty study attributes; every TPS export repeats the CT's)
    ident.patient_study.write(ds)
    ds.AccessionNumber = ""
    ds.Modality = modality
    ds.Manufacturer = "reachplan"
    ds.ReferringPhysicianName = ""
    ds.SeriesDescription = "reachplan pre-plan"
    ds.OperatorsName = ""
    ds.ManufacturerModelName = "reachplan"
    ds.PatientBirthDate = ""
    ds.PatientSex = ""
    ds.SoftwareVersions = _version()
    ds.SeriesInstanceUID = series_uid
    # a series number of its own per object (type 2; dciodvfy asks for one), clear of the image series' numbers
    ds.SeriesNumber = SERIES_NUMBERS.get(modality)
    ds.InstanceNumber = 1


def _file_bytes(ds: Dataset) -> bytes:
    meta = FileMetaDataset()
    meta.MediaStorageSOPClassUID = ds.SOPClassUID
    meta.MediaStorageSOPInstanceUID = ds.SOPInstanceUID
    meta.TransferSyntaxUID = ImplicitVRLittleEndian
    meta.ImplementationClassUID = IMPLEMENTATION_CLASS_UID
    meta.ImplementationVersionName = f"REACHPLAN_{_version()}"[:16]
    ds.file_meta = meta
    buf = io.BytesIO()
    pydicom.dcmwrite(buf, ds, enforce_file_format=True)
    return buf.getvalue()


def _interpreted_type(roi: Roi) -> str:
    t = roi.interpreted_type.strip().upper()
    return t if len(t) <= 16 and set(t) <= _INTERPRETED_TYPE_CHARS else ""


def channel_roi_numbers(plan: ExportPlan) -> tuple[int, ...]:
    """Choose the ROI numbers of the needles' BRACHY_CHANNEL ROIs: after the highest input one, in needle order."""
    first = 1 + max((r.number for r in plan.structure_set.rois), default=0) if plan.structure_set else 1
    return tuple(range(first, first + len(plan.needles)))


def _image_ref(class_uid: str, instance_uid: str) -> Dataset:
    item = Dataset()
    item.ReferencedSOPClassUID = class_uid
    item.ReferencedSOPInstanceUID = instance_uid
    return item


def _referenced_frame(plan: ExportPlan, ident: Identity) -> Dataset:
    """Build the Referenced Frame of Reference item.

    With the input images, the study → series → contour images chain (one item per slice, as every TPS export
    writes: rtplan_conventions.md §8).
    """
    ref_for = Dataset()
    ref_for.FrameOfReferenceUID = ident.frame_of_reference_uid
    v = plan.volume
    series_uid = v.series_instance_uid if v is not None else (
        plan.structure_set.referenced_series_uid if plan.structure_set is not None else None)
    if not series_uid:
        return ref_for
    series = Dataset()
    series.SeriesInstanceUID = series_uid
    ss = plan.structure_set
    if v is not None and v.slice_uids and v.series_instance_uid == series_uid:
        series.ContourImageSequence = Sequence([_image_ref(c, i) for c, i in v.slice_uids])
    elif ss is not None and ss.referenced_images and ss.referenced_series_uid == series_uid:
        series.ContourImageSequence = Sequence([_image_ref(c, i) for c, i in ss.referenced_images])
    else:  # the series is known but not its images: the chain stops here (type 1 sequence needs items)
        return ref_for
    study = Dataset()
    study.ReferencedSOPClassUID = DETACHED_STUDY_MANAGEMENT
    study.ReferencedSOPInstanceUID = ident.patient_study.study_instance_uid
    study.RTReferencedSeriesSequence = Sequence([series])
    ref_for.RTReferencedStudySequence = Sequence([study])
    return ref_for


def _slice_finder(plan: ExportPlan) -> Callable[[np.ndarray], Dataset | None]:
    """Map a planar contour (k, 3) mm to the Contour Image item of the input slice it lies on (None: none)."""
    v = plan.volume
    if v is None or not v.slice_uids:
        return lambda _points: None
    a = v.grid.patient_from_index
    normal = np.cross(a[:3, 0], a[:3, 1])
    normal /= np.linalg.norm(normal)
    heights = np.array([float((a[:3, 3] + k * a[:3, 2]) @ normal) for k in range(v.grid.shape[0])])
    step = float(abs(a[:3, 2] @ normal)) or 1.0
    uids = v.slice_uids

    def find(points: np.ndarray) -> Dataset | None:
        h = float(np.mean(points @ normal))
        k = int(np.argmin(np.abs(heights - h)))
        return _image_ref(*uids[k]) if abs(heights[k] - h) <= 0.5 * step + 1e-3 else None

    return find


def build_rtstruct(plan: ExportPlan, ident: Identity, sop_uid: str, now: datetime,
                   uid_prefix: str | None = None) -> Dataset:
    """Build the RT Structure Set dataset (no file meta): input ROIs plus one BRACHY_CHANNEL ROI per needle.

    Each needle's ROI is its path, tip first, as an OPEN_NONPLANAR contour in LPS mm.

    Raises
    ------
    ExportError
        The input structure set has duplicate or non-positive ROI numbers.
    """
    ds = Dataset()
    _common(ds, ident, RT_STRUCTURE_SET_STORAGE, sop_uid, "RTSTRUCT", now, new_uid(uid_prefix))
    ds.FrameOfReferenceUID = ident.frame_of_reference_uid
    ds.PositionReferenceIndicator = ""
    ds.StructureSetLabel = plan.label
    ds.StructureSetName = (plan.name or plan.label)[:64]
    ds.StructureSetDate = _date(now)
    ds.StructureSetTime = _time(now)
    ds.ReferencedFrameOfReferenceSequence = Sequence([_referenced_frame(plan, ident)])
    slice_of = _slice_finder(plan)

    rois: list[tuple[Roi, str]] = []  # (roi, generation algorithm)
    if plan.structure_set is not None:
        numbers = [r.number for r in plan.structure_set.rois]
        # ROI numbers need only be unique (PS3.3 C.8.8.5); Oncentra/Vitesse starts at 0 (rtplan_conventions.md
        # §8), so input numbers are kept as they are, 0 included
        if len(set(numbers)) != len(numbers) or min(numbers, default=0) < 0:
            raise ExportError("the input structure set has duplicate or negative ROI numbers; fix it first")
        rois += [(r, "") for r in plan.structure_set.rois]
    for number, needle in zip(channel_roi_numbers(plan), plan.needles, strict=True):
        tip_first = Contour(needle.path_mm[::-1], "OPEN_NONPLANAR")
        kind = "Applicator" if needle.applicator else "Needle"
        rois.append((Roi(number, f"{kind} {needle.hole_id}", (tip_first,), interpreted_type="BRACHY_CHANNEL",
                         color=CHANNEL_COLOR), "AUTOMATIC"))

    ssroi, contours, observations = [], [], []
    for i, (roi, algorithm) in enumerate(rois, start=1):
        item = Dataset()
        item.ROINumber = roi.number
        item.ReferencedFrameOfReferenceUID = ident.frame_of_reference_uid
        item.ROIName = roi.name[:64]
        item.ROIGenerationAlgorithm = algorithm
        ssroi.append(item)

        rc = Dataset()
        if roi.color is not None:
            rc.ROIDisplayColor = [int(c) for c in roi.color]
        seq = []
        for k, c in enumerate(roi.contours, start=1):
            ct = Dataset()
            ct.ContourNumber = k
            ct.ContourGeometricType = c.geometric_type
            ct.NumberOfContourPoints = len(c.points_mm)
            ct[0x30060050] = _contour_data(c.points_mm)
            ct.set_original_encoding(True, True, "iso8859")  # the file's encoding: the raw bytes go out as they are
            image = slice_of(c.points_mm) if c.geometric_type in ("CLOSED_PLANAR", "POINT") else None
            if image is None and all(c.image):  # no CT given: the slice the input named
                image = _image_ref(*c.image)
            if image is not None:
                ct.ContourImageSequence = Sequence([image])
            seq.append(ct)
        if seq:
            rc.ContourSequence = Sequence(seq)
        rc.ReferencedROINumber = roi.number
        contours.append(rc)

        ob = Dataset()
        ob.ObservationNumber = i
        ob.ReferencedROINumber = roi.number
        ob.RTROIInterpretedType = _interpreted_type(roi)
        ob.ROIInterpreter = ""
        observations.append(ob)
    ds.StructureSetROISequence = Sequence(ssroi)
    ds.ROIContourSequence = Sequence(contours)
    ds.RTROIObservationsSequence = Sequence(observations)
    ds.ApprovalStatus = "UNAPPROVED"
    return ds


def dwell_ticks(times_s: np.ndarray, resolution_s: float) -> np.ndarray:
    """Round dwell times to integer multiples of ``resolution_s`` (half to even).

    Parameters
    ----------
    times_s : (m,) float, s
        Dwell times.
    resolution_s : float, s
        The time step.

    Returns
    -------
    (m,) int64
        Multiples of ``resolution_s``.
    """
    return np.rint(np.asarray(times_s, dtype=float) / resolution_s).astype(np.int64)


def _toward_tip(needle: NeedleExport) -> np.ndarray:
    """Return the (m, 3) unit tangent of the path at each dwell, pointing toward the tip.

    That is the source's long axis in the insertion direction (PS3.3 C.8.8.15.14).
    """
    path = needle.path_mm
    arc, _ = project_on_path(path, needle.dwell_positions_mm)
    s = arc_length_mm(path)
    lo, hi = np.clip(arc - 0.5, 0.0, s[-1]), np.clip(arc + 0.5, 0.0, s[-1])
    d = np.stack([np.interp(hi, s, path[:, c]) - np.interp(lo, s, path[:, c]) for c in range(3)], axis=1)
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def is_curved(needle: NeedleExport, tolerance_mm: float = 0.1) -> bool:
    """Tell whether the needle path leaves the straight line from its entry to its tip by more than ``tolerance_mm``."""
    p = needle.path_mm
    chord = p[-1] - p[0]
    u = chord / np.linalg.norm(chord)
    off = (p - p[0]) - np.outer((p - p[0]) @ u, u)
    return bool(np.linalg.norm(off, axis=1).max() > tolerance_mm)


def _coef(x: float) -> str:
    """Format a cumulative dose reference coefficient as DS (10 significant digits, <= 16 characters)."""
    return f"{x:.10g}"


def _channel(needle: NeedleExport, number: int, roi_number: int, plan: ExportPlan, res: Decimal,
             refs: list[tuple[int, np.ndarray | None]], setup_dose_gy: float | None,
             plan_total_s: Decimal) -> tuple[Dataset, Decimal]:
    """Build one Channel Sequence item.

    ``refs``: (dose reference number, per-dwell dose rate per fraction in Gy/s, or None for the SITE target,
    whose coefficients share the setup dose by channel time).
    """
    from_tip = needle.dwell_distance_from_tip_mm
    order = np.argsort(from_tip, kind="stable")  # tip first, as BrachyVision writes
    ticks = dwell_ticks(needle.dwell_times_s, float(res))[order]
    cum = np.concatenate([[0], np.cumsum(ticks)])
    total = Decimal(int(cum[-1])) * res
    gaps = np.diff(np.sort(np.round(from_tip, 1)))
    gaps = gaps[gaps > 0]
    step = float(gaps.min()) if len(gaps) else 5.0
    length = float(plan.channel_effective_length_mm or plan.afterloader.channel_length_mm)
    curved = is_curved(needle)
    axis = _toward_tip(needle)

    ch = Dataset()
    ch.ChannelNumber = number
    ch.ChannelEffectiveLength = _ds(length, 1)
    # Channel Length (type 2) and Source Applicator Length (1C) repeat the afterloader's length, as BrachyVision
    # and Oncentra/Vitesse write them (1300 mm, rtplan_conventions.md §6); the channel's inner length and the
    # applicator tip beyond the distal-most source position are not known to a pre-plan: present and empty.
    ch.ChannelLength = ch.ChannelEffectiveLength
    ch.ChannelInnerLength = None
    ch.SourceApplicatorTipLength = None
    ch.ChannelTotalTime = _dsd(total)
    ch.SourceMovementType = "STEPWISE"
    ch.SourceApplicatorNumber = number
    ch.SourceApplicatorID = needle.hole_id
    # a plain needle is a straight rigid applicator (RIGID, as both TPSs write); a steered one bends by design
    ch.SourceApplicatorType = "FLEXIBLE" if needle.design else "RIGID"
    ch.SourceApplicatorName = f"needle {needle.hole_id}" + (f" ({needle.design})" if needle.design else "")
    ch.SourceApplicatorName = ch.SourceApplicatorName[:64]
    ch.SourceApplicatorLength = ch.ChannelEffectiveLength
    ch.SourceApplicatorStepSize = _ds(step, 1)
    ch.TransferTubeNumber = None
    ch.ReferencedROINumber = roi_number
    ch.ReferencedSourceNumber = 1
    ch.NumberOfControlPoints = 2 * len(order)
    ch.FinalCumulativeTimeWeight = _dsd(total)
    times_s = ticks.astype(float) * float(res)
    cum_dose: list[np.ndarray] = []
    for _, per_second in refs:
        if per_second is None:  # SITE target: the channel's share of the plan's time (bookkeeping, §4)
            share = np.cumsum(times_s) / float(plan_total_s) if plan_total_s > 0 else np.zeros(len(order))
            cum_dose.append(np.concatenate([[0.0], share]))
        else:
            assert setup_dose_gy is not None
            cum_dose.append(np.concatenate([[0.0], np.cumsum(per_second[order] * times_s)]) / setup_dose_gy)
    cps = []
    for j, idx in enumerate(order):
        pos = [_ds(x) for x in needle.dwell_positions_mm[idx]]
        rel = _ds(float(from_tip[idx]), 2)
        for half in (0, 1):
            cp = Dataset()
            cp.ControlPointIndex = 2 * j + half
            cp.ControlPointRelativePosition = rel
            cp.ControlPoint3DPosition = pos
            if curved:  # as Oncentra/Vitesse writes on curved needles (rtplan_conventions.md §7)
                cp.ControlPointOrientation = [float(x) for x in axis[idx]]
            cp.CumulativeTimeWeight = _dsd(Decimal(int(cum[j + half])) * res)
            if refs and setup_dose_gy is not None:
                items = []
                for (ref_number, _), c in zip(refs, cum_dose, strict=True):
                    item = Dataset()
                    item.CumulativeDoseReferenceCoefficient = _coef(float(c[j + half]))
                    item.ReferencedDoseReferenceNumber = ref_number
                    items.append(item)
                cp.BrachyReferencedDoseReferenceSequence = Sequence(items)
            cps.append(cp)
    ch.BrachyControlPointSequence = Sequence(cps)
    return ch, total


def planned_point_doses_gy(plan: ExportPlan, time_resolution_s: float | None = None) -> dict[str, float]:
    """Dose per fraction (Gy) at each reference point of ``plan`` with the dwell times as the export writes them.

    Parameters
    ----------
    plan : ExportPlan
        The plan with its reference points.
    time_resolution_s : float or None
        The step dwell times are written to; None: :class:`ExportOptions`'s default.

    Returns
    -------
    dict name -> Gy
        Σ over dwells of the point's dose rate × the dwell time rounded to ``time_resolution_s``.
    """
    res = ExportOptions().time_resolution_s if time_resolution_s is None else time_resolution_s
    out = {}
    for p in plan.reference_points:
        out[p.name] = float(sum(
            float(rate @ (dwell_ticks(n.dwell_times_s, res) * res))
            for rate, n in zip(p.rate_gy_per_s, plan.needles, strict=True)))
    return out


@dataclass(frozen=True)
class _DoseReferences:
    """The Dose Reference Sequence items, the number of each point's item, and the prescription's links."""

    items: list[Dataset]
    point_numbers: list[int]  # per reference point of the plan, its Dose Reference Number
    target_number: int | None  # the SITE/TARGET item (vitesse style), whose coefficients are bookkeeping
    setup_uid: str | None  # the item the setup dose refers to: the target (vitesse), else the specification point


def _dose_references(plan: ExportPlan, style: str, uid_prefix: str | None) -> _DoseReferences:
    """Build the Dose Reference Sequence in the layout ``style`` (rtplan_conventions.md §2).

    ``"eclipse"``: one COORDINATES item per reference point, typed ORGAN_AT_RISK as Eclipse types even its Point A
    (the plan's own type otherwise), no Target Prescription Dose (300A,0026) anywhere: Eclipse never writes it, and a
    checker written for Eclipse plans (pyTG43) then reads every point's planned dose from the coefficients.
    ``"vitesse"``: first the target as SITE/TARGET with Target Prescription Dose = the course's prescription (per
    fraction × fractions), then the points, as Oncentra/Vitesse writes it.
    """
    items: list[Dataset] = []
    target_number = None
    if style == "vitesse":
        target = Dataset()
        target.DoseReferenceNumber = 1
        target.DoseReferenceUID = new_uid(uid_prefix)
        target.DoseReferenceStructureType = "SITE"
        target.DoseReferenceDescription = plan.target_name
        target.DoseReferenceType = "TARGET"
        if plan.prescription_dose_gy is not None:
            target.TargetPrescriptionDose = _ds(plan.prescription_dose_gy * plan.fractions_planned, 4)
        items.append(target)
        target_number = 1
    numbers = []
    for p in plan.reference_points:
        item = Dataset()
        item.DoseReferenceNumber = len(items) + 1
        item.DoseReferenceUID = new_uid(uid_prefix)
        item.DoseReferenceStructureType = "COORDINATES"
        item.DoseReferenceDescription = p.name
        item.DoseReferencePointCoordinates = [_ds(x) for x in p.position_mm]
        item.DoseReferenceType = p.reference_type
        numbers.append(int(item.DoseReferenceNumber))
        items.append(item)
    link: str | None = str(items[0].DoseReferenceUID) if target_number is not None else None
    if target_number is None:
        link = next((str(it.DoseReferenceUID) for it, p in zip(items, plan.reference_points, strict=True)
                     if p.name == plan.specification_point), None)
    return _DoseReferences(items, numbers, target_number, link)


def _source_item(src: base.SourceSpec) -> Dataset:
    """Build the Source Sequence item: the model, its dimensions, the strength and the date it is given at (§5)."""
    s = Dataset()
    s.SourceNumber = 1
    if src.model_id:
        s.SourceModelID = src.model_id
    s.SourceDescription = (src.title or src.name)[:64]
    s.SourceType = src.source_type
    if src.manufacturer:
        s.SourceManufacturer = src.manufacturer
    if src.active_diameter_mm is not None:
        s.ActiveSourceDiameter = _ds(src.active_diameter_mm, 3)
    if src.active_length_mm is not None:
        s.ActiveSourceLength = _ds(src.active_length_mm, 3)
    s.SourceIsotopeName = src.isotope
    s.SourceIsotopeHalfLife = _ds(float(src.half_life_days or 0.0), 4)
    s.ReferenceAirKermaRate = _ds(src.air_kerma_rate_u, 4)
    s.SourceStrengthReferenceDate = _date(src.reference_datetime)
    s.SourceStrengthReferenceTime = _time(src.reference_datetime)
    return s


def build_rtplan(plan: ExportPlan, ident: Identity, sop_uid: str, rtstruct_uid: str, now: datetime,
                 time_resolution_s: float = 0.001, uid_prefix: str | None = None,
                 style: str = "eclipse") -> Dataset:
    """Build the RT Plan dataset (no file meta): brachy, HDR, interstitial, one channel per needle.

    Dwell times are written to ``time_resolution_s`` s as cumulative time weights; control point positions are the
    dwell positions in LPS mm. The Dose Reference Sequence is laid out as ``style`` says (:func:`_dose_references`:
    by default Eclipse's, every reference point a COORDINATES item and no Target Prescription Dose); Brachy
    Application Setup Dose is the per-fraction prescription, specified (300A,00A2) at the plan's specification point
    (where the planned dose per fraction is the prescription), and every control point carries each reference's
    Cumulative Dose Reference Coefficient, so that a reader recovers the planned dose per fraction at a point as
    Σ over channels of the last coefficient × the setup dose (rtplan_conventions.md §3-4; PS3.3 C.8.8.14.7).
    """
    when = plan.plan_datetime or now
    res = Decimal(repr(time_resolution_s))
    ds = Dataset()
    _common(ds, ident, RT_PLAN_STORAGE, sop_uid, "RTPLAN", now, new_uid(uid_prefix))
    ds.FrameOfReferenceUID = ident.frame_of_reference_uid
    ds.PositionReferenceIndicator = ""
    ds.RTPlanLabel = plan.label
    if plan.name:
        ds.RTPlanName = plan.name
    ds.RTPlanDate = _date(when)
    ds.RTPlanTime = _time(when)
    ds.RTPlanGeometry = "PATIENT"
    ref_ss = Dataset()
    ref_ss.ReferencedSOPClassUID = RT_STRUCTURE_SET_STORAGE
    ref_ss.ReferencedSOPInstanceUID = rtstruct_uid
    ds.ReferencedStructureSetSequence = Sequence([ref_ss])
    setup_dose = None if plan.prescription_dose_gy is None else float(_ds(plan.prescription_dose_gy, 4))
    dose_refs = _dose_references(plan, style, uid_prefix)
    if dose_refs.items:
        ds.DoseReferenceSequence = Sequence(dose_refs.items)

    fg = Dataset()
    fg.FractionGroupNumber = 1
    fg.NumberOfFractionsPlanned = plan.fractions_planned
    fg.NumberOfBeams = 0
    fg.NumberOfBrachyApplicationSetups = 1
    ref_setup = Dataset()
    ref_setup.ReferencedBrachyApplicationSetupNumber = 1
    if setup_dose is not None:
        spec = next((p for p in plan.reference_points if p.name == plan.specification_point), None)
        if spec is not None:
            ref_setup.BrachyApplicationSetupDoseSpecificationPoint = [_ds(x) for x in spec.position_mm]
        ref_setup.BrachyApplicationSetupDose = _ds(setup_dose, 4)
        if dose_refs.setup_uid is not None:
            ref_setup.ReferencedDoseReferenceUID = dose_refs.setup_uid
    fg.ReferencedBrachyApplicationSetupSequence = Sequence([ref_setup])
    ds.FractionGroupSequence = Sequence([fg])

    ds.BrachyTreatmentTechnique = "INTERSTITIAL"
    ds.BrachyTreatmentType = plan.source.treatment_type
    machine = Dataset()
    machine.TreatmentMachineName = plan.afterloader.name
    if plan.afterloader.manufacturer:
        machine.Manufacturer = plan.afterloader.manufacturer
    if plan.afterloader.model_name:
        machine.ManufacturerModelName = plan.afterloader.model_name
    ds.TreatmentMachineSequence = Sequence([machine])

    src = plan.source
    ds.SourceSequence = Sequence([_source_item(src)])

    setup = Dataset()
    setup.ApplicationSetupType = plan.application_setup_type
    setup.ApplicationSetupNumber = 1
    setup.ApplicationSetupName = "interstitial template"
    res_s = float(res)
    plan_total = sum((Decimal(int(dwell_ticks(n.dwell_times_s, res_s).sum())) * res for n in plan.needles),
                     Decimal(0))
    channels, total_s = [], Decimal(0)
    for k, (needle, roi_number) in enumerate(zip(plan.needles, channel_roi_numbers(plan), strict=True), start=1):
        refs: list[tuple[int, np.ndarray | None]] = [] if dose_refs.target_number is None else [
            (dose_refs.target_number, None)]
        refs += [(i, p.rate_gy_per_s[k - 1]) for i, p in zip(dose_refs.point_numbers, plan.reference_points,
                                                                strict=True)]
        ch, t = _channel(needle, k, roi_number, plan, res, refs, setup_dose, plan_total)
        channels.append(ch)
        total_s += t
    # Total Reference Air Kerma (µGy at 1 m) = S_K (U = µGy m² h⁻¹) x total time (h), S_K as written (not decayed).
    setup.TotalReferenceAirKerma = _ds(src.air_kerma_rate_u * float(total_s) / 3600.0, 6)
    setup.ChannelSequence = Sequence(channels)
    ds.ApplicationSetupSequence = Sequence([setup])
    ds.ApprovalStatus = "UNAPPROVED"
    return ds


def _input_uids(plan: ExportPlan) -> set[str]:
    uids = {plan.structure_set.sop_instance_uid} if plan.structure_set is not None else set()
    return uids - {""}


def _refuse_input_sop(path: Path, uids: set[str]) -> None:
    if not uids or not path.is_file():
        return
    try:
        old = pydicom.dcmread(path, stop_before_pixels=True, specific_tags=["SOPInstanceUID"], force=True)
        uid = str(old.get("SOPInstanceUID", ""))
    except Exception:  # not DICOM, unreadable: nothing to protect beyond check_targets
        return
    if uid in uids:
        raise ExportError(f"refusing to write {path}: it holds the input structure set ({uid})")


def export_plan(plan: ExportPlan, out_dir: Path, options: ExportOptions | None = None) -> base.ExportedFiles:
    """Write ``RS_<stem>.dcm``, ``RP_<stem>.dcm`` and, with the plan's dose, ``RD_<stem>.dcm`` into ``out_dir``.

    The RT Dose references the plan (and through it the structure set: a Referenced Structure Set Sequence in an
    RT Dose belongs to the RT DVH module, which would then need DVHs).

    Parameters
    ----------
    plan : ExportPlan
        The plan; needle paths and dwells in LPS mm.
    out_dir : Path
        Created when missing.
    options : ExportOptions, optional
        ``overwrite``, ``stem``, ``include_patient_name``, ``time_resolution_s``, ``uid_prefix`` are used.

    Returns
    -------
    base.ExportedFiles
        Roles ``"rtstruct"``, ``"rtplan"`` (and ``"rtdose"``); notes on placeholders and dwell-time rounding.

    Raises
    ------
    ExportError
        An existing file without ``overwrite``, an input file as target, inconsistent input identity.
    """
    opts = options or ExportOptions()
    uid_prefix = opts.uid_prefix
    out = base.prepare_out_dir(out_dir)
    stem = base.file_stem(plan, opts)
    rs_path, rp_path, rd_path = out / f"RS_{stem}.dcm", out / f"RP_{stem}.dcm", out / f"RD_{stem}.dcm"
    targets = (rs_path, rp_path) + ((rd_path,) if plan.dose is not None else ())
    base.check_targets(targets, plan, opts)
    for p in targets:
        _refuse_input_sop(p, _input_uids(plan))

    notes: list[str] = []
    ident = plan_identity(plan, uid_prefix)
    if ident.generated:
        notes.append(f"not in the input, generated as placeholders: {', '.join(ident.generated)}; link the "
                     "files to the patient's images and record before use")
    worst = max(float(np.max(np.abs(dwell_ticks(n.dwell_times_s, opts.time_resolution_s) * opts.time_resolution_s
                                    - n.dwell_times_s))) for n in plan.needles)
    if worst > 1e-9:
        notes.append(f"dwell times rounded to {opts.time_resolution_s} s (largest change {worst:.3g} s)")
    now = datetime.now().replace(microsecond=0)
    rs_uid, rp_uid = new_uid(uid_prefix), new_uid(uid_prefix)
    rs = build_rtstruct(plan, ident, rs_uid, now, uid_prefix)
    rp = build_rtplan(plan, ident, rp_uid, rs_uid, now, opts.time_resolution_s, uid_prefix, opts.rtplan_style)
    rs_bytes, rp_bytes = _file_bytes(rs), _file_bytes(rp)
    rd_bytes = b""
    if plan.dose is not None:
        context = DoseContext(
            frame_of_reference_uid=ident.frame_of_reference_uid, patient_study=ident.patient_study,
            referenced_plan_uid=rp_uid,
            series_description="reachplan planned dose (TG-43)")
        try:
            ceiling = None if plan.prescription_dose_gy is None else (
                CEILING_TIMES_PRESCRIPTION * plan.prescription_dose_gy * plan.fractions_planned)
            rd = rtdose_dataset(plan.dose.dose_gy, plan.dose.grid, context, ceiling_gy=ceiling)
            if ceiling is not None and float(np.max(plan.dose.dose_gy)) > ceiling:
                notes.append(f"RT Dose: {int(np.count_nonzero(plan.dose.dose_gy > ceiling))} voxel(s) next to dwells "
                             f"above {ceiling:.4g} Gy ({CEILING_TIMES_PRESCRIPTION:g} x the prescription) stored at it")
        except ValueError as exc:
            raise ExportError(f"cannot write the planned dose as RT Dose: {exc}") from None
        buf = io.BytesIO()
        rd.save_as(buf, enforce_file_format=True)
        rd_bytes = buf.getvalue()
    atomic_write_bytes(rs_path, rs_bytes)
    atomic_write_bytes(rp_path, rp_bytes)
    files = [base.ExportedFile("rtstruct", rs_path), base.ExportedFile("rtplan", rp_path)]
    if rd_bytes:
        atomic_write_bytes(rd_path, rd_bytes)
        files.append(base.ExportedFile("rtdose", rd_path))
    return base.ExportedFiles("dicom_rt", tuple(files), tuple(notes))


EXPORTER: base.Exporter = base.FunctionExporter(
    "dicom_rt", "DICOM RT Plan (brachy HDR) + RT Structure Set with BRACHY_CHANNEL ROIs", export_plan)

__all__ = ["EXPORTER", "build_rtplan", "build_rtstruct", "export_plan", "plan_identity"]
