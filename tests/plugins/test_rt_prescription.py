"""RT Plan prescription: dose references, coefficients, fractions, machine, orientation; image references; RT Dose.

The point-dose check is written as an independent reader would: pydicom and the published consensus tables only
(no reachplan reader, no reachplan TG-43 code), following rtplan_conventions.md §4 and TG-43U1.
"""

from __future__ import annotations

import dataclasses
import itertools
import json
from datetime import datetime
from importlib import resources
from pathlib import Path

import numpy as np
import pydicom
import pytest
from scipy.interpolate import RegularGridInterpolator

from reachplan.imaging.types import Contour, Grid, PatientStudy, Roi, StructureSet, Volume
from reachplan.planner.dose.dwells import dwell_directions, rate_matrix
from reachplan.planner.dose.tg43 import Tg43Kernel
from reachplan.plugins.exporters import base as exporters_base
from reachplan.plugins.exporters.base import Afterloader, ExportPlan, PlannedDose, ReferencePoint
from reachplan.plugins.exporters.dicom_rt import export_plan, planned_point_doses_gy
from reachplan.plugins.exporters.rtdose import read_rtdose_grid
from reachplan.plugins.sources import gammamed_plus_hdr

from .conftest import PlanFactory

# --- an independent TG-43 point-dose checker (pydicom + the consensus table) ------------------------------


def _consensus(name: str) -> dict:
    return json.loads(resources.files("reachplan.plugins.sources").joinpath(f"{name}.json").read_text())


def _tg43_line(table: dict, points: np.ndarray, pos: np.ndarray, axis: np.ndarray, sk: float) -> np.ndarray:
    """Dose rate (cGy/h) at ``points`` (m, 3) mm from one line source at ``pos`` along unit ``axis``."""
    length = float(table["active_length_cm"]) * 10.0  # mm
    lam = float(table["dose_rate_constant_cgy_per_h_per_u"])
    d = points - pos
    r = np.linalg.norm(d, axis=1)
    cos_t = np.clip(d @ axis / r, -1, 1)
    sin_t = np.sqrt(1 - cos_t**2)
    tip, tail = pos + 0.5 * length * axis, pos - 0.5 * length * axis
    a, b = points - tip, points - tail
    beta = np.arccos(np.clip(np.sum(a * b, axis=1) / np.linalg.norm(a, axis=1) / np.linalg.norm(b, axis=1), -1, 1))
    rc, lc = r / 10.0, length / 10.0
    g_geom = np.where(sin_t > 1e-9, beta / (lc * rc * np.maximum(sin_t, 1e-12)), 1.0 / (rc**2 - lc**2 / 4))
    g0 = 2 * np.arctan(lc / 2) / lc
    rg = np.array(table["radial_dose"]["r_cm"])
    gl = np.interp(rc, rg, np.array(table["radial_dose"]["g_l"]))
    fr, ft = np.array(table["anisotropy"]["r_cm"]), np.array(table["anisotropy"]["theta_deg"])
    f = RegularGridInterpolator((ft, fr), np.array(table["anisotropy"]["f"]))
    theta = np.degrees(np.arccos(cos_t))
    fv = f(np.column_stack([theta, np.clip(rc, fr[0], fr[-1])]))
    return sk * lam * g_geom / g0 * gl * fv


