"""The built-in clinical case: smooth anatomy written as DICOM, volumes, CT numbers, MR, variation."""

from __future__ import annotations

import dataclasses
import itertools
import json
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

from reachplan.imaging.clinical import (
    CT_RANGES,
    TISSUE_CLASS,
    TISSUES,
    ClinicalParams,
    clinical_case,
    sample_params,
    write_clinical,
)
from reachplan.imaging.dicom_io import read_series
from reachplan.imaging.meshing import roi_mesh
from reachplan.imaging.phantom import PhantomFiles
from reachplan.imaging.rtstruct import read_rtstruct
from reachplan.imaging.sweep import Sweep, Union
from reachplan.imaging.types import StructureSet, Volume
from reachplan.planner.cli import main


@pytest.fixture(scope="module")
def written(tmp_path_factory: pytest.TempPathFactory) -> PhantomFiles:
    return write_clinical(tmp_path_factory.mktemp("clinical"), clinical_case(0))


@pytest.fixture(scope="module")
def loaded(written: PhantomFiles) -> tuple[Volume, StructureSet]:
    volume = read_series(written.ct_dir)
    return volume, read_rtstruct(written.rtstruct_path, volume)


def test_each_roi_mesh_volume_within_3_percent_of_the_generator(loaded: tuple[Volume, StructureSet]) -> None:
    volume, structures = loaded
    errors = {}
    for s in clinical_case(0).spec.structures:
        mesh = roi_mesh(structures.get(s.name), volume.grid)
        assert mesh.is_watertight, s.name
        errors[s.name] = mesh.volume / s.analytic_volume_mm3 - 1
    worst = max(errors, key=lambda n: abs(errors[n]))
    assert abs(errors[worst]) < 0.03, f"{worst}: {100 * errors[worst]:+.2f} %"
    assert {"Bladder", "Rectum", "Colon_Sigmoid", "Bowel_Small", "CTV_HR", "Uterus", "Bone_Pelvic"} <= set(errors)


@pytest.mark.parametrize("name", ["Bladder", "Uterus", "Colon_Sigmoid", "Bowel_Small", "Bone_Pelvic", "Rectum"])
def test_analytic_sweep_volume_matches_monte_carlo(name: str) -> None:
    """∫ π a b ds (the sweep's closed form) against random points counted inside: an independent check."""
    s = clinical_case(0).spec.get(name)
    lo, hi = s.bounds()
    rng = np.random.default_rng(5)
    n = 400_000
    inside = np.count_nonzero(s.contains(lo + rng.random((n, 3)) * (hi - lo)))
    box = float(np.prod(hi - lo))
    p = inside / n
    sigma = np.sqrt(p * (1 - p) / n) * box
    assert abs(p * box - s.analytic_volume_mm3) < max(4 * sigma, 0.005 * s.analytic_volume_mm3), name


def test_organ_volumes_are_in_the_published_ranges() -> None:
    spec = clinical_case(0).spec
    cc = {s.name: s.analytic_volume_mm3 / 1000 for s in spec.structures}
    assert 138 - 41 <= cc["Bladder"] <= 138 + 41  # Jamema et al. 2008: 138 ± 41 cm³
    assert 60 - 28 <= cc["Rectum"] <= 60 + 28  # Jamema et al. 2008: 60 ± 28 cm³


def test_ct_numbers_per_tissue_are_in_the_cited_ranges(loaded: tuple[Volume, StructureSet]) -> None:
    volume, _ = loaded
    for tissue, (hu, _) in TISSUES.items():
        lo, hi, _source = CT_RANGES[TISSUE_CLASS[tissue]]
        assert lo <= hu <= hi, tissue
    painted = {v[0] for v in TISSUES.values()}
    assert set(np.unique(volume.array).tolist()) <= painted  # nothing else is in the image
    case = clinical_case(0)

    def hu_at(p: np.ndarray) -> float:
        i, j, k = np.round(volume.grid.to_index(np.asarray([p], float))[0]).astype(int)
        return float(volume.array[k, j, i])

    def centre(name: str, frac: float = 0.5, part: int = 0) -> np.ndarray:
        sh = case.spec.get(name).shapes[part]
        assert isinstance(sh, Sweep)
        return sh.samples_mm[int(frac * (len(sh.samples_mm) - 1))]

    probes = {
        "fluid": centre("Bladder"),  # urine
        "air": centre("Colon_Sigmoid", 0.4),  # gas in the lumen
        "cancellous bone": centre("Bone_Pelvic", 0.3),
        "muscle": np.array([125.0, 5.0, 100.0]),
        "fat": np.array([143.0, 5.0, 100.0]),  # subcutaneous
        "plastic": np.array([0.0, 0.0, 20.0]),  # obturator
    }
    for tissue, p in probes.items():
        lo, hi, _ = CT_RANGES[TISSUE_CLASS[tissue]]
        assert lo <= hu_at(p) <= hi, (tissue, p, hu_at(p))
    cortical = centre("Bone_Pelvic", 0.3) + np.array([6.0, 0.0, 0.0]) * np.sign(centre("Bone_Pelvic", 0.3)[0])
    assert hu_at(cortical) == TISSUES["cortical bone"][0]


