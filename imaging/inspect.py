"""What is in a DICOM file or folder: image series, structure sets (with volumes) and brachy plans.

Everything found is read completely (pixel data included), so a damaged or inconsistent input is reported
as a typed error here rather than later in a plan.
"""

from __future__ import annotations

import importlib
import warnings
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

from reachplan.imaging.brachy_plan import PlanProblem, RtPlan, plan_problems
from reachplan.imaging.dicom_io import FolderScan, load_series, scan
from reachplan.imaging.errors import (
    ImagingError,
    ImagingWarning,
    NoDicomError,
    ReferenceMismatchError,
    StructureError,
    UnusablePlanWarning,
)
from reachplan.imaging.meshing import structure_volume_cc
from reachplan.imaging.names import SynonymTable
from reachplan.imaging.rtstruct import read_rtstruct
from reachplan.imaging.source_strength import source_strength
from reachplan.imaging.types import Volume


@dataclass(frozen=True)
class SeriesInfo:
    """An image series, read completely.

    Parameters
    ----------
    series_instance_uid, modality, description, frame_of_reference_uid : str
        As written.
    shape : (int, int, int)
        Voxels ``(nk, nj, ni)``: slices, rows, columns.
    spacing_mm : (float, float, float), mm
        Voxel size along i (columns), j (rows), k (slices).
    n_files : int
        Files the series is stored in.
    folder : str
        The first (sorted) folder holding them.
    """

    series_instance_uid: str
    modality: str
    description: str
    frame_of_reference_uid: str
    shape: tuple[int, int, int]
    spacing_mm: tuple[float, float, float]
    n_files: int
    folder: str


@dataclass(frozen=True)
class StructureInfo:
    """One ROI of a structure set.

    From the Structure Set ROI Sequence and the RT ROI Observations Sequence of the file.

    Parameters
    ----------
    number : int
        ROI Number.
    name, normalized_name : str
        As written, and the standard name it maps to.
    type : str
        RT ROI Interpreted Type; empty when not given.
    n_contours : int
        Contours of every kind.
    geometric_types : tuple of str
        The distinct contour geometric types, sorted.
    volume_cc : float or None, cm³
        Volume of the closed planar contours (on the image slices when possible); None without closed
        contours or when they cannot be stacked.
    note : str
        Why the volume is missing or was computed without the images; empty otherwise.
    """

    number: int
    name: str
    normalized_name: str
    type: str
    n_contours: int
    geometric_types: tuple[str, ...]
    volume_cc: float | None
    note: str = ""


@dataclass(frozen=True)
class StructureSetInfo:
    """An RT Structure Set: its file, label, Frame of Reference, referenced series and ROIs.

    Parameters
    ----------
    path : str
        The RTSTRUCT file's path, as found.
    label : str
        Structure Set Label.
    frame_of_reference_uid : str
        The Frame of Reference its contours are in.
    referenced_series_uid : str or None
        The image series it references; None when it names none.
    structures : tuple of StructureInfo
        Its ROIs.
    """

    path: str
    label: str
    frame_of_reference_uid: str
    referenced_series_uid: str | None
    structures: tuple[StructureInfo, ...]


@dataclass(frozen=True)
class ChannelInfo:
    """A channel of a brachy plan.

    Parameters
    ----------
    channel_number : int
        Channel Number (300A,0282).
    n_dwells : int
        Number of dwell positions (control points with a dwell).
    total_time_s : float, s
        Channel Total Time.
    roi_number : int or None
        Referenced ROI Number; None when the channel names none.
    """

    channel_number: int
    n_dwells: int
    total_time_s: float
    roi_number: int | None


