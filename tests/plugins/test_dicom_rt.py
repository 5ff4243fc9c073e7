"""DICOM RT export: validator-clean files, an independent reader, identity, file safety."""

from __future__ import annotations

import itertools
import os
import warnings
from collections.abc import Callable
from dataclasses import dataclass, replace
from decimal import Decimal
from pathlib import Path

import numpy as np
import pydicom
import pytest
from pydicom.uid import UID

from reachplan.plugins.exporters.base import ExportError, ExportOptions, ExportPlan, SourceSpec, check_exporter
from reachplan.plugins.exporters.dicom_rt import EXPORTER, export_plan

# --- an independent reader: plain pydicom following PS3.3 (not reachplan's readers) ---------------------


@dataclass
class ReadChannel:
    number: int
    applicator_id: str
    roi_name: str
    path_tip_first: np.ndarray  # (n, 3) mm
    positions: np.ndarray  # (m, 3) mm, in control-point order
    relative_mm: np.ndarray  # (m,)
    times: list[Decimal]  # (m,) s


def read_independently(rp_path: Path, rs_path: Path) -> list[ReadChannel]:
    """Channels of a brachy RT Plan with their BRACHY_CHANNEL contours, by PS3.3 C.8.8.15 / C.8.8.5-8."""
    rp, rs = pydicom.dcmread(rp_path), pydicom.dcmread(rs_path)
    assert rp.SOPClassUID == "1.2.840.10008.5.1.4.1.1.481.5" and rp.Modality == "RTPLAN"
    assert rs.SOPClassUID == "1.2.840.10008.5.1.4.1.1.481.3" and rs.Modality == "RTSTRUCT"
    assert rp.ReferencedStructureSetSequence[0].ReferencedSOPInstanceUID == rs.SOPInstanceUID
    assert rp.ReferencedStructureSetSequence[0].ReferencedSOPClassUID == rs.SOPClassUID
    names = {int(r.ROINumber): str(r.ROIName) for r in rs.StructureSetROISequence}
    kinds = {int(o.ReferencedROINumber): str(o.RTROIInterpretedType) for o in rs.RTROIObservationsSequence}
    contours = {int(c.ReferencedROINumber): c for c in rs.ROIContourSequence}
    for r in rs.StructureSetROISequence:
        assert r.ReferencedFrameOfReferenceUID == rp.FrameOfReferenceUID
    out = []
    for ch in rp.ApplicationSetupSequence[0].ChannelSequence:
        roi = int(ch.ReferencedROINumber)
        assert kinds[roi] == "BRACHY_CHANNEL"
        (contour,) = contours[roi].ContourSequence
        assert contour.ContourGeometricType == "OPEN_NONPLANAR"
        path = np.array(contour.ContourData, dtype=float).reshape(-1, 3)
        assert len(path) == int(contour.NumberOfContourPoints)
        cps = ch.BrachyControlPointSequence
        assert len(cps) == int(ch.NumberOfControlPoints) and len(cps) % 2 == 0
        final, total = Decimal(str(ch.FinalCumulativeTimeWeight)), Decimal(str(ch.ChannelTotalTime))
        weights = [Decimal(str(cp.CumulativeTimeWeight)) for cp in cps]
        assert weights[0] == 0 and weights[-1] == final and all(b >= a for a, b in itertools.pairwise(weights))
        positions, rel, times = [], [], []
        for a, b in zip(cps[::2], cps[1::2], strict=True):
            assert a.ControlPoint3DPosition == b.ControlPoint3DPosition
            assert a.ControlPointRelativePosition == b.ControlPointRelativePosition
            positions.append([float(x) for x in a.ControlPoint3DPosition])
            rel.append(float(a.ControlPointRelativePosition))
            dw = Decimal(str(b.CumulativeTimeWeight)) - Decimal(str(a.CumulativeTimeWeight))
            times.append(total * dw / final if final else Decimal(0))
        for a, b in zip(cps[1::2][:-1], cps[2::2], strict=True):  # between dwells the source moves: no time passes
            assert a.CumulativeTimeWeight == b.CumulativeTimeWeight
        assert int(ch.ReferencedSourceNumber) in {int(s.SourceNumber) for s in rp.SourceSequence}
        out.append(ReadChannel(int(ch.ChannelNumber), str(ch.get("SourceApplicatorID", "")), names[roi], path,
                               np.array(positions), np.array(rel), times))
    return out


