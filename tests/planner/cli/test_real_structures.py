"""``reachplan plan`` on real-world structure sets: template pose without an Obturator ROI, ROI names, empty
and POINT ROIs, ROI numbers from 0, and the Eclipse pelvic phantom (issue 13, item 5)."""

from __future__ import annotations

import json
import warnings
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pydicom
import pytest
from matplotlib.path import Path as Polygon

from reachplan.imaging.phantom import phantom_spec, write_phantom
from reachplan.planner.cli import main


@pytest.fixture(scope="module")
def phantom_rs(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return write_phantom(tmp_path_factory.mktemp("phantom")).rtstruct_path


def mutate(src: Path, dst: Path, change: Callable[[Any], None]) -> Path:
    """A copy of an RT Structure Set changed by ``change(dataset)``."""
    ds = pydicom.dcmread(src)
    change(ds)
    ds.save_as(dst)
    return dst


def _number(ds: Any, name: str) -> int:
    return next(int(r.ROINumber) for r in ds.StructureSetROISequence if r.ROIName == name)


def rename(**names: str) -> Callable[[Any], None]:
    def change(ds: Any) -> None:
        for item in ds.StructureSetROISequence:
            item.ROIName = names.get(item.ROIName, item.ROIName)
    return change


def drop_roi(name: str) -> Callable[[Any], None]:
    def change(ds: Any) -> None:
        n = _number(ds, name)
        for seq in ("StructureSetROISequence", "ROIContourSequence", "RTROIObservationsSequence"):
            key = "ROINumber" if seq == "StructureSetROISequence" else "ReferencedROINumber"
            setattr(ds, seq, pydicom.Sequence([i for i in getattr(ds, seq) if int(getattr(i, key)) != n]))
    return change


def contours_of(name: str, kind: str | None, points: list[list[float]] | None = None) -> Callable[[Any], None]:
    """Remove ROI ``name``'s contours (``kind`` None) or replace them by one contour of ``kind``."""
    def change(ds: Any) -> None:
        n = _number(ds, name)
        rc = next(i for i in ds.ROIContourSequence if int(i.ReferencedROINumber) == n)
        if kind is None:
            del rc.ContourSequence
            return
        pts = points or [[0.0, 0.0, 0.0]]
        c = pydicom.Dataset()
        c.ContourGeometricType = kind
        c.NumberOfContourPoints = len(pts)
        c.ContourData = [float(v) for p in pts for v in p]
        rc.ContourSequence = pydicom.Sequence([c])
    return change


def plan(capsys: pytest.CaptureFixture[str], rs: Path, out: Path, *args: str,
         targets: tuple[str, ...] = ("Target_80_030",)) -> tuple[int, dict[str, Any] | None, str]:
    """Run ``reachplan plan`` (straight needles only, no export): exit code, plan document, stderr.

    Warnings are recorded by the command (into its JSON), as when it runs as a program, not raised as errors.
    """
    with warnings.catch_warnings():
        warnings.simplefilter("always")
        code = main(["plan", "--rtstruct", str(rs), "--targets", *targets, "--out", str(out), "--design",
                     "--no-export", "--json", *args])
    captured = capsys.readouterr()
    doc = json.loads(captured.out) if code == 0 else None
    return code, doc, captured.err


def one_line(err: str) -> str:
    assert "Traceback" not in err and "\n" not in err.strip(), err
    return err.strip()


# --- template pose -----------------------------------------------------------------------------------------


def test_without_obturator_the_pose_comes_from_the_command_line(phantom_rs: Path, tmp_path: Path,
                                                                capsys: pytest.CaptureFixture[str]) -> None:
    rs = mutate(phantom_rs, tmp_path / "rs.dcm", drop_roi("Obturator"))
    code, _, err = plan(capsys, rs, tmp_path / "a")
    assert code == 2 and "--template-origin" in one_line(err)
    # the phantom's template: centre at the origin, needles along +z (phantom_spec)
    code, doc, err = plan(capsys, rs, tmp_path / "b", "--template-origin", "0,0,0", "--template-axis", "0,0,2")
    assert code == 0, err
    assert doc is not None
    np.testing.assert_allclose(doc["template_pose"]["patient_from_template"], phantom_spec().patient_from_template,
                               atol=1e-9)
    assert "command line" in doc["template_pose"]["method"]
    assert json.loads((tmp_path / "b" / "plan.json").read_text())["template_pose"] == doc["template_pose"]
    # every straight needle enters on the template plane z = 0 at its hole
    cands = doc["targets"]["Target_80_030"]["candidates"]
    assert cands and all(abs(c["entry_position_mm"][2]) < 1e-6 for c in cands if not c["steered"])
    code, _, err = plan(capsys, rs, tmp_path / "c", "--template-origin", "0,0,0")
    assert code == 2 and "go together" in one_line(err)
    code, _, err = plan(capsys, rs, tmp_path / "d", "--template-origin", "0,nan,0", "--template-axis", "0,0,1")
    assert code == 2 and "finite" in one_line(err)


def test_pose_file_json_text_or_previous_plan(phantom_rs: Path, tmp_path: Path,
                                              capsys: pytest.CaptureFixture[str]) -> None:
    rs = mutate(phantom_rs, tmp_path / "rs.dcm", drop_roi("Obturator"))
    a = np.radians(8.0)
    pose = np.eye(4)
    pose[:3, :3] = [[1, 0, 0], [0, np.cos(a), -np.sin(a)], [0, np.sin(a), np.cos(a)]]
    pose[:3, 3] = [2.0, -3.0, 1.0]
    as_json = tmp_path / "pose.json"
    as_json.write_text(json.dumps(pose.tolist()))
    as_text = tmp_path / "pose.txt"
    as_text.write_text("# patient_from_template\n" + "\n".join(" ".join(f"{v:.12g}" for v in row) for row in pose))
    # one plan from the JSON file; the text file and the plan's own plan.json read as the same pose (the reader
    # both go through), so one plan run shows the pose reaches the plan
    code, doc, err = plan(capsys, rs, tmp_path / "json", "--template-pose", str(as_json))
    assert code == 0 and doc is not None, err
    np.testing.assert_allclose(doc["template_pose"]["patient_from_template"], pose, atol=1e-6)
    from reachplan.planner.cli.plan import read_pose_file

    np.testing.assert_allclose(read_pose_file(as_text), pose, atol=1e-9)
    assert read_pose_file(tmp_path / "json" / "plan.json").tolist() == doc["template_pose"]["patient_from_template"]
    # the pose is printed when not quiet
    assert main(["plan", "--rtstruct", str(rs), "--targets", "Target_80_030", "--out", str(tmp_path / "p"),
                 "--design", "--no-export", "--template-pose", str(as_text)]) == 0
    assert "template pose: command line: --template-pose pose.txt" in capsys.readouterr().out


@pytest.mark.parametrize(("content", "message"), [
    (json.dumps(np.diag([2.0, 1.0, 1.0, 1.0]).tolist()), "rigid"),
    (json.dumps([[1, 0, 0], [0, 1, 0]]), "4x4"),
    ("1 2 3\n", "4x4"),
    (b"\x00\xff\xfe binary", "not a text file"),
])
def test_bad_pose_files_are_one_line_errors(phantom_rs: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str],
                                            content: str | bytes, message: str) -> None:
    f = tmp_path / "pose"
    f.write_bytes(content if isinstance(content, bytes) else content.encode())
    code, _, err = plan(capsys, phantom_rs, tmp_path / "o", "--template-pose", str(f))
    assert code == 2 and message in one_line(err)
    assert not (tmp_path / "o" / "plan.json").exists()


