"""The readers validate what they read (issue 14): pixel description and length, spacing, contours, transfer syntaxes.

One test per family of the bad-input corpus that belongs to the readers; every outcome is a typed error or a named
warning, never a garbled volume or a silent acceptance.
"""

from __future__ import annotations

import warnings
from pathlib import Path
from typing import Any

import numpy as np
import pydicom
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from pydicom.uid import DeflatedExplicitVRLittleEndian

from reachplan.imaging.dicom_io import read_series
from reachplan.imaging.errors import (
    ImagingError,
    InvalidValueError,
    OutsideImageWarning,
    SeriesError,
    SparseContourWarning,
)
from reachplan.imaging.rtstruct import read_rtstruct
from reachplan.planner.cli import main


def test_bits_allocated_8_on_16_bit_ct_is_an_error_not_a_garbled_volume(tmp_path: Path, dicom: Any) -> None:
    def edit(k: int, ds: Any) -> None:
        if k == 2:  # one slice among six, as in the corpus (one among 84)
            ds.BitsAllocated = 8

    dicom.write_series(tmp_path / "ct", edit=edit)
    with pytest.raises(InvalidValueError, match=r"BitsAllocated 8") as err:
        read_series(tmp_path / "ct")
    assert "a_003.dcm" in str(err.value) and "\n" not in str(err.value)


def test_bits_allocated_8_everywhere_with_matching_bits_stored_is_caught_by_length(tmp_path: Path, dicom: Any) -> None:
    def edit(k: int, ds: Any) -> None:
        ds.BitsAllocated, ds.BitsStored, ds.HighBit = 8, 8, 7  # header says 8-bit, the bytes are 16-bit

    dicom.write_series(tmp_path / "ct", edit=edit)
    with pytest.raises(InvalidValueError, match=r"pixel data \(7FE0,0010\) has 240 bytes .* need 120"):
        read_series(tmp_path / "ct")


@pytest.mark.parametrize(("spacing", "match"), [((0.0, 0.7), "PixelSpacing"), ((0.8, 1e9), "PixelSpacing")])
def test_zero_or_huge_pixel_spacing_is_a_series_error(tmp_path: Path, dicom: Any, spacing: tuple[float, float],
                                                      match: str) -> None:
    dicom.write_series(tmp_path / "ct", pixel_spacing=spacing)
    with pytest.raises(SeriesError, match=match):
        read_series(tmp_path / "ct")


@pytest.mark.parametrize("thickness", ["inf", "1e300", "0"])
def test_single_slice_with_infinite_or_zero_thickness_never_gives_infinite_spacing(
    tmp_path: Path, dicom: Any, thickness: str, capsys: pytest.CaptureFixture[str]
) -> None:
    def edit(k: int, ds: Any) -> None:
        ds["SliceThickness"].value = thickness

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        dicom.write_series(tmp_path / "ct", n=1, edit=edit)
    code = main(["inspect", str(tmp_path / "ct"), "--json"])
    out = capsys.readouterr().out
    assert code == 0 and "Infinity" not in out and "NaN" not in out
    v = read_series(tmp_path / "ct")
    assert np.all(np.isfinite(v.grid.spacing_mm)) and v.grid.spacing_mm[2] == pytest.approx(1.0)


def test_positions_a_kilometre_away_are_a_series_error(tmp_path: Path, dicom: Any) -> None:
    dicom.write_series(tmp_path / "ct", origin=(0.0, 0.0, 1e300))
    with pytest.raises(SeriesError):
        read_series(tmp_path / "ct")


def test_deflated_files_read_the_same_volume(tmp_path: Path, dicom: Any) -> None:
    paths = dicom.write_series(tmp_path / "ref")
    expect = read_series(tmp_path / "ref").array
    (tmp_path / "alt").mkdir()
    for p in paths:
        ds = pydicom.dcmread(p)
        ds.file_meta.TransferSyntaxUID = DeflatedExplicitVRLittleEndian
        ds.save_as(tmp_path / "alt" / p.name, enforce_file_format=True)
    assert np.array_equal(read_series(tmp_path / "alt").array, expect)