def arc_from_tip(path_tip_first: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Arc distance from the first contour point of each point's nearest path vertex-interpolated foot."""
    seg = np.diff(path_tip_first, axis=0)
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(seg, axis=1))])
    fine = np.linspace(0.0, s[-1], 20001)
    dense = np.column_stack([np.interp(fine, s, path_tip_first[:, k]) for k in range(3)])
    nearest = np.argmin(np.linalg.norm(points[:, None, :] - dense[None], axis=2), axis=1)
    return fine[nearest]


# --- tests -------------------------------------------------------------------------------------------------


def _dciodvfy_clean(run: Callable[[Path], list[str]], path: Path, iod: str) -> None:
    lines = run(path)
    assert iod in lines, f"dciodvfy did not recognise the IOD: {lines}"
    errors = [line for line in lines if line.startswith("Error")]
    assert not errors, "\n".join(errors)


def test_dciodvfy_reports_no_errors(make_plan: Callable[..., ExportPlan], tmp_path: Path,
                                    dciodvfy: Callable[[Path], list[str]]) -> None:
    out = export_plan(make_plan(), tmp_path)
    _dciodvfy_clean(dciodvfy, out.path("rtplan"), "RTPlan")
    _dciodvfy_clean(dciodvfy, out.path("rtstruct"), "RTStructureSet")
    # and with generated placeholders (no input identity, no organs)
    out2 = export_plan(make_plan(identity=False, structure_set=None), tmp_path / "anon")
    _dciodvfy_clean(dciodvfy, out2.path("rtplan"), "RTPlan")
    _dciodvfy_clean(dciodvfy, out2.path("rtstruct"), "RTStructureSet")


def test_dciodvfy_catches_a_broken_plan(make_plan: Callable[..., ExportPlan], tmp_path: Path,
                                        dciodvfy: Callable[[Path], list[str]]) -> None:
    """The validator check can fail: remove a type 1 attribute and it must report an error."""
    rp_path = export_plan(make_plan(), tmp_path).path("rtplan")
    ds = pydicom.dcmread(rp_path)
    del ds.SourceSequence[0].SourceIsotopeHalfLife
    ds.save_as(tmp_path / "broken.dcm")
    lines = dciodvfy(tmp_path / "broken.dcm")
    assert any(line.startswith("Error") and "SourceIsotopeHalfLife" in line for line in lines)


def test_independent_reader_gets_channels_paths_and_times(make_plan: Callable[..., ExportPlan],
                                                           tmp_path: Path) -> None:
    plan = make_plan()
    out = export_plan(plan, tmp_path)
    channels = read_independently(out.path("rtplan"), out.path("rtstruct"))
    assert [c.applicator_id for c in channels] == [n.hole_id for n in plan.needles]
    assert [c.number for c in channels] == [1, 2, 3]
    for ch, needle in zip(channels, plan.needles, strict=True):
        assert ch.roi_name == f"Needle {needle.hole_id}"
        # path: written tip first, same points within 0.01 mm
        np.testing.assert_allclose(ch.path_tip_first[::-1], needle.path_mm, atol=0.01, rtol=0)
        # dwells: same set (written tip first), positions within 0.01 mm, times exact
        expected = {tuple(np.round(p, 2)): Decimal(str(t)) for p, t in zip(needle.dwell_positions_mm,
                                                                              needle.dwell_times_s, strict=True)}
        got = {tuple(np.round(p, 2)): t for p, t in zip(ch.positions, ch.times, strict=True)}
        assert got == expected
        # relative position = arc distance from the tip along the channel contour, tip-first order
        np.testing.assert_allclose(ch.relative_mm, arc_from_tip(ch.path_tip_first, ch.positions), atol=0.02)
        assert np.all(np.diff(ch.relative_mm) > 0)


