"""ROI numbers of the input structure set in the DICOM RT export: Oncentra/Vitesse numbers from 0."""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from pathlib import Path

import pydicom
import pytest

from reachplan.plugins.exporters.base import ExportError, ExportPlan
from reachplan.plugins.exporters.dicom_rt import export_plan


def _renumbered(plan: ExportPlan, numbers: list[int]) -> ExportPlan:
    assert plan.structure_set is not None
    rois = tuple(dataclasses.replace(r, number=n) for r, n in zip(plan.structure_set.rois, numbers, strict=True))
    return dataclasses.replace(plan, structure_set=dataclasses.replace(plan.structure_set, rois=rois))


def test_roi_numbers_from_zero_are_kept_and_channels_linked(make_plan: Callable[..., ExportPlan], tmp_path: Path,
                                                            dciodvfy: Callable[[Path], list[str]]) -> None:
    plan = _renumbered(make_plan(), [0, 1, 2])
    out = export_plan(plan, tmp_path)
    rs, rp = pydicom.dcmread(out.path("rtstruct")), pydicom.dcmread(out.path("rtplan"))
    names = {int(r.ROINumber): r.ROIName for r in rs.StructureSetROISequence}
    assert {n: names[n] for n in (0, 1, 2)} == {0: "Bladder", 1: "Rectum", 2: "HR-CTV"}
    assert {int(c.ReferencedROINumber) for c in rs.ROIContourSequence} == set(names)
    channels = rp.ApplicationSetupSequence[0].ChannelSequence
    assert [names[int(c.ReferencedROINumber)] for c in channels] == [f"Needle {n.hole_id}" for n in plan.needles]
    lines = dciodvfy(out.path("rtstruct"))
    assert not [line for line in lines if line.startswith("Error")], lines


def test_duplicate_or_negative_roi_numbers_are_refused(make_plan: Callable[..., ExportPlan], tmp_path: Path) -> None:
    for numbers in ([0, 0, 2], [-1, 1, 2]):
        with pytest.raises(ExportError, match="duplicate or negative"):
            export_plan(_renumbered(make_plan(), numbers), tmp_path / str(numbers[0]))
