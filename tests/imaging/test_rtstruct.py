"""Reading RT Structure Sets: contour kinds, names and synonyms, references, real files."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from pydicom.data import get_testdata_file

from reachplan.imaging.dicom_io import read_series
from reachplan.imaging.errors import (
    DicomQuirkWarning,
    ImagingError,
    NoDicomError,
    ReferenceMismatchError,
    StructureError,
)
from reachplan.imaging.names import DEFAULT_SYNONYMS, SynonymTable
from reachplan.imaging.rtstruct import read_rtstruct


def test_open_nonplanar_channels_and_points_are_read(tmp_path: Path, dicom: Any) -> None:
    channel = np.array([[0.0, 0, 0], [1, 2, 10], [3, 3, 20], [6, 2, 30]])
    rs = dicom.write_rtstruct(tmp_path / "rs.dcm", [
        ("Needle 1", [channel], "OPEN_NONPLANAR"),
        ("Marker", [np.array([[5.0, 6.0, 7.0]])], "POINT"),
        ("Bladder_P", [dicom.square(3, 0.0), dicom.square(3, 2.0)], "CLOSED_PLANAR"),
    ], series_uid=None, for_uid="1.2.3.4")
    ss = read_rtstruct(rs)
    needle, marker, bladder = ss.rois
    assert needle.contours[0].geometric_type == "OPEN_NONPLANAR"
    assert np.allclose(needle.contours[0].points_mm, channel)
    assert marker.contours[0].geometric_type == "POINT" and marker.contours[0].points_mm.shape == (1, 3)
    assert bladder.name == "Bladder_P" and bladder.normalized_name == "Bladder"
    assert ss.get("bladder") is bladder and ss.get("Bladder_P") is bladder
    assert ss.frame_of_reference_uid == "1.2.3.4" and ss.referenced_series_uid is None
    with pytest.raises(StructureError, match="no ROI named 'Sigmoid'"):
        ss.get("Sigmoid")


@pytest.mark.parametrize("name", ["BLADDER", "Bladder_P", "Blase", "bladder", "Urinary Bladder", "VESSIE"])
def test_bladder_synonyms(name: str) -> None:
    assert DEFAULT_SYNONYMS.normalize(name) == "Bladder"


def test_synonym_table_is_configurable(tmp_path: Path) -> None:
    assert DEFAULT_SYNONYMS.normalize("HRCTV") == "HR-CTV"
    assert DEFAULT_SYNONYMS.normalize("Femoral Head Lt") == "Femur_Head_L"
    assert DEFAULT_SYNONYMS.normalize("optBladder") == "optBladder"  # optimisation structures stay themselves
    assert DEFAULT_SYNONYMS.normalize("  Tumour ") == "Tumour"
    csv = tmp_path / "syn.csv"
    csv.write_text("standard,synonym\nBladder,VB\nHR-CTV,CTV_T_HR_1\n")
    table = SynonymTable.from_csv(csv)
    assert table.normalize("vb") == "Bladder" and table.normalize("ctv t hr 1") == "HR-CTV"
    assert table.normalize("Blase") == "Bladder"  # built-ins kept
    with pytest.raises(ValueError, match="maps to both"):
        SynonymTable((("Bladder", ("BL",)), ("Bowel", ("bl",))))
    bad = tmp_path / "bad.csv"
    bad.write_text("a,b\nx,y\n")
    with pytest.raises(ImagingError, match="standard,synonym"):
        SynonymTable.from_csv(bad)


def test_synonyms_reach_the_structure_set(tmp_path: Path, dicom: Any) -> None:
    rs = dicom.write_rtstruct(tmp_path / "rs.dcm", [("VB", [dicom.square(3, 0.0)], "CLOSED_PLANAR")],
                              series_uid=None, for_uid="1.2.3")
    assert read_rtstruct(rs).rois[0].normalized_name == "VB"
    table = DEFAULT_SYNONYMS.extended((("Bladder", ("VB",)),))
    roi = read_rtstruct(rs, synonyms=table).rois[0]
    assert (roi.name, roi.normalized_name) == ("VB", "Bladder")


def test_point_count_mismatch_is_a_named_warning(tmp_path: Path, dicom: Any) -> None:
    def edit(ds: Any) -> None:
        ds.ROIContourSequence[0].ContourSequence[0].NumberOfContourPoints = 7

    rs = dicom.write_rtstruct(tmp_path / "rs.dcm", [("Box", [dicom.square(3, 0.0)], "CLOSED_PLANAR")],
                              series_uid=None, for_uid="1.2.3", edit=edit)
    with pytest.warns(DicomQuirkWarning, match="NumberOfContourPoints is 7 but ContourData holds 4"):
        ss = read_rtstruct(rs)
    assert len(ss.rois[0].contours[0].points_mm) == 4


def test_reference_checks_against_the_volume(tmp_path: Path, dicom: Any) -> None:
    dicom.write_series(tmp_path / "ct")
    volume = read_series(tmp_path / "ct")
    good = dicom.write_rtstruct(tmp_path / "good.dcm", [("Box", [dicom.square(3, 10.0)], "CLOSED_PLANAR")],
                                series_uid=volume.series_instance_uid, for_uid=volume.frame_of_reference_uid)
    assert read_rtstruct(good, volume).referenced_series_uid == volume.series_instance_uid
    same_for = dicom.write_rtstruct(tmp_path / "for.dcm", [("Box", [dicom.square(3, 10.0)], "CLOSED_PLANAR")],
                                    series_uid=None, for_uid=volume.frame_of_reference_uid)
    assert read_rtstruct(same_for, volume).frame_of_reference_uid == volume.frame_of_reference_uid
    other = dicom.write_rtstruct(tmp_path / "other.dcm", [("Box", [dicom.square(3, 10.0)], "CLOSED_PLANAR")],
                                 series_uid="1.2.826.0.1.3680043.10.1.5", for_uid=volume.frame_of_reference_uid)
    with pytest.raises(ReferenceMismatchError, match=r"references series 1\.2\.826\.0\.1\.3680043\.10\.1\.5"):
        read_rtstruct(other, volume)
    assert read_rtstruct(other).referenced_series_uid == "1.2.826.0.1.3680043.10.1.5"


def test_not_a_structure_set(tmp_path: Path, dicom: Any) -> None:
    paths = dicom.write_series(tmp_path / "ct", n=2)
    with pytest.raises(NoDicomError, match="not an RT Structure Set"):
        read_rtstruct(paths[0])
    (tmp_path / "x.txt").write_text("hello")
    with pytest.raises(NoDicomError, match="not a DICOM file"):
        read_rtstruct(tmp_path / "x.txt")
    with pytest.raises(NoDicomError, match="not a file"):
        read_rtstruct(tmp_path)


def test_pydicom_test_files() -> None:
    ss = read_rtstruct(Path(get_testdata_file("rtstruct.dcm")))
    assert [r.name for r in ss.rois] == ["patient", "Isocenter 1", "Isocenter 2"]
    assert [r.interpreted_type for r in ss.rois] == ["EXTERNAL", "ISOCENTER", "ISOCENTER"]
    assert len(ss.rois[0].contours) == 3 and ss.rois[1].contours[0].geometric_type == "POINT"
    ct = read_series(Path(get_testdata_file("CT_small.dcm")))
    assert ct.grid.shape == (1, 128, 128) and ct.modality == "CT"
    assert np.allclose(ct.grid.spacing_mm[:2], 0.661468)


def test_eclipse_structure_sets(reference_file: Callable[[str], Path]) -> None:
    pros = read_rtstruct(reference_file("tps_examples/eclipse_prostate_phantom/RS.dcm"))
    assert len(pros.rois) == 16
    assert {"Body", "Bladder", "Rectum", "Femur_Head_L", "Femur_Head_R", "Prostate"} <= set(pros.names)
    counts = {r.name: len(r.contours) for r in pros.rois}
    assert counts["Bladder"] == 21 and counts["Rectum"] == 40 and counts["BODY"] == 92
    hdr = read_rtstruct(reference_file("tps_examples/hdr/RS.HDR.dcm"))
    channels = [r for r in hdr.rois if r.interpreted_type == "BRACHY_CHANNEL"]
    assert len(channels) == 13 and all(r.contours[0].geometric_type == "OPEN_NONPLANAR" for r in channels)
    tandem = hdr.get("tandem")
    assert tandem.contours[0].points_mm.shape == (23, 3)
    assert hdr.get("HR-CTV").name == "HRCTV" and len(hdr.get("HR-CTV").contours) == 27
    pdr = read_rtstruct(reference_file("tps_examples/pdr/RS.PDR.dcm"))
    assert [r.name for r in pdr.rois if r.interpreted_type == "BRACHY_CHANNEL"] == \
        ["right ovoid", "left ovoid", "tandem"]
    assert pdr.frame_of_reference_uid.startswith("1.3.12.2.1107")