def test_plan_and_structure_set_metadata(make_plan: Callable[..., ExportPlan], tmp_path: Path) -> None:
    plan = make_plan()
    out = export_plan(plan, tmp_path)
    rp, rs = pydicom.dcmread(out.path("rtplan")), pydicom.dcmread(out.path("rtstruct"))
    assert plan.volume is not None and plan.structure_set is not None
    for ds in (rp, rs):
        assert ds.PatientID == "P-0042" and str(ds.PatientName) == "Doe^Jane"
        assert ds.StudyInstanceUID == plan.volume.patient_study.study_instance_uid
        assert ds.FrameOfReferenceUID == plan.volume.frame_of_reference_uid
        assert UID(ds.SOPInstanceUID).is_valid and UID(ds.SeriesInstanceUID).is_valid
        assert ds.file_meta.MediaStorageSOPInstanceUID == ds.SOPInstanceUID
        assert ds.ApprovalStatus == "UNAPPROVED"
    assert len({rp.SOPInstanceUID, rs.SOPInstanceUID, rp.SeriesInstanceUID, rs.SeriesInstanceUID,
                plan.structure_set.sop_instance_uid, plan.volume.series_instance_uid}) == 6
    assert rs.ReferencedFrameOfReferenceSequence[0].FrameOfReferenceUID == plan.volume.frame_of_reference_uid
    assert (rp.BrachyTreatmentTechnique, rp.BrachyTreatmentType, rp.RTPlanGeometry) == ("INTERSTITIAL", "HDR",
                                                                                      "PATIENT")
    (src,) = rp.SourceSequence
    assert (src.SourceIsotopeName, float(src.SourceIsotopeHalfLife), src.SourceType) == ("Ir-192", 73.83, "LINE")
    assert float(src.ReferenceAirKermaRate) == 40700.0 and float(src.ActiveSourceLength) == 3.5
    assert (src.SourceStrengthReferenceDate, src.SourceStrengthReferenceTime) == ("20261101", "080000")
    assert "GammaMed Plus HDR" in src.SourceDescription
    setup = rp.ApplicationSetupSequence[0]
    total_s = sum(float(t) for n in plan.needles for t in n.dwell_times_s)
    assert float(setup.TotalReferenceAirKerma) == pytest.approx(40700.0 * total_s / 3600.0, rel=1e-9)
    for ch, needle in zip(setup.ChannelSequence, plan.needles, strict=True):
        assert float(ch.ChannelEffectiveLength) == 1300.0
        assert Decimal(str(ch.ChannelTotalTime)) == sum(Decimal(str(t)) for t in needle.dwell_times_s)
        assert ch.FinalCumulativeTimeWeight == ch.ChannelTotalTime
        # the afterloader's length, as BrachyVision and Vitesse write it (not the in-tissue depth)
        assert float(ch.SourceApplicatorLength) == float(ch.ChannelLength) == 1300.0
    assert (rp.RTPlanDate, rp.RTPlanTime) == ("20261123", "093000")


def test_organs_carried_over_unchanged(make_plan: Callable[..., ExportPlan], tmp_path: Path) -> None:
    plan = make_plan()
    assert plan.structure_set is not None
    rs = pydicom.dcmread(export_plan(plan, tmp_path).path("rtstruct"))
    names = {int(r.ROINumber): r.ROIName for r in rs.StructureSetROISequence}
    kinds = {int(o.ReferencedROINumber): o.RTROIInterpretedType for o in rs.RTROIObservationsSequence}
    contours = {int(c.ReferencedROINumber): c for c in rs.ROIContourSequence}
    for roi in plan.structure_set.rois:
        assert names[roi.number] == roi.name and kinds[roi.number] == roi.interpreted_type
        got = [np.array(c.ContourData, dtype=float).reshape(-1, 3) for c in contours[roi.number].ContourSequence]
        assert len(got) == len(roi.contours)
        for g, c in zip(got, roi.contours, strict=True):
            np.testing.assert_allclose(g, c.points_mm, atol=1e-4, rtol=0)
        assert [c.ContourGeometricType for c in contours[roi.number].ContourSequence] == [
            c.geometric_type for c in roi.contours]
    # channel ROIs numbered after the highest input ROI (4)
    assert sorted(n for n, k in kinds.items() if k == "BRACHY_CHANNEL") == [5, 6, 7]
    assert list(contours[1].ROIDisplayColor) == [255, 0, 0]


