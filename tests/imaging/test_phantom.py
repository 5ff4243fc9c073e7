"""The phantom round trip: analytic solids -> DICOM on disk -> reader -> masks and meshes."""

from __future__ import annotations

import hashlib
import itertools
import json
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pydicom
import pytest

from reachplan.imaging.case_spec import PhantomStructure
from reachplan.imaging.dicom_io import read_series
from reachplan.imaging.errors import OutputExistsError
from reachplan.imaging.meshing import roi_mask, roi_mesh
from reachplan.imaging.phantom import PhantomFiles, phantom_spec, write_phantom
from reachplan.imaging.rtstruct import read_rtstruct
from reachplan.imaging.types import StructureSet, Volume
from reachplan.planner.cli import main


@pytest.fixture(scope="module")
def written(phantom_files: PhantomFiles) -> PhantomFiles:
    return phantom_files


@pytest.fixture(scope="module")
def loaded(written: PhantomFiles) -> tuple[Volume, StructureSet]:
    volume = read_series(written.ct_dir)
    return volume, read_rtstruct(written.rtstruct_path, volume)


def _hashes(folder: Path) -> dict[str, str]:
    return {str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(folder.rglob("*")) if p.is_file()}


@pytest.mark.parametrize("use_grid", [True, False], ids=["ct-grid", "contours-only"])
def test_mesh_volume_matches_analytic_volume(loaded: tuple[Volume, StructureSet], use_grid: bool) -> None:
    volume, structures = loaded
    spec = phantom_spec()
    errors = {}
    for s in spec.structures:
        mesh = roi_mesh(structures.get(s.name), volume.grid if use_grid else None)
        assert mesh.is_watertight, s.name
        assert mesh.volume > 0, s.name
        errors[s.name] = mesh.volume / s.analytic_volume_mm3 - 1
    worst = max(errors, key=lambda n: abs(errors[n]))
    assert abs(errors[worst]) < 0.03, f"{worst}: {100 * errors[worst]:+.2f} %"


def test_mesh_is_in_patient_coordinates(loaded: tuple[Volume, StructureSet]) -> None:
    volume, structures = loaded
    spec = phantom_spec()
    for name in ("Bladder", "Target_80_090", "Rectum"):
        mesh = roi_mesh(structures.get(name), volume.grid)
        lo, hi = spec.get(name).bounds()
        # the slab representation moves z extents to slice boundaries (multiples of 2.5 mm)
        assert np.allclose(mesh.bounds[0, :2], lo[:2], atol=1.0), name
        assert np.allclose(mesh.bounds[1, :2], hi[:2], atol=1.0), name
        assert lo[2] - 2.5 <= mesh.bounds[0, 2] <= lo[2] + 2.5
        assert hi[2] - 2.5 <= mesh.bounds[1, 2] <= hi[2] + 2.5
    target = roi_mesh(structures.get("Target_80_090"), volume.grid)
    assert np.allclose(target.center_mass, [0.0, -40.0, 80.0], atol=0.2)  # 90 degrees = anterior (-y)


def test_ct_geometry_and_hounsfield_units(loaded: tuple[Volume, StructureSet]) -> None:
    volume, _ = loaded
    spec = phantom_spec()
    assert volume.modality == "CT"
    assert volume.grid.shape == (spec.n_slices, spec.matrix, spec.matrix)
    assert np.allclose(volume.grid.spacing_mm, [1.0, 1.0, 2.5])
    assert spec.n_slices * spec.slice_thickness_mm >= 200 and spec.matrix * spec.pixel_mm >= 200

    def hu_at(xyz: tuple[float, float, float]) -> float:
        i, j, k = np.round(volume.grid.to_index(np.array([xyz]))[0]).astype(int)
        return float(volume.array[k, j, i])

    assert hu_at((0.5, -64.5, 101.25)) == 10  # bladder
    assert hu_at((68.5, 0.5, 51.25)) == 700  # left pelvic wall
    assert hu_at((0.5, 0.5, 21.25)) == 100  # obturator
    assert hu_at((120.5, 120.5, 51.25)) == -1000  # air outside the body
    assert hu_at((-50.5, 50.5, 51.25)) == 30  # gel
    assert hu_at((0.5, 86.5, 51.25)) == -90  # subcutaneous fat under the body outline


