"""Applicators as a type: the :class:`Applicator` exchange type, the :class:`ApplicatorKind` Protocol, the builders.

The built-in kinds (tandem, ring, ovoid, cylinder, obturator) are one module each and register through the
``reachplan.applicators`` entry-point group, as a third party's kind does (one file plus its entry point). Code
that is handed no kinds uses :data:`BUILTIN_KINDS`.
"""

from __future__ import annotations

from collections.abc import Mapping
from types import MappingProxyType

from reachplan.plugins.applicators.base import (
    Applicator,
    ApplicatorKind,
    CentrelineKind,
    KindSpec,
    PlanOnlyKind,
    check_applicator_kind,
    plan_centreline,
    principal_chord,
    roi_points,
)
from reachplan.plugins.applicators.build import (
    applicator_from_roi,
    applicators_from_rtplan,
    applicators_from_structures,
    channel_label,
    kind_of_name,
    name_table,
)
from reachplan.plugins.applicators.centreline import roi_centreline
from reachplan.plugins.applicators.cylinder import CYLINDER
from reachplan.plugins.applicators.obturator import OBTURATOR
from reachplan.plugins.applicators.ovoid import OVOID
from reachplan.plugins.applicators.ring import RING
from reachplan.plugins.applicators.tandem import TANDEM

#: The built-in kinds by name (the same objects the ``reachplan.applicators`` entry points name).
BUILTIN_KINDS: Mapping[str, ApplicatorKind] = MappingProxyType(
    {k.name: k for k in (TANDEM, RING, OVOID, CYLINDER, OBTURATOR)})

__all__ = [
    "BUILTIN_KINDS",
    "Applicator",
    "ApplicatorKind",
    "CentrelineKind",
    "KindSpec",
    "PlanOnlyKind",
    "applicator_from_roi",
    "applicators_from_rtplan",
    "applicators_from_structures",
    "channel_label",
    "check_applicator_kind",
    "kind_of_name",
    "name_table",
    "plan_centreline",
    "principal_chord",
    "roi_centreline",
    "roi_points",
]