def independent_check(rp_path: Path, rs_path: Path, table: dict) -> list[tuple[str, float, float, float]]:
    """Per COORDINATES dose reference: (name, stated Gy per fraction, recomputed Gy per fraction, distance to the
    nearest dwell in mm), reading only the RT Plan and RT Structure Set (rtplan_conventions.md §4, §7)."""
    rp, rs = pydicom.dcmread(rp_path), pydicom.dcmread(rs_path)
    (ref_setup,) = rp.FractionGroupSequence[0].ReferencedBrachyApplicationSetupSequence
    setup_dose = float(ref_setup.BrachyApplicationSetupDose)
    points = {int(d.DoseReferenceNumber): (str(d.DoseReferenceDescription),
                                           np.array(d.DoseReferencePointCoordinates, dtype=float))
              for d in rp.DoseReferenceSequence if d.DoseReferenceStructureType == "COORDINATES"}
    contours = {int(c.ReferencedROINumber): np.array(c.ContourSequence[0].ContourData, dtype=float).reshape(-1, 3)
                for c in rs.ROIContourSequence if "ContourSequence" in c}
    src = rp.SourceSequence[0]
    elapsed = (datetime.strptime(str(rp.RTPlanDate), "%Y%m%d")
               - datetime.strptime(str(src.SourceStrengthReferenceDate), "%Y%m%d")).days
    sk = float(src.ReferenceAirKermaRate) * 2.0 ** (-elapsed / float(src.SourceIsotopeHalfLife))
    stated = dict.fromkeys(points, 0.0)
    ours = dict.fromkeys(points, 0.0)
    nearest = dict.fromkeys(points, np.inf)
    for ch in rp.ApplicationSetupSequence[0].ChannelSequence:
        cps = ch.BrachyControlPointSequence
        for item in cps[-1].BrachyReferencedDoseReferenceSequence:
            if int(item.ReferencedDoseReferenceNumber) in points:
                stated[int(item.ReferencedDoseReferenceNumber)] += float(item.CumulativeDoseReferenceCoefficient) \
                    * setup_dose
        path = contours[int(ch.ReferencedROINumber)]  # tip first
        total, final = float(ch.ChannelTotalTime), float(ch.FinalCumulativeTimeWeight)
        for a, b in zip(cps[::2], cps[1::2], strict=True):
            pos = np.array(a.ControlPoint3DPosition, dtype=float)
            if final <= 0:  # an unused channel (no time): nothing to add
                break
            t = total * (float(b.CumulativeTimeWeight) - float(a.CumulativeTimeWeight)) / final
            if "ControlPointOrientation" in a:
                axis = np.array(a.ControlPointOrientation, dtype=float)
            else:  # from the channel ROI: the nearest segment, toward the tip (its first point)
                seg = np.argmin([np.linalg.norm(pos - (p + q) / 2) for p, q in itertools.pairwise(path)])
                axis = path[seg] - path[seg + 1]
            axis = axis / np.linalg.norm(axis)
            for n, (_, p) in points.items():
                nearest[n] = min(nearest[n], float(np.linalg.norm(p - pos)))
                ours[n] += float(_tg43_line(table, p[None], pos, axis, sk)[0]) * t / 3600.0 / 100.0
    return [(points[n][0], stated[n], ours[n], nearest[n]) for n in points]


# --- plans with reference points ---------------------------------------------------------------------------

POINTS = {"p near": (3.0, -12.0, 5.0), "p mid": (-20.0, -20.0, -10.0), "p far": (40.0, 10.0, 0.0),
          "p axis": (0.0, -20.0, 40.0)}


def with_points(plan: ExportPlan, rx_gy: float = 7.0, fractions: int = 4, **kw: object) -> ExportPlan:
    """``plan`` with the prescription and reference points whose rates come from reachplan's TG-43 kernel."""
    kernel = Tg43Kernel(gammamed_plus_hdr())
    source = dataclasses.replace(plan.source, reference_datetime=plan.plan_datetime)
    gy_per_s = source.air_kerma_rate_u / 360000.0
    refs = []
    for name, xyz in POINTS.items():
        p = np.array([xyz], dtype=float)
        rates = tuple(rate_matrix(p, n.dwell_positions_mm, dwell_directions(n.path_mm[::-1], n.dwell_positions_mm),
                                  kernel)[0] * gy_per_s for n in plan.needles)
        refs.append(ReferencePoint(name, p[0], rates))
    return dataclasses.replace(plan, source=source, prescription_dose_gy=rx_gy, fractions_planned=fractions,
                               reference_points=tuple(refs), **kw)


def test_independent_checker_reproduces_the_stated_point_doses(make_plan: PlanFactory, tmp_path: Path) -> None:
    plan = with_points(make_plan())
    files = export_plan(plan, tmp_path)
    rows = independent_check(files.path("rtplan"), files.path("rtstruct"), _consensus("gammamed_plus_hdr"))
    assert {r[0] for r in rows} == set(POINTS)
    checked = [r for r in rows if r[3] > 5.0]
    assert len(checked) >= 3
    for name, stated, ours, _ in checked:
        assert stated > 0.05, name
        assert ours == pytest.approx(stated, rel=0.01), name
    # the stated doses are the rates × the dwell times as written (0.1 s)
    planned = planned_point_doses_gy(plan)
    for name, stated, _, _ in rows:
        assert stated == pytest.approx(planned[name], rel=1e-8)