@pytest.mark.parametrize("seed", [0, 7, 22])  # 7: bulky, retroflexed, vaginal extension; 22: retroverted
def test_no_organ_at_risk_overlaps_the_hrctv_or_another(seed: int) -> None:
    spec = clinical_case(seed).spec
    oars = [s for s in spec.structures if s.is_oar]
    assert {s.name for s in oars} == {"Bladder", "Rectum", "Colon_Sigmoid", "Bowel_Small", "Bone_Pelvic"}
    hr = spec.get("CTV_HR")
    for a, b in [*itertools.combinations(oars, 2), *((o, hr) for o in oars)]:
        (lo_a, hi_a), (lo_b, hi_b) = a.bounds(), b.bounds()
        lo, hi = np.maximum(lo_a, lo_b), np.minimum(hi_a, hi_b)
        if np.any(hi <= lo):
            continue
        axes = [np.arange(x0, x1, 1.0) for x0, x1 in zip(lo, hi, strict=True)]
        pts = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
        assert not np.any(a.contains(pts) & b.contains(pts)), f"{a.name} overlaps {b.name}"


def test_story_anteverted_uterus_over_the_bladder_and_targets_in_the_hrctv() -> None:
    case = clinical_case(0)
    uterus = case.spec.get("Uterus").shapes[0]
    assert isinstance(uterus, Sweep)
    c = uterus.samples_mm
    direction = c[-1] - c[0]
    assert direction[1] < -0.5 * np.linalg.norm(direction)  # fundus toward anterior (the bladder)
    bladder = case.spec.get("Bladder").shapes[0]
    assert bladder.bounds()[1][2] < uterus.bounds()[1][2]  # below the fundus
    hr = case.spec.get("CTV_HR")
    names = {n for n, _ in case.targets}
    assert {"corpus_ant", "param_L"} <= names
    for _, p in case.targets:
        assert hr.contains(np.asarray(p, float)), p
    assert np.allclose(case.spec.patient_from_template, np.eye(4))


def test_variation_is_deterministic_and_within_the_ranges() -> None:
    a, b = clinical_case(4), clinical_case(4)
    assert a.params == b.params and a.targets == b.targets
    assert a.spec.get("Bladder").cross_section(60.0)[0].tobytes() == b.spec.get("Bladder").cross_section(60.0)[
        0].tobytes()
    params = [sample_params(s) for s in range(1, 61)]
    assert len({p.bladder_volume_cc for p in params}) == len(params)  # seeds differ
    for p in params:
        assert -20 <= p.version_deg <= 45 and -40 <= p.flexion_deg <= 50
        assert 50 <= p.bladder_volume_cc <= 260 and 8 <= p.rectum_radius_mm <= 16
        assert 25 <= p.cervix_length_mm <= 40 and p.cervix_length_mm + p.corpus_length_mm >= 60  # uterus >= 60 mm
        assert p.parametria in ("", "L", "R", "LR") and 0 < p.hrctv_corpus_fraction <= 1
    # the published shares, loosely (60 draws): most uteri anteverted (84.8 %) and anteflexed (83.9 %)
    assert 0.65 < np.mean([p.version_deg >= 0 for p in params]) < 0.98
    assert 0.65 < np.mean([p.flexion_deg >= 0 for p in params]) < 0.98
    assert {p.parametria for p in params} == {"", "L", "R", "LR"}
    assert np.mean([p.parametria != "" for p in params]) >= 1 / 3  # the cohort's acceptance: a third or more
    assert {p.parametrial_extension.split()[-1] for p in params} == {"none", "proximal", "distal"}
    bladder = [p.bladder_volume_cc for p in params]
    assert max(bladder) / min(bladder) >= 2  # as drawn; cases.csv records the placed volume
    with pytest.raises(ValueError, match="parametria"):
        ClinicalParams(parametria="X")
    with pytest.raises(ValueError, match="hrctv_corpus_fraction"):
        ClinicalParams(hrctv_corpus_fraction=0.0)


def test_drawn_anatomy_is_built_and_measured() -> None:
    """A small and a bulky case (seeds 11 and 7): the HR-CTV volumes differ by more than a factor 2, each measured
    volume agrees with a voxel count on a 1 mm lattice (an independent integration), a retroverted uterus leans
    posteriorly, and the drawn distributions are documented with a source or ASSUMED."""
    from reachplan.imaging.anatomy import VARIETY, variety_table
    from reachplan.planner.study.cohort import case_anatomy

    small, bulky = clinical_case(11), clinical_case(7)
    vols = []
    for case in (small, bulky):
        a = case_anatomy(case)
        shape = case.spec.get("CTV_HR").shapes[0]
        lo, hi = shape.bounds()
        axes = [np.arange(x0 + 0.5, x1, 1.0) for x0, x1 in zip(lo, hi, strict=True)]
        pts = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1)
        voxels = sum(int(np.count_nonzero(shape.contains(pts[i]))) for i in range(len(pts))) / 1000.0
        assert a.hrctv_cm3 == pytest.approx(voxels, rel=0.03)
        vols.append(a.hrctv_cm3)
    assert vols[1] > 2 * vols[0]
    assert small.params.version_deg < 0 and case_anatomy(small).parametrial_extension == "none"
    cervix = small.spec.get("Cervix").shapes[0].samples_mm
    assert cervix[-1][1] > cervix[0][1]  # retroverted: the cervix axis runs posteriorly (+y) from the os
    assert all(d.source and ("ASSUMED" in d.source or any(ch.isdigit() for ch in d.source)) for d in VARIETY.values())
    assert variety_table().count("\n") == len(VARIETY) + 1