@dataclass(frozen=True)
class PlanInfo:
    """A brachy RT Plan: file, treatment type, technique, source label and channels; ``note`` when unread.

    Parameters
    ----------
    path : str
        The RT Plan file's path, as found.
    type : str
        Brachy Treatment Type (``HDR``, ``PDR``, ...).
    technique : str
        Brachy Treatment Technique.
    source : str
        The source's label (isotope and model).
    channels : tuple of ChannelInfo
        The channels of every application setup.
    note : str
        Why the plan could not be read; empty when it was.
    machine : str
        Treatment Machine Name.
    fractions : int
        Number of Fractions Planned.
    prescription_gy : float or None, Gy
        Brachy Application Setup Dose, per fraction; None when absent.
    target : str
        The TARGET dose reference's description; empty when the plan has none.
    points : tuple of (str, float or None)
        Each dose reference point with the plan's dose there over all fractions (Gy; None when the plan carries no
        coefficients).
    strength : str
        The source strength ``reachplan dose`` computes with, by the rule of
        :func:`~reachplan.imaging.source_strength.source_strength` at the RT Plan Date; empty without a source.
    """

    path: str
    type: str  # HDR, PDR, ... (the plan's brachy treatment type)
    technique: str
    source: str
    channels: tuple[ChannelInfo, ...]
    note: str = ""
    machine: str = ""
    fractions: int = 1
    prescription_gy: float | None = None
    target: str = ""
    points: tuple[tuple[str, float | None], ...] = ()
    strength: str = ""


@dataclass(frozen=True)
class OtherInfo:
    """A DICOM object that is neither an image, a structure set nor a plan.

    Parameters
    ----------
    path : str
        The file's path, as found.
    modality : str
        Modality, as written.
    sop_class_uid : str
        SOP Class UID.
    """

    path: str
    modality: str
    sop_class_uid: str


@dataclass(frozen=True)
class Inspection:
    """The result of :func:`inspect_path`.

    Built only after every object found was read completely, pixel data included (see the module notes).

    Parameters
    ----------
    path : str
        The file or folder inspected, as given.
    series, structure_sets, plans, others
        What was found, by kind.
    n_non_dicom : int
        Files that are not DICOM.
    warnings : tuple of str
        ``"WarningClass: message"`` of each distinct quirk the readers worked around.
    """

    path: str
    series: tuple[SeriesInfo, ...]
    structure_sets: tuple[StructureSetInfo, ...]
    plans: tuple[PlanInfo, ...]
    others: tuple[OtherInfo, ...]
    n_non_dicom: int
    warnings: tuple[str, ...] = ()

    def to_json(self) -> dict[str, Any]:
        """Return a JSON-ready dict: ``series``, ``structure_sets`` with ``structures``, ``plans`` with ``channels``.

        Returns
        -------
        dict
            ``series``, ``structure_sets`` with ``structures``, ``plans`` with ``channels``: the fields as plain
            dicts, lists and numbers.
        """
        from dataclasses import asdict

        return asdict(self)


def _volume_cc(roi: Any, volume: Volume | None) -> tuple[float | None, str]:
    if not any(c.geometric_type == "CLOSED_PLANAR" for c in roi.contours):
        return None, ""
    try:
        return structure_volume_cc(roi, volume.grid if volume is not None else None), ""
    except StructureError as exc:
        if volume is not None:  # contours that do not stack on the images: try them on their own
            try:
                return structure_volume_cc(roi), f"not on the image slices: {exc}"
            except StructureError:
                pass
        return None, str(exc)


def _first(obj: Any, *names: str) -> Any:
    """Return the first of ``obj``'s attributes ``names`` that is not None (plan readers differ in naming)."""
    for name in names:
        value = getattr(obj, name, None)
        if value is not None:
            return value
    return None


def _source_label(plan: Any) -> str:
    source = _first(plan, "source")
    if callable(source):
        try:
            source = source()
        except ImagingError:
            return ""
    if source is None:
        return ""
    if isinstance(source, str):
        return source
    labels = getattr(source, "labels", None)
    parts = labels() if callable(labels) else ()
    return " / ".join(str(x) for x in parts) or str(source)


