"""The readers' second pass over bad input (issue 28): spacing floors, exact pixel lengths, signedness, degenerate
contours and truncated files.

Each case is a typed error (exit 2 from ``inspect``) or a named warning, with the input files unchanged; the
property tests draw the cases' neighbours with Hypothesis.
"""

from __future__ import annotations

import json
import warnings
from pathlib import Path
from typing import Any

import numpy as np
import pydicom
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from reachplan.imaging.contour_checks import encloses_no_area, self_crossings
from reachplan.imaging.ct_numbers import CT_MAX_HU, ct_stored_values
from reachplan.imaging.dicom_io import read_series
from reachplan.imaging.errors import (
    CorruptFileError,
    InvalidValueError,
    SelfIntersectingContourWarning,
    SeriesError,
    SignednessWarning,
    ZeroAreaContourWarning,
)
from reachplan.imaging.meshing import roi_mask
from reachplan.imaging.rtstruct import read_rtstruct
from reachplan.imaging.series_geometry import MIN_SPACING_MM
from reachplan.imaging.types import Grid
from reachplan.planner.cli import main

FUZZ = settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])


def _inspect(path: Path, capsys: pytest.CaptureFixture[str]) -> tuple[int, str, str]:
    with warnings.catch_warnings():
        warnings.simplefilter("always")
        code = main(["inspect", str(path), "--json"])
    out, err = capsys.readouterr()
    return code, out, err


# --- spacing below a physical minimum ----------------------------------------------------------------------------


@pytest.mark.parametrize("spacing", [(1.0, 1e-320), (1e-3, 1.0), (0.0099, 0.0099)])
def test_pixel_spacing_below_the_minimum_is_a_series_error_in_inspect(
    tmp_path: Path, dicom: Any, spacing: tuple[float, float], capsys: pytest.CaptureFixture[str]
) -> None:
    dicom.write_series(tmp_path / "ct", pixel_spacing=spacing)
    before = dicom.hashes(tmp_path / "ct")
    with pytest.raises(SeriesError, match=r"PixelSpacing .* not between 0.01 and 1000 mm"):
        read_series(tmp_path / "ct")
    code, out, err = _inspect(tmp_path / "ct", capsys)
    assert code == 2 and out == "" and "PixelSpacing" in err and "internal error" not in err
    assert dicom.hashes(tmp_path / "ct") == before


def test_slice_spacing_below_the_minimum_is_a_series_error(tmp_path: Path, dicom: Any) -> None:
    dicom.write_series(tmp_path / "ct", slice_spacing=0.005)
    with pytest.raises(SeriesError, match=r"slice spacing is 0.005 mm \(allowed 0.01 to 1000 mm\)"):
        read_series(tmp_path / "ct")


@FUZZ
@given(st.floats(min_value=1e-320, max_value=MIN_SPACING_MM, exclude_max=True), st.booleans())
def test_any_spacing_below_the_minimum_is_refused(tmp_path_factory: pytest.TempPathFactory, dicom: Any,
                                                  tiny: float, in_plane: bool) -> None:
    folder = tmp_path_factory.mktemp("tiny") / "ct"
    if in_plane:
        dicom.write_series(folder, n=2, pixel_spacing=(0.8, tiny))
    else:
        dicom.write_series(folder, n=2, slice_spacing=tiny)
    with pytest.raises(SeriesError):
        read_series(folder)


# --- pixel data length -------------------------------------------------------------------------------------------


def _insert(path: Path, n: int, at_from_end: int = 37) -> None:
    data = path.read_bytes()
    at = len(data) - at_from_end
    path.write_bytes(data[:at] + b"\x07" * n + data[at:])


@pytest.mark.parametrize("n", [1, 2])
def test_bytes_inserted_into_the_pixel_data_are_a_typed_error_naming_the_file(
    tmp_path: Path, dicom: Any, n: int, capsys: pytest.CaptureFixture[str]
) -> None:
    paths = dicom.write_series(tmp_path / "ct")
    _insert(paths[3], n)
    before = dicom.hashes(tmp_path / "ct")
    with pytest.raises(CorruptFileError, match=rf"{n} byte\(s\) follow the last element \(7FE0,0010\)"):
        read_series(tmp_path / "ct")
    code, out, err = _inspect(tmp_path / "ct", capsys)
    assert code == 2 and paths[3].name in err and out == ""
    assert dicom.hashes(tmp_path / "ct") == before


