"""Straight against steered implants over a cohort: needles saved and HR-CTV D90 gained by steering.

Each case contributes one pair of arms (:class:`reachplan.planner.pipeline.ImplantComparison`, or the
``implant`` section of a plan.json). The summary gives the mean of the paired differences with a percentile
bootstrap confidence interval (resampling cases with replacement; seeded, so the same cohort gives the same
interval).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from reachplan.planner.errors import StudyError


@dataclass(frozen=True)
class PairedStat:
    """Mean of a paired difference over the cases and its bootstrap confidence interval (same unit)."""

    mean: float
    low: float
    high: float
    n: int


@dataclass(frozen=True)
class ImplantCohortSummary:
    """Needles saved and D90 gained by steering over a cohort.

    ``needles_saved``: straight-arm needles minus steered-arm needles of each case's chosen implant;
    ``d90_gained_gy``: steered minus straight HR-CTV D90 (EQD2, Gy); ``aims_met_*``: cases whose chosen implant
    meets every aim, per arm.
    """

    needles_saved: PairedStat
    d90_gained_gy: PairedStat
    aims_met_straight: int
    aims_met_steered: int
    n_cases: int


def _bootstrap(values: np.ndarray, level: float, resamples: int, seed: int) -> PairedStat:
    rng = np.random.default_rng(seed)
    idx = rng.integers(0, len(values), size=(resamples, len(values)))
    means = values[idx].mean(axis=1)
    tail = 100.0 * (1.0 - level) / 2.0
    low, high = np.percentile(means, [tail, 100.0 - tail])
    return PairedStat(float(values.mean()), float(low), float(high), len(values))


def summarise_implants(cases: Sequence[Mapping[str, object]], level: float = 0.95, resamples: int = 10_000,
                       seed: int = 0) -> ImplantCohortSummary:
    """Summarise a cohort from each case's plan.json ``implant`` section.

    Each section has ``straight`` and ``steered`` with ``n_needles``, ``hrctv_d90_eqd2_gy`` and ``aims_met``.

    Raises
    ------
    StudyError
        No case, or a case whose arms have no chosen implant.
    """
    if not cases:
        raise StudyError("no case to summarise: give at least one plan.json implant section")
    saved, gained, met = [], [], [0, 0]
    for k, case in enumerate(cases):
        arms = [case.get("straight"), case.get("steered")]
        if not all(isinstance(a, Mapping) and "n_needles" in a for a in arms):
            raise StudyError(f"case {k + 1}: both arms need a chosen implant (n_needles); plan it again")
        straight, steered = arms
        assert isinstance(straight, Mapping) and isinstance(steered, Mapping)
        saved.append(float(straight["n_needles"]) - float(steered["n_needles"]))
        gained.append(float(steered["hrctv_d90_eqd2_gy"]) - float(straight["hrctv_d90_eqd2_gy"]))
        met[0] += bool(straight.get("aims_met"))
        met[1] += bool(steered.get("aims_met"))
    return ImplantCohortSummary(_bootstrap(np.array(saved), level, resamples, seed),
                                _bootstrap(np.array(gained), level, resamples, seed + 1), met[0], met[1], len(cases))