def test_rtstruct_contours_lie_on_ct_slices(written: PhantomFiles, loaded: tuple[Volume, StructureSet]) -> None:
    volume, structures = loaded
    ct = {pydicom.dcmread(p, stop_before_pixels=True).SOPInstanceUID: p for p in sorted(written.ct_dir.iterdir())}
    rs = pydicom.dcmread(written.rtstruct_path)
    assert rs.FrameOfReferenceUID == volume.frame_of_reference_uid
    assert structures.referenced_series_uid == volume.series_instance_uid
    z_ct = {uid: float(pydicom.dcmread(p, stop_before_pixels=True).ImagePositionPatient[2]) for uid, p in ct.items()}
    n, used = 0, set()
    for rc in rs.ROIContourSequence:
        for c in rc.ContourSequence:
            uid = c.ContourImageSequence[0].ReferencedSOPInstanceUID
            assert uid in ct
            assert c.ContourGeometricType == "CLOSED_PLANAR"
            assert np.allclose(np.asarray(c.ContourData, float)[2::3], z_ct[uid])
            n += 1
            used.add(uid)
    assert used == set(ct)  # the body is contoured on every CT slice
    assert n > 400
    types = {r.name: r.interpreted_type for r in structures.rois}
    assert types["HR-CTV"] == "CTV" and types["Bladder"] == "ORGAN" and types["Target_65_000"] == "PTV"
    assert types["Bone"] == "AVOIDANCE"


def _overlap_points(a: PhantomStructure, b: PhantomStructure, step_mm: float = 0.5) -> int:
    """Number of sample points (a ``step_mm`` lattice) inside both solids."""
    lo = np.maximum(a.bounds()[0], b.bounds()[0])
    hi = np.minimum(a.bounds()[1], b.bounds()[1])
    if np.any(hi <= lo):
        return 0
    axes = [np.arange(x0, x1 + step_mm, step_mm) for x0, x1 in zip(lo, hi, strict=True)]
    pts = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1)
    return int(np.count_nonzero(a.contains(pts) & b.contains(pts)))


def test_no_organ_at_risk_overlaps_a_target_or_another_organ_at_risk() -> None:
    spec = phantom_spec()
    assert {"Bladder", "Rectum", "Sigmoid", "Bowel", "Bone"} <= {s.name for s in spec.oars}
    targets = [*spec.targets, spec.get("HR-CTV")]
    for a, b in [*itertools.combinations(spec.oars, 2), *itertools.product(spec.oars, targets)]:
        assert _overlap_points(a, b) == 0, f"{a.name} overlaps {b.name}"
    # the uterus leans toward the bladder but does not enter it or the bowel
    assert _overlap_points(spec.get("Uterus"), spec.get("Bladder")) == 0
    assert _overlap_points(spec.get("Uterus"), spec.get("Bowel")) == 0
    # the test can fail: the HR-CTV does contain the lateral targets
    assert _overlap_points(spec.get("HR-CTV"), spec.get("Target_65_000")) > 0


def test_ct_masks_of_organs_at_risk_are_disjoint(loaded: tuple[Volume, StructureSet]) -> None:
    volume, structures = loaded
    spec = phantom_spec()
    names = [s.name for s in spec.oars] + [s.name for s in spec.targets]
    masks = {n: roi_mask(structures.get(n), volume.grid) for n in names}
    for a, b in itertools.combinations(names, 2):
        assert not np.any(masks[a] & masks[b]), f"{a} overlaps {b}"
    assert all(m.any() for m in masks.values())


