"""Read DICOM RT Plans, in particular brachytherapy plans, into plain typed data.

What is read (PS3.3 C.8.8.14-15, RT Brachy Application Setups): the source (isotope, model,
reference air-kerma rate, reference date, active length), application setups, channels with their
control points turned into dwell positions and times, dose reference points with the TPS's own doses,
the channel ↔ RT Structure Set ROI links (ReferencedROINumber), and Oncentra's private catheter
sequence (300F,1000). External-beam plans are read too (``is_brachy`` false, no channels) so a caller
can say what the file is.

Conventions (``reference/oncoreach.md``, Dose; they reproduce the Eclipse point doses):

* dwell time = ChannelTotalTime × ΔCumulativeTimeWeight / FinalCumulativeTimeWeight over the
  control-point pair at each position; for PDR, Eclipse writes FinalCumulativeTimeWeight =
  ChannelTotalTime × NumberOfPulses, so the times are per pulse;
* the TPS's dose at a dose reference point = Σ over channels of the last
  CumulativeDoseReferenceCoefficient × BrachyApplicationSetupDose × NumberOfFractionsPlanned
  (× NumberOfPulses for PDR).

Real files break rules; every quirk met is read anyway and reported once per file by a
:class:`PlanQuirkWarning` naming it: invalid values (over-long decimal strings, ``UNKNOWN`` UIDs, ...),
cumulative time weights that restart at 0 for every dwell, a FinalCumulativeTimeWeight that differs
from the last control point's, weight between two different positions of a stepwise channel, a missing
Frame of Reference UID, a private catheter sequence stored as raw bytes.

Positions are mm, DICOM patient coordinates (LPS); times s; doses Gy; air-kerma rate in U
(µGy m² h⁻¹ = cGy cm² h⁻¹). The plan's types live in :mod:`reachplan.imaging.brachy_plan` and are exported here
too, so ``from reachplan.imaging.rtplan import RtPlan, read_rtplan`` gives the reader and what it returns.
"""

from __future__ import annotations

import io
import os
import warnings
from collections.abc import Iterator, Mapping
from contextlib import contextmanager
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
from pydicom.dataset import Dataset
from pydicom.filereader import read_sequence

from reachplan._arrays import frozen_floats
from reachplan.imaging.brachy_plan import (
    ApplicationSetup,
    BrachySource,
    CatheterPath,
    Channel,
    DoseReference,
    RtPlan,
)
from reachplan.imaging.dicom_files import parsing, read_dataset
from reachplan.imaging.errors import (
    CorruptFileError,
    DicomQuirkWarning,
    InvalidValueError,
    NoDicomError,
)
from reachplan.imaging.types import PatientStudy, StructureSet

__all__ = [
    "MAX_CHANNEL_TOTAL_TIME_S",
    "ONCENTRA_CATHETER_TAG",
    "ONCENTRA_CHANNEL_ROI_TAG",
    "RT_PLAN_SOP_CLASSES",
    "ApplicationSetup",
    "BrachySource",
    "CatheterPath",
    "Channel",
    "DoseReference",
    "PlanQuirkWarning",
    "RtPlan",
    "channel_paths",
    "read_rtplan",
]

RT_PLAN_SOP_CLASSES = {
    "1.2.840.10008.5.1.4.1.1.481.5": "RT Plan",
    "1.2.840.10008.5.1.4.1.1.481.8": "RT Ion Plan",
}
ONCENTRA_CATHETER_TAG = (0x300F, 0x1000)
ONCENTRA_CHANNEL_ROI_TAG = (0x300B, 0x1000)
_SAME_POSITION_MM = 1e-3
#: Largest Channel Total Time accepted, s (about 116 days): far above any HDR/PDR channel (minutes) and above a
#: temporary LDR implant (days); a larger value is a damaged or mis-scaled file, not a treatment.
MAX_CHANNEL_TOTAL_TIME_S = 1e7


class PlanQuirkWarning(DicomQuirkWarning):
    """A plan breaks a DICOM rule in a known way; it was read anyway (the message names the quirk)."""


# --- reading ------------------------------------------------------------------------------------------