def test_mirrors_the_brachyvision_channel_layout(make_plan: Callable[..., ExportPlan], tmp_path: Path,
                                                 reference_file: Callable[[str], Path]) -> None:
    """Every attribute BrachyVision writes in a Channel and a Source item is written by us too."""
    ref = pydicom.dcmread(reference_file("tps_examples/hdr/RP.HDR.dcm"))
    ours = pydicom.dcmread(export_plan(make_plan(), tmp_path).path("rtplan"))

    def keys(item: pydicom.Dataset) -> set[str]:
        return {e.keyword for e in item if e.keyword}

    ref_ch = ref.ApplicationSetupSequence[0].ChannelSequence[0]
    our_ch = ours.ApplicationSetupSequence[0].ChannelSequence[0]
    assert keys(ref_ch) <= keys(our_ch)
    assert keys(ref_ch.BrachyControlPointSequence[0]) - {"BrachyReferencedDoseReferenceSequence"} <= keys(
        our_ch.BrachyControlPointSequence[0])
    assert keys(ref.SourceSequence[0]) <= keys(ours.SourceSequence[0])
    assert "ChannelEffectiveLength" in keys(our_ch)
    # the independent reader also reads the real BrachyVision export; there too the channel ROI is written tip
    # first, dwells are ordered from the tip, and Control Point Relative Position is the arc distance from the
    # tip along the channel ROI (to 0.006 mm): the convention we write
    for ch in read_independently(reference_file("tps_examples/hdr/RP.HDR.dcm"),
                                 reference_file("tps_examples/hdr/RS.HDR.dcm")):
        assert len(ch.positions) >= 5 and sum(ch.times) > 0
        np.testing.assert_allclose(ch.relative_mm, arc_from_tip(ch.path_tip_first, ch.positions), atol=0.02)
        assert np.all(np.diff(ch.relative_mm) > 0)


def test_placeholders_when_no_input_identity(make_plan: Callable[..., ExportPlan], tmp_path: Path) -> None:
    assert not export_plan(make_plan(), tmp_path / "full").notes
    out = export_plan(make_plan(identity=False), tmp_path)
    (note,) = out.notes
    assert "placeholders" in note and "Study Instance UID" in note and "Frame of Reference UID" in note
    rp, rs = pydicom.dcmread(out.path("rtplan")), pydicom.dcmread(out.path("rtstruct"))
    assert rp.StudyInstanceUID == rs.StudyInstanceUID and UID(rp.StudyInstanceUID).is_valid
    assert rp.FrameOfReferenceUID == rs.FrameOfReferenceUID and UID(rp.FrameOfReferenceUID).is_valid
    assert rp.PatientID == ""


def test_mismatched_input_identity_is_refused(make_plan: Callable[..., ExportPlan], tmp_path: Path) -> None:
    plan = make_plan()
    other = make_plan()
    mixed = ExportPlan(plan.label, plan.needles, plan.source, plan.structure_set, other.volume)
    with pytest.raises(ExportError, match="Frame of Reference"):
        export_plan(mixed, tmp_path)
    assert not list(tmp_path.iterdir())


def test_never_overwrites(make_plan: Callable[..., ExportPlan], tmp_path: Path) -> None:
    plan = make_plan()
    out = export_plan(plan, tmp_path)
    before = out.path("rtplan").read_bytes()
    with pytest.raises(ExportError, match="exists"):
        export_plan(plan, tmp_path)
    assert out.path("rtplan").read_bytes() == before
    export_plan(plan, tmp_path, ExportOptions(overwrite=True))
    assert out.path("rtplan").read_bytes() != before  # new UIDs
    # an input file of the plan is never written, even with overwrite
    guarded = ExportPlan(plan.label, plan.needles, plan.source, plan.structure_set, plan.volume,
                         input_paths=(out.path("rtstruct"),))
    with pytest.raises(ExportError, match="input file"):
        export_plan(guarded, tmp_path, ExportOptions(overwrite=True))
    # nor into an input series folder
    series = tmp_path / "ct"
    series.mkdir()
    in_folder = ExportPlan(plan.label, plan.needles, plan.source, plan.structure_set, plan.volume,
                           input_paths=(series,))
    with pytest.raises(ExportError, match="input folder"):
        export_plan(in_folder, series)
    assert not list(series.iterdir())
    # nor a file that holds the input structure set, even when the caller forgot to list it
    assert plan.structure_set is not None
    ds = pydicom.dcmread(out.path("rtstruct"))
    ds.SOPInstanceUID = plan.structure_set.sop_instance_uid
    ds.save_as(out.path("rtstruct"))
    with pytest.raises(ExportError, match="input structure set"):
        export_plan(plan, tmp_path, ExportOptions(overwrite=True))
    assert not [p for p in os.listdir(tmp_path) if p.startswith(".")]  # no temporary files left


