"""RT Plan layout of issue 27: the first dwell at its source-tip offset, the dates, both styles valid DICOM."""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from datetime import datetime
from pathlib import Path

import numpy as np
import pydicom
import pytest

from reachplan._arrays import arc_length_mm
from reachplan.plugins.exporters.base import ExportOptions, NeedleExport
from reachplan.plugins.exporters.dicom_rt import export_plan

from .conftest import PlanFactory
from .test_rt_prescription import with_points


@pytest.mark.parametrize("offset_mm", [0.0, 3.5, 6.25])
def test_the_first_dwell_is_written_at_the_source_tip_offset_it_is_given_at(make_plan: PlanFactory, tmp_path: Path,
                                                                           offset_mm: float) -> None:
    """Relative position = arc distance from the channel's end (its tip, the contour's first point), as given."""
    tip = np.array([12.0, -8.0, 40.0])
    axis = np.array([0.0, 0.6, 0.8])  # base to tip
    path = tip - np.outer([80.0, 30.0, 0.0], axis)  # base, a middle point, the tip
    dwells = tip - np.outer(offset_mm + np.arange(4) * 5.0, axis)
    needle = NeedleExport("T1", path, dwells, np.array([2.5, 0.187, 4.0, 1.0]), applicator=True)
    files = export_plan(make_plan(needles=(needle,)), tmp_path)
    rp, rs = pydicom.dcmread(files.path("rtplan")), pydicom.dcmread(files.path("rtstruct"))
    (ch,) = rp.ApplicationSetupSequence[0].ChannelSequence
    cps = ch.BrachyControlPointSequence
    contour = {int(c.ReferencedROINumber): c for c in rs.ROIContourSequence}[int(ch.ReferencedROINumber)]
    line = np.array(contour.ContourSequence[0].ContourData, dtype=float).reshape(-1, 3)
    assert np.allclose(line[0], tip)  # the channel is written tip first
    first = np.array(cps[0].ControlPoint3DPosition, dtype=float)
    assert float(cps[0].ControlPointRelativePosition) == pytest.approx(offset_mm, abs=0.005)
    assert np.linalg.norm(first - line[0]) == pytest.approx(offset_mm, abs=1e-3)
    rel = [float(cp.ControlPointRelativePosition) for cp in cps[::2]]
    assert np.allclose(rel, offset_mm + np.arange(4) * 5.0, atol=0.005)
    assert arc_length_mm(line)[-1] == pytest.approx(80.0)
    # the times as planned, to the millisecond (0.187 s is not 0.2 s)
    weights = [float(cp.CumulativeTimeWeight) for cp in cps]
    assert np.allclose(np.diff(weights)[::2], [2.5, 0.187, 4.0, 1.0], atol=1e-9)


def test_dates_are_the_plans_and_the_strength_is_dated_as_given(make_plan: PlanFactory, tmp_path: Path) -> None:
    """RT Plan Date/Time = the plan's; the source strength is dated as the spec says (the planner: the plan day at
    midnight, as Eclipse dates it), never to the second of export."""
    base = make_plan()
    midnight = datetime(2026, 11, 23)
    plan = dataclasses.replace(base, source=dataclasses.replace(base.source, reference_datetime=midnight))
    rp = pydicom.dcmread(export_plan(plan, tmp_path).path("rtplan"))
    assert (rp.RTPlanDate, rp.RTPlanTime) == ("20261123", "093000")
    src = rp.SourceSequence[0]
    assert (src.SourceStrengthReferenceDate, src.SourceStrengthReferenceTime) == ("20261123", "000000")


@pytest.mark.parametrize("style", ["eclipse", "vitesse"])
def test_both_styles_pass_dciodvfy(make_plan: PlanFactory, tmp_path: Path, style: str,
                                   dciodvfy: Callable[[Path], list[str]]) -> None:
    plan = with_points(make_plan(), specification_point="p mid")
    rp = export_plan(plan, tmp_path, ExportOptions(rtplan_style=style)).path("rtplan")
    lines = dciodvfy(rp)
    assert not [x for x in lines if x.startswith("Error")], lines
    ds = pydicom.dcmread(rp)
    has_tpd = any((0x300A, 0x0026) in d for d in ds.DoseReferenceSequence)
    assert has_tpd == (style == "vitesse")