@pytest.mark.parametrize("style", ["eclipse", "vitesse"])
def test_prescription_fractions_and_coefficients(make_plan: PlanFactory, tmp_path: Path, style: str) -> None:
    """Eclipse's layout by default (no (300A,0026) anywhere, every point a COORDINATES item, the setup dose specified
    at a point); ``vitesse`` adds the SITE/TARGET item with Target Prescription Dose (rtplan_conventions.md §2-3)."""
    plan = with_points(make_plan(), rx_gy=7.0, fractions=4, specification_point="p mid")
    options = exporters_base.ExportOptions() if style == "eclipse" else exporters_base.ExportOptions(rtplan_style=style)
    rp = pydicom.dcmread(export_plan(plan, tmp_path, options).path("rtplan"))
    fg = rp.FractionGroupSequence[0]
    assert int(fg.NumberOfFractionsPlanned) == 4
    ref_setup = fg.ReferencedBrachyApplicationSetupSequence[0]
    assert float(ref_setup.BrachyApplicationSetupDose) == 7.0
    assert np.allclose(np.array(ref_setup.BrachyApplicationSetupDoseSpecificationPoint, float), POINTS["p mid"])
    refs = rp.DoseReferenceSequence
    by_name = {str(d.DoseReferenceDescription): d for d in refs}
    if style == "eclipse":
        assert not [d for d in refs if (0x300A, 0x0026) in d]  # what stops pyTG43 (KeyError) on our plans
        assert {(d.DoseReferenceStructureType, d.DoseReferenceType) for d in refs} == {("COORDINATES",
                                                                                         "ORGAN_AT_RISK")}
        assert ref_setup.ReferencedDoseReferenceUID == by_name["p mid"].DoseReferenceUID
    else:
        target = refs[0]
        assert (target.DoseReferenceType, target.DoseReferenceStructureType) == ("TARGET", "SITE")
        assert target.DoseReferenceDescription == "HR-CTV" and float(target.TargetPrescriptionDose) == 28.0
        assert ref_setup.ReferencedDoseReferenceUID == target.DoseReferenceUID
    numbers = [int(d.DoseReferenceNumber) for d in refs]
    assert len(set(numbers)) == len(numbers) == (style == "vitesse") + len(POINTS)
    site_sum = 0.0
    for ch in rp.ApplicationSetupSequence[0].ChannelSequence:
        cps = ch.BrachyControlPointSequence
        series: dict[int, list[float]] = {n: [] for n in numbers}
        for cp in cps:
            got = {int(i.ReferencedDoseReferenceNumber): float(i.CumulativeDoseReferenceCoefficient)
                   for i in cp.BrachyReferencedDoseReferenceSequence}
            assert set(got) == set(numbers)  # every control point lists every dose reference
            for n, c in got.items():
                series[n].append(c)
        for values in series.values():
            assert values[0] == 0.0 and all(b >= a for a, b in itertools.pairwise(values))
            # constant while the source moves between dwells (from a pair's end to the next pair's start)
            assert all(values[k] == values[k + 1] for k in range(1, len(values) - 1, 2))
        site_sum += series[1][-1]
    if style == "vitesse":
        assert site_sum == pytest.approx(1.0, abs=1e-8)


def test_reachplan_reader_and_dose_command_list_every_point(make_plan: PlanFactory, tmp_path: Path,
                                                            capsys: pytest.CaptureFixture[str]) -> None:
    from reachplan.imaging.rtplan import read_rtplan
    from reachplan.planner.cli import main

    plan = with_points(make_plan())
    files = export_plan(plan, tmp_path / "x")
    rp = read_rtplan(files.path("rtplan"))
    planned = planned_point_doses_gy(plan)
    by_name = {r.description: r for r in rp.dose_references}
    for name, per_fraction in planned.items():
        assert by_name[name].tps_dose_gy == pytest.approx(4 * per_fraction, rel=1e-6)
    assert main(["dose", "--plan", str(files.path("rtplan")), "--structures", str(files.path("rtstruct")),
                 "--points", "--json", "--spacing", "10", "--out", str(tmp_path / "RD.dcm")]) == 0
    rows = json.loads(capsys.readouterr().out)["points"]
    assert {r["name"] for r in rows} == set(POINTS)
    for r in rows:
        assert r["tps_gy"] == pytest.approx(4 * planned[r["name"]], rel=1e-6)
        assert r["dose_gy"] == pytest.approx(r["tps_gy"], rel=0.002)