def test_safe_file_names(make_plan: Callable[..., ExportPlan], tmp_path: Path) -> None:
    plan = make_plan(label="../Pl an/é*1")
    out = export_plan(plan, tmp_path)
    for f in out.files:
        assert f.path.parent == tmp_path and "Doe" not in f.path.name
        assert all(c.isalnum() or c in "._-" for c in f.path.name)
    named = export_plan(plan, tmp_path / "n", ExportOptions(include_patient_name=True))
    assert all(f.path.name.split("_", 1)[1].startswith("Doe_Jane") for f in named.files)


def test_dwell_times_rounded_to_resolution_and_noted(make_plan: Callable[..., ExportPlan], tmp_path: Path) -> None:
    plan = make_plan()
    n0 = plan.needles[0]
    # issue 27: a planned 0.187 s is written as 0.187 s (not 0.2 s): dwell times are kept to 1 ms by default
    ms = type(n0)(n0.hole_id, n0.path_mm, n0.dwell_positions_mm, n0.dwell_times_s + 0.187)
    out = export_plan(make_plan(needles=(ms,)), tmp_path / "ms")
    assert not any("rounded" in n for n in out.notes)
    (ch,) = read_independently(out.path("rtplan"), out.path("rtstruct"))
    assert sorted(ch.times) == sorted(Decimal(str(t)) + Decimal("0.187") for t in n0.dwell_times_s)
    odd = type(n0)(n0.hole_id, n0.path_mm, n0.dwell_positions_mm, n0.dwell_times_s + 0.04)
    out = export_plan(make_plan(needles=(odd,)), tmp_path, ExportOptions(time_resolution_s=0.1))
    assert any("rounded to 0.1 s" in n for n in out.notes)
    (ch,) = read_independently(out.path("rtplan"), out.path("rtstruct"))
    assert sorted(ch.times) == sorted(Decimal(str(t)) for t in n0.dwell_times_s)
    fine = type(n0)(n0.hole_id, n0.path_mm, n0.dwell_positions_mm, n0.dwell_times_s + 0.18734)
    out = export_plan(make_plan(needles=(fine,)), tmp_path / "fine")
    assert any("rounded to 0.001 s (largest change 0.00034 s)" in n for n in out.notes)


def test_exporter_plugin_passes_its_protocol_check(make_plan: Callable[..., ExportPlan], tmp_path: Path) -> None:
    check_exporter(EXPORTER)
    out = EXPORTER.export(make_plan(), tmp_path)
    assert {f.role for f in out.files} == {"rtplan", "rtstruct"}
    with pytest.raises(TypeError):
        check_exporter(object())