def _plan_info(path: Path, plan_check: PlanCheck | None) -> PlanInfo:
    """Summarise a brachy RT Plan through :func:`reachplan.imaging.rtplan.read_rtplan` (loaded lazily).

    Each problem ``plan_check`` (default :func:`~reachplan.imaging.brachy_plan.plan_problems`) finds is an
    :class:`UnusablePlanWarning`.
    """
    try:
        rtplan = importlib.import_module("reachplan.imaging.rtplan")
    except ModuleNotFoundError as exc:
        if exc.name != "reachplan.imaging.rtplan":
            raise
        return PlanInfo(str(path), "", "", "", (), note="RT Plan reader not available")
    plan = rtplan.read_rtplan(path)
    for problem in (plan_check or plan_problems)(plan):
        warnings.warn(UnusablePlanWarning(f"{path}: {problem.message}"), stacklevel=2)
    channels = []
    for c in plan.channels:
        roi = _first(c, "roi_number")
        channels.append(ChannelInfo(int(_first(c, "channel_number", "number")), int(c.n_dwells),
                                    float(_first(c, "total_time_s") or 0.0), None if roi is None else int(roi)))
    refs = tuple(getattr(plan, "dose_references", ()))
    strength = ""
    sources = tuple(getattr(plan, "sources", ()))
    if sources:  # the strength `reachplan dose` computes with, by the same rule (it warns when used as written)
        number = plan.channels[0].source_number if plan.channels else sources[0].number
        src = next((x for x in sources if x.number == number), sources[0])
        got = source_strength(src, str(getattr(plan, "plan_date", "")), label=path.name)
        strength = f"S_K {got.reference_u:.6g} U on {got.reference_date or 'no date'}, " + (
            f"{got.treatment_u:.6g} U on {got.treatment_date}" if got.decayed else "used as written (not decayed)")
    setup_doses = [d for _, d in getattr(plan, "setup_doses_gy", ()) if d > 0]
    return PlanInfo(str(path), str(_first(plan, "plan_type", "treatment_type") or ""),
                    str(_first(plan, "technique") or ""), _source_label(plan), tuple(channels),
                    machine=str(getattr(plan, "machine_name", "")), fractions=int(getattr(plan, "n_fractions", 1)),
                    prescription_gy=setup_doses[0] if setup_doses else None,
                    target=next((r.description for r in refs if r.reference_type == "TARGET"), ""),
                    points=tuple((r.description, r.tps_dose_gy) for r in refs if r.position_mm is not None),
                    strength=strength)


def _structure_sets(
    found: FolderScan, root: Path, volumes: dict[str, Volume], synonyms: SynonymTable | None
) -> list[StructureSetInfo]:
    out = []
    by_for: dict[str, list[Volume]] = {}
    for v in volumes.values():
        by_for.setdefault(v.frame_of_reference_uid, []).append(v)
    for ds, path in found.others:
        if str(ds.get("Modality", "")).upper() != "RTSTRUCT":
            continue
        ss = read_rtstruct(path, synonyms=synonyms)
        volume: Volume | None = None
        if ss.referenced_series_uid and ss.referenced_series_uid in volumes:
            volume = volumes[ss.referenced_series_uid]
        elif volumes and ss.referenced_series_uid:
            have = ", ".join(volumes)
            raise ReferenceMismatchError(
                f"RT Structure Set {path} references series {ss.referenced_series_uid}, which is not in "
                f"{root} (it holds {have}); put it beside the images it was drawn on"
            )
        elif volumes:
            same = by_for.get(ss.frame_of_reference_uid, [])
            if not same:
                raise ReferenceMismatchError(
                    f"RT Structure Set {path} is in Frame of Reference {ss.frame_of_reference_uid or 'unknown'}, "
                    "which no image series here shares; put it beside the images it was drawn on"
                )
            volume = same[0]
        if volume is not None:
            ss = read_rtstruct(path, volume, synonyms=synonyms)  # checks FoR and series
        infos = []
        for roi in ss.rois:
            vol, note = _volume_cc(roi, volume)
            infos.append(StructureInfo(
                number=roi.number, name=roi.name, normalized_name=roi.normalized_name, type=roi.interpreted_type,
                n_contours=len(roi.contours), geometric_types=tuple(sorted({c.geometric_type for c in roi.contours})),
                volume_cc=None if vol is None else round(vol, 3), note=note))
        out.append(StructureSetInfo(str(path), ss.label, ss.frame_of_reference_uid, ss.referenced_series_uid,
                                    tuple(infos)))
    return out


