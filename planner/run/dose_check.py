"""The TG-43 secondary check of a brachy RT Plan: the chain behind ``reachplan dose``.

The source data set is the one named in the plan (Source Model ID, Isotope Name, manufacturer, treatment machine)
when its isotope, kind and active length agree; for an anonymised plan the only registered one of the plan's isotope
(named or told by the half-life), treatment type and active length
(:func:`reachplan.plugins.sources.identify.identify_source`); else the one the caller names. S_K is the plan's
Reference Air Kerma Rate decayed to the treatment date (the one given, else the RT Plan Date) across a plausible
interval only, else used as written with a warning that says so: the rule of
:func:`reachplan.imaging.source_strength.source_strength`, which ``inspect`` applies too. Dwell times follow the
Eclipse conventions (see :mod:`reachplan.imaging.rtplan`); doses are totals over fractions and pulses.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from datetime import datetime
from typing import Literal

import numpy as np

from reachplan.imaging.brachy_plan import BrachySource, RtPlan
from reachplan.imaging.errors import InvalidValueError
from reachplan.imaging.rtplan import channel_paths
from reachplan.imaging.source_strength import DecayWindow, SourceStrength, dicom_datetime, source_strength
from reachplan.imaging.types import Grid, StructureSet
from reachplan.planner.dose.dwells import dose_on_grid, plan_dwells
from reachplan.planner.dose.plan_check import PointCheck, check_isotope, check_points
from reachplan.planner.dose.plan_usable import plan_source, require_usable
from reachplan.planner.dose.tg43 import Tg43Kernel
from reachplan.planner.errors import PlanInputError
from reachplan.planner.lookup import all_sources, get_source
from reachplan.plugins.errors import SourceMatchError
from reachplan.plugins.exporters.rtdose import CEILING_TIMES_PRESCRIPTION, DoseContext
from reachplan.plugins.sources.identify import SourceChoice, identify_source, plan_isotope

#: the largest dose grid computed (voxels); a finer one asks for a coarser spacing
MAX_GRID_VOXELS = 60_000_000


@dataclass(frozen=True)
class DoseCheckConfig:
    """How to recompute a plan's dose.

    Parameters
    ----------
    source : str or None
        The TG-43 data set to use; None: identified from the plan.
    model : str
        ``"line"`` (TG-43 line source) or ``"point"`` (1D point source).
    spacing_mm : float
        Grid spacing around the dwells, mm (ignored with ``like``).
    margin_mm : float
        Margin of that grid around the dwell positions, mm.
    like : Grid or None
        A grid to compute on (an RT Dose's), LPS mm.
    treatment_date : str or None
        ``YYYYMMDD[HHMMSS]`` the source strength is decayed to; None: the RT Plan Date, within ``decay``.
    points : bool
        Also compute the dose at the plan's dose reference points.
    decay : DecayWindow
        Across which interval after the calibration the strength is decayed to the RT Plan Date.
    """

    source: str | None = None
    model: Literal["line", "point"] = "line"
    spacing_mm: float = 2.5
    margin_mm: float = 30.0
    like: Grid | None = None
    treatment_date: str | None = None
    points: bool = False
    decay: DecayWindow = field(default_factory=DecayWindow)


@dataclass(frozen=True, eq=False)
class DoseCheck:
    """A plan's dose recomputed with TG-43.

    Parameters
    ----------
    choice : SourceChoice
        The TG-43 data set and how it was chosen.
    strength : SourceStrength
        S_K as written and at the treatment date.
    grid : Grid
        The dose grid (LPS mm).
    dose_gy : (nk, nj, ni) float
        Total dose over fractions and pulses, Gy, on ``grid``.
    n_dwells : int
        Dwell positions with time.
    checks : tuple of PointCheck
        The dose at the plan's reference points against the plan's own (empty unless asked for).
    context : DoseContext
        What the RT Dose refers to (Frame of Reference, patient and study, the plan).
    ceiling_gy : float or None
        The largest dose the RT Dose stores (a multiple of the prescription), None when the plan has none.
    fractions : str
        ``"N fraction(s) x M pulse(s)"``.
    """

    choice: SourceChoice
    strength: SourceStrength
    grid: Grid
    dose_gy: np.ndarray
    n_dwells: int
    checks: tuple[PointCheck, ...]
    context: DoseContext
    ceiling_gy: float | None
    fractions: str


def check_plan_dose(plan: RtPlan, structures: StructureSet, config: DoseCheckConfig, label: str = "plan") -> DoseCheck:
    """Recompute a brachy plan's dose with TG-43 on a grid around its dwells (or the one given).

    Parameters
    ----------
    plan : RtPlan
        The brachy RT Plan as read.
    structures : StructureSet
        The RT Structure Set with its channels' ROIs.
    config : DoseCheckConfig
        Source, model, grid, treatment date, points.
    label : str
        The plan's name in messages (its file name).

    Returns
    -------
    DoseCheck
        The dose and what it was computed with.

    Raises
    ------
    PlanInputError
        A problem :func:`~reachplan.planner.dose.plan_usable.require_usable` finds (no channels, a channel without
        control points, no source or strength, no source data that fits), no dwell, no Frame of Reference, a grid
        too large, or a dose that is not finite.
    """
    require_usable(plan, label, source=config.source)  # the checks inspect warns about (one shared function)
    src = plan.source(plan.channels[0].source_number)
    try:
        choice = choose_source(plan, src, config.source)
    except (PlanInputError, SourceMatchError) as exc:
        raise PlanInputError(f"{label}: {exc}") from None
    data = get_source(choice.name)
    check_isotope(src, data, label)
    strength = decayed_strength(plan, src, config.treatment_date, config.decay, label)
    kernel = Tg43Kernel(data, config.model)
    dwells = plan_dwells(plan, channel_paths(plan, structures))
    if not len(dwells):
        raise PlanInputError(f"{label}: the plan has no dwell positions; there is no dose to compute")
    grid = config.like if config.like is not None else dose_grid(dwells.positions_mm, config.spacing_mm,
                                                                 config.margin_mm)
    if int(np.prod(grid.shape)) > MAX_GRID_VOXELS:
        raise PlanInputError(f"the dose grid {grid.shape} is too large; use a coarser --spacing")
    for_uid = plan.frame_of_reference_uid or structures.frame_of_reference_uid
    if not for_uid:
        raise PlanInputError("neither the plan nor the structure set gives a Frame of Reference UID")
    dose = dose_on_grid(grid, dwells, kernel, strength.treatment_u)
    if not np.all(np.isfinite(dose)):
        raise PlanInputError(f"{label}: the dose is not finite on the grid (a dwell time or strength out of "
                             "range); check the plan's times and source")
    checks = tuple(check_points(plan, dwells, kernel, strength.treatment_u)) if config.points else ()
    context = DoseContext(frame_of_reference_uid=for_uid, patient_study=plan.patient_study,
                          referenced_plan_uid=plan.sop_instance_uid)
    setup = max((d for _, d in plan.setup_doses_gy), default=0.0) * plan.n_fractions * plan.n_pulses
    return DoseCheck(choice, strength, grid, dose, len(dwells), checks, context,
                     CEILING_TIMES_PRESCRIPTION * setup if setup > 0 else None,
                     f"{plan.n_fractions} fraction(s) x {plan.n_pulses} pulse(s)")


def dose_grid(positions_mm: np.ndarray, spacing_mm: float, margin_mm: float) -> Grid:
    """Return an axis-aligned grid holding the dwells with a margin.

    Parameters
    ----------
    positions_mm : (n, 3) float
        Dwell positions, mm, LPS.
    spacing_mm : float
        Voxel size, mm (cubic).
    margin_mm : float
        Margin around the dwells on every side, mm.

    Returns
    -------
    Grid
        The grid, LPS mm.
    """
    lo = positions_mm.min(axis=0) - margin_mm
    hi = positions_mm.max(axis=0) + margin_mm
    n = np.floor((hi - lo) / spacing_mm).astype(int) + 1
    affine = np.diag([spacing_mm, spacing_mm, spacing_mm, 1.0])
    affine[:3, 3] = lo
    return Grid((int(n[2]), int(n[1]), int(n[0])), affine)


def choose_source(plan: RtPlan, src: BrachySource, given: str | None) -> SourceChoice:
    """Return the TG-43 data set: ``given`` (checked against the plan's isotope) or identified from the plan.

    Parameters
    ----------
    plan : RtPlan
        The plan (treatment type, machine name).
    src : BrachySource
        Its source.
    given : str or None
        The data set the user named (``--source``).

    Returns
    -------
    SourceChoice
        The data set and how it was chosen.

    Raises
    ------
    PlanInputError
        ``given`` is of another isotope than the plan's source.
    SourceMatchError
        No data set, or several, fit the plan (:func:`~reachplan.plugins.sources.identify.identify_source`).
    """
    if given:
        data = get_source(given)
        isotope = plan_isotope(src.isotope_name, src.half_life_days)
        if isotope is not None and isotope != data.isotope:
            raise PlanInputError(f"--source {given} is {data.isotope} but the plan's source is {isotope}; "
                                 "choose a data set of that isotope")
        return SourceChoice(given, f"{given}: given with --source")
    return identify_source(all_sources(), plan_source(plan, src))


def parse_date(text: str, what: str) -> datetime:
    """Parse a DICOM date (and time) ``YYYYMMDD[HH[MM[SS]]]``, fractions of a second ignored.

    Parameters
    ----------
    text : str
        A DICOM DA value, optionally followed by a TM value, as written.
    what : str
        What it is, for the message.

    Returns
    -------
    datetime
        Naive (no time zone), as DICOM writes it.

    Raises
    ------
    PlanInputError
        Not such a date.
    """
    when = dicom_datetime(text)
    if when is None:
        raise PlanInputError(f"{what} {text!r} is not a date YYYYMMDD[HHMMSS]")
    return when


def decayed_strength(plan: RtPlan, src: BrachySource, treatment: str | None, window: DecayWindow | None = None,
                     label: str = "plan") -> SourceStrength:
    """Return S_K at the treatment date by the one rule of :func:`~reachplan.imaging.source_strength.source_strength`.

    Parameters
    ----------
    plan : RtPlan
        The plan (its RT Plan Date).
    src : BrachySource
        Its source: strength, reference date and time, half-life.
    treatment : str or None
        ``YYYYMMDD[HHMMSS]`` to decay to (``--treatment-date``); None: the RT Plan Date within ``window``.
    window : DecayWindow or None
        The plausible interval; None: the default (up to 2 half-lives after the calibration, none before).
    label : str
        The plan's name in messages.

    Returns
    -------
    SourceStrength
        What :func:`~reachplan.imaging.source_strength.source_strength` returns.

    Raises
    ------
    PlanInputError
        ``treatment`` is not a date, or the strength cannot be decayed to it.

    Warns
    -----
    CalibrationDateWarning
        S_K used as written (see :func:`~reachplan.imaging.source_strength.source_strength`).
    """
    when = parse_date(treatment, "--treatment-date") if treatment else None
    try:
        return source_strength(src, plan.plan_date, when, window, label=label)
    except InvalidValueError as exc:
        raise PlanInputError(str(exc)) from None
