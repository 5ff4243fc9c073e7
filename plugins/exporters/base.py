"""What every exporter receives and returns, the exporter Protocol, and safe output files.

An exporter is a plugin of kind ``exporters`` (entry-point group ``reachplan.exporters``): an object with a
``name``, a ``description`` and ``export(plan, out_dir, options) -> ExportedFiles``. The planner fills one
:class:`ExportPlan` (plain data: needle paths and dwells in LPS mm, the source, the input identity) and
hands it to any exporter.

File safety (all exporters): writes are atomic (:func:`reachplan.imaging.files.atomic_write_bytes`), an input file of
the plan is never written, an existing file is replaced only with ``overwrite=True``, and file names are
built from the plan label with only ``[A-Za-z0-9._-]`` (no patient name unless asked for).
"""

from __future__ import annotations

import math
import os
import re
import unicodedata
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field, replace
from datetime import datetime
from pathlib import Path
from types import MappingProxyType
from typing import Any, Protocol, runtime_checkable

import numpy as np

from reachplan._arrays import arc_length_mm, frozen_floats
from reachplan.imaging.types import Grid, StructureSet, Volume
from reachplan.plugins.errors import ExportError
from reachplan.plugins.exporters.handoff import InsertList
from reachplan.plugins.sources import SourceData

#: A dwell farther than this from its needle's path is an input error (mm).
DWELL_ON_PATH_TOLERANCE_MM = 0.5
#: Two dwells closer than this along a needle are an input error (mm).
MIN_DWELL_SPACING_MM = 0.1

#: Half-lives (days) of the isotopes used for HDR/PDR afterloaders. Ir-192: 73.83 d as written by
#: Varian BrachyVision (reference/tps_examples/hdr, SourceIsotopeHalfLife) and NNDC NuDat 3 (73.829 d);
#: Co-60: 1925.28 d (NNDC NuDat 3, 5.2714 y).
HALF_LIFE_DAYS: Mapping[str, float] = MappingProxyType({"Ir-192": 73.83, "Co-60": 1925.28})

_SOURCE_TYPES = ("POINT", "LINE", "CYLINDER", "SPHERE")
#: RT Plan layouts of the prescription (:class:`ExportOptions` ``rtplan_style``; rtplan_conventions.md §2-3).
RTPLAN_STYLES = ("eclipse", "vitesse")


def _check_short_text(value: str, what: str, max_len: int) -> None:
    if not value or len(value) > max_len or "\\" in value or any(unicodedata.category(c)[0] == "C" for c in value):
        raise ValueError(f"{what} must be 1-{max_len} printable characters without backslash, got {value!r}")