@contextmanager
def _quirks(path: str, found: list[str]) -> Iterator[None]:
    """Collect pydicom's validation warnings (emitted lazily while values are read)."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        yield
    for w in caught:
        if issubclass(w.category, DicomQuirkWarning) or "pydicom" in w.filename:
            msg = str(w.message).split(" Please see")[0].strip()
            found.append(f"invalid value ({msg})")
        else:  # not about the file: pass it on unchanged
            warnings.warn_explicit(w.message, w.category, w.filename, w.lineno)


def _float(ds: Dataset, keyword: str, default: float | None = None) -> float | None:
    v = ds.get(keyword)
    if v is None or v == "":
        return default
    try:
        return float(v)
    except (TypeError, ValueError):
        return default


#: The range of a DICOM Integer String (IS), PS3.5 §6.2: a value outside it is no integer of the file.
_IS_RANGE = (-(2**31), 2**31 - 1)


def _int(ds: Dataset, keyword: str, default: int | None = None) -> int | None:
    v = _float(ds, keyword)
    usable = v is not None and np.isfinite(v) and _IS_RANGE[0] <= v <= _IS_RANGE[1]
    return round(v) if usable and v is not None else default


def _value(ds: Dataset, keyword: str, where: str, *, lo: float | None = None, hi: float | None = None,
           lo_open: bool = False, unit: str = "") -> float | None:
    """Read a numeric element that must be finite and within [lo, hi] ((lo, hi] with ``lo_open``); None when absent.

    Raises
    ------
    InvalidValueError
        Not a number, not finite or out of range; the message names the file, the element and what to do.
    """
    v = ds.get(keyword)
    if v is None or v == "":
        return None
    try:
        x = float(v)
    except (TypeError, ValueError):
        raise InvalidValueError(f"{where}: {keyword} {v!r} is not a number; fix the plan in the planning system "
                                "and export it again") from None
    bad = not np.isfinite(x) or (lo is not None and (x < lo or (lo_open and x == lo))) or (hi is not None and x > hi)
    if bad:
        rng = f"{'>' if lo_open else '>='} {lo:g}" if hi is None and lo is not None else \
            f"between {lo:g} and {hi:g}" if lo is not None and hi is not None else "finite"
        raise InvalidValueError(f"{where}: {keyword} is {x:g}{unit}, it must be finite and {rng}{unit}; fix the "
                                "plan in the planning system and export it again")
    return x


def _str(ds: Dataset, keyword: str) -> str:
    v = ds.get(keyword)
    return "" if v is None else str(v).strip()


def read_rtplan(path: str | os.PathLike[str]) -> RtPlan:
    """Read an RT Plan file.

    Parameters
    ----------
    path : path-like
        The RP file.

    Returns
    -------
    RtPlan

    Raises
    ------
    NoDicomError
        The file is DICOM but not an RT Plan.
    CorruptFileError
        Not DICOM, truncated, a value pydicom cannot parse, or a brachy channel without the data needed to place
        its dwells.
    InvalidValueError
        A value that no real plan holds: a Channel Total Time negative, not finite or above
        :data:`MAX_CHANNEL_TOTAL_TIME_S`; cumulative time weights negative, not finite or decreasing (other than
        the known restart-at-0 quirk); a Final Cumulative Time Weight not finite or 0 while the control points
        carry weight; a negative or non-finite Reference Air Kerma Rate, source length or half-life; a dose
        reference point that is not finite.

    Warns
    -----
    PlanQuirkWarning
        Once per distinct quirk met (see the module docstring). Whether the source strength is decayed is not
        the reader's business: :func:`reachplan.imaging.source_strength.source_strength` decides it (and warns).
    """
    p = str(path)
    found: list[str] = []
    with _quirks(p, found):
        if not Path(p).is_file():
            raise NoDicomError(f"{p} is not a file; pass the path of an RT Plan (RP) file")
        ds = read_dataset(Path(p), required=True)
        if ds is None:  # not reached: required=True raises instead
            raise NoDicomError(f"{p} is not a DICOM file; pass an RT Plan (RP) file")
        with parsing(Path(p)):  # pydicom errors met while values are used become typed errors
            plan = _plan_from_dataset(ds, p, found)
    quirks = _emit(p, found)
    return replace(plan, quirks=quirks)


def _emit(path: str, found: list[str]) -> tuple[str, ...]:
    quirks = tuple(dict.fromkeys(found))
    for q in quirks:
        warnings.warn(f"{Path(path).name}: {q}; read anyway", PlanQuirkWarning, stacklevel=3)
    return quirks


def _plan_from_dataset(ds: Dataset, path: str, found: list[str]) -> RtPlan:
    sop_class = str(ds.get("SOPClassUID", ""))
    modality = _str(ds, "Modality")
    if sop_class not in RT_PLAN_SOP_CLASSES and modality != "RTPLAN":
        kind = getattr(ds.get("SOPClassUID"), "name", "") or modality or "unknown object"
        raise NoDicomError(f"{path}: is a {kind}, not an RT Plan; pass the plan (RP) file")
    long_ds = _overlong_decimal_strings(ds)
    if long_ds:
        found.append(f"over-long decimal strings (> 16 characters) in {', '.join(long_ds)}")
    for_uid = _str(ds, "FrameOfReferenceUID")
    if not for_uid:
        found.append("missing Frame of Reference UID")
    is_brachy = "BrachyTreatmentType" in ds or "ApplicationSetupSequence" in ds
    fg = ds.FractionGroupSequence[0] if ds.get("FractionGroupSequence") else Dataset()
    fractions = _value(fg, "NumberOfFractionsPlanned", f"{path}: fraction group", lo=0, hi=1e4)
    n_fractions = max(1, round(fractions)) if fractions is not None else 1
    setup_doses = tuple(
        (
            _int(item, "ReferencedBrachyApplicationSetupNumber", 0) or 0,
            _value(item, "BrachyApplicationSetupDose", f"{path}: fraction group", lo=0, hi=1e6, unit=" Gy") or 0.0,
        )
        for item in fg.get("ReferencedBrachyApplicationSetupSequence", [])
    )
    sources = tuple(_source(s, path) for s in ds.get("SourceSequence", []))
    catheters = _oncentra_catheters(ds, path, found)
    setups = tuple(_setup(s, path, found) for s in ds.get("ApplicationSetupSequence", []))
    treatment_type = _str(ds, "BrachyTreatmentType")
    machine = ""
    if ds.get("TreatmentMachineSequence"):
        machine = _str(ds.TreatmentMachineSequence[0], "TreatmentMachineName")
    plan = RtPlan(
        path=path,
        sop_instance_uid=_str(ds, "SOPInstanceUID"),
        frame_of_reference_uid=for_uid,
        label=_str(ds, "RTPlanLabel"),
        name=_str(ds, "RTPlanName"),
        manufacturer=_str(ds, "Manufacturer"),
        is_brachy=is_brachy,
        treatment_type=treatment_type,
        technique=_str(ds, "BrachyTreatmentTechnique"),
        n_fractions=n_fractions,
        n_beams=len(ds.get("BeamSequence", [])) + len(ds.get("IonBeamSequence", [])),
        sources=sources,
        setups=setups,
        dose_references=(),
        setup_doses_gy=setup_doses,
        catheter_paths=catheters,
        machine_name=machine,
        patient_study=PatientStudy.read(ds),
        plan_date=_str(ds, "RTPlanDate"),
        plan_time=_str(ds, "RTPlanTime"),
    )
    refs = tuple(_dose_reference(d, plan) for d in ds.get("DoseReferenceSequence", []))
    return replace(plan, dose_references=refs)


def _overlong_decimal_strings(ds: Dataset) -> list[str]:
    """List the keywords of DS elements holding a value longer than the 16 characters PS3.5 allows."""
    names: list[str] = []

    def visit(_: Dataset, elem: Any) -> None:
        if elem.VR != "DS" or elem.value is None:
            return
        values = elem.value if elem.VM > 1 else [elem.value]
        for v in values:
            text = getattr(v, "original_string", None) or str(v)
            if len(text) > 16 and (elem.keyword or str(elem.tag)) not in names:
                names.append(elem.keyword or str(elem.tag))

    ds.walk(visit)
    return names


def _source(s: Dataset, path: str) -> BrachySource:
    number = _int(s, "SourceNumber", 0) or 0
    where = f"{path}: source {number}"
    return BrachySource(
        number=number,
        isotope_name=_str(s, "SourceIsotopeName"),
        source_type=_str(s, "SourceType"),
        manufacturer=_str(s, "SourceManufacturer"),
        # 1e7 U: ten times the strongest Ir-192 HDR source (10 Ci is about 4e4 U)
        air_kerma_rate_u=_value(s, "ReferenceAirKermaRate", where, lo=0, hi=1e7, unit=" U") or 0.0,
        reference_date=_str(s, "SourceStrengthReferenceDate"),
        reference_time=_str(s, "SourceStrengthReferenceTime"),
        half_life_days=_value(s, "SourceIsotopeHalfLife", where, lo=0, lo_open=True, unit=" d"),
        active_length_mm=_value(s, "ActiveSourceLength", where, lo=0, hi=1e3, unit=" mm"),
        diameter_mm=_value(s, "ActiveSourceDiameter", where, lo=0, hi=1e3, unit=" mm"),
        model_id=_str(s, "SourceModelID"),
    )


def _setup(s: Dataset, path: str, found: list[str]) -> ApplicationSetup:
    number = _int(s, "ApplicationSetupNumber", 0) or 0
    return ApplicationSetup(
        number=number,
        name=_str(s, "ApplicationSetupName"),
        setup_type=_str(s, "ApplicationSetupType"),
        channels=tuple(_channel(c, number, path, found) for c in s.get("ChannelSequence", [])),
    )


def _private_roi_number(c: Dataset) -> int | None:
    elem = c.get(ONCENTRA_CHANNEL_ROI_TAG)
    if elem is None:
        return None
    v = elem.value
    if isinstance(v, bytes):
        v = v.decode("ascii", "ignore").strip("\x00 ")
    try:
        return round(float(v))
    except (TypeError, ValueError):
        return None


def _channel(c: Dataset, setup_number: int, path: str, found: list[str]) -> Channel:
    """Read one item of a Channel Sequence: its control points become dwell positions and times.

    Parameters
    ----------
    c : pydicom.Dataset
        The channel item.
    setup_number : int
        The Application Setup Number it belongs to.
    path : str
        The plan's file (for the messages).
    found : list of str
        Quirks met so far; the channel's are appended.

    Returns
    -------
    Channel

    Raises
    ------
    CorruptFileError
        No Channel Total Time, or a control point without its position or cumulative time weight.
    InvalidValueError
        A value out of range (see :func:`read_rtplan`).
    """
    number = _int(c, "ChannelNumber", 0) or 0
    where = f"{path}: channel {number}"
    if c.get("ChannelTotalTime") in (None, ""):
        raise CorruptFileError(f"{where} has no Channel Total Time; the dwell times cannot be known")
    total = _value(c, "ChannelTotalTime", where, lo=0, hi=MAX_CHANNEL_TOTAL_TIME_S, unit=" s")
    assert total is not None
    cps = list(c.get("BrachyControlPointSequence", []))
    if not cps and total == 0:
        found.append("a channel without control points and with 0 s (nothing to deliver; ignored)")
    rel, pos, ctw = _control_points(cps, where)
    final = _value(c, "FinalCumulativeTimeWeight", where, lo=0)
    restarts = bool(np.any(np.diff(ctw) < 0))
    if restarts:
        found.append("cumulative time weights do not accumulate (restart at 0 for each dwell)")
    dwell_pos, dwell_rel, weights, transit = _dwell_weights(rel, pos, ctw)
    movement = _str(c, "SourceMovementType")
    if transit > 0 and movement == "STEPWISE":
        found.append("time weight between two different positions of a stepwise channel (ignored)")
    times, norm = _dwell_times(total, weights, ctw, final, restarts, where, found)
    coeffs = _dose_coefficients(cps, where)
    roi = _int(c, "ReferencedROINumber")
    if roi is None:
        roi = _private_roi_number(c)
    length = _float(c, "ChannelEffectiveLength")
    if length is None:
        length = _float(c, "ChannelLength")
    return Channel(
        number=number,
        setup_number=setup_number,
        roi_number=roi,
        source_number=_int(c, "ReferencedSourceNumber"),
        applicator_id=_str(c, "SourceApplicatorID"),
        source_movement=movement,
        total_time_s=total,
        final_weight=norm,
        n_pulses=None if (pulses := _value(c, "NumberOfPulses", where, lo=0, hi=1e4)) is None else round(pulses),
        pulse_interval_s=_value(c, "PulseRepetitionInterval", where, lo=0, hi=1e7, unit=" s"),
        length_mm=length,
        step_mm=_float(c, "SourceApplicatorStepSize"),
        dwell_positions_mm=dwell_pos,
        dwell_relative_mm=dwell_rel,
        dwell_times_s=times,
        dose_coefficients=coeffs,
        n_control_points=len(cps),
    )


def _control_points(cps: list[Dataset], where: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Read a channel's control points as arrays and check them.

    Parameters
    ----------
    cps : list of pydicom.Dataset
        The Brachy Control Point Sequence, in file order.
    where : str
        Names the channel in messages.

    Returns
    -------
    rel : (n,) float, mm
        Control Point Relative Position (NaN where absent).
    pos : (n, 3) float, mm, LPS
        Control Point 3D Position.
    ctw : (n,) float
        Cumulative Time Weight.

    Raises
    ------
    CorruptFileError
        A control point lacks its 3D position or cumulative time weight.
    InvalidValueError
        A position infinite or beyond 100 m, a weight negative or infinite, or weights that decrease (other than
        the restart-at-0 quirk).
    """
    rel = np.array([_float(cp, "ControlPointRelativePosition", np.nan) for cp in cps], dtype=float)
    pos = np.full((len(cps), 3), np.nan)
    for k, cp in enumerate(cps):
        v = cp.get("ControlPoint3DPosition")
        if v is not None and len(v) == 3:
            pos[k] = [float(x) for x in v]
    ctw = np.array([_float(cp, "CumulativeTimeWeight", np.nan) for cp in cps], dtype=float)
    if len(cps) and (np.any(np.isnan(ctw)) or np.any(np.isnan(pos))):
        raise CorruptFileError(
            f"{where}: a control point lacks its 3D position or cumulative time weight; "
            "re-export the plan with control point positions"
        )
    if not np.all(np.isfinite(pos)) or np.abs(pos).max(initial=0.0) > 1e5:
        raise InvalidValueError(f"{where}: a Control Point 3D Position is infinite or beyond 100 m; fix the plan in "
                                "the planning system and export it again")
    if not np.all(np.isfinite(ctw)) or np.any(ctw < 0):
        raise InvalidValueError(f"{where}: a Cumulative Time Weight is negative or infinite; time weights must be "
                                "finite and >= 0: fix the plan in the planning system and export it again")
    _check_accumulating(ctw, pos, where)
    return rel, pos, ctw