#: A plan check: the problems that make a brachy plan unusable (``plan_problems`` or the planner's fuller one).
PlanCheck = Callable[[RtPlan], Sequence[PlanProblem]]


def inspect_path(path: Path, synonyms: SynonymTable | None = None, plan_check: PlanCheck | None = None) -> Inspection:
    """Read everything at ``path`` (a DICOM file or a folder, recursively) and summarise it.

    Warnings about quirks the readers worked around (:class:`~reachplan.imaging.errors.ImagingWarning`) are collected
    in :attr:`Inspection.warnings` instead of being emitted.

    Parameters
    ----------
    path : Path
        A DICOM file or folder.
    synonyms : SynonymTable, optional
        ROI name table (default :data:`reachplan.imaging.names.DEFAULT_SYNONYMS`).
    plan_check : callable, optional
        ``plan_check(plan) -> problems`` for each brachy plan found (default
        :func:`~reachplan.imaging.brachy_plan.plan_problems`); each problem is an :class:`UnusablePlanWarning`.

    Returns
    -------
    Inspection
        What was found, with the warnings collected.

    Raises
    ------
    NoDicomError
        Nothing DICOM there.
    CorruptFileError, SeriesError, UnsupportedDataError, StructureError, ReferenceMismatchError
        From the readers: the first problem found.
    """
    path = Path(path)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", ImagingWarning)
        result = _inspect(path, synonyms, plan_check)
    notes = tuple(dict.fromkeys(f"{type(w.message).__name__}: {w.message}" for w in caught
                                if isinstance(w.message, ImagingWarning)))
    for w in caught:  # anything that is not ours goes on as a warning
        if not isinstance(w.message, ImagingWarning):
            warnings.warn_explicit(w.message, w.category, w.filename, w.lineno)
    return replace(result, warnings=notes)


def _inspect(path: Path, synonyms: SynonymTable | None, plan_check: PlanCheck | None) -> Inspection:
    found = scan(path)
    if not found.images and not found.others:
        raise NoDicomError(f"no DICOM files in {path} ({found.n_non_dicom} other files); "
                           "give a folder that holds a DICOM series, structure set or plan")
    series, volumes = [], {}
    for s in found.series():
        v = load_series(found, s, folder=path)
        volumes[s.series_instance_uid] = v
        sp = v.grid.spacing_mm
        folders = {str(p.parent) for p in s.paths}
        series.append(SeriesInfo(
            series_instance_uid=s.series_instance_uid, modality=s.modality, description=s.description,
            frame_of_reference_uid=s.frame_of_reference_uid, shape=v.grid.shape,
            spacing_mm=(round(float(sp[0]), 4), round(float(sp[1]), 4), round(float(sp[2]), 4)),
            n_files=len(s.paths), folder=sorted(folders)[0]))
    structure_sets = _structure_sets(found, path, volumes, synonyms)
    plans = [_plan_info(p, plan_check) for ds, p in found.others if str(ds.get("Modality", "")).upper() == "RTPLAN"]
    others = [OtherInfo(str(p), str(ds.get("Modality", "")), str(ds.get("SOPClassUID", "")))
              for ds, p in found.others if str(ds.get("Modality", "")).upper() not in ("RTSTRUCT", "RTPLAN")]
    return Inspection(str(path), tuple(series), tuple(structure_sets), tuple(plans), tuple(others),
                      found.n_non_dicom)
