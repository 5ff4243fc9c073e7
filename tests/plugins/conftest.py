"""Synthetic plans for the exporter tests (no phantom writer, no reference files)."""

from __future__ import annotations

from collections.abc import Callable
from datetime import datetime

import numpy as np
import pytest
from pydicom.uid import generate_uid

from reachplan.imaging.types import Contour, Grid, PatientStudy, Roi, StructureSet, Volume
from reachplan.plugins.exporters.base import ExportPlan, NeedleExport, SourceSpec
from reachplan.plugins.sources import gammamed_plus_hdr


def curved_needle(hole_id: str, x0_mm: float, bend_mm: float, n_dwells: int = 10) -> NeedleExport:
    """A 120 mm needle along +z from z = -100 mm, bending by ``bend_mm`` in x at the tip (parabola)."""
    s = np.linspace(0.0, 120.0, 41)
    path = np.column_stack([x0_mm + bend_mm * (s / 120.0) ** 2, np.full_like(s, -20.0), -100.0 + s])
    # dwells on the path's vertices from 5 mm below the tip, every 6 mm (vertex spacing 3 mm)
    idx = len(s) - 1 - (np.arange(n_dwells) * 2 + 2)
    times = np.round(np.linspace(3.0, 12.3, n_dwells), 1)
    return NeedleExport(hole_id, path, path[idx], times, design="15ga_20j_tip",
                        schedule=np.array([[0.0, 0.0, 0.0], [40.0, 0.0, 0.0], [80.0, 9.9, 90.0], [110.0, 9.9, 90.0]]))


def organ_rois() -> tuple[Roi, ...]:
    sq = np.array([[0.0, 0.0, 0.0], [10.0, 0.0, 0.0], [10.0, 10.0, 0.0], [0.0, 10.0, 0.0]])
    bladder = Roi(1, "Bladder", tuple(Contour(sq + np.array([0.0, 0.0, z])) for z in (0.0, 2.5, 5.0)),
                  interpreted_type="ORGAN", color=(255, 0, 0))
    ctv = Roi(4, "HR-CTV", (Contour(sq * 2.123456 + [20.0, -5.5, -1.25]),), interpreted_type="CTV")
    rectum = Roi(2, "Rectum", (Contour(sq + np.array([0.0, 30.0, 0.0])),))
    return (bladder, rectum, ctv)


PlanFactory = Callable[..., ExportPlan]


@pytest.fixture
def make_plan() -> PlanFactory:
    """Factory: ``make_plan(identity=True, **overrides)`` -> a 3-needle HDR plan with input CT + structures."""

    def factory(identity: bool = True, **overrides: object) -> ExportPlan:
        for_uid, study = generate_uid(), generate_uid()
        who = PatientStudy("P-0042", "Doe^Jane", study) if identity else PatientStudy()
        ss = StructureSet(organ_rois(), for_uid if identity else "", sop_instance_uid=generate_uid(),
                          patient_study=who)
        vol = Volume(np.zeros((2, 2, 2), np.float32), Grid((2, 2, 2), np.eye(4)), "CT", generate_uid(), for_uid,
                     who) if identity else None
        src = SourceSpec.from_source_data(gammamed_plus_hdr(), 40700.0, datetime(2026, 11, 1, 8, 0),
                                          manufacturer="Varian Medical Systems", active_diameter_mm=0.6)
        kw: dict[str, object] = {
            "label": "PrePlan1",
            "needles": (curved_needle("A1", 0.0, 8.0), curved_needle("B12", 15.0, -12.0, 6),
                        curved_needle("C3", -15.0, 0.0, 4)),
            "source": src, "structure_set": ss, "volume": vol, "plan_datetime": datetime(2026, 11, 23, 9, 30),
        }
        kw.update(overrides)
        return ExportPlan(**kw)  # type: ignore[arg-type]

    return factory