def test_sweep_rejects_bad_input() -> None:
    with pytest.raises(ValueError, match="semi-axes"):
        Sweep(np.zeros((3, 3)) + np.arange(3)[:, None], np.ones(2), np.ones(3))
    with pytest.raises(ValueError, match="at least one"):
        Union(())


def test_mr_series_and_cli(tmp_path: Path, capsys: pytest.CaptureFixture[str],
                           dciodvfy: Callable[[Path], list[str]]) -> None:
    assert main(["phantom", "--out", str(tmp_path / "mr"), "--modality", "MR", "--seed", "2", "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["modality"] == "MR" and doc["seed"] == 2 and "corpus_ant" in doc["targets"]
    volume = read_series(Path(doc["ct_dir"]))
    assert volume.modality == "MR"
    structures = read_rtstruct(Path(doc["rtstruct_path"]), volume)
    assert {"Bladder", "Rectum", "Sigmoid", "Bowel", "HR-CTV", "Obturator"} <= set(structures.names)
    spec = clinical_case(2, modality="MR").spec

    def value_at(p: np.ndarray) -> float:
        i, j, k = np.round(volume.grid.to_index(np.asarray([p], float))[0]).astype(int)
        return float(volume.array[k, j, i])

    urine = spec.get("Bladder").shapes[0]
    assert isinstance(urine, Sweep)
    # T2-like: urine bright, muscle dark, gas void
    assert value_at(urine.samples_mm[len(urine.samples_mm) // 2]) > 3 * value_at(np.array([125.0, 5.0, 100.0]))
    assert json.loads((tmp_path / "mr" / "case.json").read_text())["modality"] == "MR"
    for path in (Path(doc["rtstruct_path"]), sorted(Path(doc["ct_dir"]).iterdir())[0]):
        report = "\n".join(dciodvfy(path))
        assert "Error" not in report, report
    assert main(["phantom", "--out", str(tmp_path / "p"), "--case", "pilot", "--seed", "3"]) == 2


def test_written_ct_passes_dciodvfy(written: PhantomFiles, dciodvfy: Callable[[Path], list[str]]) -> None:
    for path in (written.rtstruct_path, sorted(written.ct_dir.iterdir())[0]):
        report = "\n".join(dciodvfy(path))
        assert "Error" not in report, report


def test_case_json_lists_targets(written: PhantomFiles) -> None:
    doc = json.loads((written.ct_dir.parent / "case.json").read_text())
    assert doc["case"] == "clinical" and doc["seed"] == 0
    assert json.loads(json.dumps(dataclasses.asdict(ClinicalParams()))) == doc["params"]
    assert set(doc["targets"]) == {n for n, _ in clinical_case(0).targets}


def test_sweep_field_finds_the_nearest_sample_as_a_plain_scan_does() -> None:
    """The chunked nearest-sample search (chunks skipped by their bounding balls) against every sample compared."""
    from reachplan.imaging._sweep_kernel import field_at

    bent = Sweep(arc_curve_for_test(), np.full(281, 12.0), np.full(281, 7.0), reference=(0.0, 1.0, 0.0))
    rng = np.random.default_rng(5)
    reach = 14.0
    for z in (5.0, 30.0, 60.0):  # slices, as the CT painting and the contour tracing ask, and scattered points
        for pts in (np.column_stack([rng.uniform(-40.0, 80.0, (2000, 2)), np.full(2000, z)]),
                    rng.uniform(-40.0, 80.0, (2000, 3))):
            d2 = ((pts[:, None, :] - bent.samples_mm[None]) ** 2).sum(axis=-1)
            idx = np.where(d2.min(axis=1) < reach**2, d2.argmin(axis=1), -1)  # argmin: the first of equals
            lo, hi = bent.bounds()
            idx[np.any((pts < lo - 2.0) | (pts > hi + 2.0), axis=1)] = -1
            plain = np.empty(len(pts))
            field_at(pts, idx, bent.samples_mm, bent._s, bent._frames, bent.semi_a_mm, bent.semi_b_mm, reach, plain)
            got = bent.field(pts)
            assert np.array_equal(got, plain) and (got < 0).sum() > 10


def arc_curve_for_test() -> np.ndarray:
    from reachplan.imaging.sweep import arc_curve

    return arc_curve(np.zeros(3), np.array([0.0, 0.0, 1.0]), np.array([1.0, 0.0, 0.0]), 60.0, 60.0, straight_mm=10.0)
