"""DICOM RT export of a plan: an RT Plan (brachy, HDR, interstitial) and an RT Structure Set.

Mirrors what Varian BrachyVision writes (reference/tps_examples/hdr, see ``oncoreach.md`` "Export
conventions"):

* RT Structure Set: the patient's ROIs as read (numbers, names, colours, contours kept) plus one ROI per
  needle of interpreted type ``BRACHY_CHANNEL`` holding one ``OPEN_NONPLANAR`` contour, the needle path
  written tip first.
* RT Plan: one Application Setup with one Channel per needle (Channel Sequence), each linked to its ROI by
  Referenced ROI Number; Brachy Control Points in pairs per dwell (same position; the cumulative time weight
  rises across the pair by the dwell time), ordered from the tip; Control Point Relative Position = arc
  distance from the tip (the distal-most source position) along the path; cumulative time weights in
  seconds, Final Cumulative Time Weight = Channel Total Time (as Eclipse writes); Channel Effective Length
  (PS3.3 prefers it to the retired Channel Length); one Source from the plan's :class:`SourceSpec`.
* Both files share one Study and Frame of Reference (the input's), carry the input patient identity, get
  new SOP Instance and Series UIDs, and the plan references the structure set. Approval status is
  ``UNAPPROVED``: this is a pre-plan.

Written with Implicit VR Little Endian (as BrachyVision does: contour data can exceed the 64 kB value
length of explicit-VR DS).
"""

from __future__ import annotations

import io
from dataclasses import dataclass
from datetime import datetime
from decimal import Decimal
from importlib import metadata
from pathlib import Path

import numpy as np
import pydicom
from pydicom.dataset import Dataset, FileMetaDataset
from pydicom.sequence import Sequence
from pydicom.uid import ImplicitVRLittleEndian, generate_uid

from reachplan.imaging.files import atomic_write_bytes
from reachplan.imaging.types import Contour, Roi
from reachplan.plugins.exporters.base import (
    ExportedFile,
    ExportedFiles,
    Exporter,
    ExportError,
    ExportOptions,
    ExportPlan,
    FunctionExporter,
    NeedleExport,
    check_targets,
    file_stem,
    prepare_out_dir,
)

