"""The plain data of an RT Plan, as :func:`reachplan.imaging.rtplan.read_rtplan` reads it.

A brachytherapy plan (PS3.3 C.8.8.14-15): its sources, application setups, channels with their dwell positions and
times, dose reference points with the TPS's own doses, and Oncentra's catheter paths. Positions are mm, DICOM
patient coordinates (LPS); times s; doses Gy; air-kerma rate in U (µGy m² h⁻¹ = cGy cm² h⁻¹).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from reachplan._arrays import frozen_floats
from reachplan.imaging.errors import CorruptFileError, NoDicomError
from reachplan.imaging.types import PatientStudy


@dataclass(frozen=True)
class BrachySource:
    """One item of the Source Sequence.

    Channels refer to it by ``number`` (Referenced Source Number).

    Parameters
    ----------
    number : int
        Source Number (0 when missing).
    isotope_name, source_type, manufacturer : str
        As written; empty when missing.
    air_kerma_rate_u : float, U (µGy m² h⁻¹)
        Reference Air Kerma Rate at the reference date and time (0 when missing).
    reference_date, reference_time : str
        Source Strength Reference Date (``YYYYMMDD``) and Time (``HHMMSS``), as written.
    half_life_days : float or None, d
        Source Isotope Half Life.
    active_length_mm, diameter_mm : float or None, mm
        Active Source Length and Diameter.
    model_id : str
        Source Model ID; empty when missing.
    """

    number: int
    isotope_name: str
    source_type: str
    manufacturer: str
    air_kerma_rate_u: float
    reference_date: str
    reference_time: str
    half_life_days: float | None
    active_length_mm: float | None
    diameter_mm: float | None
    model_id: str = ""

    def labels(self) -> tuple[str, ...]:
        """Strings that may identify the source model (for matching TG-43 data sets).

        Returns
        -------
        tuple of str
            Model ID, isotope name and manufacturer, the empty ones left out.
        """
        return tuple(x for x in (self.model_id, self.isotope_name, self.manufacturer) if x)


@dataclass(frozen=True, eq=False)
class Channel:
    """A channel of a brachy application setup with its dwells.

    One item of the Channel Sequence, its Brachy Control Point Sequence read into dwell positions and times.

    Parameters
    ----------
    number : int
        Channel Number.
    setup_number : int
        Application Setup Number it belongs to.
    roi_number : int or None
        ReferencedROINumber of the channel's ROI (an RT Structure Set BRACHY_CHANNEL ROI, or for
        Oncentra the ROI of the private catheter sequence), None when the plan gives none.
    total_time_s : float
        Channel Total Time as written (per pulse for PDR).
    dwell_positions_mm : (n, 3) float, mm, LPS
        Control Point 3D Position of each dwell, in file order.
    dwell_relative_mm : (n,) float, mm
        Control Point Relative Position of each dwell.
    dwell_times_s : (n,) float, s
        Per fraction, per pulse for PDR.
    source_number : int or None
        Referenced Source Number.
    applicator_id : str
        Source Applicator ID.
    source_movement : str
        Source Movement Type (``"STEPWISE"``, ``"FIXED"``, ...).
    final_weight : float
        The Final Cumulative Time Weight the dwell times were normalised by (the sum of the dwell weights when
        the file's value is missing or unusable).
    n_pulses : int or None
        Number of Pulses (PDR).
    pulse_interval_s : float or None, s
        Pulse Repetition Interval (PDR).
    length_mm : float or None, mm
        Channel Effective Length, else Channel Length.
    step_mm : float or None, mm
        Source Applicator Step Size.
    dose_coefficients : tuple of (int, float)
        (dose reference number, cumulative dose reference coefficient at the last control point).
    n_control_points : int or None
        Items of the Brachy Control Point Sequence; None when not known (a channel built in code).

    Raises
    ------
    ValueError
        Dwell arrays of different lengths.
    """

    number: int
    setup_number: int
    roi_number: int | None
    source_number: int | None
    applicator_id: str
    source_movement: str
    total_time_s: float
    final_weight: float
    n_pulses: int | None
    pulse_interval_s: float | None
    length_mm: float | None
    step_mm: float | None
    dwell_positions_mm: np.ndarray
    dwell_relative_mm: np.ndarray
    dwell_times_s: np.ndarray
    dose_coefficients: tuple[tuple[int, float], ...] = ()
    n_control_points: int | None = None

    def __post_init__(self) -> None:
        object.__setattr__(self, "dwell_positions_mm", frozen_floats(np.reshape(self.dwell_positions_mm, (-1, 3))))
        object.__setattr__(self, "dwell_relative_mm", frozen_floats(self.dwell_relative_mm))
        object.__setattr__(self, "dwell_times_s", frozen_floats(self.dwell_times_s))
        n = len(self.dwell_times_s)
        if not (len(self.dwell_positions_mm) == len(self.dwell_relative_mm) == n):
            raise ValueError(f"channel {self.number}: dwell arrays disagree in length")

    @property
    def n_dwells(self) -> int:
        """Number of dwell positions."""
        return len(self.dwell_times_s)


@dataclass(frozen=True)
class ApplicationSetup:
    """An item of the Application Setup Sequence: Application Setup Number, Name and Type, and its channels.

    Parameters
    ----------
    number : int
        Application Setup Number.
    name : str
        Application Setup Name, as written.
    setup_type : str
        Application Setup Type (``"FLETCHER"``, ``"NEEDLE"``, ...).
    channels : tuple of Channel
        Its channels, in the order of the Channel Sequence.
    """

    number: int
    name: str
    setup_type: str
    channels: tuple[Channel, ...]


@dataclass(frozen=True, eq=False)
class DoseReference:
    """A dose reference of the plan.

    Parameters
    ----------
    number : int
        Dose Reference Number (300A,0012).
    description, structure_type, reference_type : str
        Dose Reference Description, Structure Type (``"POINT"``, ``"VOLUME"``, ...) and Type
        (``"TARGET"``, ``"ORGAN_AT_RISK"``).
    position_mm : (3,) float, mm, LPS, or None
        Dose Reference Point Coordinates; None when the reference is not a point.
    tps_dose_gy : float or None, Gy
        The TPS's total dose there (all fractions, all pulses) from the cumulative dose reference
        coefficients (see the module docstring); None when the plan does not carry them.
    """

    number: int
    description: str
    structure_type: str
    reference_type: str
    position_mm: np.ndarray | None
    tps_dose_gy: float | None


@dataclass(frozen=True, eq=False)
class CatheterPath:
    """A catheter reconstruction from Oncentra's private sequence (300F,1000).

    Parameters
    ----------
    roi_number : int
        The ROI the catheter belongs to (channels refer to it).
    points_mm : (k, 3) float, mm, LPS
        The catheter's centre line, as written.
    """

    roi_number: int
    points_mm: np.ndarray

    def __post_init__(self) -> None:
        object.__setattr__(self, "points_mm", frozen_floats(np.reshape(self.points_mm, (-1, 3))))


@dataclass(frozen=True, eq=False)
class RtPlan:
    """An RT Plan: for brachy plans ``setups`` holds the channels; ``is_brachy`` is False otherwise.

    Parameters
    ----------
    path : str
        The file it was read from.
    sop_instance_uid, frame_of_reference_uid, label, name, manufacturer : str
        As written (RT Plan Label and Name); empty when missing.
    is_brachy : bool
        The plan has a Brachy Treatment Type or application setups.
    treatment_type : str
        Brachy Treatment Type: ``"HDR"``, ``"PDR"``, ``"MDR"``, ``"LDR"``; empty for a beam plan.
    technique : str
        Brachy Treatment Technique: ``"INTERSTITIAL"``, ``"INTRACAVITARY"``, ...
    n_fractions : int
        Number of Fractions Planned of the first fraction group (1 when missing).
    n_beams : int
        External beams (0 for brachy).
    sources : tuple of BrachySource
    setups : tuple of ApplicationSetup
    dose_references : tuple of DoseReference
    setup_doses_gy : tuple of (int, float)
        (application setup number, Brachy Application Setup Dose in Gy) of the first fraction group.
    catheter_paths : tuple of CatheterPath
        From Oncentra's private catheter sequence; empty otherwise.
    machine_name : str
        Treatment Machine Name as written; empty when missing.
    patient_study : PatientStudy
        Patient and study as written.
    plan_date, plan_time : str
        RT Plan Date (``YYYYMMDD``) and Time as written; empty when missing.
    quirks : tuple of str
        Every rule the file breaks that was read anyway (also warned as
        :class:`~reachplan.imaging.rtplan.PlanQuirkWarning`).
    """

    path: str
    sop_instance_uid: str
    frame_of_reference_uid: str
    label: str
    name: str
    manufacturer: str
    is_brachy: bool
    treatment_type: str  # HDR, PDR, MDR, LDR (brachy) or "" (beam)
    technique: str  # INTRACAVITARY, INTERSTITIAL, ...
    n_fractions: int
    n_beams: int
    sources: tuple[BrachySource, ...]
    setups: tuple[ApplicationSetup, ...]
    dose_references: tuple[DoseReference, ...]
    setup_doses_gy: tuple[tuple[int, float], ...] = ()
    catheter_paths: tuple[CatheterPath, ...] = ()
    machine_name: str = ""
    patient_study: PatientStudy = field(default_factory=PatientStudy)
    plan_date: str = ""
    plan_time: str = ""
    quirks: tuple[str, ...] = field(default=())

    @property
    def channels(self) -> tuple[Channel, ...]:
        """Every channel of every application setup, in file order."""
        return tuple(c for s in self.setups for c in s.channels)

    @property
    def n_pulses(self) -> int:
        """Pulses per fraction (1 unless PDR)."""
        pulses = {c.n_pulses for c in self.channels if c.n_pulses}
        return int(max(pulses)) if pulses and self.treatment_type == "PDR" else 1

    @property
    def n_dwells(self) -> int:
        """Number of dwell positions over all channels."""
        return sum(c.n_dwells for c in self.channels)

    @property
    def total_time_s(self) -> float:
        """Σ Channel Total Time as written (per pulse for PDR)."""
        return float(sum(c.total_time_s for c in self.channels))

    def source(self, number: int | None = None) -> BrachySource:
        """Return the source with ``number`` (or the only / first one).

        Parameters
        ----------
        number : int, optional
            Source Number a channel refers to; None takes the first source.

        Returns
        -------
        BrachySource
            The source.

        Raises
        ------
        NoDicomError
            The plan has no sources (it is not a brachy plan).
        CorruptFileError
            No source has ``number``.
        """
        if not self.sources:
            raise NoDicomError(f"{self.path}: the plan has no Source Sequence; it is not a brachy plan")
        for s in self.sources:
            if number is None or s.number == number:
                return s
        raise CorruptFileError(f"{self.path}: a channel refers to source {number}, which the plan lacks")


@dataclass(frozen=True)
class PlanProblem:
    """Why a brachy plan cannot be planned on or recomputed (``plan`` and ``dose`` refuse it; ``inspect`` warns).

    Parameters
    ----------
    kind : str
        ``"geometry"`` (no application setups or channels, a channel whose dwells are unknown) or ``"source"`` (no
        source, no strength, no TG-43 data for its isotope).
    message : str
        What is wrong and what to do, one line (the file is not named: the caller names it).
    """

    kind: str
    message: str


def plan_problems(plan: RtPlan) -> tuple[PlanProblem, ...]:
    """Find what makes a brachy plan unusable, as far as the plan alone tells.

    The one list of these checks: ``dose`` and ``plan --rtplan`` refuse a plan with a problem (the planner adds the
    check that TG-43 data exist for the source), ``inspect`` lists each as a warning.

    Parameters
    ----------
    plan : RtPlan
        The plan as read.

    Returns
    -------
    tuple of PlanProblem
        Empty for a usable plan. Geometry: no Application Setup Sequence or no channels; a channel with a Channel
        Total Time but no control points (its dwells unknown: it would be dropped with its time). Source: no
        Source Sequence; a channel referring to a source the plan lacks; a Reference Air Kerma Rate of 0 or missing.
    """
    out: list[PlanProblem] = []
    if not plan.setups or not plan.channels:
        what = "no Application Setup Sequence" if not plan.setups else "no channels in its application setups"
        out.append(PlanProblem("geometry", f"the plan has {what}; it is not a brachytherapy plan that "
                                           "can be used: pass a brachy RT Plan with its channels"))
    empty = [c for c in plan.channels if c.n_control_points == 0 and c.total_time_s > 0]
    if empty:
        out.append(PlanProblem("geometry", f"channel(s) {', '.join(str(c.number) for c in empty)} have no "
                                           f"control points but {sum(c.total_time_s for c in empty):.1f} s of "
                                           "Channel Total Time: their dwells are unknown; re-export the plan with "
                                           "the control points of every channel"))
    if not plan.sources:
        out.append(PlanProblem("source", "the plan has no Source Sequence; the source and its strength are "
                                         "unknown: re-export the brachy plan with its source"))
        return tuple(out)
    numbers = {s.number for s in plan.sources}
    missing = sorted({c.source_number for c in plan.channels if c.source_number is not None} - numbers)
    if missing:
        out.append(PlanProblem("source", f"channels refer to source(s) {missing}, which the plan lacks"))
    used = [s for s in plan.sources if s.number in {c.source_number for c in plan.channels}] or [plan.sources[0]]
    weak = [s for s in used if s.air_kerma_rate_u <= 0]
    if weak:
        out.append(PlanProblem("source", f"source {weak[0].number} has no Reference Air Kerma Rate (0 or "
                                         "missing); the dose cannot be computed: re-export the plan with the "
                                         "source strength"))
    return tuple(out)