def test_truncated_deflated_file_is_a_typed_error(tmp_path: Path, dicom: Any) -> None:
    p = dicom.write_series(tmp_path / "ref", n=1)[0]
    ds = pydicom.dcmread(p)
    ds.file_meta.TransferSyntaxUID = DeflatedExplicitVRLittleEndian
    (tmp_path / "cut").mkdir()
    ds.save_as(tmp_path / "cut" / "x.dcm", enforce_file_format=True)
    data = (tmp_path / "cut" / "x.dcm").read_bytes()
    (tmp_path / "cut" / "x.dcm").write_bytes(data[: len(data) * 2 // 3])
    with pytest.raises(ImagingError):
        read_series(tmp_path / "cut")


@pytest.mark.parametrize("n_points", [1, 2])
def test_one_and_two_point_contours_warn_by_name(tmp_path: Path, dicom: Any, n_points: int,
                                                 capsys: pytest.CaptureFixture[str]) -> None:
    good = [dicom.circle(5.0, 10.0 + 2 * k, n=20) for k in range(3)]
    sparse = dicom.circle(5.0, 16.0, n=20)[:n_points]
    rs = dicom.write_rtstruct(tmp_path / "RS.dcm", [("Bladder", [*good, sparse], "CLOSED_PLANAR")],
                              series_uid=None, for_uid="1.2.3")
    with pytest.warns(SparseContourWarning, match=rf"ROI 1 \(Bladder\): 1 CLOSED_PLANAR contour\(s\) with only "
                                                  rf"{n_points} point"):
        ss = read_rtstruct(rs)
    assert len(ss.rois[0].contours) == 4
    with warnings.catch_warnings():
        warnings.simplefilter("always")
        assert main(["inspect", str(rs), "--json"]) == 0
    import json

    doc = json.loads(capsys.readouterr().out)
    assert any(w.startswith("SparseContourWarning") for w in doc["warnings"])


# --- property-based: any header values give a volume or a typed error ---------------------------------------

_NUMBER_TEXT = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True, width=32).map(lambda x: f"{x:.6g}"),
    st.sampled_from(["nan", "inf", "-inf", "0", "-0", "1e30", "-1e30", "", "abc", "1\\2"]),
)


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(keyword=st.sampled_from(["PixelSpacing", "ImagePositionPatient", "ImageOrientationPatient", "SliceThickness",
                                "RescaleSlope", "RescaleIntercept", "Rows", "Columns", "BitsAllocated",
                                "BitsStored", "HighBit"]),
       values=st.lists(_NUMBER_TEXT, min_size=1, max_size=6), slice_index=st.integers(0, 2))
def test_any_header_value_gives_a_finite_volume_or_a_typed_error(
    tmp_path_factory: pytest.TempPathFactory, dicom: Any, keyword: str, values: list[str], slice_index: int
) -> None:
    folder = tmp_path_factory.mktemp("prop")

    def edit(k: int, ds: Any) -> None:
        if k == slice_index:
            elem = ds.data_element(keyword)
            vr = elem.VR if elem is not None else "DS"
            text = "\\".join(values)
            if vr in ("US", "SS"):  # binary VRs: write the number if it is one, else a mangled value
                try:
                    ds[keyword].value = int(float(values[0])) % 65536
                except (ValueError, OverflowError):
                    ds[keyword].value = 0
            else:
                ds.add_new(keyword, vr, text)

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        try:
            dicom.write_series(folder, n=3, edit=edit)
        except (ValueError, OverflowError, TypeError):
            return  # pydicom refuses to write that value at all: nothing to read
        try:
            v = read_series(folder)
        except ImagingError as exc:
            assert "\n" not in str(exc)
            return
    assert np.all(np.isfinite(v.array)) and np.all(np.isfinite(v.grid.patient_from_index))
    assert np.all(np.asarray(v.grid.spacing_mm) > 0)


def test_a_roi_a_metre_outside_the_images_warns_by_name(tmp_path: Path, dicom: Any) -> None:
    dicom.write_series(tmp_path / "ct")
    volume = read_series(tmp_path / "ct")
    inside = [dicom.circle(2.0, 10.0 + 2 * k, n=12) for k in range(3)]
    far = [dicom.circle(2.0, 1000.0 + 2 * k, n=12) for k in range(3)]
    rs = dicom.write_rtstruct(tmp_path / "RS.dcm", [("Target", inside, "CLOSED_PLANAR"),
                                                    ("Bladder", far, "CLOSED_PLANAR")],
                              series_uid=volume.series_instance_uid, for_uid=volume.frame_of_reference_uid)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        read_rtstruct(rs, volume)
    named = [str(w.message) for w in caught if issubclass(w.category, OutsideImageWarning)]
    assert len(named) == 1 and "ROI 2 (Bladder): all contour points lie outside the images" in named[0]
    far_mm = float(named[0].split("up to ")[1].split(" mm")[0])
    assert 975 < far_mm < 1000  # the top slice is at z = 20 mm, the far ROI at z = 1000 to 1004 mm