def test_machine_lengths_orientation_and_applicator_types(make_plan: PlanFactory, tmp_path: Path) -> None:
    straight = exporters_base.NeedleExport("D4", np.array([[30.0, -20.0, -100.0], [30.0, -20.0, 20.0]]),
                            np.array([[30.0, -20.0, 15.0], [30.0, -20.0, 10.0]]), np.array([4.0, 5.0]))
    base = make_plan()
    plan = dataclasses.replace(base, needles=(*base.needles, straight), application_setup_type="PERINEAL",
                               afterloader=Afterloader("Flexitron", "Elekta", "Flexitron HDR", 1500.0),
                               channel_effective_length_mm=None)
    rp = pydicom.dcmread(export_plan(plan, tmp_path).path("rtplan"))
    machine = rp.TreatmentMachineSequence[0]
    assert machine.TreatmentMachineName == "Flexitron" and machine.Manufacturer == "Elekta"
    setup = rp.ApplicationSetupSequence[0]
    assert setup.ApplicationSetupType == "PERINEAL"
    for ch, needle in zip(setup.ChannelSequence, plan.needles, strict=True):
        assert float(ch.ChannelLength) == float(ch.SourceApplicatorLength) == float(ch.ChannelEffectiveLength) == 1500
        assert ch.SourceApplicatorType == ("FLEXIBLE" if needle.design else "RIGID")
        cps = ch.BrachyControlPointSequence
        bent = float(np.ptp(needle.path_mm[:, 0])) > 0.1
        assert all(("ControlPointOrientation" in cp) == bent for cp in cps)
        if bent:
            for cp in cps:
                u = np.array(cp.ControlPointOrientation, dtype=float)
                assert np.linalg.norm(u) == pytest.approx(1.0, abs=1e-6)
                # the local tangent toward the tip: compare with the path's nearest segment
                pos = np.array(cp.ControlPoint3DPosition, dtype=float)
                k = int(np.argmin(np.linalg.norm(needle.path_mm - pos, axis=1)))
                k = min(max(k, 1), len(needle.path_mm) - 1)
                seg = needle.path_mm[k] - needle.path_mm[k - 1]
                assert u @ (seg / np.linalg.norm(seg)) > 0.999
    default = pydicom.dcmread(export_plan(base, tmp_path / "d").path("rtplan"))
    assert default.TreatmentMachineSequence[0].TreatmentMachineName == "GammaMed PlusHDR"


def _ct_volume(for_uid: str, study: str) -> Volume:
    """A 5-slice CT (2.5 mm) at z = -2.5 .. 7.5 mm with instance UIDs, covering the organ contours."""
    affine = np.diag([1.0, 1.0, 2.5, 1.0])
    affine[:3, 3] = [-10.0, -10.0, -2.5]
    grid = Grid((5, 60, 60), affine)
    uids = tuple(("1.2.840.10008.5.1.4.1.1.2", pydicom.uid.generate_uid()) for _ in range(5))
    who = PatientStudy("P-0042", "Doe^Jane", study, study_date="20261120", study_time="101500", study_id="S77")
    return Volume(np.zeros(grid.shape, np.float32), grid, "CT", pydicom.uid.generate_uid(), for_uid, who,
                  slice_uids=uids)