def _dwell_weights(
    rel: np.ndarray, pos: np.ndarray, ctw: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """Turn control points into dwells: each run of control points at one position is one dwell.

    Parameters
    ----------
    rel : (n,) float, mm
        Control Point Relative Position.
    pos : (n, 3) float, mm, LPS
        Control Point 3D Position.
    ctw : (n,) float
        Cumulative Time Weight.

    Returns
    -------
    dwell_pos : (m, 3) float, mm, LPS
        Position of each dwell.
    dwell_rel : (m,) float, mm
        Its relative position.
    weights : (m,) float
        Its time weight (the increase of the cumulative weight at that position, at least 0).
    transit : float
        Weight gained between two different positions (a moving source).
    """
    dwell_pos: list[np.ndarray] = []
    dwell_rel: list[float] = []
    weights: list[float] = []
    transit = 0.0
    for k in range(len(pos) - 1):
        delta = ctw[k + 1] - ctw[k]
        if np.linalg.norm(pos[k + 1] - pos[k]) <= _SAME_POSITION_MM:
            if dwell_pos and np.linalg.norm(dwell_pos[-1] - pos[k]) <= _SAME_POSITION_MM and k > 0 and (
                np.linalg.norm(pos[k] - pos[k - 1]) <= _SAME_POSITION_MM
            ):
                weights[-1] += max(delta, 0.0)  # three or more control points at one position
            else:
                dwell_pos.append(pos[k])
                dwell_rel.append(float(rel[k]))
                weights.append(max(delta, 0.0))
        elif delta > 0:
            transit += delta
    return np.array(dwell_pos).reshape(-1, 3), np.array(dwell_rel), np.array(weights, dtype=float), transit


def _dwell_times(total: float, w: np.ndarray, ctw: np.ndarray, final: float | None, restarts: bool, where: str,
                 found: list[str]) -> tuple[np.ndarray, float]:
    """Scale dwell weights to dwell times: ``total * w / norm`` with the Final Cumulative Time Weight as ``norm``.

    The sum of the weights is the norm instead when the weights restart at 0 for every dwell or the final weight
    is missing or 0 (the missing one is a quirk); a final weight that differs from the last control point's is a
    quirk too.

    Parameters
    ----------
    total : float, s
        Channel Total Time.
    w : (m,) float
        Dwell weights (:func:`_dwell_weights`).
    ctw : (n,) float
        Cumulative Time Weights of the control points.
    final : float or None
        Final Cumulative Time Weight, None when absent.
    restarts : bool
        The weights restart at 0 for every dwell.
    where : str
        Names the channel in messages.
    found : list of str
        Quirks met so far; appended to.

    Returns
    -------
    times : (m,) float, s
        Dwell times.
    norm : float
        The weight that stands for ``total``.

    Raises
    ------
    InvalidValueError
        A final weight of 0 while the control points carry weight, or dwell times adding up to more than ``total``.
    """
    last = float(ctw[-1]) if len(ctw) else 0.0
    if final is not None and final <= 0 and w.sum() > 0:
        raise InvalidValueError(f"{where}: Final Cumulative Time Weight is {final:g} but the control points carry "
                                "weight; it must be > 0: fix the plan in the planning system and export it again")
    if restarts or final is None or final <= 0:
        norm = float(w.sum())
        if final is None and not restarts:
            found.append("missing Final Cumulative Time Weight (used the sum of dwell weights)")
    else:
        norm = final
        if abs(final - last) > 1e-6 * max(abs(final), 1.0):
            found.append("Final Cumulative Time Weight differs from the last control point's (used the former)")
    times = total * w / norm if norm > 0 else np.zeros_like(w)
    if times.sum() > total * (1 + 1e-6) + 1e-9:
        raise InvalidValueError(
            f"{where}: the dwell times add up to {times.sum():g} s, more than the Channel Total Time {total:g} s "
            f"(Final Cumulative Time Weight {norm:g} below the control points' {last:g}); fix the plan in the "
            "planning system and export it again")
    return times, norm


def _dose_coefficients(cps: list[Dataset], where: str) -> tuple[tuple[int, float], ...]:
    """Read the last control point's (Referenced Dose Reference Number, Cumulative Dose Reference Coefficient) pairs.

    Raises
    ------
    InvalidValueError
        A coefficient beyond 1e6 in magnitude or not finite.
    """
    coeffs: list[tuple[int, float]] = []
    if cps:
        for item in cps[-1].get("BrachyReferencedDoseReferenceSequence", []):
            ref = _int(item, "ReferencedDoseReferenceNumber")
            coef = _value(item, "CumulativeDoseReferenceCoefficient", where, lo=-1e6, hi=1e6)
            if ref is not None and coef is not None:
                coeffs.append((ref, coef))
    return tuple(coeffs)


def _check_accumulating(ctw: np.ndarray, pos: np.ndarray, where: str) -> None:
    """Check that cumulative time weights do not decrease.

    The known quirk of weights that restart at 0 at every dwell (each pair of control points at one position
    going 0 -> w) is accepted.

    Raises
    ------
    InvalidValueError
        A weight decreases in any other way.
    """
    drops = np.flatnonzero(np.diff(ctw) < 0)
    if not len(drops):
        return
    same = np.linalg.norm(np.diff(pos, axis=0), axis=1) <= _SAME_POSITION_MM
    starts = [k for k in range(len(ctw) - 1) if same[k] and (k == 0 or not same[k - 1])]
    if all(ctw[k] == 0 for k in starts) and all(ctw[k + 1] == 0 for k in drops):
        return  # restarts at 0 for every dwell (reported as a quirk)
    k = int(drops[0])
    raise InvalidValueError(
        f"{where}: Cumulative Time Weight decreases from {ctw[k]:g} to {ctw[k + 1]:g} at control point {k + 1}; "
        "cumulative weights must not decrease: fix the plan in the planning system and export it again")


def _dose_reference(d: Dataset, plan: RtPlan) -> DoseReference:
    number = _int(d, "DoseReferenceNumber", 0) or 0
    coords = d.get("DoseReferencePointCoordinates")
    position = frozen_floats([float(x) for x in coords]) if coords is not None and len(coords) == 3 else None
    if position is not None and (not np.all(np.isfinite(position)) or np.abs(position).max() > 1e5):
        raise InvalidValueError(
            f"{plan.path}: dose reference {number}: DoseReferencePointCoordinates {position.tolist()} are not finite "
            "coordinates within 100 m; fix the point in the planning system and export the plan again")
    tps: float | None = None
    setup_dose = dict(plan.setup_doses_gy)
    terms = [
        coef * setup_dose.get(ch.setup_number, 0.0)
        for ch in plan.channels
        for ref, coef in ch.dose_coefficients
        if ref == number
    ]
    if terms:
        tps = float(sum(terms)) * plan.n_fractions * plan.n_pulses
    return DoseReference(
        number=number, description=_str(d, "DoseReferenceDescription"),
        structure_type=_str(d, "DoseReferenceStructureType"), reference_type=_str(d, "DoseReferenceType"),
        position_mm=position, tps_dose_gy=tps)


def _oncentra_catheters(ds: Dataset, path: str, found: list[str]) -> tuple[CatheterPath, ...]:
    elem = ds.get(ONCENTRA_CATHETER_TAG)
    if elem is None:
        return ()
    value = elem.value
    if isinstance(value, bytes):
        found.append("private catheter sequence (300F,1000) stored as raw bytes (parsed as implicit VR)")
        try:
            value = read_sequence(io.BytesIO(value), True, True, len(value), ds.get("SpecificCharacterSet", "ISO_IR 6"))
        except Exception as exc:  # malformed private data must not stop reading the standard part
            found.append(f"private catheter sequence (300F,1000) unreadable ({type(exc).__name__}; ignored)")
            return ()
    out: list[CatheterPath] = []
    for item in value or []:
        for roi in item.get((0x3006, 0x0039), []):  # ROI Contour Sequence
            number = _int(roi, "ReferencedROINumber")
            contours = roi.get("ContourSequence", [])
            if number is None or len(contours) != 1 or "ContourData" not in contours[0]:
                continue
            pts = np.array([float(x) for x in contours[0].ContourData], dtype=float)
            if len(pts) >= 6 and len(pts) % 3 == 0:
                out.append(CatheterPath(number, pts.reshape(-1, 3)))
    return tuple(out)


# --- channel paths ------------------------------------------------------------------------------------


def channel_paths(plan: RtPlan, structures: StructureSet | None = None) -> Mapping[int, np.ndarray]:
    """Find the centre line of each channel, ordered as written (Eclipse: tip first), keyed by channel number.

    Looked up through the channel's ReferencedROINumber in ``structures`` (an OPEN_NONPLANAR contour
    of that ROI) or in the plan's Oncentra catheter sequence.

    Parameters
    ----------
    plan : RtPlan
        The plan whose channels are looked up.
    structures : StructureSet, optional
        The structure set the plan refers to (its BRACHY_CHANNEL ROIs).

    Returns
    -------
    mapping channel number -> (k, 3) float, mm, LPS
        Channels whose path cannot be found are absent.
    """
    by_roi: dict[int, np.ndarray] = {c.roi_number: c.points_mm for c in plan.catheter_paths}
    if structures is not None:
        for roi in structures.rois:
            lines = [c.points_mm for c in roi.contours if c.geometric_type in ("OPEN_NONPLANAR", "OPEN_PLANAR")]
            if lines and len(lines[0]) >= 2:
                by_roi.setdefault(roi.number, lines[0])
    return {c.number: by_roi[c.roi_number] for c in plan.channels if c.roi_number in by_roi}
