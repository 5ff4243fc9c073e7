"""A generated corpus of broken inputs: each breaks one rule once.

For every case: the library raises the expected typed error with a one-line message, ``reachplan inspect``
exits with code 2 and one line on stderr (no traceback), and no input file is changed.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from pydicom.dataelem import RawDataElement
from pydicom.tag import Tag

from reachplan.imaging.dicom_io import read_series
from reachplan.imaging.errors import (
    CorruptFileError,
    ImagingError,
    NoDicomError,
    ReferenceMismatchError,
    SeriesError,
    StructureError,
    UnsupportedDataError,
)
from reachplan.imaging.inspect import inspect_path
from reachplan.imaging.rtstruct import read_rtstruct
from reachplan.planner.cli import main


@dataclass(frozen=True)
class Case:
    """``build(folder, dicom)`` writes the bad input into ``folder`` and returns the path to give the CLI and
    the library call that must fail."""

    name: str
    build: Callable[[Path, Any], tuple[Path, Callable[[], object]]]
    error: type[ImagingError]
    match: str


def _series(folder: Path, dicom: Any, **kw: Any) -> list[Path]:
    return dicom.write_series(folder / "ct", **kw)


def _read(folder: Path) -> Callable[[], object]:
    return lambda: read_series(folder)


def _cut(path: Path, keep: float | int) -> None:
    data = path.read_bytes()
    path.write_bytes(data[: int(len(data) * keep) if isinstance(keep, float) else keep])


def _edit_one(k0: int, fn: Callable[[Any], None]) -> Callable[[int, Any], None]:
    def edit(k: int, ds: Any) -> None:
        if k == k0:
            fn(ds)
    return edit


def _raw(tag: int, vr: str, text: bytes) -> RawDataElement:
    if len(text) % 2:
        text += b" "
    return RawDataElement(Tag(tag), vr, len(text), text, 0, False, True)


# --- image series -----------------------------------------------------------------------------------


def empty_folder(f: Path, dicom: Any) -> tuple[Path, Callable[[], object]]:
    f.mkdir(parents=True, exist_ok=True)
    return f, _read(f)


def only_text_files(f: Path, dicom: Any) -> tuple[Path, Callable[[], object]]:
    f.mkdir(parents=True, exist_ok=True)
    (f / "readme.txt").write_text("no images here")
    (f / "image.png").write_bytes(b"\x89PNG\r\n\x1a\n" + bytes(100))
    return f, _read(f)


def missing_path(f: Path, dicom: Any) -> tuple[Path, Callable[[], object]]:
    f.mkdir(parents=True, exist_ok=True)
    return f / "nowhere", _read(f / "nowhere")


def truncated_pixel_data(f: Path, dicom: Any) -> tuple[Path, Callable[[], object]]:
    paths = _series(f, dicom)
    _cut(paths[2], 0.8)
    return f, _read(f)


def truncated_header(f: Path, dicom: Any) -> tuple[Path, Callable[[], object]]:
    paths = _series(f, dicom)
    _cut(paths[3], 300)
    return f, _read(f)


def garbage_after_magic(f: Path, dicom: Any) -> tuple[Path, Callable[[], object]]:
    _series(f, dicom)
    (f / "ct" / "zz.dcm").write_bytes(b"\0" * 128 + b"DICM" + np.random.default_rng(1).bytes(400))
    return f, _read(f)


def empty_dcm_file(f: Path, dicom: Any) -> tuple[Path, Callable[[], object]]:
    _series(f, dicom)
    (f / "ct" / "empty.dcm").write_bytes(b"")
    return f, _read(f)


def missing_slice(f: Path, dicom: Any) -> tuple[Path, Callable[[], object]]:
    paths = _series(f, dicom, n=8)
    paths[4].unlink()
    return f, _read(f)


def duplicate_position(f: Path, dicom: Any) -> tuple[Path, Callable[[], object]]:
    z = [10.0, 12.0, 14.0, 14.0, 16.0]
    _series(f, dicom, positions=[(-5.0, -4.0, zz) for zz in z])
    return f, _read(f)


def mixed_orientation(f: Path, dicom: Any) -> tuple[Path, Callable[[], object]]:
    _series(f, dicom, edit=_edit_one(2, lambda ds: setattr(ds, "ImageOrientationPatient", [1, 0, 0, 0, 0, -1])))
    return f, _read(f)


def gantry_tilt(f: Path, dicom: Any) -> tuple[Path, Callable[[], object]]:
    _series(f, dicom, step=(0.0, 0.5, 2.0))
    return f, _read(f)


def irregular_spacing(f: Path, dicom: Any) -> tuple[Path, Callable[[], object]]:
    z = [10.0, 12.0, 14.0, 15.3, 17.0, 19.0]
    _series(f, dicom, positions=[(-5.0, -4.0, zz) for zz in z])
    return f, _read(f)


def positions_not_on_a_line(f: Path, dicom: Any) -> tuple[Path, Callable[[], object]]:
    pos = [(-5.0, -4.0, 10.0 + 2 * k) for k in range(6)]
    pos[3] = (-3.0, -4.0, 16.0)
    _series(f, dicom, positions=pos)
    return f, _read(f)


def different_pixel_spacing(f: Path, dicom: Any) -> tuple[Path, Callable[[], object]]:
    _series(f, dicom, edit=_edit_one(1, lambda ds: setattr(ds, "PixelSpacing", [0.9, 0.7])))
    return f, _read(f)


def different_image_sizes(f: Path, dicom: Any) -> tuple[Path, Callable[[], object]]:
    _series(f / "a", dicom, n=3, tag="s", series_uid="1.2.826.0.1.3680043.10.1.77")
    _series(f / "b", dicom, n=3, rows=8, tag="s2", series_uid="1.2.826.0.1.3680043.10.1.77",
            origin=(-5.0, -4.0, 16.0), for_uid=dicom.uid("for", "s"))
    return f, _read(f)


def missing_image_position(f: Path, dicom: Any) -> tuple[Path, Callable[[], object]]:
    _series(f, dicom, edit=_edit_one(0, lambda ds: delattr(ds, "ImagePositionPatient")))
    return f, _read(f)


def orientation_not_orthogonal(f: Path, dicom: Any) -> tuple[Path, Callable[[], object]]:
    _series(f, dicom, orientation=(1, 0, 0, 0.5, 0.866, 0))
    return f, _read(f)


def zero_pixel_spacing(f: Path, dicom: Any) -> tuple[Path, Callable[[], object]]:
    _series(f, dicom, pixel_spacing=(0.0, 0.7))
    return f, _read(f)


def zero_rescale_slope(f: Path, dicom: Any) -> tuple[Path, Callable[[], object]]:
    _series(f, dicom, edit=_edit_one(2, lambda ds: setattr(ds, "RescaleSlope", 0)))
    return f, _read(f)


def pixel_data_too_short(f: Path, dicom: Any) -> tuple[Path, Callable[[], object]]:
    _series(f, dicom, edit=_edit_one(1, lambda ds: setattr(ds, "PixelData", ds.PixelData[:100])))
    return f, _read(f)


def two_frames_of_reference(f: Path, dicom: Any) -> tuple[Path, Callable[[], object]]:
    _series(f, dicom, edit=_edit_one(4, lambda ds: setattr(ds, "FrameOfReferenceUID", "1.2.826.0.1.3680043.10.1.9")))
    return f, _read(f)


def multiframe_without_positions(f: Path, dicom: Any) -> tuple[Path, Callable[[], object]]:
    def two_frames(ds: Any) -> None:
        ds.NumberOfFrames = 2
        ds.PixelData = ds.PixelData * 2
    _series(f, dicom, n=1, edit=_edit_one(0, two_frames))
    return f, _read(f)


def undecodable_transfer_syntax(f: Path, dicom: Any) -> tuple[Path, Callable[[], object]]:
    def mpeg(ds: Any) -> None:
        from pydicom.encaps import encapsulate
        from pydicom.uid import UID

        ds.file_meta.TransferSyntaxUID = UID("1.2.840.10008.1.2.4.100")  # MPEG2: no pydicom decoder
        ds.PixelData = encapsulate([bytes(ds.PixelData)])
    _series(f, dicom, edit=_edit_one(0, mpeg))
    return f, _read(f)


# --- RT Structure Sets beside a good series ----------------------------------------------------------


def _with_rs(f: Path, dicom: Any, *, series_uid: str | None = "own", for_uid: str | None = None,
             rois: list[Any] | None = None, edit: Callable[[Any], None] | None = None) \
        -> tuple[Path, Callable[[], object]]:
    paths = _series(f, dicom)
    v = read_series(f / "ct")
    rs = dicom.write_rtstruct(
        f / "RS.dcm", rois or [("Bladder", [dicom.square(2.0, 10.0 + 2 * k) for k in range(3)], "CLOSED_PLANAR")],
        series_uid=v.series_instance_uid if series_uid == "own" else series_uid,
        for_uid=for_uid or v.frame_of_reference_uid, image_uids=[p.stem for p in paths[:0]], edit=edit)
    return f, lambda: read_rtstruct(rs, read_series(f / "ct"))


def rs_references_another_series(f: Path, dicom: Any) -> tuple[Path, Callable[[], object]]:
    return _with_rs(f, dicom, series_uid="1.2.826.0.1.3680043.10.1.12345")


def rs_in_another_frame_of_reference(f: Path, dicom: Any) -> tuple[Path, Callable[[], object]]:
    return _with_rs(f, dicom, series_uid=None, for_uid="1.2.826.0.1.3680043.10.1.54321")


def rs_contour_data_not_triplets(f: Path, dicom: Any) -> tuple[Path, Callable[[], object]]:
    def edit(ds: Any) -> None:
        c = ds.ROIContourSequence[0].ContourSequence[0]
        c.ContourData = c.ContourData[:-1]
    return _with_rs(f, dicom, edit=edit)


def rs_contour_data_not_numeric(f: Path, dicom: Any) -> tuple[Path, Callable[[], object]]:
    def edit(ds: Any) -> None:
        c = ds.ROIContourSequence[0].ContourSequence[0]
        c[0x30060050] = _raw(0x30060050, "DS", b"1.0\\2.0\\abc\\4\\5\\6\\7\\8\\9")
    return _with_rs(f, dicom, edit=edit)


def rs_contour_data_nan(f: Path, dicom: Any) -> tuple[Path, Callable[[], object]]:
    def edit(ds: Any) -> None:
        c = ds.ROIContourSequence[0].ContourSequence[0]
        c[0x30060050] = _raw(0x30060050, "DS", b"1.0\\2.0\\nan\\4\\5\\10\\7\\8\\10")
    return _with_rs(f, dicom, edit=edit)


def rs_undeclared_roi_number(f: Path, dicom: Any) -> tuple[Path, Callable[[], object]]:
    def edit(ds: Any) -> None:
        ds.ROIContourSequence[0].ReferencedROINumber = 99
    return _with_rs(f, dicom, edit=edit)


def rs_without_roi_list(f: Path, dicom: Any) -> tuple[Path, Callable[[], object]]:
    def edit(ds: Any) -> None:
        del ds.StructureSetROISequence
    return _with_rs(f, dicom, edit=edit)


def rs_duplicate_roi_number(f: Path, dicom: Any) -> tuple[Path, Callable[[], object]]:
    rois = [("Bladder", [dicom.square(2.0, 10.0)], "CLOSED_PLANAR"), ("Rectum", [dicom.square(1.0, 12.0)], "POINT")]

    def edit(ds: Any) -> None:
        ds.StructureSetROISequence[1].ROINumber = 1
    return _with_rs(f, dicom, rois=rois, edit=edit)


def rs_unknown_geometric_type(f: Path, dicom: Any) -> tuple[Path, Callable[[], object]]:
    return _with_rs(f, dicom, rois=[("Bladder", [dicom.square(2.0, 10.0)], "CLOSED_CURVY")])


def rs_truncated(f: Path, dicom: Any) -> tuple[Path, Callable[[], object]]:
    folder, _ = _with_rs(f, dicom, rois=[("Bladder", [dicom.circle(3.0, 10.0 + 2 * k) for k in range(4)],
                                          "CLOSED_PLANAR")])
    _cut(folder / "RS.dcm", 0.6)
    return folder, lambda: read_rtstruct(folder / "RS.dcm")


def rs_contour_without_data(f: Path, dicom: Any) -> tuple[Path, Callable[[], object]]:
    def edit(ds: Any) -> None:
        del ds.ROIContourSequence[0].ContourSequence[0].ContourData
    return _with_rs(f, dicom, edit=edit)


CASES = [
    Case("empty_folder", empty_folder, NoDicomError, "no CT/MR|no image series|no DICOM"),
    Case("only_text_files", only_text_files, NoDicomError, "no image series|no DICOM"),
    Case("missing_path", missing_path, NoDicomError, "does not exist"),
    Case("truncated_pixel_data", truncated_pixel_data, CorruptFileError, "truncated or damaged"),
    Case("truncated_header", truncated_header, CorruptFileError, "truncated or damaged"),
    Case("garbage_after_magic", garbage_after_magic, CorruptFileError, "zz.dcm"),
    Case("empty_dcm_file", empty_dcm_file, CorruptFileError, "empty.dcm"),
    Case("missing_slice", missing_slice, SeriesError, "missing slice"),
    Case("duplicate_position", duplicate_position, SeriesError, "duplicate slice position"),
    Case("mixed_orientation", mixed_orientation, SeriesError, "different orientations"),
    Case("gantry_tilt", gantry_tilt, SeriesError, "gantry tilt"),
    Case("irregular_spacing", irregular_spacing, SeriesError, "irregular slice spacing"),
    Case("positions_not_on_a_line", positions_not_on_a_line, SeriesError, "straight line"),
    Case("different_pixel_spacing", different_pixel_spacing, SeriesError, "PixelSpacing"),
    Case("different_image_sizes", different_image_sizes, SeriesError, "different sizes"),
    Case("missing_image_position", missing_image_position, CorruptFileError, "ImagePositionPatient is missing"),
    Case("orientation_not_orthogonal", orientation_not_orthogonal, SeriesError, "orthogonal unit vectors"),
    Case("zero_pixel_spacing", zero_pixel_spacing, SeriesError, "PixelSpacing"),
    Case("zero_rescale_slope", zero_rescale_slope, CorruptFileError, "RescaleSlope is 0"),
    Case("pixel_data_too_short", pixel_data_too_short, CorruptFileError, "pixel data"),
    Case("two_frames_of_reference", two_frames_of_reference, SeriesError, "Frame of Reference"),
    Case("multiframe_without_positions", multiframe_without_positions, UnsupportedDataError, "per-frame"),
    Case("undecodable_transfer_syntax", undecodable_transfer_syntax, UnsupportedDataError, "can decode"),
    Case("rs_references_another_series", rs_references_another_series, ReferenceMismatchError, "references series"),
    Case("rs_in_another_frame_of_reference", rs_in_another_frame_of_reference, ReferenceMismatchError,
         "Frame of Reference"),
    Case("rs_contour_data_not_triplets", rs_contour_data_not_triplets, StructureError, "multiple of 3"),
    Case("rs_contour_data_not_numeric", rs_contour_data_not_numeric, CorruptFileError, "non-numeric"),
    Case("rs_contour_data_nan", rs_contour_data_nan, StructureError, "NaN"),
    Case("rs_undeclared_roi_number", rs_undeclared_roi_number, StructureError, "does not declare"),
    Case("rs_without_roi_list", rs_without_roi_list, StructureError, "StructureSetROISequence"),
    Case("rs_duplicate_roi_number", rs_duplicate_roi_number, StructureError, "declared twice"),
    Case("rs_unknown_geometric_type", rs_unknown_geometric_type, StructureError, "unknown type"),
    Case("rs_truncated", rs_truncated, CorruptFileError, "truncated or damaged"),
    Case("rs_contour_without_data", rs_contour_without_data, StructureError, "no ContourData"),
]


def test_corpus_is_large_enough() -> None:
    assert len(CASES) >= 25
    assert len({c.name for c in CASES}) == len(CASES)


@pytest.mark.parametrize("case", CASES, ids=[c.name for c in CASES])
def test_bad_input_gives_typed_error_exit_2_and_leaves_files_alone(
    case: Case, tmp_path: Path, dicom: Any, capsys: pytest.CaptureFixture[str]
) -> None:
    folder = tmp_path / "input"
    target, call = case.build(folder, dicom)
    before = dicom.hashes(folder)

    with pytest.raises(case.error, match=case.match) as err:
        call()
    message = str(err.value)
    assert message and "\n" not in message and len(message) < 400, message

    with pytest.raises(case.error):
        inspect_path(target)

    capsys.readouterr()
    assert main(["inspect", str(target)]) == 2
    captured = capsys.readouterr()
    lines = captured.err.strip().splitlines()
    assert len(lines) == 1, captured.err
    assert lines[0].startswith("reachplan inspect: error:") and "Traceback" not in captured.err
    assert captured.out == ""

    assert dicom.hashes(folder) == before


def test_damaged_bytes_never_escape_as_untyped_errors(tmp_path: Path, dicom: Any) -> None:
    """Random truncations and byte flips of a CT slice and a structure set (fixed seed): every outcome is a
    volume or a typed error, never a pydicom/numpy exception."""
    import random
    import warnings

    paths = dicom.write_series(tmp_path / "src", n=1)
    rs = dicom.write_rtstruct(tmp_path / "src" / "RS.dcm",
                              [("Bladder", [dicom.circle(3.0, 10.0 + 2 * k, n=40) for k in range(3)], "CLOSED_PLANAR")],
                              series_uid=None, for_uid="1.2.3")
    sources = [paths[0].read_bytes(), rs.read_bytes()]
    rng = random.Random(1350)
    outcomes = {"ok": 0, "typed": 0}
    for trial in range(240):
        data = bytearray(sources[trial % 2])
        if rng.random() < 0.4:
            data = data[: rng.randrange(1, len(data))]
        else:
            for _ in range(rng.randint(1, 12)):
                data[rng.randrange(0, len(data))] = rng.randrange(256)
        folder = tmp_path / f"t{trial}"
        folder.mkdir()
        (folder / "x.dcm").write_bytes(bytes(data))
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                inspect_path(folder)
                if trial % 2:
                    read_rtstruct(folder / "x.dcm")
                else:
                    read_series(folder)
            outcomes["ok"] += 1
        except ImagingError as exc:
            assert "\n" not in str(exc)
            outcomes["typed"] += 1
    assert outcomes["typed"] > 50 and sum(outcomes.values()) == 240
