"""The source strength a brachy plan is computed with: one rule for ``dose``, ``inspect`` and ``plan --rtplan``.

A plan gives the Reference Air Kerma Rate S_K at its Source Strength Reference Date/Time. Decaying it to the
treatment is right across a plausible interval only: a source is used from its calibration for a few half-lives
(an Ir-192 source, half-life 73.8 d, is exchanged about every 3 months), never before it. Genuine exports carry
dates outside any such interval: anonymised plans have the placeholder plan date 1901-01-01 (Oncentra/Vitesse,
rtplan_conventions.md §1 and §11), a damaged one a calibration date decades before the plan. Decaying across
such a gap overflows or vanishes (2^(±400)); so outside the interval S_K is used **as written** and one
:class:`~reachplan.imaging.errors.CalibrationDateWarning` says so in the words of what is done.

The interval (:class:`DecayWindow`) is by default from the calibration date to 2 half-lives after it; a treatment
date given by the user (``--treatment-date``) overrides it up to :data:`EXPLICIT_MAX_HALF_LIVES` forward and
:data:`EXPLICIT_MAX_BACK_HALF_LIVES` back (beyond: :class:`~reachplan.imaging.errors.InvalidValueError`). Without a
treatment date the plan's RT Plan Date is taken in whole days (Eclipse dates the strength to the plan day at
midnight, rtplan_conventions.md §5).
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass
from datetime import datetime

from reachplan.imaging.brachy_plan import BrachySource
from reachplan.imaging.errors import CalibrationDateWarning, InvalidValueError

#: With a treatment date the user gives, the strength is decayed up to this many half-lives forward ...
EXPLICIT_MAX_HALF_LIVES = 20.0
#: ... and this many back (a treatment before the calibration time, e.g. the morning of the calibration day).
EXPLICIT_MAX_BACK_HALF_LIVES = 1.0


@dataclass(frozen=True)
class DecayWindow:
    """Across which interval after the calibration the source strength is decayed (otherwise used as written).

    Parameters
    ----------
    max_forward_half_lives : float
        Decay up to this many half-lives after the Source Strength Reference Date (default 2: 147.7 d for Ir-192).
    max_backward_days : float
        Decay back up to this many days before it (default 0: a plan dated before its calibration is not decayed).

    Raises
    ------
    ValueError
        A negative or non-finite bound.
    """

    max_forward_half_lives: float = 2.0
    max_backward_days: float = 0.0

    def __post_init__(self) -> None:
        for v, what in ((self.max_forward_half_lives, "max_forward_half_lives"),
                        (self.max_backward_days, "max_backward_days")):
            if not (math.isfinite(v) and v >= 0):
                raise ValueError(f"{what} must be finite and >= 0, got {v}")


@dataclass(frozen=True)
class SourceStrength:
    """The source strength used: as written in the plan and at the treatment date, and whether it was decayed.

    What :func:`source_strength` returns.

    Parameters
    ----------
    reference_u : float
        Reference Air Kerma Rate, U (µGy m² h⁻¹), at the reference date.
    reference_date : str
        The reference date and time as written (empty when the plan gives none).
    treatment_date : str
        The date decayed to and where it came from (or why there is none).
    elapsed_days : float
        Days from the reference date to the treatment date (0 when not known).
    treatment_u : float
        S_K used, U: decayed to the treatment date, or as written.
    decayed : bool
        True when ``treatment_u`` is the decayed strength (also when the interval is 0 days).
    note : str
        Why S_K is used as written (the warning's words); empty when decayed.
    """

    reference_u: float
    reference_date: str
    treatment_date: str
    elapsed_days: float
    treatment_u: float
    decayed: bool = True
    note: str = ""

    def to_json(self) -> dict[str, object]:
        """Return the strength as the command's JSON keys.

        Returns
        -------
        dict
            ``air_kerma_reference_u``, ``reference_date``, ``treatment_date``, ``elapsed_days``,
            ``air_kerma_treatment_u``, ``decayed``, ``decay_note``.
        """
        return {"air_kerma_reference_u": self.reference_u, "reference_date": self.reference_date,
                "treatment_date": self.treatment_date, "elapsed_days": self.elapsed_days,
                "air_kerma_treatment_u": self.treatment_u, "decayed": self.decayed, "decay_note": self.note}


def decay_factor(half_life_days: float, elapsed_days: float) -> float:
    """Return the fraction of the source strength left after ``elapsed_days``, 2^(-t/T½).

    Parameters
    ----------
    half_life_days : float
        Half-life, days (> 0).
    elapsed_days : float
        Time since calibration, days (negative: before calibration).

    Returns
    -------
    float
        The decay factor (> 0).

    Raises
    ------
    InvalidValueError
        A half-life that is not a positive number, or a non-finite elapsed time.
    """
    if not (math.isfinite(half_life_days) and half_life_days > 0 and math.isfinite(elapsed_days)):
        raise InvalidValueError(f"cannot decay the source: half-life {half_life_days} d, elapsed {elapsed_days} d")
    return float(2.0 ** (-elapsed_days / half_life_days))


def dicom_datetime(text: str) -> datetime | None:
    """Parse a DICOM date (and time) ``YYYYMMDD[HH[MM[SS]]]``, fractions of a second ignored.

    Parameters
    ----------
    text : str
        A DICOM DA value, optionally followed by a TM value, as written.

    Returns
    -------
    datetime or None
        Naive (no time zone), as DICOM writes it; None when ``text`` is not such a date.
    """
    digits = text.strip().split(".")[0]
    fmt = {8: "%Y%m%d", 10: "%Y%m%d%H", 12: "%Y%m%d%H%M", 14: "%Y%m%d%H%M%S"}.get(len(digits))
    if fmt is None or not digits.isdigit():
        return None
    try:
        return datetime.strptime(digits, fmt)
    except ValueError:
        return None


def source_strength(src: BrachySource, plan_date: str, treatment: datetime | None = None,
                    window: DecayWindow | None = None, *, label: str = "plan") -> SourceStrength:
    """Return the S_K a plan is computed with, and warn when it is used as written for want of a plausible date.

    With ``treatment`` (the user's date) S_K is decayed to it (within the explicit bounds of the module docstring).
    Otherwise to ``plan_date`` (whole days) when that lies in ``window`` after the reference date; else (a
    placeholder or implausible date, no date, no half-life, an unreadable reference date) as written, with one
    :class:`~reachplan.imaging.errors.CalibrationDateWarning` whose words say so.

    Parameters
    ----------
    src : BrachySource
        The plan's source: strength, reference date and time, half-life.
    plan_date : str
        RT Plan Date as written (``YYYYMMDD``; may be empty).
    treatment : datetime or None
        The treatment date and time the user gives.
    window : DecayWindow or None
        The plausible interval; None: :class:`DecayWindow` ().
    label : str
        The plan's name in messages.

    Returns
    -------
    SourceStrength
        As written and as used, with the dates, the elapsed days and whether it was decayed.

    Raises
    ------
    InvalidValueError
        ``treatment`` given but the strength cannot be decayed to it (no readable reference date, no half-life,
        or farther from the reference date than the explicit bounds).

    Warns
    -----
    CalibrationDateWarning
        S_K used as written because the interval is not plausible or not known.
    """
    window = window or DecayWindow()
    written = f"{src.reference_date} {src.reference_time}".strip()
    ref = dicom_datetime(src.reference_date + (src.reference_time or "")) if src.reference_date else None
    half = src.half_life_days if src.half_life_days and src.half_life_days > 0 else None
    if treatment is not None:
        return _explicit(src, written, ref, half, treatment, label)
    plan_day = dicom_datetime(plan_date) if plan_date else None
    when = f"{plan_date} (RT Plan Date)" if plan_day is not None else "unknown"
    elapsed = float((plan_day.date() - ref.date()).days) if plan_day is not None and ref is not None else 0.0
    why = ""
    if not src.reference_date:
        why = "the plan gives no Source Strength Reference Date"
    elif ref is None:
        why = f"its Source Strength Reference Date {src.reference_date!r} is not a date"
    elif plan_day is None:
        why = ("the plan gives no RT Plan Date" if not plan_date.strip()
               else f"its RT Plan Date {plan_date!r} is not a date")
    elif half is None and elapsed != 0.0:
        why = "the plan's source has no half-life"
    elif half is not None and not (-window.max_backward_days <= elapsed <= window.max_forward_half_lives * half):
        rel = "before" if elapsed < 0 else "after"
        why = (f"the RT Plan Date {plan_day.date().isoformat()} is {abs(elapsed):.0f} days {rel} the Source Strength "
               f"Reference Date {ref.date().isoformat()}, outside the interval the strength is decayed across "
               f"(from {window.max_backward_days:g} days before that date to {window.max_forward_half_lives:g} "
               f"half-lives = {window.max_forward_half_lives * half:.1f} days after it)")
    if why:
        note = (f"{label}: source {src.number}: the Reference Air Kerma Rate {src.air_kerma_rate_u:.6g} U is used as "
                f"written (not decayed): {why}; pass --treatment-date YYYYMMDD to decay it to the treatment date")
        warnings.warn(CalibrationDateWarning(note), stacklevel=2)
        return SourceStrength(src.air_kerma_rate_u, written, when, elapsed, src.air_kerma_rate_u, False, note)
    factor = decay_factor(half, elapsed) if half is not None else 1.0
    return SourceStrength(src.air_kerma_rate_u, written, when, elapsed, src.air_kerma_rate_u * factor)


def _explicit(src: BrachySource, written: str, ref: datetime | None, half: float | None, treatment: datetime,
              label: str) -> SourceStrength:
    """S_K decayed to a treatment date the user gave; a typed error when it cannot be."""
    when = f"{treatment:%Y%m%d%H%M%S} (--treatment-date)"
    if ref is None:
        raise InvalidValueError(f"{label}: cannot decay the source to --treatment-date: its Source Strength "
                                f"Reference Date {src.reference_date!r} is not a date; leave --treatment-date out "
                                "to use the Reference Air Kerma Rate as written")
    elapsed = (treatment - ref).total_seconds() / 86400.0
    if half is None:
        if elapsed != 0.0:
            raise InvalidValueError(f"{label}: the plan's source has no half-life; cannot decay its strength to "
                                    "--treatment-date (leave it out, or give the reference date, to use it as "
                                    "written)")
        return SourceStrength(src.air_kerma_rate_u, written, when, 0.0, src.air_kerma_rate_u)
    if not (-EXPLICIT_MAX_BACK_HALF_LIVES * half <= elapsed <= EXPLICIT_MAX_HALF_LIVES * half):
        raise InvalidValueError(
            f"{label}: --treatment-date {treatment:%Y-%m-%d} is {elapsed:.1f} days from the Source Strength Reference "
            f"Date {ref:%Y-%m-%d} (half-life {half:g} d): the strength would be x{2.0 ** (-elapsed / half):.3g}; "
            f"give a date within {EXPLICIT_MAX_BACK_HALF_LIVES:g} half-life before to {EXPLICIT_MAX_HALF_LIVES:g} "
            "half-lives after the calibration")
    return SourceStrength(src.air_kerma_rate_u, written, when, elapsed,
                          src.air_kerma_rate_u * decay_factor(half, elapsed))