@pytest.mark.parametrize("extra", [1, 2])
def test_pixel_data_one_or_two_bytes_longer_than_declared_size_is_refused(tmp_path: Path, dicom: Any,
                                                                          extra: int) -> None:
    def edit(k: int, ds: Any) -> None:
        if k == 1:  # the element's length says so too: 240 bytes + 1 or 2 (a padding byte only for an odd size)
            ds.PixelData = ds.PixelData + b"\0" * extra

    dicom.write_series(tmp_path / "ct", edit=edit)
    with pytest.raises(InvalidValueError, match=r"has 24[12] bytes .* need 240;"):
        read_series(tmp_path / "ct")


@FUZZ
@given(st.integers(1, 9), st.integers(1, 239))
def test_any_bytes_inserted_anywhere_in_the_pixels_are_refused(tmp_path_factory: pytest.TempPathFactory,
                                                               dicom: Any, n: int, at_from_end: int) -> None:
    folder = tmp_path_factory.mktemp("ins") / "ct"
    paths = dicom.write_series(folder, n=2)
    _insert(paths[0], n, at_from_end)
    with pytest.raises(CorruptFileError):
        read_series(folder)


# --- signed / unsigned --------------------------------------------------------------------------------------------


def _hu_slices(n: int, rows: int = 10, cols: int = 12) -> np.ndarray:
    """Air (-1000) around water (0) and a little bone (700), int16 stored values (slope 1, intercept 0)."""
    a = np.full((n, rows, cols), -1000, dtype=np.int16)
    a[:, 2:8, 3:9] = 0
    a[:, 4:6, 5:7] = 700
    return a


def _write_ct(folder: Path, dicom: Any, values: np.ndarray, pixel_representation: int) -> list[Path]:
    def edit(k: int, ds: Any) -> None:
        ds.PixelRepresentation = pixel_representation
        ds.PixelData = values[k].tobytes()

    return dicom.write_series(folder, n=len(values), slope=None, intercept=None, edit=edit)


def test_signed_ct_declared_unsigned_is_read_as_signed_with_a_named_warning(
    tmp_path: Path, dicom: Any, capsys: pytest.CaptureFixture[str]
) -> None:
    values = _hu_slices(4)
    _write_ct(tmp_path / "ct", dicom, values, pixel_representation=0)
    with pytest.warns(SignednessWarning, match=r"4 of 4 file\(s\).*as unsigned: 0 to 64536 HU.*read as signed: "
                                               r"-1000 to 700 HU"):
        volume = read_series(tmp_path / "ct")
    assert np.array_equal(volume.array, values.astype(np.float32))
    code, out, _ = _inspect(tmp_path / "ct", capsys)
    assert code == 0 and any(w.startswith("SignednessWarning: ") for w in json.loads(out)["warnings"])


def test_ct_numbers_impossible_either_way_are_a_typed_error(tmp_path: Path, dicom: Any,
                                                            capsys: pytest.CaptureFixture[str]) -> None:
    values = _hu_slices(3)
    values[1, 0, :3] = [-20000, -15000, 9000]  # -15,000 HU as signed (-20,000 may be padding), 50,536 as unsigned
    _write_ct(tmp_path / "ct", dicom, values, pixel_representation=1)
    with pytest.raises(InvalidValueError, match=r"a_002.dcm: the CT numbers are impossible read either way"):
        read_series(tmp_path / "ct")
    assert _inspect(tmp_path / "ct", capsys)[0] == 2


def test_an_mr_series_is_never_judged_by_ct_numbers(tmp_path: Path, dicom: Any) -> None:
    def edit(k: int, ds: Any) -> None:
        ds.PixelRepresentation = 0
        ds.PixelData = np.full((10, 12), 60000, dtype=np.uint16).tobytes()

    dicom.write_series(tmp_path / "mr", modality="MR", slope=None, intercept=None, edit=edit)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert float(read_series(tmp_path / "mr").array.max()) == 60000.0