RT_PLAN_STORAGE = "1.2.840.10008.5.1.4.1.1.481.5"
RT_STRUCTURE_SET_STORAGE = "1.2.840.10008.5.1.4.1.1.481.3"
#: Implementation Class UID of reachplan's writer (derived from a fixed name, so stable across runs).
IMPLEMENTATION_CLASS_UID = generate_uid(entropy_srcs=["reachplan DICOM RT exporter"])
CHANNEL_COLOR = (255, 255, 0)
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
    """Patient, study and Frame of Reference identity shared by both files.

    Parameters
    ----------
    patient_id, patient_name, study_instance_uid, frame_of_reference_uid : str
        As written to both files.
    generated : tuple of str
        What the input did not give and was generated (placeholders), e.g.
        ``("Study Instance UID", "Frame of Reference UID")``.
    """

    patient_id: str
    patient_name: str
    study_instance_uid: str
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
    pairs = {
        "Frame of Reference UID": (v.frame_of_reference_uid if v else "", s.frame_of_reference_uid if s else ""),
        "Study Instance UID": (v.study_instance_uid if v else "", s.study_instance_uid if s else ""),
        "Patient ID": (v.patient_id if v else "", s.patient_id if s else ""),
    }
    for what, (a, b) in pairs.items():
        if a and b and a != b:
            raise ExportError(f"the input volume and structure set differ in {what} ({a} vs {b}); "
                              "export with the structure set drawn on that volume")
    given = {what: a or b for what, (a, b) in pairs.items()}
    generated = tuple(what for what in ("Study Instance UID", "Frame of Reference UID") if not given[what])
    return Identity(
        patient_id=given["Patient ID"],
        patient_name=(v.patient_name if v else "") or (s.patient_name if s else ""),
        study_instance_uid=given["Study Instance UID"] or new_uid(uid_prefix),
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
    ds.StudyDate = ""
    ds.StudyTime = ""
    ds.AccessionNumber = ""
    ds.Modality = modality
    ds.Manufacturer = "reachplan"
    ds.ReferringPhysicianName = ""
    ds.SeriesDescription = "reachplan pre-plan"
    ds.OperatorsName = ""
    ds.ManufacturerModelName = "reachplan"
    ds.PatientName = ident.patient_name
    ds.PatientID = ident.patient_id
    ds.PatientBirthDate = ""
    ds.PatientSex = ""
    ds.SoftwareVersions = _version()
    ds.StudyInstanceUID = ident.study_instance_uid
    ds.SeriesInstanceUID = series_uid
    ds.StudyID = ""
    ds.SeriesNumber = None
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
    ref_for = Dataset()
    ref_for.FrameOfReferenceUID = ident.frame_of_reference_uid
    ds.ReferencedFrameOfReferenceSequence = Sequence([ref_for])

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
        rois.append((Roi(number, f"Needle {needle.hole_id}", (tip_first,), interpreted_type="BRACHY_CHANNEL",
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
            ct.ContourData = [_ds(x) for x in c.points_mm.ravel()]
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


def _channel(needle: NeedleExport, number: int, roi_number: int, plan: ExportPlan,
             res: Decimal) -> tuple[Dataset, Decimal]:
    from_tip = needle.dwell_distance_from_tip_mm
    order = np.argsort(from_tip, kind="stable")  # tip first, as BrachyVision writes
    ticks = dwell_ticks(needle.dwell_times_s, float(res))[order]
    cum = np.concatenate([[0], np.cumsum(ticks)])
    total = Decimal(int(cum[-1])) * res
    gaps = np.diff(np.sort(np.round(from_tip, 1)))
    gaps = gaps[gaps > 0]
    step = float(gaps.min()) if len(gaps) else 5.0

    ch = Dataset()
    ch.ChannelNumber = number
    ch.ChannelEffectiveLength = _ds(plan.channel_effective_length_mm, 1)
    # Channel Length (type 2) repeats it for readers that predate Channel Effective Length (BrachyVision writes
    # its 1300 mm there); the channel's inner length and the applicator tip beyond the distal-most source
    # position are not known to a pre-plan: present and empty (type 2C).
    ch.ChannelLength = ch.ChannelEffectiveLength
    ch.ChannelInnerLength = None
    ch.SourceApplicatorTipLength = None
    ch.ChannelTotalTime = _dsd(total)
    ch.SourceMovementType = "STEPWISE"
    ch.SourceApplicatorNumber = number
    ch.SourceApplicatorID = needle.hole_id
    ch.SourceApplicatorType = "FLEXIBLE"
    ch.SourceApplicatorName = f"needle {needle.hole_id}" + (f" ({needle.design})" if needle.design else "")
    ch.SourceApplicatorName = ch.SourceApplicatorName[:64]
    ch.SourceApplicatorLength = _ds(needle.length_mm, 2)
    ch.SourceApplicatorStepSize = _ds(step, 1)
    ch.TransferTubeNumber = None
    ch.ReferencedROINumber = roi_number
    ch.ReferencedSourceNumber = 1
    ch.NumberOfControlPoints = 2 * len(order)
    ch.FinalCumulativeTimeWeight = _dsd(total)
    cps = []
    for j, idx in enumerate(order):
        pos = [_ds(x) for x in needle.dwell_positions_mm[idx]]
        rel = _ds(float(from_tip[idx]), 2)
        for half in (0, 1):
            cp = Dataset()
            cp.ControlPointIndex = 2 * j + half
            cp.ControlPointRelativePosition = rel
            cp.ControlPoint3DPosition = pos
            cp.CumulativeTimeWeight = _dsd(Decimal(int(cum[j + half])) * res)
            cps.append(cp)
    ch.BrachyControlPointSequence = Sequence(cps)
    return ch, total


def build_rtplan(plan: ExportPlan, ident: Identity, sop_uid: str, rtstruct_uid: str, now: datetime,
                 time_resolution_s: float = 0.1, uid_prefix: str | None = None) -> Dataset:
    """Build the RT Plan dataset (no file meta): brachy, HDR, interstitial, one channel per needle.

    Dwell times are rounded to ``time_resolution_s`` s and written as cumulative time weights; control point
    positions are the dwell positions in LPS mm.
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

    fg = Dataset()
    fg.FractionGroupNumber = 1
    fg.NumberOfFractionsPlanned = plan.fractions_planned
    fg.NumberOfBeams = 0
    fg.NumberOfBrachyApplicationSetups = 1
    ref_setup = Dataset()
    ref_setup.ReferencedBrachyApplicationSetupNumber = 1
    if plan.prescription_dose_gy is not None:
        ref_setup.BrachyApplicationSetupDose = _ds(plan.prescription_dose_gy, 4)
    fg.ReferencedBrachyApplicationSetupSequence = Sequence([ref_setup])
    ds.FractionGroupSequence = Sequence([fg])

    ds.BrachyTreatmentTechnique = "INTERSTITIAL"
    ds.BrachyTreatmentType = plan.source.treatment_type
    machine = Dataset()
    machine.TreatmentMachineName = ""
    ds.TreatmentMachineSequence = Sequence([machine])

    src = plan.source
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
    ds.SourceSequence = Sequence([s])

    setup = Dataset()
    setup.ApplicationSetupType = plan.application_setup_type
    setup.ApplicationSetupNumber = 1
    setup.ApplicationSetupName = "interstitial template"
    channels, total_s = [], Decimal(0)
    for k, (needle, roi_number) in enumerate(zip(plan.needles, channel_roi_numbers(plan), strict=True), start=1):
        ch, t = _channel(needle, k, roi_number, plan, res)
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


def export_plan(plan: ExportPlan, out_dir: Path, options: ExportOptions | None = None) -> ExportedFiles:
    """Write ``RS_<stem>.dcm`` (RT Structure Set) and ``RP_<stem>.dcm`` (RT Plan) into ``out_dir``.

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
    ExportedFiles
        Roles ``"rtstruct"`` and ``"rtplan"``; notes on placeholders and dwell-time rounding.

    Raises
    ------
    ExportError
        An existing file without ``overwrite``, an input file as target, inconsistent input identity.
    """
    opts = options or ExportOptions()
    uid_prefix = opts.uid_prefix
    out = prepare_out_dir(out_dir)
    stem = file_stem(plan, opts)
    rs_path, rp_path = out / f"RS_{stem}.dcm", out / f"RP_{stem}.dcm"
    check_targets((rs_path, rp_path), plan, opts)
    for p in (rs_path, rp_path):
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
    rp = build_rtplan(plan, ident, rp_uid, rs_uid, now, opts.time_resolution_s, uid_prefix)
    rs_bytes, rp_bytes = _file_bytes(rs), _file_bytes(rp)
    atomic_write_bytes(rs_path, rs_bytes)
    atomic_write_bytes(rp_path, rp_bytes)
    return ExportedFiles("dicom_rt", (ExportedFile("rtstruct", rs_path), ExportedFile("rtplan", rp_path)),
                         tuple(notes))


EXPORTER: Exporter = FunctionExporter(
    "dicom_rt", "DICOM RT Plan (brachy HDR) + RT Structure Set with BRACHY_CHANNEL ROIs", export_plan)

__all__ = ["EXPORTER", "build_rtplan", "build_rtstruct", "export_plan", "plan_identity"]