def test_round_trip_through_reachplan_readers(make_plan: Callable[..., ExportPlan], tmp_path: Path) -> None:
    from reachplan.imaging.errors import OutsideImageWarning
    from reachplan.imaging.rtplan import read_rtplan
    from reachplan.imaging.rtstruct import read_rtstruct
    from reachplan.planner.lookup import all_sources
    from reachplan.plugins.sources.identify import recognise_source

    plan = make_plan()
    out = export_plan(plan, tmp_path)
    with warnings.catch_warnings():  # the fixture's volume is a 2 x 2 x 2 mm stand-in that carries only the UIDs
        warnings.simplefilter("ignore", OutsideImageWarning)
        ss = read_rtstruct(out.path("rtstruct"), volume=plan.volume)
    rp = read_rtplan(out.path("rtplan"))
    assert not rp.quirks
    assert (rp.is_brachy, rp.treatment_type, rp.technique) == (True, "HDR", "INTERSTITIAL")
    assert rp.frame_of_reference_uid == ss.frame_of_reference_uid == plan.structure_set.frame_of_reference_uid
    (src,) = rp.sources
    assert (src.isotope_name, src.air_kerma_rate_u, src.half_life_days, src.active_length_mm) == (
        "Ir-192", 40700.0, 73.83, 3.5)
    assert recognise_source(all_sources(), *src.labels(), rp.machine_name) == plan.source.name == "gammamed_plus_hdr"
    (setup,) = rp.setups
    assert [c.applicator_id for c in setup.channels] == [n.hole_id for n in plan.needles]
    for ch, needle in zip(setup.channels, plan.needles, strict=True):
        roi = next(r for r in ss.rois if r.number == ch.roi_number)  # channel -> ROI link intact
        assert roi.interpreted_type == "BRACHY_CHANNEL" and roi.name == f"Needle {needle.hole_id}"
        (contour,) = roi.contours
        assert contour.geometric_type == "OPEN_NONPLANAR"
        np.testing.assert_allclose(contour.points_mm[::-1], needle.path_mm, atol=0.01, rtol=0)
        order = np.argsort(needle.dwell_distance_from_tip_mm)  # written tip first
        np.testing.assert_allclose(ch.dwell_positions_mm, needle.dwell_positions_mm[order], atol=0.01, rtol=0)
        # the file holds the exact decimals (see the independent reader); imaging.rtplan subtracts cumulative
        # weights in binary floating point, which costs up to a few 1e-15 s
        np.testing.assert_allclose(ch.dwell_times_s, needle.dwell_times_s[order], atol=1e-9, rtol=0)
        np.testing.assert_allclose(ch.dwell_relative_mm, needle.dwell_distance_from_tip_mm[order], atol=0.01)
    organs = {r.name: r for r in ss.rois if r.interpreted_type != "BRACHY_CHANNEL"}
    assert plan.structure_set is not None
    assert set(organs) == {r.name for r in plan.structure_set.rois}


def test_non_ascii_patient_name(make_plan: Callable[..., ExportPlan], tmp_path: Path,
                                dciodvfy: Callable[[Path], list[str]]) -> None:

    plan = make_plan()
    v = plan.volume
    assert v is not None
    zoe = replace(v.patient_study, patient_name="Müller^Zoë")
    vol = replace(v, patient_study=zoe)
    ss = plan.structure_set
    assert ss is not None
    ss2 = type(ss)(ss.rois, ss.frame_of_reference_uid, sop_instance_uid=ss.sop_instance_uid, patient_study=zoe)
    out = export_plan(make_plan(volume=vol, structure_set=ss2), tmp_path, ExportOptions(include_patient_name=True))
    assert str(pydicom.dcmread(out.path("rtplan")).PatientName) == "Müller^Zoë"
    assert out.path("rtplan").name == "RP_Muller_Zoe_PrePlan1.dcm"
    _dciodvfy_clean(dciodvfy, out.path("rtplan"), "RTPlan")


def test_needle_validation() -> None:
    from reachplan.plugins.exporters.base import NeedleExport

    path = np.column_stack([np.zeros(3), np.zeros(3), [0.0, 50.0, 100.0]])
    with pytest.raises(ValueError, match="apart"):
        NeedleExport("A1", path, np.array([[0.0, 0.0, 50.0], [0.0, 0.0, 50.05]]), [1.0, 2.0])
    with pytest.raises(ValueError, match="one dwell time per dwell"):
        NeedleExport("A1", path, path[1:2], [1.0, 2.0])
    with pytest.raises(ValueError, match="two distinct points"):
        NeedleExport("A1", path[:1], path[:1], [1.0])
    n = NeedleExport("A1", path, path[1:2], [1.0])
    with pytest.raises(ValueError, match="channel_effective_length_mm"):
        ExportPlan("P", (n,), make_source(), channel_effective_length_mm=90.0)
    with pytest.raises(ValueError, match="unique"):
        ExportPlan("P", (n, n), make_source())
    with pytest.raises(ValueError, match="only HDR"):
        ExportPlan("P", (n,), make_source(treatment_type="PDR"))
    with pytest.raises(ValueError, match="half-life"):
        make_source(isotope="Yb-169")