def test_phantom_story() -> None:
    spec = phantom_spec()
    hr = spec.get("HR-CTV").shapes[0]
    # the HR-CTV reaches laterally (parametria) well beyond the 20 mm hole ring
    assert hr.bounds()[1][0] >= 40
    uterus = spec.get("Uterus").shapes[0]
    long_axis = np.asarray(uterus.rotation)[:, 2]
    assert long_axis[1] < -0.5 and long_axis[2] > 0.5  # anteverted: tilted toward anterior (bladder)
    assert len(spec.targets) == 12
    assert np.allclose(spec.patient_from_template, np.eye(4))
    sizes = sorted({round(s.analytic_volume_mm3) for s in spec.targets})
    assert sizes == [round(np.pi * 25 * 5), round(np.pi * 25 * 15)]


def test_write_is_deterministic_and_refuses_foreign_files(tmp_path: Path, written: PhantomFiles) -> None:
    again = write_phantom(tmp_path / "a")
    assert _hashes(again.ct_dir.parent) == _hashes(written.ct_dir.parent)
    write_phantom(tmp_path / "a")  # rewriting its own files is fine
    assert _hashes(again.ct_dir.parent) == _hashes(written.ct_dir.parent)

    foreign = tmp_path / "b"
    (foreign / "CT").mkdir(parents=True)
    (foreign / "CT" / "CT.0001.dcm").write_bytes(b"precious data")
    (foreign / "CT" / "notes.txt").write_text("mine")
    before = _hashes(foreign)
    with pytest.raises(OutputExistsError, match="refusing to overwrite"):
        write_phantom(foreign)
    assert _hashes(foreign) == before


def test_written_dicom_passes_dciodvfy(written: PhantomFiles, dciodvfy: Callable[[Path], list[str]]) -> None:
    for path in (written.rtstruct_path, *sorted(written.ct_dir.iterdir())[:2]):
        report = "\n".join(dciodvfy(path))
        assert "Error" not in report, report


def test_cli_phantom_writes_the_phantom(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["phantom", "--out", str(tmp_path / "p"), "--case", "pilot", "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["rtstruct_path"] == str(tmp_path / "p" / "RS.phantom.dcm")
    assert np.allclose(doc["patient_from_template"], np.eye(4))
    vols = {s["name"]: s["analytic_volume_cc"] for s in doc["structures"]}
    assert vols["Target_80_030"] == pytest.approx(np.pi * 25 * 5 / 1000)
    assert len(list((tmp_path / "p" / "CT").glob("*.dcm"))) == 84
    assert main(["phantom", "--out", str(tmp_path / "p"), "--case", "pilot"]) == 0  # rewriting its own phantom is fine
    assert "84 CT slices" in capsys.readouterr().out
    (tmp_path / "q").write_text("a file")
    assert main(["phantom", "--out", str(tmp_path / "q"), "--case", "pilot"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "error" in err[0]


def test_spec_is_validated() -> None:
    spec = phantom_spec()
    with pytest.raises(ValueError, match="unique"):
        type(spec)((*spec.structures, spec.structures[0]))
    with pytest.raises(ValueError, match="whole number of slices"):
        type(spec)(spec.structures, z_range_mm=(-30.0, 181.0))
    with pytest.raises(ValueError, match="positive"):
        from reachplan.imaging.solids import Cylinder

        Cylinder((0.0, 0.0), -1.0, 0.0, 1.0)


def test_phantom_variants_are_distinct_patients(tmp_path) -> None:  # type: ignore[no-untyped-def]
    import dataclasses

    import pydicom

    from reachplan.imaging.phantom import phantom_spec, write_phantom

    a = write_phantom(tmp_path / "a")
    b = write_phantom(tmp_path / "b", dataclasses.replace(phantom_spec(), case_id="case_007"))
    ra, rb = pydicom.dcmread(a.rtstruct_path), pydicom.dcmread(b.rtstruct_path)
    assert ra.PatientID == "REACHPLAN-PHANTOM" and rb.PatientID == "REACHPLAN-PHANTOM-case_007"
    assert ra.StudyInstanceUID != rb.StudyInstanceUID and ra.FrameOfReferenceUID != rb.FrameOfReferenceUID
    again = write_phantom(tmp_path / "c", dataclasses.replace(phantom_spec(), case_id="case_007"))
    assert pydicom.dcmread(again.rtstruct_path).SOPInstanceUID == rb.SOPInstanceUID  # deterministic