def project_on_path(path_mm: np.ndarray, points_mm: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Project points on a polyline: the arc length of the nearest polyline point, and the distance to it.

    Parameters
    ----------
    path_mm : (n, 3) float, mm
        Polyline vertices (LPS for a needle path).
    points_mm : (m, 3) float, mm
        Points in the same frame.

    Returns
    -------
    arc_mm : (m,) float, mm
        Arc length of the nearest point, from ``path_mm[0]``.
    distance_mm : (m,) float, mm
        Distance from the polyline.
    """
    a, b = path_mm[:-1], path_mm[1:]
    d = b - a
    length = np.linalg.norm(d, axis=1)
    u = d / np.where(length > 0, length, 1.0)[:, None]
    rel = points_mm[:, None, :] - a[None, :, :]  # (m, s, 3)
    t = np.clip(np.einsum("msk,sk->ms", rel, u), 0.0, length[None, :])
    foot = a[None] + t[..., None] * u[None]
    dist = np.linalg.norm(points_mm[:, None, :] - foot, axis=2)
    best = np.argmin(dist, axis=1)
    rows = np.arange(len(points_mm))
    return arc_length_mm(path_mm)[best] + t[rows, best], dist[rows, best]


@dataclass(frozen=True, eq=False)
class NeedleExport:
    """One needle of a plan.

    Parameters
    ----------
    hole_id : str
        Template hole (1-16 characters: it becomes the DICOM Source Applicator ID).
    path_mm : (n, 3) float, mm, LPS
        Predicted needle centre line from the entry (template plane) to the tip, n >= 2.
    dwell_positions_mm : (m, 3) float, mm, LPS
        Source dwell positions, m >= 1, each within :data:`DWELL_ON_PATH_TOLERANCE_MM` of the path.
    dwell_times_s : (m,) float, s, >= 0
        Dwell time at each position.
    design : str
        Stylet preset name ("" for a plain needle).
    schedule : (k, 3) float or None
        Breakpoints (depth_mm, tension_n, roll_deg) of the insertion schedule: depth along the path from
        its entry, strictly increasing and >= 0; tension >= 0 N; roll in degrees, taken as given (not
        wrapped). Piecewise linear between breakpoints, constant outside. None: no tendon pulled.
    applicator : bool
        True for an intracavitary applicator channel (tandem, ring, ovoid): a channel of the RT Plan placed by
        hand, not a template needle, so it gets no device instructions.

    Raises
    ------
    ValueError
        A bad hole id, arrays of the wrong shape or non-finite, a path shorter than two distinct points or
        beyond 100 m (not mm), negative dwell times, a dwell off the path or two dwells closer than
        :data:`MIN_DWELL_SPACING_MM`, or a schedule whose depths do not increase or whose tension is negative.
    """

    hole_id: str
    path_mm: np.ndarray
    dwell_positions_mm: np.ndarray
    dwell_times_s: np.ndarray
    design: str = ""
    schedule: np.ndarray | None = None
    applicator: bool = False

    def __post_init__(self) -> None:
        _check_short_text(self.hole_id, "hole_id", 16)
        path = frozen_floats(self.path_mm, (3,), f"needle {self.hole_id}: path_mm")
        pos = frozen_floats(self.dwell_positions_mm, (3,), f"needle {self.hole_id}: dwell_positions_mm")
        times = frozen_floats(self.dwell_times_s, (), f"needle {self.hole_id}: dwell_times_s")
        if len(path) < 2 or arc_length_mm(path)[-1] <= 0:
            raise ValueError(f"needle {self.hole_id}: path_mm needs at least two distinct points")
        if np.abs(path).max() > 1e5:
            raise ValueError(f"needle {self.hole_id}: path_mm is beyond 100 m from the origin; units must be mm")
        if len(pos) < 1 or len(times) != len(pos):
            raise ValueError(f"needle {self.hole_id}: give one dwell time per dwell position (at least one)")
        if np.any(times < 0):
            raise ValueError(f"needle {self.hole_id}: dwell times must be >= 0 s")
        arc, dist = project_on_path(path, pos)
        if dist.max() > DWELL_ON_PATH_TOLERANCE_MM:
            raise ValueError(f"needle {self.hole_id}: a dwell position is {dist.max():.2f} mm off the needle path "
                             f"(tolerance {DWELL_ON_PATH_TOLERANCE_MM} mm); place dwells on the path")
        if len(pos) > 1 and np.diff(np.sort(arc)).min() < MIN_DWELL_SPACING_MM:
            raise ValueError(f"needle {self.hole_id}: two dwell positions are less than {MIN_DWELL_SPACING_MM} mm "
                             "apart along the needle; merge them (add their times)")
        object.__setattr__(self, "path_mm", path)
        object.__setattr__(self, "dwell_positions_mm", pos)
        object.__setattr__(self, "dwell_times_s", times)
        if self.schedule is not None:
            sch = frozen_floats(self.schedule, (3,), f"needle {self.hole_id}: schedule")
            if len(sch) < 1 or sch[0, 0] < 0 or np.any(np.diff(sch[:, 0]) <= 0):
                raise ValueError(f"needle {self.hole_id}: schedule depths must start >= 0 mm and increase strictly")
            if np.any(sch[:, 1] < 0):
                raise ValueError(f"needle {self.hole_id}: schedule tension must be >= 0 N (the tendon only pulls)")
            object.__setattr__(self, "schedule", sch)

    @property
    def length_mm(self) -> float:
        """Arc length of the path (mm): the insertion depth at the tip."""
        return float(arc_length_mm(self.path_mm)[-1])

    @property
    def dwell_distance_from_tip_mm(self) -> np.ndarray:
        """(m,) float, mm: arc distance of each dwell from the tip along the path."""
        arc, _ = project_on_path(self.path_mm, self.dwell_positions_mm)
        return np.maximum(self.length_mm - arc, 0.0)


@dataclass(frozen=True)
class SourceSpec:
    """The treatment source as an RT Plan needs it.

    Parameters
    ----------
    name : str
        TG-43 data set name (``reachplan.sources`` plugin), e.g. ``"gammamed_plus_hdr"``.
    air_kerma_rate_u : float
        Reference air-kerma rate S_K at the reference date, U = µGy m² h⁻¹ (DICOM Reference Air Kerma Rate).
    reference_datetime : datetime
        Date and time of the source strength calibration.
    isotope : str
        e.g. ``"Ir-192"``.
    half_life_days : float or None
        None: taken from :data:`HALF_LIFE_DAYS` for ``isotope``.
    title : str
        Human-readable model (written as Source Description; TG-43 readers recognise the model from it).
    manufacturer, model_id : str
        Source Manufacturer (<= 64 characters) and Source Model ID (<= 16); "" when unknown.
    treatment_type : str
        ``"HDR"`` (``"PDR"`` and ``"LDR"`` are not exported).
    source_type : str
        ``"LINE"``, ``"POINT"``, ``"CYLINDER"`` or ``"SPHERE"``.
    active_length_mm, active_diameter_mm : float or None
        Active dimensions, mm; None when unknown.

    Raises
    ------
    ValueError
        A non-positive air-kerma rate, half-life or active dimension, an isotope without a known half-life
        (and none given), an unknown source type, or a text too long.
    """

    name: str
    air_kerma_rate_u: float
    reference_datetime: datetime
    isotope: str = "Ir-192"
    half_life_days: float | None = None
    title: str = ""
    manufacturer: str = ""
    model_id: str = ""
    treatment_type: str = "HDR"
    source_type: str = "LINE"
    active_length_mm: float | None = None
    active_diameter_mm: float | None = None

    def __post_init__(self) -> None:
        if not (math.isfinite(self.air_kerma_rate_u) and self.air_kerma_rate_u > 0):
            raise ValueError(f"source {self.name}: air_kerma_rate_u must be positive (U = µGy m² h⁻¹)")
        if self.half_life_days is None:
            if self.isotope not in HALF_LIFE_DAYS:
                raise ValueError(f"source {self.name}: no half-life known for {self.isotope!r}; give half_life_days")
            object.__setattr__(self, "half_life_days", HALF_LIFE_DAYS[self.isotope])
        elif not (math.isfinite(self.half_life_days) and self.half_life_days > 0):
            raise ValueError(f"source {self.name}: half_life_days must be positive")
        if self.source_type not in _SOURCE_TYPES:
            raise ValueError(f"source {self.name}: source_type must be one of {', '.join(_SOURCE_TYPES)}")
        for v, what in ((self.active_length_mm, "active_length_mm"), (self.active_diameter_mm, "active_diameter_mm")):
            if v is not None and not (math.isfinite(v) and v > 0):
                raise ValueError(f"source {self.name}: {what} must be positive when given")
        if len(self.model_id) > 16 or len(self.manufacturer) > 64 or len(self.title) > 64:
            raise ValueError(f"source {self.name}: model_id <= 16, manufacturer and title <= 64 characters")
        _check_short_text(self.isotope, "isotope", 64)

    @classmethod
    def from_source_data(cls, data: SourceData, air_kerma_rate_u: float, reference_datetime: datetime,
                         **extra: Any) -> SourceSpec:
        """Build from the TG-43 data set (name, title, kind, isotope, active length) of a ``sources`` plugin.

        ``extra`` sets the fields SourceData does not hold (manufacturer, active_diameter_mm, ...). Source Model
        ID defaults to the data set's first alias of at most 16 characters (e.g. ``gammamedplushdr``), which
        :func:`reachplan.plugins.sources.identify.recognise_source` maps back to the data set.

        Parameters
        ----------
        data : SourceData
            The TG-43 data set (its active length in cm becomes ``active_length_mm``).
        air_kerma_rate_u : float, U (µGy m² h⁻¹)
            Reference air-kerma rate at ``reference_datetime``.
        reference_datetime : datetime
            Date and time of the source strength calibration.
        **extra
            Other fields of :class:`SourceSpec`.
        """
        aliases = [a for a in data.aliases if 0 < len(a) <= 16]
        spec = cls(name=data.name, air_kerma_rate_u=air_kerma_rate_u, reference_datetime=reference_datetime,
                   isotope=data.isotope, title=data.title[:64], treatment_type=data.kind,
                   model_id=aliases[0] if aliases else "", active_length_mm=10.0 * float(data.active_length_cm))
        return replace(spec, **extra) if extra else spec


@dataclass(frozen=True)
class Afterloader:
    """The treatment machine as the RT Plan names it, and its length convention.

    Parameters
    ----------
    name : str
        Treatment Machine Name (<= 16 characters).
    manufacturer, model_name : str
        Manufacturer and Manufacturer's Model Name of the machine (<= 64 characters each).
    channel_length_mm : float
        Afterloader to the distal-most source position, mm: written as Channel Length, Channel Effective
        Length and Source Applicator Length.

    The default :data:`GAMMAMED_PLUS_HDR` is what Varian BrachyVision writes for the GammaMed Plus HDR
    afterloader (reference/tps_examples/hdr, rtplan_conventions.md §5-6: "GammaMed PlusHDR", Varian Medical
    Systems, GammaMedPlus_iX, Channel Length = Source Applicator Length = 1300 mm; Oncentra/Vitesse also
    writes 1300 mm for both).

    Raises
    ------
    ValueError
        A name too long or empty, or a non-positive length.
    """

    name: str
    manufacturer: str = ""
    model_name: str = ""
    channel_length_mm: float = 1300.0

    def __post_init__(self) -> None:
        _check_short_text(self.name, "treatment machine name", 16)
        if len(self.manufacturer) > 64 or len(self.model_name) > 64:
            raise ValueError("afterloader manufacturer and model name must be <= 64 characters")
        if not (math.isfinite(self.channel_length_mm) and self.channel_length_mm > 0):
            raise ValueError("afterloader channel_length_mm must be positive (mm)")


#: BrachyVision's GammaMed Plus HDR (reference/tps_examples/hdr; see :class:`Afterloader`).
GAMMAMED_PLUS_HDR = Afterloader("GammaMed PlusHDR", "Varian Medical Systems", "GammaMedPlus_iX", 1300.0)

_REFERENCE_TYPES = ("ORGAN_AT_RISK", "TARGET")


@dataclass(frozen=True, eq=False)
class ReferencePoint:
    """A dose reference point of the plan, with what each dwell gives it.

    Parameters
    ----------
    name : str, 1-64 characters
        Dose Reference Description, e.g. ``"Point A left"``.
    position_mm : (3,) float, mm, LPS
        Where the point is.
    rate_gy_per_s : tuple of (m_i,) float, Gy s⁻¹
        For each needle of the plan (in needle order) and each of its dwells (in the needle's dwell order),
        the dose per fraction at the point per second of dwell (TG-43 with the plan's source strength).
        The exporter multiplies it with the (rounded) dwell times: the planned dose and the cumulative dose
        reference coefficients follow from the times as written.
    reference_type : str
        ``"ORGAN_AT_RISK"`` (bladder, rectum, Point A as Eclipse writes it) or ``"TARGET"``.

    Raises
    ------
    ValueError
        A bad name or type, a non-finite position, or negative or non-finite rates.
    """

    name: str
    position_mm: np.ndarray
    rate_gy_per_s: tuple[np.ndarray, ...]
    reference_type: str = "ORGAN_AT_RISK"

    def __post_init__(self) -> None:
        _check_short_text(self.name, "reference point name", 64)
        if self.reference_type not in _REFERENCE_TYPES:
            raise ValueError(f"reference point {self.name}: type must be one of {', '.join(_REFERENCE_TYPES)}")
        pos = frozen_floats(np.reshape(self.position_mm, (3,)), (), f"reference point {self.name}: position_mm")
        rates = tuple(frozen_floats(np.reshape(r, (-1,)), (), f"reference point {self.name}: rates")
                      for r in self.rate_gy_per_s)
        if any(np.any(r < 0) for r in rates):
            raise ValueError(f"reference point {self.name}: dose rates must be >= 0 Gy/s")
        object.__setattr__(self, "position_mm", pos)
        object.__setattr__(self, "rate_gy_per_s", rates)

    def planned_dose_gy(self, needles: Sequence[NeedleExport]) -> float:
        """Return the planned dose per fraction at the point with the needles' dwell times (as planned, unrounded).

        Parameters
        ----------
        needles : sequence of NeedleExport
            The plan's needles, in the order of ``rate_gy_per_s``.

        Returns
        -------
        float, Gy
            Σ over needles and dwells of the rate × the dwell time.
        """
        return float(sum(float(r @ n.dwell_times_s) for r, n in zip(self.rate_gy_per_s, needles, strict=True)))


@dataclass(frozen=True, eq=False)
class PlannedDose:
    """The planned dose on a grid, written as the plan's RT Dose.

    Parameters
    ----------
    dose_gy : (nk, nj, ni) float, Gy
        Dose of the whole plan (all fractions) on ``grid`` (array order slice, row, column).
    grid : Grid
        Where, LPS mm.
    """

    dose_gy: np.ndarray
    grid: Grid

    def __post_init__(self) -> None:
        dose = np.asarray(self.dose_gy, dtype=float)
        if dose.shape != self.grid.shape or not np.all(np.isfinite(dose)) or np.any(dose < 0):
            raise ValueError(f"planned dose must be finite, >= 0 Gy and of the grid's shape {self.grid.shape}")


@dataclass(frozen=True, eq=False)
class ExportPlan:
    """Everything an exporter needs, as plain data.

    Parameters
    ----------
    label : str, 1-16 characters
        RT Plan Label; also the default file-name stem.
    needles : tuple of NeedleExport
        One channel per needle, in channel order; hole ids unique.
    source : SourceSpec
        The treatment source (HDR only).
    structure_set : StructureSet or None
        The patient's structures as read; carried over into the exported structure set.
    volume : Volume or None
        The input image series: patient, study and Frame of Reference identity. None (and no structure
        set identity): placeholders are generated and the export says so in its notes.
    plan_datetime : datetime or None
        RT Plan Date/Time; None: the time of export.
    name : str
        RT Plan Name (<= 64 characters, optional).
    fractions_planned : int
        Number of Fractions Planned, >= 1 (4 for the EMBRACE II schedule the EQD2 figures assume).
    prescription_dose_gy : float or None
        Dose per fraction prescribed to the target (Brachy Application Setup Dose), Gy, when known.
    target_name : str
        The prescription target (Dose Reference Description of the TARGET item), e.g. ``"HR-CTV"``.
    reference_points : tuple of ReferencePoint
        Dose reference points with what each dwell gives them (Point A, ICRU bladder and rectum points, points
        the user names).
    application_setup_type : str
        DICOM Application Setup Type (defined terms; ``SYED_NEBLETT`` for a perineal interstitial template).
    afterloader : Afterloader
        Treatment machine name and length convention (default :data:`GAMMAMED_PLUS_HDR`).
    channel_effective_length_mm : float or None
        Afterloader to the distal-most source position, mm; None: the afterloader's channel length. Must
        exceed every path.
    dose : PlannedDose or None
        The planned dose on a grid, written as an RT Dose that references the plan; None: no RT Dose.
    input_paths : tuple of Path
        Files (or series folders) the plan was made from: never written, nor written into, by an export.
    specification_point : str
        The reference point at which the prescription (Brachy Application Setup Dose) is specified, by name: its
        planned dose per fraction is the prescription. "" when there is none.
    handoff : InsertList or None
        The planner's "insert these" list of this plan (:mod:`reachplan.plugins.exporters.handoff`): the device
        instructions print it; None: they give what the channels alone say.

    Raises
    ------
    ValueError
        A bad label or name, no needles or duplicate hole ids, fewer than one fraction, a non-positive
        prescription, a channel length not beyond the longest path, or a source that is not HDR.
    """

    label: str
    needles: tuple[NeedleExport, ...]
    source: SourceSpec
    structure_set: StructureSet | None = None
    volume: Volume | None = None
    plan_datetime: datetime | None = None
    name: str = ""
    fractions_planned: int = 1
    prescription_dose_gy: float | None = None
    target_name: str = "HR-CTV"
    reference_points: tuple[ReferencePoint, ...] = ()
    application_setup_type: str = "SYED_NEBLETT"
    afterloader: Afterloader = GAMMAMED_PLUS_HDR
    channel_effective_length_mm: float | None = None
    dose: PlannedDose | None = None
    input_paths: tuple[Path, ...] = field(default=())
    specification_point: str = ""
    handoff: InsertList | None = None

    def __post_init__(self) -> None:
        _check_short_text(self.label, "plan label", 16)
        object.__setattr__(self, "needles", tuple(self.needles))
        object.__setattr__(self, "input_paths", tuple(Path(p) for p in self.input_paths))
        if not self.needles:
            raise ValueError("a plan to export needs at least one needle")
        ids = [n.hole_id for n in self.needles]
        if len(set(ids)) != len(ids):
            raise ValueError(f"needle hole ids must be unique, got {ids}")
        if len(self.name) > 64:
            raise ValueError("plan name must be <= 64 characters")
        if self.fractions_planned < 1:
            raise ValueError("fractions_planned must be >= 1")
        if self.prescription_dose_gy is not None and not (
                math.isfinite(self.prescription_dose_gy) and self.prescription_dose_gy > 0):
            raise ValueError("prescription_dose_gy must be positive when given")
        if self.channel_effective_length_mm is None:
            object.__setattr__(self, "channel_effective_length_mm", self.afterloader.channel_length_mm)
        assert self.channel_effective_length_mm is not None
        longest = max(n.length_mm for n in self.needles)
        if not (math.isfinite(self.channel_effective_length_mm) and self.channel_effective_length_mm > longest):
            raise ValueError(f"channel_effective_length_mm ({self.channel_effective_length_mm}) must exceed the "
                             f"longest needle path ({longest:.1f} mm)")
        object.__setattr__(self, "reference_points", tuple(self.reference_points))
        names = [p.name for p in self.reference_points]
        if len(set(names)) != len(names):
            raise ValueError(f"reference point names must be unique, got {names}")
        for p in self.reference_points:
            if [len(r) for r in p.rate_gy_per_s] != [len(n.dwell_times_s) for n in self.needles]:
                raise ValueError(f"reference point {p.name}: give one dose rate per dwell of every needle")
        if self.specification_point and self.specification_point not in names:
            raise ValueError(f"specification point {self.specification_point!r} is not one of the reference points")
        if self.source.treatment_type != "HDR":
            raise ValueError(f"only HDR plans are exported, the source is {self.source.treatment_type}")
        _check_short_text(self.target_name, "target name", 64)


@dataclass(frozen=True)
class ExportOptions:
    """How an exporter writes its files (what it writes comes from the plan).

    Parameters
    ----------
    overwrite : bool
        Replace output files that exist already (an input file of the plan: never).
    stem : str
        File-name stem; "" uses the plan label. Made safe (``[A-Za-z0-9._-]``).
    include_patient_name : bool
        Prefix file names with the (safe) patient name; off by default.
    step_mm : float
        Depth step of device-instruction rows, mm.
    time_resolution_s : float
        Dwell times are written to this (default 0.001 s: the plan's times are kept, a planned 0.187 s stays
        0.187 s; the afterloader rounds to its own step, 0.1 s for the GammaMed Plus, on delivery).
        Cumulative weights are then exact decimals.
    uid_prefix : str or None
        Root of new DICOM UIDs (digits and dots, ending with a dot); None: pydicom's registered root.
    rtplan_style : str
        Layout of the RT Plan's prescription (:data:`RTPLAN_STYLES`): ``"eclipse"`` (default) as Varian
        Eclipse/BrachyVision writes it, no Target Prescription Dose (300A,0026) in the Dose Reference Sequence;
        ``"vitesse"`` adds the target as a SITE/TARGET item with Target Prescription Dose, as Oncentra/Vitesse
        writes it.

    Raises
    ------
    ValueError
        A malformed ``uid_prefix``, a non-positive ``step_mm``, ``time_resolution_s`` outside 1e-6 .. 10 s, or an
        unknown ``rtplan_style``.
    """

    overwrite: bool = False
    stem: str = ""
    include_patient_name: bool = False
    step_mm: float = 5.0
    time_resolution_s: float = 0.001
    uid_prefix: str | None = None
    rtplan_style: str = "eclipse"

    def __post_init__(self) -> None:
        prefix = self.uid_prefix
        if prefix is not None and (len(prefix) > 54 or not re.fullmatch(r"(?:(?:[1-9][0-9]*|0)\.)+", prefix)):
            raise ValueError(f"uid_prefix must be digits and dots ending with a dot, <= 54 characters, "
                             f"got {self.uid_prefix!r}")
        if not (math.isfinite(self.step_mm) and self.step_mm > 0):
            raise ValueError("step_mm must be > 0")
        if not (math.isfinite(self.time_resolution_s) and 1e-6 <= self.time_resolution_s <= 10):
            raise ValueError("time_resolution_s must be within 1e-6 .. 10 s")
        if self.rtplan_style not in RTPLAN_STYLES:
            raise ValueError(f"rtplan_style must be one of {', '.join(RTPLAN_STYLES)}, got {self.rtplan_style!r}")


@dataclass(frozen=True)
class ExportedFile:
    """One written file and its role (``"rtstruct"``, ``"rtplan"``, ``"device_json"``, ``"device_csv"``)."""

    role: str
    path: Path


@dataclass(frozen=True)
class ExportedFiles:
    """What an export wrote, and anything the user must know.

    An exporter's ``export`` returns it; :meth:`path` finds a file by its role.

    Parameters
    ----------
    exporter : str
        The exporter's plugin name (its entry point).
    files : tuple of ExportedFile
        In the order written.
    notes : tuple of str
        One line each: placeholders generated, values rounded, ...
    """

    exporter: str
    files: tuple[ExportedFile, ...]
    notes: tuple[str, ...] = ()

    def path(self, role: str) -> Path:
        """Return the one file of ``role``.

        Raises
        ------
        KeyError
            When there is not exactly one.
        """
        found = [f.path for f in self.files if f.role == role]
        if len(found) != 1:
            raise KeyError(f"{len(found)} files of role {role!r} in this export")
        return found[0]


@runtime_checkable
class Exporter(Protocol):
    """The exporter plugin Protocol (entry-point group ``reachplan.exporters``).

    ``name`` is the plugin name, ``description`` one line for ``reachplan plugins``; ``export`` writes into
    ``out_dir`` (created when missing) and raises :class:`ExportError` for expected failures.
    """

    @property
    def name(self) -> str:
        """Plugin name (``dicom_rt``, ...)."""
        ...

    @property
    def description(self) -> str:
        """One line for ``reachplan plugins``."""
        ...

    def export(self, plan: ExportPlan, out_dir: Path, options: ExportOptions | None = None) -> ExportedFiles:
        """Write ``plan`` into ``out_dir`` (created when missing).

        Parameters
        ----------
        plan : ExportPlan
            What to write (needle paths and dwells in LPS mm).
        out_dir : Path
            Output folder.
        options : ExportOptions, optional
            How to write (default :class:`ExportOptions`).

        Returns
        -------
        ExportedFiles

        Raises
        ------
        ExportError
            An expected failure (a file in the way, an input that would be overwritten, ...).
        """
        ...


@dataclass(frozen=True)
class FunctionExporter:
    """An exporter plugin made of a name, a one-line description and an export function."""

    name: str
    description: str
    function: Callable[[ExportPlan, Path, ExportOptions | None], ExportedFiles]

    def export(self, plan: ExportPlan, out_dir: Path, options: ExportOptions | None = None) -> ExportedFiles:
        """Call the export function (see :meth:`Exporter.export`)."""
        return self.function(plan, out_dir, options)


def check_exporter(obj: object) -> None:
    """Check that ``obj`` implements :class:`Exporter` (the registry's check).

    Raises
    ------
    TypeError
        A missing member, an empty or non-str name, or a non-str description.
    """
    if not isinstance(obj, Exporter):
        raise TypeError(f"{obj!r} does not implement plugins.exporters.base.Exporter (name, description, export)")
    if not isinstance(obj.name, str) or not obj.name or not isinstance(obj.description, str):
        raise TypeError(f"{obj!r}: name must be a non-empty str and description a str")


# --- files ------------------------------------------------------------------------------------------------


def safe_name(text: str, fallback: str = "plan", max_len: int = 64) -> str:
    """Reduce ``text`` to ASCII ``[A-Za-z0-9._-]`` (others become ``_``), never empty, never hidden."""
    ascii_text = unicodedata.normalize("NFKD", text).encode("ascii", "ignore").decode("ascii")
    out = re.sub(r"[^A-Za-z0-9._-]+", "_", ascii_text).strip("._-")[:max_len].strip("._-")
    return out or fallback


def file_stem(plan: ExportPlan, options: ExportOptions) -> str:
    """Build the safe file-name stem of ``plan`` (patient name only with ``include_patient_name``)."""
    stem = safe_name(options.stem or plan.label)
    if options.include_patient_name:
        who = (plan.volume.patient_study.patient_name if plan.volume is not None else "") or (
            plan.structure_set.patient_study.patient_name if plan.structure_set is not None else "")
        if who:
            stem = f"{safe_name(who, fallback='patient')}_{stem}"
    return stem


def _same(a: Path, b: Path) -> bool:
    try:
        return a.resolve() == b.resolve() or (a.exists() and b.exists() and os.path.samefile(a, b))
    except OSError:
        return False


def check_targets(targets: Iterable[Path], plan: ExportPlan, options: ExportOptions) -> None:
    """Check that an export may write ``targets``.

    Raises
    ------
    ExportError
        A target is an input file of ``plan`` or lies in an input folder, exists without ``overwrite`` (or is
        not a file), or is written twice.
    """
    seen: list[Path] = []
    for t in targets:
        if any(_same(t, s) for s in seen):
            raise ExportError(f"two outputs of this export would be written to {t}; choose another stem")
        seen.append(t)
        if any(_same(t, p) for p in plan.input_paths):
            raise ExportError(f"refusing to write {t}: it is an input file of the plan; export to another folder")
        if any(p.is_dir() and t.resolve().is_relative_to(p.resolve()) for p in plan.input_paths):
            raise ExportError(f"refusing to write {t} into an input folder of the plan (its series would gain "
                              "files); export to another folder")
        if t.exists() and not options.overwrite:
            raise ExportError(f"{t} exists; choose another folder or stem, or pass overwrite=True")
        if t.exists() and not t.is_file():
            raise ExportError(f"{t} exists and is not a file; choose another folder or stem")


def prepare_out_dir(out_dir: Path) -> Path:
    """Create ``out_dir`` if needed and return it.

    Raises
    ------
    ExportError
        It cannot be created, or is not a writable folder.
    """
    out = Path(out_dir)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise ExportError(f"cannot create output folder {out}: {exc.strerror}") from None
    if not out.is_dir() or not os.access(out, os.W_OK):
        raise ExportError(f"output folder {out} is not a writable folder")
    return out
