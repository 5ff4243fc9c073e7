"""``reachplan inspect``: series, structures with volumes, plans with channels."""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest

from reachplan.imaging.phantom import PhantomFiles, phantom_spec
from reachplan.planner.cli import main


def _inspect_json(path: Path, capsys: pytest.CaptureFixture[str]) -> dict[str, Any]:
    capsys.readouterr()
    assert main(["inspect", str(path), "--json"]) == 0
    out = capsys.readouterr()
    return json.loads(out.out)


def test_inspect_phantom(phantom_files: PhantomFiles, capsys: pytest.CaptureFixture[str]) -> None:
    files = phantom_files
    doc = _inspect_json(files.ct_dir.parent, capsys)
    (series,) = doc["series"]
    assert series["modality"] == "CT" and series["shape"] == [84, 256, 256]
    assert series["spacing_mm"] == [1.0, 1.0, 2.5] and series["n_files"] == 84
    (ss,) = doc["structure_sets"]
    assert ss["path"] == str(files.rtstruct_path) and ss["referenced_series_uid"] == series["series_instance_uid"]
    by_name = {s["name"]: s for s in ss["structures"]}
    for s in phantom_spec().structures:
        got = by_name[s.name]
        assert got["normalized_name"] == s.name and got["type"] == s.interpreted_type
        assert got["volume_cc"] == pytest.approx(s.analytic_volume_mm3 / 1000, rel=0.03), s.name
    assert doc["plans"] == [] and doc["n_non_dicom"] == 0 and doc["warnings"] == []

    assert main(["inspect", str(files.ct_dir.parent)]) == 0
    text = capsys.readouterr().out
    assert "series CT 256x256x84 voxels" in text and "HR-CTV" in text


def test_inspect_counts_files_that_are_not_dicom(tmp_path: Path, dicom: Any, capsys: pytest.CaptureFixture[str]) \
        -> None:
    dicom.write_series(tmp_path / "ct", n=3)
    (tmp_path / "notes.txt").write_text("not DICOM")
    doc = _inspect_json(tmp_path, capsys)
    assert doc["n_non_dicom"] == 1 and doc["series"][0]["shape"] == [3, 10, 12]
    assert main(["inspect", str(tmp_path)]) == 0
    assert "1 non-DICOM files ignored" in capsys.readouterr().out


def test_inspect_synonym_file(tmp_path: Path, dicom: Any, capsys: pytest.CaptureFixture[str]) -> None:
    dicom.write_rtstruct(tmp_path / "rs.dcm", [("VB", [dicom.square(3, z) for z in (0.0, 2.0)], "CLOSED_PLANAR")],
                         series_uid=None, for_uid="1.2.3")
    (tmp_path / "syn.csv").write_text("standard,synonym\nBladder,VB\n")
    capsys.readouterr()
    assert main(["inspect", str(tmp_path / "rs.dcm"), "--json", "--synonyms", str(tmp_path / "syn.csv")]) == 0
    roi = json.loads(capsys.readouterr().out)["structure_sets"][0]["structures"][0]
    assert roi["name"] == "VB" and roi["normalized_name"] == "Bladder"
    assert roi["volume_cc"] == pytest.approx(36 * 2 * 2 / 1000, rel=0.03)


@pytest.mark.parametrize(("case", "dwells", "times", "rois", "kind"), [
    ("hdr", [15, 5, 5], [271.4, 101.0, 100.7], [18, 16, 17], "HDR"),
    ("pdr", [12, 5, 4], [276.3, 69.0, 54.6], [6, 5, 4], "PDR"),
])
def test_inspect_real_tps_exports(reference_file: Callable[[str], Path], capsys: pytest.CaptureFixture[str],
                                  case: str, dwells: list[int], times: list[float], rois: list[int], kind: str) -> None:
    rp = reference_file(f"tps_examples/{case}/RP.{kind}.dcm")
    reference_file(f"tps_examples/{case}/RS.{kind}.dcm")  # the folder holds both
    doc = _inspect_json(rp.parent, capsys)
    (plan,) = doc["plans"]
    assert plan["type"] == kind and plan["technique"] == "INTRACAVITARY"
    assert "GammaMed" in plan["source"]
    assert [c["channel_number"] for c in plan["channels"]] == [1, 2, 3]
    assert [c["n_dwells"] for c in plan["channels"]] == dwells
    assert [c["total_time_s"] for c in plan["channels"]] == pytest.approx(times, abs=0.05)
    assert [c["roi_number"] for c in plan["channels"]] == rois
    (ss,) = doc["structure_sets"]
    numbers = {s["number"]: s for s in ss["structures"]}
    assert all(numbers[r]["type"] == "BRACHY_CHANNEL" for r in rois)
    assert all(s["volume_cc"] is None for s in ss["structures"] if s["type"] == "BRACHY_CHANNEL")
    assert doc["series"] == []