def test_structure_set_references_the_images_and_study_attributes_are_the_cts(
        make_plan: PlanFactory, tmp_path: Path, dciodvfy) -> None:
    base = make_plan()
    assert base.structure_set is not None
    vol = _ct_volume(base.structure_set.frame_of_reference_uid, base.structure_set.patient_study.study_instance_uid)
    dose_grid = Grid((3, 4, 5), np.diag([2.0, 2.0, 2.0, 1.0]))
    dose = np.arange(60, dtype=float).reshape(3, 4, 5) / 10.0
    plan = with_points(dataclasses.replace(base, volume=vol), dose=PlannedDose(dose, dose_grid))
    files = export_plan(plan, tmp_path)
    rs, rp, rd = (pydicom.dcmread(files.path(r)) for r in ("rtstruct", "rtplan", "rtdose"))
    for ds in (rs, rp, rd):
        assert (ds.StudyDate, ds.StudyTime, ds.StudyID) == ("20261120", "101500", "S77")
        assert ds.StudyInstanceUID == vol.patient_study.study_instance_uid
        assert ds.FrameOfReferenceUID == vol.frame_of_reference_uid
    study = rs.ReferencedFrameOfReferenceSequence[0].RTReferencedStudySequence[0]
    assert study.ReferencedSOPInstanceUID == vol.patient_study.study_instance_uid
    series = study.RTReferencedSeriesSequence[0]
    assert series.SeriesInstanceUID == vol.series_instance_uid
    assert [i.ReferencedSOPInstanceUID for i in series.ContourImageSequence] == [u for _, u in vol.slice_uids]
    kinds = {int(o.ReferencedROINumber): o.RTROIInterpretedType for o in rs.RTROIObservationsSequence}
    slice_z = {u: -2.5 + 2.5 * k for k, (_, u) in enumerate(vol.slice_uids)}
    for rc in rs.ROIContourSequence:
        for c in rc.ContourSequence:
            if kinds[int(rc.ReferencedROINumber)] == "BRACHY_CHANNEL":
                assert c.ContourGeometricType == "OPEN_NONPLANAR" and "ContourImageSequence" not in c
                continue
            z = float(np.array(c.ContourData, dtype=float).reshape(-1, 3)[:, 2].mean())
            (img,) = c.ContourImageSequence
            assert abs(slice_z[img.ReferencedSOPInstanceUID] - z) <= 1.25
    # the RT Dose: the plan's dose, referencing the plan
    assert rd.ReferencedRTPlanSequence[0].ReferencedSOPInstanceUID == rp.SOPInstanceUID
    back, grid = read_rtdose_grid(files.path("rtdose"))
    assert grid.shape == dose_grid.shape and np.allclose(back, dose, atol=dose.max() / 60000)
    for path in (files.path("rtstruct"), files.path("rtplan"), files.path("rtdose")):
        lines = dciodvfy(path)
        assert not [x for x in lines if x.startswith("Error")], (path.name, lines)
        assert not [x for x in lines if x.startswith("Warning") and "Study" in x and "empty" in x.lower()], lines


# --- reference point geometry ------------------------------------------------------------------------------


def _circle_roi(number: int, name: str, centre: tuple[float, float], radius: float, zs: np.ndarray) -> Roi:
    t = np.linspace(0, 2 * np.pi, 72, endpoint=False)
    contours = tuple(Contour(np.column_stack([centre[0] + radius * np.cos(t), centre[1] + radius * np.sin(t),
                                              np.full_like(t, z)])) for z in zs)
    return Roi(number, name, contours)


def test_point_a_and_icru_points_follow_their_definitions() -> None:
    from reachplan.planner.geometry.reference_points import place_reference_points, point_a

    # a tandem tilted 30 degrees anteriorly in the sagittal plane; the flange at the origin
    u = np.array([0.0, -np.sin(np.radians(30)), np.cos(np.radians(30))])
    tandem = np.outer(np.linspace(-10, 60, 15), u)
    left, right = point_a(tandem, np.zeros(3))
    for p, side in ((left, 1.0), (right, -1.0)):
        assert np.linalg.norm(p - 20 * u) == pytest.approx(20.0)  # 20 mm from the axis point 20 mm up
        assert (p - 20 * u) @ u == pytest.approx(0.0, abs=1e-9)  # perpendicular to the tandem
        assert np.sign(p[0]) == side  # LPS: +x is the patient's left
    obturator = _circle_roi(1, "Obturator", (0.0, 0.0), 15.0, np.arange(-30.0, 60.1, 2.5))
    foley = _circle_roi(2, "Foley", (0.0, -40.0), 12.0, np.arange(85.0, 105.1, 2.5))
    tandem_roi = Roi(3, "Tandem", (Contour(np.outer(np.linspace(160, 60, 5), [0, 0, 1.0]),
                                           "OPEN_NONPLANAR"),))
    points, notes = place_reference_points(StructureSet((obturator, foley, tandem_roi), "1.2.3"))
    got = {p.name: p.position_mm for p in points}
    assert not notes
    assert np.allclose(got["Point A left"], [20.0, 0.0, 80.0]) and np.allclose(got["Point A right"], [-20.0, 0, 80])
    # ICRU 38: bladder point on the balloon's posterior surface through its centre; rectum 5 mm behind the
    # vaginal cylinder's posterior wall at its cranial end
    assert np.allclose(got["ICRU bladder"], [0.0, -28.0, 95.0], atol=0.05)
    assert np.allclose(got["ICRU rectum"], [0.0, 20.0, 60.0], atol=0.05)
    none, notes = place_reference_points(StructureSet((foley,), "1.2.3"))
    assert [p.name for p in none] == ["ICRU bladder"] and len(notes) == 2