def make_source(**kw: object) -> SourceSpec:
    from datetime import datetime

    return SourceSpec(**{"name": "x", "air_kerma_rate_u": 40000.0, "reference_datetime": datetime(2026, 1, 1),
                         **kw})  # type: ignore[arg-type]


def test_uid_prefix(make_plan: Callable[..., ExportPlan], tmp_path: Path) -> None:
    out = export_plan(make_plan(identity=False), tmp_path, ExportOptions(uid_prefix="1.2.3.4."))
    for role in ("rtplan", "rtstruct"):
        ds = pydicom.dcmread(out.path(role))
        for uid in (ds.SOPInstanceUID, ds.SeriesInstanceUID, ds.StudyInstanceUID, ds.FrameOfReferenceUID):
            assert uid.startswith("1.2.3.4.") and UID(uid).is_valid
    for bad in ("1.2.3", "1.02.3.", "abc."):
        with pytest.raises(ValueError, match="uid_prefix"):
            ExportOptions(uid_prefix=bad)


def test_real_eclipse_structure_set_carried_over(reference_file: Callable[[str], Path], tmp_path: Path,
                                                 dciodvfy: Callable[[Path], list[str]]) -> None:
    """Organs read by imaging.rtstruct from a real Eclipse export (16 ROIs, some empty, 47848-point BODY)."""
    from datetime import datetime

    from reachplan.imaging.rtstruct import read_rtstruct
    from reachplan.plugins.exporters.base import NeedleExport
    from reachplan.plugins.sources import gammamed_plus_hdr

    ss = read_rtstruct(reference_file("tps_examples/eclipse_prostate_phantom/RS.dcm"))
    c = np.concatenate([k.points_mm for k in ss.get("PTV").contours]).mean(axis=0)
    z = np.array([0.0, 0.0, 1.0])
    needle = NeedleExport("A1", np.array([c - 60 * z, c + 10 * z]), np.array([c - 5 * z, c, c + 5 * z]),
                          [5.0, 6.0, 7.0])
    src = SourceSpec.from_source_data(gammamed_plus_hdr(), 40700.0, datetime(2026, 1, 1))
    out = export_plan(ExportPlan("Rando", (needle,), src, ss), tmp_path)
    assert not out.notes  # the structure set's identity is used
    _dciodvfy_clean(dciodvfy, out.path("rtstruct"), "RTStructureSet")
    _dciodvfy_clean(dciodvfy, out.path("rtplan"), "RTPlan")
    back = read_rtstruct(out.path("rtstruct"))
    assert (back.frame_of_reference_uid, back.patient_study.study_instance_uid, back.patient_study.patient_id) == (
        ss.frame_of_reference_uid, ss.patient_study.study_instance_uid, ss.patient_study.patient_id)
    assert [r.name for r in back.rois] == [r.name for r in ss.rois] + ["Needle A1"]
    body_in, body_out = ss.get("BODY"), back.get("BODY")
    assert sum(len(k.points_mm) for k in body_out.contours) == sum(len(k.points_mm) for k in body_in.contours)
    for a, b in zip(body_in.contours, body_out.contours, strict=True):
        np.testing.assert_allclose(b.points_mm, a.points_mm, atol=1e-4, rtol=0)


def test_a_contour_written_twice_is_formatted_once_and_forgotten_with_its_array() -> None:
    import gc

    from reachplan.plugins.exporters import dicom_rt

    points = np.array([[1.23456, -0.00004, 100.0], [2.5, 3.0, -4.125]])
    first = dicom_rt._contour_data(points)
    assert dicom_rt._contour_data(points) is first  # the same structure set in the plan's and each arm's export
    assert first.value == b"1.2346\\0\\100\\2.5\\3\\-4.125 "  # padded to an even length
    copy = points.copy()
    assert dicom_rt._contour_data(copy) is not first and dicom_rt._contour_data(copy).value == first.value
    key = id(points)
    del points
    gc.collect()
    assert key not in dicom_rt._WRITTEN
