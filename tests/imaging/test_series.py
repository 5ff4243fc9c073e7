"""Reading image series: sorting, geometry, rescale, selection, multi-frame, compression."""

from __future__ import annotations

import warnings
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from reachplan.imaging.dicom_io import read_series
from reachplan.imaging.errors import NoDicomError, ObliqueSliceWarning, SeriesError
from reachplan.imaging.series_geometry import SeriesTolerance


def _sitk_affine(paths: list[Path]) -> tuple[np.ndarray, np.ndarray]:
    """Independent reference: SimpleITK's reader (array [k, j, i] and patient_from_index)."""
    import SimpleITK as sitk

    reader = sitk.ImageSeriesReader()
    reader.SetFileNames([str(p) for p in paths])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        img = reader.Execute()
    m = np.eye(4)
    m[:3, :3] = np.asarray(img.GetDirection()).reshape(3, 3) * np.asarray(img.GetSpacing())
    m[:3, 3] = img.GetOrigin()
    return sitk.GetArrayFromImage(img).astype(np.float32), m


def test_values_geometry_and_rescale(tmp_path: Path, dicom: Any) -> None:
    paths = dicom.write_series(tmp_path, n=5, slope=2.0, intercept=-1024.0)
    v = read_series(tmp_path)
    assert v.grid.shape == (5, 10, 12) and v.modality == "CT"
    expected = dicom.raw_values(5, 10, 12) * 2.0 - 1024.0
    assert np.array_equal(v.array, expected)
    assert np.allclose(v.grid.spacing_mm, [0.7, 0.8, 2.0])  # column spacing is PixelSpacing[1]
    assert np.allclose(v.grid.to_patient(np.array([[3, 2, 4]])), [[-5 + 3 * 0.7, -4 + 2 * 0.8, 10 + 8]])
    ref, m = _sitk_affine(paths)
    assert np.allclose(v.grid.patient_from_index, m, atol=1e-6)
    assert np.array_equal(v.array, ref)


def test_slices_are_sorted_by_position_not_by_name_or_instance_number(tmp_path: Path, dicom: Any) -> None:
    dicom.write_series(tmp_path, n=7, reverse_names=True)
    v = read_series(tmp_path)
    assert np.array_equal(v.array, dicom.raw_values(7, 10, 12) * 2.0 - 1024.0)
    assert v.grid.patient_from_index[2, 3] == pytest.approx(10.0)


@pytest.mark.parametrize("angle_deg", [30.0, -65.0])
def test_oblique_orientation_matches_simpleitk(tmp_path: Path, dicom: Any, angle_deg: float) -> None:
    a = np.radians(angle_deg)
    row = np.array([np.cos(a), np.sin(a), 0.0])
    col = np.array([0.0, np.cos(0.4), -np.sin(0.4)])
    col -= (col @ row) * row
    col /= np.linalg.norm(col)
    paths = dicom.write_series(tmp_path, n=6, orientation=(*row, *col), origin=(3.0, -7.0, 20.0),
                               slice_spacing=1.5, reverse_names=True)
    v = read_series(tmp_path)
    ref, m = _sitk_affine(sorted(paths, key=lambda p: -int(p.stem.split("_")[1])))
    assert np.allclose(v.grid.patient_from_index, m, atol=1e-5)
    assert np.array_equal(v.array, ref)


def test_mr_without_rescale_keeps_stored_values(tmp_path: Path, dicom: Any) -> None:
    dicom.write_series(tmp_path, modality="MR", slope=None, intercept=None)
    v = read_series(tmp_path)
    assert v.modality == "MR"
    assert np.array_equal(v.array, dicom.raw_values(6, 10, 12))


def test_several_series_need_a_choice(tmp_path: Path, dicom: Any) -> None:
    dicom.write_series(tmp_path / "ct", tag="ct")
    dicom.write_series(tmp_path / "mr", tag="mr", modality="MR", slope=None, intercept=None, n=4)
    (tmp_path / "README.txt").write_text("not DICOM")
    with pytest.raises(SeriesError, match="2 image series") as err:
        read_series(tmp_path)
    assert "\n" not in str(err.value)
    assert read_series(tmp_path, modality="MR").grid.shape[0] == 4
    uid = read_series(tmp_path, modality="CT").series_instance_uid
    assert read_series(tmp_path, series_uid=uid).modality == "CT"
    with pytest.raises(NoDicomError, match="no PT image series"):
        read_series(tmp_path, modality="PT")
    with pytest.raises(NoDicomError, match=r"SeriesInstanceUID 1\.2\.3"):
        read_series(tmp_path, series_uid="1.2.3")


def test_structure_sets_and_other_files_beside_the_series_are_ignored(tmp_path: Path, dicom: Any) -> None:
    paths = dicom.write_series(tmp_path)
    (tmp_path / "notes.txt").write_text("hello")
    dicom.write_rtstruct(tmp_path / "RS.dcm", [("Box", [dicom.square(2, 10.0)], "CLOSED_PLANAR")],
                         series_uid=None, for_uid="1.2.3")
    assert read_series(tmp_path).grid.shape[0] == len(paths)