@settings(max_examples=60, deadline=None)
@given(st.lists(st.integers(-1024, 3071), min_size=1, max_size=40), st.sampled_from([(1.0, 0.0), (1.0, -1024.0)]))
def test_a_signed_ct_is_read_back_to_its_ct_numbers_whatever_its_declared_signedness(
    hu: list[int], rescale: tuple[float, float]
) -> None:
    slope, intercept = rescale
    stored = (np.array(hu) - intercept).astype(np.int16)
    for declared in (stored, stored.view(np.uint16)):  # right, and signed data declared unsigned
        ds = pydicom.Dataset()
        ds.Modality, ds.BitsStored = "CT", 16
        values, readings = ct_stored_values(declared.reshape(1, -1), ds, Path("x.dcm"), [rescale])
        assert np.array_equal(values.reshape(-1) * slope + intercept, np.array(hu))
        flipped = declared.dtype.kind == "u" and bool(np.any(stored < 0))
        assert (readings is not None) == flipped
        if readings is not None:
            assert readings[0].hi > CT_MAX_HU and readings[1].consistent


# --- degenerate contours ------------------------------------------------------------------------------------------


def _bow_tie(z: float) -> np.ndarray:
    return np.array([[-6.0, -6.0, z], [6.0, 6.0, z], [6.0, -6.0, z], [-6.0, 6.0, z]])


def test_a_self_intersecting_contour_warns_by_name_and_is_filled_by_even_odd(
    tmp_path: Path, dicom: Any, capsys: pytest.CaptureFixture[str]
) -> None:
    polys = [dicom.circle(8.0, 10.0 + 2 * k, n=40) for k in range(3)] + [_bow_tie(16.0)]
    rs = dicom.write_rtstruct(tmp_path / "RS.dcm", [("Bladder", polys, "CLOSED_PLANAR")], series_uid=None,
                              for_uid="1.2.3")
    before = dicom.hashes(rs)
    with pytest.warns(SelfIntersectingContourWarning, match=r"ROI 1 \(Bladder\): 1 closed contour\(s\) cross "
                                                            r"themselves \(1 crossing\(s\).*even-odd rule"):
        ss = read_rtstruct(rs)
    grid = Grid((1, 25, 25), np.array([[1.0, 0, 0, -12], [0, 1.0, 0, -12], [0, 0, 2.0, 16], [0, 0, 0, 1]]))
    mask = roi_mask(ss.rois[0], grid)[0]
    j, i = np.mgrid[-12:13, -12:13]
    expect = (np.abs(j) < np.abs(i)) & (np.abs(i) < 6)  # the bow tie's two lobes (left and right), voxel centres
    clear = (np.abs(j) != np.abs(i)) & (np.abs(i) != 6)  # voxel centres on an edge may go either way
    assert mask[clear].tolist() == expect[clear].tolist() and mask.sum() > 40
    code, out, _ = _inspect(rs, capsys)
    assert code == 0 and any("SelfIntersectingContourWarning" in w for w in json.loads(out)["warnings"])
    assert dicom.hashes(rs) == before


def test_a_zero_area_contour_warns_by_name_and_is_left_out_of_the_mask(tmp_path: Path, dicom: Any,
                                                                       capsys: pytest.CaptureFixture[str]) -> None:
    good = [dicom.circle(8.0, 10.0 + 2 * k, n=40) for k in range(4)]
    flat = np.array([[-5.0, 0.0, 12.0], [0.0, 0.0, 12.0], [5.0, 0.0, 12.0], [0.0, 0.0, 12.0]])  # there and back
    rs = dicom.write_rtstruct(tmp_path / "RS.dcm", [("Bladder", [*good, flat], "CLOSED_PLANAR")], series_uid=None,
                              for_uid="1.2.3")
    with pytest.warns(ZeroAreaContourWarning, match=r"ROI 1 \(Bladder\): 1 closed contour\(s\) enclose no area.*"
                                                    r"left out of masks and volumes"):
        ss = read_rtstruct(rs)
    ref = dicom.write_rtstruct(tmp_path / "ref.dcm", [("Bladder", good, "CLOSED_PLANAR")], series_uid=None,
                               for_uid="1.2.3")
    grid = Grid((4, 20, 20), np.array([[1.0, 0, 0, -10], [0, 1.0, 0, -10], [0, 0, 2.0, 10], [0, 0, 0, 1]]))
    assert np.array_equal(roi_mask(ss.rois[0], grid), roi_mask(read_rtstruct(ref).rois[0], grid))
    code, out, _ = _inspect(rs, capsys)
    assert code == 0 and any("ZeroAreaContourWarning" in w for w in json.loads(out)["warnings"])


