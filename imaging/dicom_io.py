"""Read DICOM image series (CT, MR, ...) into a :class:`reachplan.imaging.types.Volume`.

A folder may hold several series and other objects (RT Structure Sets, plans, non-DICOM files). Slices
are sorted along the slice normal (never by file name or InstanceNumber); spacing, orientation and
geometry are checked, and anything that would give a silently wrong volume is a typed error
(:mod:`reachplan.imaging.errors`). Enhanced (multi-frame) CT/MR objects are read frame by frame.

This module finds the series (:func:`scan`, :func:`select_series`) and assembles the volume (:func:`read_series`,
:func:`load_series`); files are opened by :mod:`reachplan.imaging.dicom_files`, the grid is checked by
:mod:`reachplan.imaging.series_geometry` and the pixels are decoded by :mod:`reachplan.imaging.pixels`.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from reachplan.imaging.ct_numbers import CT_MAX_HU, CT_MIN_HU, Reading, ct_stored_values
from reachplan.imaging.dicom_files import corrupt_error, list_files, parsing, read_dataset
from reachplan.imaging.errors import (
    NoDicomError,
    ReferenceMismatchError,
    SeriesError,
    SignednessWarning,
    UnsupportedDataError,
)
from reachplan.imaging.pixels import check_pixel_length, read_pixels
from reachplan.imaging.series_geometry import Frame, SeriesTolerance, assemble_geometry, frames_of
from reachplan.imaging.types import PatientStudy, Volume

#: Modalities that are never image series, whatever pixel data they carry.
NON_IMAGE_MODALITIES = frozenset({"RTSTRUCT", "RTPLAN", "RTDOSE", "RTRECORD", "REG", "SEG", "SR", "KO", "PR"})


@dataclass(frozen=True)
class SeriesSummary:
    """What a folder holds for one image series (no pixel data read).

    Parameters
    ----------
    series_instance_uid, modality, description, frame_of_reference_uid : str
        From the first object of the series (empty when not given).
    n_frames : int
        Image frames over all the series' objects.
    rows, columns : int
        Image size of the first object, pixels.
    paths : tuple of Path
        The series' files, in scan order.
    """

    series_instance_uid: str
    modality: str
    description: str
    frame_of_reference_uid: str
    n_frames: int
    rows: int
    columns: int
    paths: tuple[Path, ...]


def _is_image(ds: Any) -> bool:
    modality = str(ds.get("Modality", "")).upper()
    return modality not in NON_IMAGE_MODALITIES and "Rows" in ds and "Columns" in ds


_SUMMARY_KEYWORDS = ("SeriesInstanceUID", "FrameOfReferenceUID", "SeriesDescription", "NumberOfFrames", "Rows",
                     "Columns", "StudyInstanceUID", "PatientID", "PatientName")


@dataclass(frozen=True)
class FolderScan:
    """Headers of every DICOM object below a path (pixel data not read).

    Parameters
    ----------
    images : tuple of (pydicom.Dataset, Path)
        Image objects (CT, MR, ...; see :data:`NON_IMAGE_MODALITIES`), with their file.
    others : tuple of (pydicom.Dataset, Path)
        The other DICOM objects (structure sets, plans, DICOMDIR, ...).
    n_non_dicom : int
        Files that are not DICOM.
    """

    images: tuple[tuple[Any, Path], ...]
    others: tuple[tuple[Any, Path], ...]
    n_non_dicom: int

    def series(self) -> tuple[SeriesSummary, ...]:
        """One summary per SeriesInstanceUID of the image objects, in order of first appearance.

        Returns
        -------
        tuple of SeriesSummary
            One summary per SeriesInstanceUID of the image objects, in order of first appearance.
        """
        groups: dict[str, list[tuple[Any, Path]]] = {}
        for ds, path in self.images:
            groups.setdefault(str(ds.get("SeriesInstanceUID", "")), []).append((ds, path))
        out = []
        for uid, items in groups.items():
            ds0 = items[0][0]
            out.append(SeriesSummary(
                series_instance_uid=uid, modality=str(ds0.get("Modality", "")),
                description=str(ds0.get("SeriesDescription", "")),
                frame_of_reference_uid=str(ds0.get("FrameOfReferenceUID", "")),
                n_frames=sum(int(d.get("NumberOfFrames", 1) or 1) for d, _ in items),
                rows=int(ds0.get("Rows", 0)), columns=int(ds0.get("Columns", 0)),
                paths=tuple(p for _, p in items)))
        return tuple(out)


def scan(path: Path) -> FolderScan:
    """Read the headers of every file at ``path`` (a file or a folder, recursively).

    Values over 1 KiB (pixel data, long contour lists) stay on disk until used. Every DICOM file is checked to
    be complete.

    Parameters
    ----------
    path : Path
        A DICOM file, or a folder holding them (searched recursively).

    Returns
    -------
    FolderScan
        The headers of the image objects and of the other DICOM objects, and the count of non-DICOM files.

    Raises
    ------
    NoDicomError
        ``path`` does not exist.
    CorruptFileError
        A file that claims to be DICOM cannot be read.
    """
    images, others, n_non = [], [], 0
    for p in list_files(Path(path)):
        ds = read_dataset(p, defer_size=1024)
        if ds is None:
            n_non += 1
            continue
        with parsing(p):
            image = _is_image(ds)
            if image:  # parse now what the series summaries and the volume use, so damage shows here
                for keyword in _SUMMARY_KEYWORDS:
                    ds.get(keyword)
                for keyword in ("Rows", "Columns", "NumberOfFrames"):
                    int(ds.get(keyword, 1) or 1)
        if image:
            images.append((ds, p))
        else:
            others.append((ds, p))
    return FolderScan(tuple(images), tuple(others), n_non)


def _describe(s: SeriesSummary) -> str:
    return f"{s.series_instance_uid} ({s.modality}, {s.n_frames} images, {s.description or 'no description'})"


def select_series(
    found: FolderScan, folder: Path, series_uid: str | None = None, modality: str | None = None
) -> SeriesSummary:
    """Pick the one image series of a scan matching ``series_uid`` and ``modality`` (None matches any).

    Parameters
    ----------
    found : FolderScan
        What :func:`scan` found.
    folder : Path
        Where it was found (for the messages).
    series_uid : str, optional
        SeriesInstanceUID to pick.
    modality : str, optional
        ``"CT"``, ``"MR"``, ... (case-insensitive).

    Returns
    -------
    SeriesSummary
        The one matching series.

    Raises
    ------
    NoDicomError
        No image series matches; the message lists what the folder holds.
    SeriesError
        More than one series matches.
    """
    all_series = found.series()
    chosen = [s for s in all_series
              if (series_uid is None or s.series_instance_uid == series_uid)
              and (modality is None or s.modality.upper() == modality.upper())]
    if not chosen:
        what = " ".join(x for x in (modality, "image series", f"with SeriesInstanceUID {series_uid}"
                                    if series_uid else "") if x)
        if all_series:
            have = "; ".join(_describe(s) for s in all_series)
            raise NoDicomError(f"no {what} in {folder}; it holds: {have}")
        raise NoDicomError(
            f"no {what} in {folder} ({len(found.others)} non-image DICOM objects, {found.n_non_dicom} other "
            "files); give the folder of a CT or MR series"
        )
    if len(chosen) > 1:
        have = "; ".join(_describe(s) for s in chosen)
        raise SeriesError(f"{folder} holds {len(chosen)} image series: {have}; choose one by its SeriesInstanceUID "
                          "(reachplan plan --series-uid UID; series_uid= in read_series)")
    return chosen[0]


def read_series(
    folder: Path,
    series_uid: str | None = None,
    modality: str | None = None,
    tolerance: SeriesTolerance | None = None,
) -> Volume:
    """Read one CT/MR image series into a :class:`~reachplan.imaging.types.Volume`.

    :func:`scan`, :func:`select_series` and :func:`load_series` in turn.

    Parameters
    ----------
    folder : Path
        A folder (searched recursively) or a single (multi-frame) file.
    series_uid : str, optional
        SeriesInstanceUID to pick when the folder holds several series.
    modality : str, optional
        ``"CT"``, ``"MR"``, ... to pick by modality.
    tolerance : SeriesTolerance, optional
        Regularity checks (default :class:`SeriesTolerance`).

    Returns
    -------
    Volume
        ``array`` (nk, nj, ni) float32 (CT in HU: rescale slope and intercept applied per slice),
        ``grid.patient_from_index`` in LPS mm.

    Raises
    ------
    NoDicomError
        No file, or no (single) matching image series.
    CorruptFileError
        A file is truncated or breaks the standard.
    SeriesError
        The slices do not form one regular volume, or several series match.
    UnsupportedDataError
        Pixel data that cannot be decoded, or a volume too large for memory.
    """
    folder = Path(folder)
    found = scan(folder)
    return load_series(found, select_series(found, folder, series_uid, modality), tolerance, folder)


def load_series(
    found: FolderScan, chosen: SeriesSummary, tolerance: SeriesTolerance | None = None, folder: Path | None = None
) -> Volume:
    """Read the pixel data of one series of a :func:`scan` into a volume.

    Slices in order along the slice normal; CT values rescaled (slope, intercept) to Hounsfield units.

    Parameters
    ----------
    found : FolderScan
        The folder's headers, as :func:`scan` read them.
    chosen : SeriesSummary
        The series to read (from :func:`select_series` or :meth:`FolderScan.series`).
    tolerance : SeriesTolerance, optional
        Regularity checks (default :class:`SeriesTolerance`).
    folder : Path, optional
        Where the series was found (for the messages).

    Returns
    -------
    Volume
        As for :func:`read_series`.

    Raises
    ------
    CorruptFileError, SeriesError, UnsupportedDataError
        As for :func:`read_series`.
    """
    tol = tolerance or SeriesTolerance()
    where = folder if folder is not None else (chosen.paths[0].parent if chosen.paths else Path("."))
    label = f"series {chosen.series_instance_uid} in {where}"
    wanted = set(chosen.paths)
    headers = [(ds, p) for ds, p in found.images if p in wanted]
    uids = {str(ds.get("FrameOfReferenceUID", "")) for ds, _ in headers}
    if len(uids) > 1:
        raise SeriesError(f"{label}: images have {len(uids)} different Frame of Reference UIDs")
    frames = []
    for ds, p in headers:
        with parsing(p):
            frames += frames_of(ds, p)
    grid, order = assemble_geometry(frames, tol, label)
    for ds, p in headers:
        check_pixel_length(ds, p)
    try:
        out = np.empty(grid.shape, dtype=np.float32)
    except MemoryError:
        raise UnsupportedDataError(f"{label}: a volume of {grid.shape} voxels does not fit in memory") from None
    slot = {(frames[i].path, frames[i].frame): k for k, i in enumerate(order)}
    by_path: dict[Path, list[Frame]] = {}
    for f in frames:
        by_path.setdefault(f.path, []).append(f)
    flipped: list[tuple[Path, tuple[Reading, Reading]]] = []
    for ds, path in headers:
        with parsing(path):
            arr = read_pixels(ds, path)
        mine = by_path[path]
        if arr.ndim == 2:
            arr = arr[None]
        if arr.shape[0] != len(mine) or arr.shape[1:] != grid.shape[1:]:
            raise corrupt_error(path, f"pixel data has shape {arr.shape}, expected {len(mine)} x {grid.shape[1:]}")
        arr, readings = ct_stored_values(arr, ds, path, [(f.slope, f.intercept) for f in mine])
        if readings is not None:
            flipped.append((path, readings))
        for f in mine:
            k = slot[(f.path, f.frame)]
            np.multiply(arr[f.frame or 0], np.float32(f.slope), out=out[k], casting="unsafe")
            if f.intercept:
                out[k] += np.float32(f.intercept)
    if flipped:
        _warn_signedness(label, flipped, len(headers))
    sop = {p: (str(ds.get("SOPClassUID", "")), str(ds.get("SOPInstanceUID", ""))) for ds, p in headers}
    slice_uids = [("", "")] * len(order)
    for (path, frame), k in slot.items():
        slice_uids[k] = sop[path] if frame is None else ("", "")  # multi-frame: no per-slice instance
    return Volume(
        array=out, grid=grid, modality=chosen.modality, series_instance_uid=chosen.series_instance_uid,
        frame_of_reference_uid=chosen.frame_of_reference_uid,
        patient_study=PatientStudy.read(headers[0][0]),
        slice_uids=tuple(slice_uids) if all(all(u) for u in slice_uids) else (),
    )


def _warn_signedness(label: str, flipped: list[tuple[Path, tuple[Reading, Reading]]], n_files: int) -> None:
    """One :class:`SignednessWarning` for the files of a series read with the other Pixel Representation."""
    declared, used = flipped[0][1]
    warnings.warn(SignednessWarning(
        f"{label}: {len(flipped)} of {n_files} file(s) (first {flipped[0][0].name}) give impossible CT numbers read "
        f"as declared (Pixel Representation {int(declared.signed)}, {declared.describe()}); read "
        f"{used.describe()} instead, within {CT_MIN_HU:g} to {CT_MAX_HU:g} HU where a CT holds air (-1000 HU) and "
        "water (0 HU): check the series' Pixel Representation"), stacklevel=3)


def check_reference(volume: Volume, frame_of_reference_uid: str | None, series_uid: str | None, what: str) -> None:
    """Check that an object drawn on images refers to ``volume``.

    Parameters
    ----------
    volume : Volume
        The images at hand.
    frame_of_reference_uid : str or None
        The Frame of Reference the object refers to; empty or None is not checked.
    series_uid : str or None
        The image series the object refers to; empty or None is not checked.
    what : str
        Names the object in the message.

    Raises
    ------
    ReferenceMismatchError
        The object refers to another Frame of Reference or series than ``volume``.
    """
    if frame_of_reference_uid and volume.frame_of_reference_uid and \
            frame_of_reference_uid != volume.frame_of_reference_uid:
        raise ReferenceMismatchError(
            f"{what} is in Frame of Reference {frame_of_reference_uid} but the image series is in "
            f"{volume.frame_of_reference_uid}; give the images it was drawn on"
        )
    if series_uid and series_uid != volume.series_instance_uid:
        raise ReferenceMismatchError(
            f"{what} references series {series_uid} but the image series is {volume.series_instance_uid}; "
            "give the images it was drawn on, or read it without images"
        )