def test_enhanced_multiframe_ct_equals_single_frame_series(tmp_path: Path, dicom: Any) -> None:
    dicom.write_series(tmp_path / "single")
    dicom.write_enhanced_ct(tmp_path / "mf.dcm")
    single, multi = read_series(tmp_path / "single"), read_series(tmp_path / "mf.dcm")
    assert np.array_equal(single.array, multi.array)
    assert np.allclose(single.grid.patient_from_index, multi.grid.patient_from_index)


def test_rle_compressed_series_is_decoded(tmp_path: Path, dicom: Any) -> None:
    from pydicom.uid import RLELossless

    def compress(_: int, ds: Any) -> None:
        ds.compress(RLELossless)

    dicom.write_series(tmp_path / "plain")
    dicom.write_series(tmp_path / "rle", edit=compress)
    assert np.array_equal(read_series(tmp_path / "plain").array, read_series(tmp_path / "rle").array)


def test_gantry_tilt_is_an_error_unless_allowed(tmp_path: Path, dicom: Any) -> None:
    step = (0.0, 2.0 * np.sin(np.radians(15)), 2.0 * np.cos(np.radians(15)))
    paths = dicom.write_series(tmp_path, step=step)
    with pytest.raises(SeriesError, match="gantry tilt"):
        read_series(tmp_path)
    with pytest.warns(ObliqueSliceWarning, match="15.0 degrees"):
        v = read_series(tmp_path, tolerance=SeriesTolerance(allow_gantry_tilt=True))
    assert np.allclose(v.grid.patient_from_index[:3, 2], step)
    # a voxel centre lands where the slice's own ImagePositionPatient says
    assert np.allclose(v.grid.to_patient(np.array([[0, 0, 4]]))[0], np.array([-5.0, -4.0, 10.0]) + 4 * np.array(step))
    assert len(paths) == 6


def test_spacing_tolerance_is_configurable(tmp_path: Path, dicom: Any) -> None:
    z = 10.0 + 2.0 * np.arange(6)
    z[3] += 0.05  # 2.5 % jitter
    dicom.write_series(tmp_path, positions=[(-5.0, -4.0, zz) for zz in z])
    with pytest.raises(SeriesError, match="irregular slice spacing"):
        read_series(tmp_path)
    v = read_series(tmp_path, tolerance=SeriesTolerance(spacing=0.05))
    assert v.grid.shape[0] == 6
    with pytest.raises(ValueError, match="SeriesTolerance"):
        SeriesTolerance(spacing=0.0)


def test_dicomdir_and_single_slices(tmp_path: Path, dicom: Any) -> None:
    from pydicom.dataset import FileDataset, FileMetaDataset
    from pydicom.uid import UID, ExplicitVRLittleEndian

    dicom.write_series(tmp_path, n=1)
    meta = FileMetaDataset()
    meta.MediaStorageSOPClassUID = UID("1.2.840.10008.1.3.10")
    meta.MediaStorageSOPInstanceUID = UID("1.2.3.4.5")
    meta.TransferSyntaxUID = ExplicitVRLittleEndian
    ds = FileDataset("", {}, file_meta=meta, preamble=b"\0" * 128)
    ds.FileSetID = "TEST"
    ds.save_as(tmp_path / "DICOMDIR", enforce_file_format=True)
    v = read_series(tmp_path)
    assert v.grid.shape == (1, 10, 12)
    assert np.allclose(v.grid.spacing_mm, [0.7, 0.8, 2.0])  # a single slice is SliceThickness thick


def test_jpeg_lossless_is_decoded_even_without_a_pydicom_plugin(tmp_path: Path, dicom: Any) -> None:
    """JPEG Lossless (process 14), common in clinical archives: pydicom needs a plugin, SimpleITK's GDCM
    does not; the reader falls back to it."""
    import pydicom
    import SimpleITK as sitk
    from pydicom.uid import JPEGLosslessSV1

    def to_jpeg_lossless(k: int, ds: Any) -> None:
        arr = np.frombuffer(ds.PixelData, dtype=np.int16).reshape(ds.Rows, ds.Columns)
        out = tmp_path / f"j{k}.dcm"
        writer = sitk.ImageFileWriter()
        writer.SetImageIO("GDCMImageIO")
        writer.SetFileName(str(out))
        writer.SetUseCompression(True)
        writer.SetCompressor("JPEG")
        writer.Execute(sitk.GetImageFromArray(arr[None]))
        encoded = pydicom.dcmread(out)
        assert encoded.file_meta.TransferSyntaxUID == JPEGLosslessSV1
        ds.file_meta.TransferSyntaxUID = JPEGLosslessSV1
        ds.PixelData = encoded.PixelData
        ds["PixelData"].is_undefined_length = True
        out.unlink()

    dicom.write_series(tmp_path / "plain")
    dicom.write_series(tmp_path / "jpeg", edit=to_jpeg_lossless)
    assert np.array_equal(read_series(tmp_path / "plain").array, read_series(tmp_path / "jpeg").array)