def _brute_crossings(uv: np.ndarray) -> int:
    n, count = len(uv), 0
    for a in range(n):
        for b in range(a + 2, n):
            if a == 0 and b == n - 1:
                continue
            p, q, r, s = uv[a], uv[(a + 1) % n], uv[b], uv[(b + 1) % n]

            def side(x: np.ndarray, y: np.ndarray, z: np.ndarray) -> float:
                return float(np.sign((y[0] - x[0]) * (z[1] - x[1]) - (y[1] - x[1]) * (z[0] - x[0])))

            count += side(p, q, r) * side(p, q, s) < 0 and side(r, s, p) * side(r, s, q) < 0
    return count


@settings(max_examples=80, deadline=None)
@given(st.lists(st.tuples(st.integers(-20, 20), st.integers(-20, 20)), min_size=3, max_size=14, unique=True),
       st.sampled_from(["axial", "sagittal", "oblique"]))
def test_self_crossings_count_every_proper_crossing_in_any_plane(pts: list[tuple[int, int]], plane: str) -> None:
    uv = np.array(pts, dtype=float)
    axes = {"axial": np.eye(3)[:, :2], "sagittal": np.eye(3)[:, 1:],
            "oblique": np.array([[1.0, 0.0], [0.0, 0.6], [0.0, 0.8]])}[plane]
    xyz = uv @ axes.T + np.array([3.0, -2.0, 40.0])
    if encloses_no_area(xyz):
        return
    assert self_crossings(xyz) == _brute_crossings(uv)


def test_a_crossing_through_a_vertex_counts_and_a_keyhole_does_not() -> None:
    t = np.linspace(0, 2 * np.pi, 200, endpoint=False)  # t = pi is a vertex: the eight crosses there
    eight = np.round(np.column_stack([20 * np.sin(2 * t), 30 * np.sin(t), np.zeros_like(t)]), 9)
    keyhole = [(0, 0), (10, 0), (10, 10), (0, 10), (0, 5), (3, 5), (3, 3), (7, 3), (7, 7), (3, 7), (3, 5), (0, 5)]
    touching = [(0, 0), (5, 5), (10, 0), (10, 10), (5, 5), (0, 10)]  # two lobes meeting at (5, 5) without crossing
    assert self_crossings(eight) == 1
    assert self_crossings(np.array([(x, y, 2.0) for x, y in keyhole], dtype=float)) == 0
    assert self_crossings(np.array([(x, y, 2.0) for x, y in touching], dtype=float)) == 0


# --- truncated files ----------------------------------------------------------------------------------------------


@pytest.mark.parametrize("cut", [462, 460])  # mid-element (2 bytes past SOP Instance UID), and at its end exactly
def test_a_truncated_rt_plan_is_a_typed_error_naming_the_file(tmp_path: Path, reference_file: Any, cut: int,
                                                              capsys: pytest.CaptureFixture[str]) -> None:
    rp = tmp_path / "RP.cut.dcm"
    rp.write_bytes(reference_file("tps_examples/hdr/RP.HDR.dcm").read_bytes()[:cut])
    code, out, err = _inspect(tmp_path, capsys)
    assert code == 2 and out == "" and str(rp) in err and "truncated" in err


@FUZZ
@given(st.data())
def test_a_plan_cut_anywhere_is_never_listed_as_another_object(tmp_path_factory: pytest.TempPathFactory,
                                                               reference_file: Any, data: st.DataObject) -> None:
    src = reference_file("tps_examples/hdr/RP.HDR.dcm").read_bytes()
    cut = data.draw(st.integers(132, len(src) - 1))
    folder = tmp_path_factory.mktemp("cut")
    (folder / "RP.dcm").write_bytes(src[:cut])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        import contextlib
        import io

        buf = io.StringIO()
        with contextlib.redirect_stdout(buf), contextlib.redirect_stderr(io.StringIO()):
            code = main(["inspect", str(folder), "--json"])
    assert code in (0, 2)
    if code == 0:
        doc = json.loads(buf.getvalue())
        assert doc["others"] == [] and len(doc["plans"]) == 1