def test_one_way_to_give_the_pose(phantom_rs: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    f = tmp_path / "pose.json"
    f.write_text(json.dumps(np.eye(4).tolist()))
    code, _, err = plan(capsys, phantom_rs, tmp_path / "o", "--template-pose", str(f), "--template-origin",
                        "0,0,0", "--template-axis", "0,0,1")
    assert code == 2 and "one way" in one_line(err)


def test_pose_from_the_tandem_of_an_eclipse_plan(reference_file: Callable[[str], Path], tmp_path: Path,
                                                 capsys: pytest.CaptureFixture[str]) -> None:
    from reachplan.imaging.rtplan import channel_paths, read_rtplan
    from reachplan.imaging.rtstruct import read_rtstruct

    rp_hdr, rs_hdr = reference_file("tps_examples/hdr/RP.HDR.dcm"), reference_file("tps_examples/hdr/RS.HDR.dcm")
    code, doc, err = plan(capsys, rs_hdr, tmp_path / "o", "--rtplan", str(rp_hdr),
                          "--allow-no-oars", targets=("HRCTV",))
    assert code == 0, err
    assert doc is not None
    assert "channel 1 'tandem'" in doc["template_pose"]["method"]
    m = np.array(doc["template_pose"]["patient_from_template"])
    with pytest.warns(UserWarning):
        rp = read_rtplan(rp_hdr)
    tandem = channel_paths(rp, read_rtstruct(rs_hdr))[1]
    # the template looks along the tandem's extra-uterine part toward its tip, 60 mm before its last dwell
    proximal = tandem[-1] - tandem[len(tandem) // 2]
    assert float(np.dot(m[:3, 2], -proximal / np.linalg.norm(proximal))) > 0.99
    last_dwell = rp.channels[0].dwell_positions_mm[np.argmax(rp.channels[0].dwell_relative_mm)]
    assert float(np.linalg.norm(m[:3, 3] + 60.0 * m[:3, 2] - last_dwell)) < 0.5
    # a plan of another Frame of Reference is refused
    pdr = reference_file("tps_examples/pdr/RP.PDR.dcm")
    code, _, err = plan(capsys, rs_hdr, tmp_path / "p", "--rtplan", str(pdr), "--allow-no-oars",
                        targets=("HRCTV",))
    assert code == 2 and "Frame of Reference" in one_line(err)


# --- organs at risk and ROI names ------------------------------------------------------------------------


def test_unrecognised_rectum_is_named_in_the_warning_and_mapped_with_oar(phantom_rs: Path, tmp_path: Path,
                                                                         capsys: pytest.CaptureFixture[str]) -> None:
    rs = mutate(phantom_rs, tmp_path / "rs.dcm", rename(Rectum="Rect_PRV"))
    code, doc, err = plan(capsys, rs, tmp_path / "a")
    assert code == 0 and doc is not None
    (warning,) = doc["warnings"]
    assert "not found: Rectum" in warning and "'Rect_PRV'" in warning and "Rectum might be 'Rect_PRV'" in warning
    assert warning in err
    assert "Rectum" not in doc["config"]["oar_names"]
    code, doc, err = plan(capsys, rs, tmp_path / "b", "--oar", "rectum=Rect_PRV")
    assert code == 0 and doc is not None, err
    assert doc["warnings"] == [] and "Rectum" in doc["config"]["oar_names"]
    code, _, err = plan(capsys, rs, tmp_path / "c", "--oar", "Rectum=NoSuchRoi")
    assert code == 2 and "no ROI named 'NoSuchRoi'" in one_line(err)
    code, _, err = plan(capsys, rs, tmp_path / "d", "--oar", "Rectum")
    assert code == 2 and "ORGAN=ROI_NAME" in one_line(err)


def test_synonyms_file_on_plan(phantom_rs: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    rs = mutate(phantom_rs, tmp_path / "rs.dcm", rename(Bladder="Vesica urinaria"))
    table = tmp_path / "names.csv"
    table.write_text("standard,synonym\nBladder,Vesica urinaria\n")
    code, doc, err = plan(capsys, rs, tmp_path / "a", "--synonyms", str(table))
    assert code == 0 and doc is not None, err
    assert doc["warnings"] == [] and "Bladder" in doc["config"]["oar_names"]
    table.write_bytes(b"\xff\xfe\x00\x01 not text")
    code, _, err = plan(capsys, rs, tmp_path / "b", "--synonyms", str(table))
    assert code == 2 and "not UTF-8 CSV" in one_line(err)


def test_no_organ_at_risk_refused_unless_allowed(phantom_rs: Path, tmp_path: Path,
                                                 capsys: pytest.CaptureFixture[str]) -> None:
    rs = mutate(phantom_rs, tmp_path / "rs.dcm",
                rename(Bladder="A1", Rectum="A2", Sigmoid="A3", Bowel="A4", Bone="A5"))
    code, _, err = plan(capsys, rs, tmp_path / "a")
    assert code == 2 and "--allow-no-oars" in one_line(err)
    assert not (tmp_path / "a" / "plan.json").exists()
    code, doc, err = plan(capsys, rs, tmp_path / "b", "--allow-no-oars")
    assert code == 0 and doc is not None
    assert doc["config"]["oar_names"] == []
    assert "Bladder, Rectum, Sigmoid, Bowel, Bone" in doc["warnings"][0] and "'A1'" in doc["warnings"][0]


def test_names_that_differ_only_in_case_are_told_apart_by_number(phantom_rs: Path, tmp_path: Path,
                                                                 capsys: pytest.CaptureFixture[str]) -> None:
    """Issue 27: a Vitesse set has channels ``B5.5`` and ``b5.5``; unused, they are a warning, not a refusal; used as a
    target they are refused; ``inspect`` gives the same warning."""
    rs = mutate(phantom_rs, tmp_path / "rs.dcm", rename(Target_65_000="B5.5", Target_65_060="b5.5"))
    code, doc, err = plan(capsys, rs, tmp_path / "a")
    assert code == 0 and doc is not None, err
    (named,) = [w for w in doc["warnings"] if "DuplicateRoiNameWarning" in w]
    assert "'B5.5' (ROI 11)" in named and "'b5.5' (ROI 12)" in named and "differ only in case" in named
    code, _, err = plan(capsys, rs, tmp_path / "b", targets=("b5.5",))
    assert code == 2 and "used as a target or organ" in one_line(err.splitlines()[-1]) and "'b5.5'" in err
    with warnings.catch_warnings():
        warnings.simplefilter("always")
        assert main(["inspect", "--json", str(rs)]) == 0
    shown = json.loads(capsys.readouterr().out)
    assert [w for w in shown["warnings"] if "DuplicateRoiNameWarning" in w] == [named]


def test_duplicate_roi_names_are_an_error_that_lists_them(phantom_rs: Path, tmp_path: Path,
                                                          capsys: pytest.CaptureFixture[str]) -> None:
    rs = mutate(phantom_rs, tmp_path / "rs.dcm", rename(Sigmoid="Bladder"))
    code, _, err = plan(capsys, rs, tmp_path / "a")
    # the reader's warning first, then the one-line error
    assert code == 2 and "duplicate ROI names" in one_line(err.splitlines()[-1])
    assert "'Bladder' (ROI numbers 4, 6)" in err
    # two names that both mean the bladder: ambiguous until one is chosen
    rs = mutate(phantom_rs, tmp_path / "rs2.dcm", rename(Sigmoid="Blase"))
    code, _, err = plan(capsys, rs, tmp_path / "b")
    assert code == 2 and "'Blase'" in one_line(err) and "'Bladder'" in err and "--oar Bladder=" in err
    code, doc, err = plan(capsys, rs, tmp_path / "c", "--oar", "Bladder=Bladder")
    assert code == 0 and doc is not None, err
    assert "Bladder" in doc["config"]["oar_names"] and "'Blase'" in doc["warnings"][0]


# --- empty and POINT ROIs --------------------------------------------------------------------------------


@pytest.mark.parametrize(("kind", "says"), [(None, "no contours"), ("POINT", "only POINT contours"),
                                            ("CLOSED_PLANAR", "only closed contours of fewer than 3 points")])
def test_organ_without_closed_contours_is_skipped_with_a_warning(phantom_rs: Path, tmp_path: Path,
                                                                 capsys: pytest.CaptureFixture[str],
                                                                 kind: str | None, says: str) -> None:
    rs = mutate(phantom_rs, tmp_path / "rs.dcm", contours_of("Bladder", kind))
    code, doc, err = plan(capsys, rs, tmp_path / "a")
    assert code == 0 and doc is not None, err
    assert doc["warnings"], "the skipped organ is named in a warning"
    warning = doc["warnings"][0]  # the scene's note first; a reader's warning (e.g. sparse contours) may follow
    assert f"organ at risk Bladder (ROI 'Bladder') has {says}: skipped" in warning
    assert "Bladder" not in doc["config"]["oar_names"]


def test_point_target_roi_is_planned_to_its_point(phantom_rs: Path, tmp_path: Path,
                                                  capsys: pytest.CaptureFixture[str]) -> None:
    rs = mutate(phantom_rs, tmp_path / "rs.dcm", contours_of("Target_80_030", "POINT", [[35.0, 10.0, 80.0]]))
    code, doc, err = plan(capsys, rs, tmp_path / "a")
    assert code == 0 and doc is not None, err
    assert "target ROI 'Target_80_030' is made of POINT contours: planned to its 1 point(s)" in doc["warnings"]
    # straight needles along +z from the template plane: each misses the point by its hole's offset in x, y
    cands = doc["targets"]["Target_80_030"]["candidates"]
    assert len(cands) == 62
    for c in cands:
        offset = np.hypot(c["entry_position_mm"][0] - 35.0, c["entry_position_mm"][1] - 10.0)
        assert c["reach_error_mm"] == pytest.approx(offset, abs=0.01)


@pytest.mark.parametrize(("kind", "says"), [(None, "has no contours"), ("OPEN_NONPLANAR", "has only OPEN_NONPLANAR")])
def test_target_roi_without_anything_to_aim_at_is_a_typed_error(phantom_rs: Path, tmp_path: Path,
                                                                capsys: pytest.CaptureFixture[str],
                                                                kind: str | None, says: str) -> None:
    rs = mutate(phantom_rs, tmp_path / "rs.dcm",
                contours_of("Target_80_030", kind, [[0.0, 0.0, 70.0], [0.0, 0.0, 90.0]]))
    code, _, err = plan(capsys, rs, tmp_path / "a")
    assert code == 2 and f"target ROI 'Target_80_030' {says}" in one_line(err)


def test_empty_dose_target_is_refused_before_planning(phantom_rs: Path, tmp_path: Path,
                                                      capsys: pytest.CaptureFixture[str]) -> None:
    rs = mutate(phantom_rs, tmp_path / "rs.dcm", contours_of("HR-CTV", None))
    code = main(["plan", "--rtstruct", str(rs), "--targets", "Target_80_030", "--out", str(tmp_path / "a"),
                 "--design", "--quiet"])
    assert code == 2 and "--no-export" in one_line(capsys.readouterr().err)
    assert not (tmp_path / "a").exists()


def test_roi_numbers_from_zero_plan_and_export(phantom_rs: Path, tmp_path: Path,
                                               capsys: pytest.CaptureFixture[str]) -> None:
    def from_zero(ds: Any) -> None:
        for seq, key in (("StructureSetROISequence", "ROINumber"), ("ROIContourSequence", "ReferencedROINumber"),
                         ("RTROIObservationsSequence", "ReferencedROINumber")):
            for item in getattr(ds, seq):
                setattr(item, key, int(getattr(item, key)) - 1)

    rs = mutate(phantom_rs, tmp_path / "rs.dcm", from_zero)
    out = tmp_path / "a"
    code = main(["plan", "--rtstruct", str(rs), "--targets", "Target_80_030", "--out", str(out), "--design",
                 "--no-implant", "--quiet"])  # the export's ROI numbers: the per-target needles' plan suffices
    assert code == 0, capsys.readouterr().err
    exported = pydicom.dcmread(out / "export" / "RS_reachplan.dcm")
    numbers = {int(r.ROINumber): r.ROIName for r in exported.StructureSetROISequence}
    assert numbers[0] == "Body"  # kept as in the input
    rp = pydicom.dcmread(out / "export" / "RP_reachplan.dcm")
    for ch in rp.ApplicationSetupSequence[0].ChannelSequence:
        assert numbers[int(ch.ReferencedROINumber)] in (f"Needle {ch.SourceApplicatorID}",
                                                        f"Applicator {ch.SourceApplicatorID}")


# --- the Eclipse pelvic phantom (bladder, rectum, prostate, femoral heads; no obturator) ------------------


def test_eclipse_pelvic_phantom_plans_and_reports_the_bladder(reference_file: Callable[[str], Path], tmp_path: Path,
                                                             capsys: pytest.CaptureFixture[str]) -> None:
    rs = reference_file("tps_examples/eclipse_prostate_phantom/RS.dcm")
    # template 130 mm below the origin, needles cranial along +z; hole Bd (0, -20) enters at (0, -15, -130)
    code, doc, err = plan(capsys, rs, tmp_path / "a", "--template-origin", "0,5,-130", "--template-axis", "0,0,1",
                          targets=("PTV", "0,-15,0"))
    assert code == 0 and doc is not None, err
    (warning,) = doc["warnings"]
    assert "not found: Sigmoid, Bowel, Bone" in warning and "'optBladder'" in warning
    assert doc["config"]["oar_names"] == ["Bladder", "Rectum"]
    ds = pydicom.dcmread(rs)
    bladder = next(r for r in ds.ROIContourSequence if int(r.ReferencedROINumber) == _number(ds, "Bladder"))
    crossing = []  # straight needles that reach their target: does the path pass inside a bladder contour?
    for t in doc["targets"].values():
        for c in t["candidates"]:
            if c["steered"] or not c["reaches"]:
                continue
            a, b = np.array(c["entry_position_mm"]), np.array(c["tip_position_mm"])
            inside = False
            for contour in bladder.ContourSequence:
                pts = np.array(contour.ContourData, dtype=float).reshape(-1, 3)
                z = pts[0, 2]
                if min(a[2], b[2]) < z < max(a[2], b[2]):
                    p = a + (b - a) * (z - a[2]) / (b[2] - a[2])
                    inside |= bool(Polygon(pts[:, :2]).contains_point(p[:2]))
            crossing.append((c, inside))
    assert any(inside for _, inside in crossing)
    for c, inside in crossing:
        if inside:
            assert c["collides"] and c["closest_organ"] == "Bladder" and "collides with Bladder" in c["reason"]
    # the prostate ROI of this set has no contours: a typed error, not a KeyError
    code, _, err = plan(capsys, rs, tmp_path / "b", "--template-origin", "0,5,-130", "--template-axis", "0,0,1",
                        targets=("PROS",))
    assert code == 2 and "target ROI 'PROS' has no contours" in one_line(err)
