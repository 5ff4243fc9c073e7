"""Which TG-43 data set a plan's source is: pure logic on the plan's attributes and the registered data sets.

The caller passes the data sets by name (the planner's look-up module loads them from the registry); nothing here
calls the registry. A named source is kept only when its isotope, kind and active length agree with the plan's;
an anonymised plan is matched by inference (isotope from its name or half-life, treatment type, active length,
manufacturer).
"""

from __future__ import annotations

import re
from collections.abc import Mapping
from dataclasses import dataclass

from reachplan.plugins.errors import SourceMatchError
from reachplan.plugins.sources import SourceData, normalise_label

#: Half-lives (days) used to tell the isotope of an anonymised plan (NNDC NuDat 3): Ir-192 73.829 d, Co-60
#: 5.2714 y, Cs-137 30.08 y, I-125 59.49 d, Pd-103 16.99 d, Yb-169 32.02 d, Se-75 119.78 d.
ISOTOPE_HALF_LIVES_DAYS: tuple[tuple[str, float], ...] = (
    ("Ir-192", 73.83), ("Co-60", 1925.28), ("Cs-137", 10987.0), ("I-125", 59.49), ("Pd-103", 16.99),
    ("Yb-169", 32.02), ("Se-75", 119.78),
)
_ISOTOPE_RE = re.compile(r"\b(ir|co|cs|i|pd|yb|se)[\s-]?(192|60|137|125|103|169|75)\b", re.IGNORECASE)
#: Active lengths agree when within this (mm): the DICOM values are written to 0.1 mm or better.
ACTIVE_LENGTH_TOLERANCE_MM = 0.05


@dataclass(frozen=True)
class SourceChoice:
    """The TG-43 data set chosen for a plan's source.

    What :func:`identify_source` returns.

    Parameters
    ----------
    name : str
        The data set's registered name.
    how : str
        How it was chosen (one line, for the terminal and the JSON).
    """

    name: str
    how: str


@dataclass(frozen=True)
class PlanSource:
    """What a brachy RT Plan says of its source (DICOM Source Sequence and the machine).

    A field the plan does not give stays empty (or None). The fields come in three groups: the isotope, the
    source model, the treatment.

    Parameters
    ----------
    isotope_name : str
        Source Isotope Name (300A,0226).
    half_life_days : float or None
        Source Isotope Half Life (300A,0228), days.
    model_id : str
        Source Model ID (300A,021B).
    manufacturer : str
        Source Manufacturer (300A,0216).
    active_length_mm : float or None
        Active Source Length (300A,021E), mm.
    treatment_type : str
        Brachy Treatment Type (300A,0202): ``HDR``, ``PDR``, ``LDR`` or other.
    machine_name : str
        Treatment Machine Name (300A,00B2).
    """

    isotope_name: str = ""
    half_life_days: float | None = None
    model_id: str = ""
    manufacturer: str = ""
    active_length_mm: float | None = None
    treatment_type: str = ""
    machine_name: str = ""


def recognise_source(sources: Mapping[str, SourceData], *labels: str) -> str | None:
    """Return the name of the data set whose alias occurs in one of ``labels``.

    Parameters
    ----------
    sources : Mapping of str to SourceData
        The registered data sets by name, in order of preference.
    *labels : str
        DICOM strings (Source Isotope Name, Source Model ID, Treatment Machine Name). They and the aliases are
        compared without case, spaces, dashes, underscores or dots.

    Returns
    -------
    str or None
        The first data set with a matching alias; None when no alias matches.
    """
    norm = [normalise_label(x) for x in labels if x]
    for name, data in sources.items():
        if any(alias in text for alias in data.aliases for text in norm):
            return name
    return None


def plan_isotope(isotope_name: str, half_life_days: float | None) -> str | None:
    """Return the isotope of a plan's source: from Source Isotope Name when it names one, else from the half-life.

    Parameters
    ----------
    isotope_name : str
        Source Isotope Name (may be empty).
    half_life_days : float or None
        Source Isotope Half Life, days.

    Returns
    -------
    str or None
        e.g. ``"Ir-192"``; None when neither tells (a half-life within 2 % of a known isotope's counts).
    """
    m = _ISOTOPE_RE.search(isotope_name or "")
    if m:
        symbol = m.group(1).capitalize() if len(m.group(1)) > 1 else m.group(1).upper()
        return f"{symbol}-{m.group(2)}"
    if half_life_days:
        for iso, t in ISOTOPE_HALF_LIVES_DAYS:
            if abs(half_life_days / t - 1.0) <= 0.02:
                return iso
    return None