def test_reference_points_are_checked(make_plan: PlanFactory) -> None:
    plan = make_plan()
    with pytest.raises(ValueError, match="one dose rate per dwell"):
        dataclasses.replace(plan, reference_points=(ReferencePoint("x", np.zeros(3), (np.zeros(1),)),))
    with pytest.raises(ValueError, match="finite"):
        ReferencePoint("x", np.array([0.0, np.nan, 0.0]), ())
    with pytest.raises(ValueError, match="treatment machine name"):
        Afterloader("a name that is far too long")
    assert exporters_base.ExportOptions().time_resolution_s == 0.001
    with pytest.raises(ValueError, match="rtplan_style"):
        exporters_base.ExportOptions(rtplan_style="monaco")
    with pytest.raises(ValueError, match="specification point"):
        dataclasses.replace(plan, specification_point="nowhere")


def test_rt_dose_keeps_the_clinical_range_resolved(make_plan: PlanFactory, tmp_path: Path) -> None:
    """A voxel at a dwell (TG-43 grows without bound there) must not coarsen the 16-bit steps elsewhere."""
    grid = Grid((2, 3, 4), np.diag([2.0, 2.0, 2.0, 1.0]))
    dose = np.linspace(0.0, 40.0, 24).reshape(2, 3, 4)
    dose[0, 0, 0] = 1.0e5  # at a dwell
    plan = with_points(make_plan(), rx_gy=7.0, fractions=4, dose=PlannedDose(dose, grid))
    files = export_plan(plan, tmp_path)
    back, _ = read_rtdose_grid(files.path("rtdose"))
    assert back[0, 0, 0] == pytest.approx(280.0, rel=1e-4)  # 10 x 28 Gy
    assert np.allclose(back.ravel()[1:], dose.ravel()[1:], atol=280.0 / 65535)
    assert any("stored at it" in n for n in files.notes)


def test_structure_set_keeps_the_inputs_image_references_without_the_ct(tmp_path: Path) -> None:
    """Planned from the structure set alone: the export keeps its study, series, images and per-contour slices."""
    from reachplan.imaging.phantom import write_phantom
    from reachplan.imaging.rtstruct import read_rtstruct
    from reachplan.plugins.sources import gammamed_plus_hdr as data

    from .conftest import curved_needle

    rs_in = write_phantom(tmp_path / "phantom").rtstruct_path
    ss = read_rtstruct(rs_in)
    src = exporters_base.SourceSpec.from_source_data(data(), 40700.0, datetime(2026, 11, 1, 8, 0))
    plan = ExportPlan("P", (curved_needle("A1", 0.0, 8.0),), src, structure_set=ss, input_paths=(rs_in,))
    out = pydicom.dcmread(export_plan(plan, tmp_path / "x").path("rtstruct"))
    original = pydicom.dcmread(rs_in)
    chain = [ds.ReferencedFrameOfReferenceSequence[0].RTReferencedStudySequence[0] for ds in (out, original)]
    assert chain[0].ReferencedSOPInstanceUID == chain[1].ReferencedSOPInstanceUID == original.StudyInstanceUID
    series = [c.RTReferencedSeriesSequence[0] for c in chain]
    assert series[0].SeriesInstanceUID == series[1].SeriesInstanceUID
    assert [i.ReferencedSOPInstanceUID for i in series[0].ContourImageSequence] == \
        [i.ReferencedSOPInstanceUID for i in series[1].ContourImageSequence]
    assert (out.StudyDate, out.StudyTime, out.StudyID) == (original.StudyDate, original.StudyTime, original.StudyID)
    by_roi = {int(rc.ReferencedROINumber): rc for rc in original.ROIContourSequence}
    for rc in out.ROIContourSequence:
        if int(rc.ReferencedROINumber) not in by_roi or "ContourSequence" not in rc:
            continue
        before = by_roi[int(rc.ReferencedROINumber)].ContourSequence
        for a, b in zip(rc.ContourSequence, before, strict=True):
            if "ContourImageSequence" in b:
                assert a.ContourImageSequence[0].ReferencedSOPInstanceUID == \
                    b.ContourImageSequence[0].ReferencedSOPInstanceUID
