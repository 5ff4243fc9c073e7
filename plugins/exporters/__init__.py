"""Exporters of a plan (plugins of kind ``exporters``, entry-point group ``reachplan.exporters``).

The planner fills one :class:`~reachplan.plugins.exporters.base.ExportPlan` and hands it to an exporter:

>>> from reachplan.plugins import registry                          # doctest: +SKIP
>>> files = registry.get("exporters", "dicom_rt").export(plan, out_dir)  # doctest: +SKIP

Built-ins: ``dicom_rt`` (:mod:`reachplan.plugins.exporters.dicom_rt`: RT Plan + RT Structure Set + RT Dose),
``device_json`` and ``device_csv`` (:mod:`reachplan.plugins.exporters.device`: stylet instructions per needle). The
types and the Protocol are in :mod:`reachplan.plugins.exporters.base`, re-exported here.
"""

from __future__ import annotations

from reachplan.plugins.exporters.base import (
    GAMMAMED_PLUS_HDR,
    Afterloader,
    ExportedFile,
    ExportedFiles,
    Exporter,
    ExportError,
    ExportOptions,
    ExportPlan,
    NeedleExport,
    PlannedDose,
    ReferencePoint,
    SourceSpec,
    check_exporter,
)

__all__ = [
    "GAMMAMED_PLUS_HDR",
    "Afterloader",
    "ExportError",
    "ExportOptions",
    "ExportPlan",
    "ExportedFile",
    "ExportedFiles",
    "Exporter",
    "NeedleExport",
    "PlannedDose",
    "ReferencePoint",
    "SourceSpec",
    "check_exporter",
]