def _conflicts(d: SourceData, isotope: str | None, plan: PlanSource) -> list[str]:
    """Return what in the plan contradicts data set ``d`` (isotope, treatment type, active length)."""
    out = []
    if isotope and d.isotope != isotope:
        out.append(f"isotope {isotope} vs {d.isotope}")
    if plan.treatment_type in ("HDR", "PDR", "LDR") and d.kind != plan.treatment_type:
        out.append(f"treatment type {plan.treatment_type} vs {d.kind}")
    length = plan.active_length_mm
    if length and abs(length - 10 * d.active_length_cm) > ACTIVE_LENGTH_TOLERANCE_MM:
        out.append(f"active length {length:g} mm vs {10 * d.active_length_cm:g} mm")
    return out


def identify_source(sources: Mapping[str, SourceData], plan: PlanSource) -> SourceChoice:
    """Choose the registered TG-43 data set of a plan's source.

    First by name: a data set whose alias occurs in the Source Model ID, Source Isotope Name, manufacturer or
    Treatment Machine Name (:func:`recognise_source`), kept when its isotope, kind and active length agree with
    the plan's. Otherwise (an anonymised plan) by inference: the data sets of the plan's isotope (named, or told
    by the half-life), treatment type (HDR, PDR) and active length (within :data:`ACTIVE_LENGTH_TOLERANCE_MM`),
    narrowed by the manufacturer when it names one; chosen when exactly one remains.

    Parameters
    ----------
    sources : Mapping of str to SourceData
        The registered data sets by name, in order of preference.
    plan : PlanSource
        What the plan says of its source.

    Returns
    -------
    SourceChoice
        The data set's name and how it was chosen.

    Raises
    ------
    SourceMatchError
        The isotope has no registered TG-43 data (e.g. Cs-137), the named source contradicts the plan, or no
        or several data sets match (the message lists them and says to pass ``--source``).
    """
    isotope = plan_isotope(plan.isotope_name, plan.half_life_days)
    if isotope is not None and not any(d.isotope == isotope for d in sources.values()):
        raise SourceMatchError(f"no TG-43 data is registered for {isotope} (registered: "
                               f"{', '.join(sorted({d.isotope for d in sources.values()}))}); this plan cannot be "
                               "checked with reachplan")
    named = recognise_source(sources, plan.model_id, plan.isotope_name, plan.manufacturer, plan.machine_name)
    if named is not None:
        bad = _conflicts(sources[named], isotope, plan)
        if bad:
            raise SourceMatchError(f"the plan names the source {named}, but its {'; '.join(bad)}; pass --source "
                                   "NAME for the data set that matches")
        return SourceChoice(named, f"{named}: named in the plan")
    fits = [n for n, d in sources.items() if not _conflicts(d, isotope, plan)]
    manufacturer = plan.manufacturer
    maker = normalise_label(manufacturer.split()[0]) if manufacturer.strip() else ""
    by_maker = [n for n in fits if maker and len(maker) >= 3 and maker in normalise_label(sources[n].title)]
    if by_maker:
        fits = by_maker
    length = plan.active_length_mm
    told = ", ".join(x for x in (isotope or "", plan.treatment_type, f"{length:g} mm active" if length else "",
                                 f"manufacturer {manufacturer}" if by_maker else "") if x)
    if len(fits) == 1:
        return SourceChoice(fits[0], f"{fits[0]}: inferred from {told} (the only registered source that fits)")
    if not fits:
        raise SourceMatchError(f"no registered TG-43 source fits the plan's source ({told}); pass --source NAME "
                               "(see `reachplan plugins`)")
    raise SourceMatchError(f"the plan's source ({told}) fits {len(fits)} registered sources ({', '.join(fits)}); "
                           "pass --source NAME")
