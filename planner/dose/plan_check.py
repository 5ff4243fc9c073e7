"""Checks of an existing brachy plan against TG-43 (a secondary check).

The source's isotope against the data set, and the dose at the plan's dose reference points beside the TPS's.

Positions in mm, DICOM patient coordinates (LPS); dose in Gy over the whole plan.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

import numpy as np

from reachplan.imaging.brachy_plan import BrachySource, RtPlan
from reachplan.planner.dose.dwells import DwellSet, dose_at_points
from reachplan.planner.dose.tg43 import Tg43Kernel
from reachplan.planner.errors import PlanInputError
from reachplan.plugins.sources import SourceData

_ISOTOPE = re.compile(r"(?<![a-z])([a-z]{1,2})\s*-?\s*(\d{2,3})(?!\d)|(?<!\d)(\d{2,3})\s*-?\s*([a-z]{1,2})(?![a-z])")


#: Brachytherapy isotopes (element symbol, mass number) that a Source Isotope Name may name.
_KNOWN_ISOTOPES = frozenset({"ir192", "co60", "cs137", "i125", "pd103", "yb169", "cs131", "se75", "au198", "ra226"})


def isotope_of(text: str) -> str | None:
    """Return the isotope named in ``text`` as ``"ir192"`` (``"Ir-192"``, ``"192Ir"``, ``"GammaMed Ir192 HDR"``).

    Parameters
    ----------
    text : str
        A Source Isotope Name, a source's name or any label.

    Returns
    -------
    str or None
        Element symbol and mass number in lower case; None when it names no known brachytherapy isotope.
    """
    for m in _ISOTOPE.finditer(text.lower()):
        key = f"{m.group(1)}{m.group(2)}" if m.group(1) else f"{m.group(4)}{m.group(3)}"
        if key in _KNOWN_ISOTOPES:
            return key
    return None


def check_isotope(source: BrachySource, data: SourceData, where: str) -> None:
    """Refuse TG-43 data of another isotope than the plan's source.

    Parameters
    ----------
    source : BrachySource
        The plan's source.
    data : SourceData
        The TG-43 data to compute with.
    where : str
        What is being checked (starts the error message).

    Raises
    ------
    PlanInputError
        The plan's Source Isotope Name names another isotope than ``data.isotope``.
    """
    ours, theirs = isotope_of(data.isotope), isotope_of(source.isotope_name)
    if ours and theirs and ours != theirs:
        raise PlanInputError(
            f"{where}: the plan's source is {source.isotope_name!r} but the TG-43 data {data.name!r} are for "
            f"{data.isotope}; choose data of the plan's isotope with --source (see `reachplan plugins`)")


@dataclass(frozen=True, eq=False)
class PointCheck:
    """Our dose and the TPS's at one dose reference point.

    Doses are in Gy over the whole plan (all fractions and pulses).

    Parameters
    ----------
    number : int
        Dose Reference Number.
    name : str
        Dose Reference Description.
    position_mm : (3,) float, mm, LPS
        The point.
    dose_gy : float, Gy
        Our dose there.
    tps_gy : float or None, Gy
        The TPS's dose; None when the plan carries none for the point.
    diff_percent : float or None, %
        ``100 (dose_gy / tps_gy − 1)``; None without a TPS dose.
    """

    number: int
    name: str
    position_mm: np.ndarray
    dose_gy: float
    tps_gy: float | None
    diff_percent: float | None


def check_points(
    plan: RtPlan, dwells: DwellSet, kernel: Tg43Kernel, air_kerma_strength_u: float
) -> tuple[PointCheck, ...]:
    """Recompute the dose at every point dose reference of ``plan`` and set it beside the TPS's.

    Parameters
    ----------
    plan : RtPlan
        The plan; references without a position are skipped.
    dwells : DwellSet
        The plan's dwells with whole-plan times (see :func:`reachplan.planner.dose.dwells.plan_dwells`).
    kernel : Tg43Kernel
        The source's dose-rate kernel.
    air_kerma_strength_u : float, U
        Source strength (cGy cm² h⁻¹).

    Returns
    -------
    tuple of PointCheck
        One per point reference with a position, in the plan's order.
    """
    refs = [r for r in plan.dose_references if r.position_mm is not None]
    if not refs:
        return ()
    pts = np.array([r.position_mm for r in refs])
    doses = dose_at_points(pts, dwells, kernel, air_kerma_strength_u)
    out = []
    for r, p, d in zip(refs, pts, doses, strict=True):
        diff = None if not r.tps_dose_gy else 100.0 * (float(d) / r.tps_dose_gy - 1.0)
        out.append(PointCheck(r.number, r.description, p, float(d), r.tps_dose_gy, diff))
    return tuple(out)
