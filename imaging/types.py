"""Plain typed data produced by :mod:`reachplan.imaging` (no I/O here).

Conventions
-----------
* Patient coordinates are DICOM patient coordinates (LPS), millimetres.
* A volume array is indexed ``array[k, j, i]``: slice ``k``, row ``j``, column ``i`` (the order of
  ``SimpleITK.GetArrayFromImage`` and of stacked pydicom ``pixel_array``).
* ``patient_from_index`` is a 4x4 matrix mapping the homogeneous index ``(i, j, k, 1)`` (column, row,
  slice; note the reversed order with respect to the array axes) to ``(x, y, z, 1)`` in LPS mm.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from reachplan.imaging.errors import StructureError

FloatArray = np.ndarray  # float64 arrays; shapes and units in each docstring


def _check_affine(m: np.ndarray, name: str) -> None:
    if m.shape != (4, 4) or not np.all(np.isfinite(m)) or not np.allclose(m[3], [0, 0, 0, 1]):
        raise ValueError(f"{name} must be a finite 4x4 homogeneous matrix with last row (0, 0, 0, 1)")
    if abs(np.linalg.det(m[:3, :3])) < 1e-12:
        raise ValueError(f"{name} is singular: voxel spacing must be non-zero along every axis")


@dataclass(frozen=True)
class PatientStudy:
    """Who and which study a series belongs to: the DICOM Patient and General Study modules (PS3.3 C.7.1.1, C.7.2.1).

    Every series of one study (images, structure set, plan, dose) carries the same values; exports copy them.
    Empty strings where a file does not give them.

    Parameters
    ----------
    patient_id, patient_name : str
        Patient ID (0010,0020) and Patient's Name (0010,0010).
    study_instance_uid : str
        Study Instance UID (0020,000D).
    study_date, study_time, study_id : str
        Study Date (``YYYYMMDD``), Study Time and Study ID (0008,0020), (0008,0030), (0020,0010).
    """

    # Patient module
    patient_id: str = ""
    patient_name: str = ""
    # General Study module
    study_instance_uid: str = ""
    study_date: str = ""
    study_time: str = ""
    study_id: str = ""

    @classmethod
    def read(cls, ds: Any) -> PatientStudy:
        """Read the values from a pydicom ``Dataset`` (missing or empty attributes give ``""``).

        Parameters
        ----------
        ds : pydicom.Dataset
            A dataset holding the patient's and the study's attributes.

        Returns
        -------
        PatientStudy
            The six values as text.
        """
        def text(keyword: str) -> str:
            return str(ds.get(keyword, "") or "")
        return cls(text("PatientID"), text("PatientName"), text("StudyInstanceUID"), text("StudyDate"),
                   text("StudyTime"), text("StudyID"))

    def write(self, ds: Any) -> None:
        """Set the six attributes on a pydicom ``Dataset`` (the Study Instance UID as given, even empty).

        Parameters
        ----------
        ds : pydicom.Dataset
            The dataset to set them on (changed in place).
        """
        ds.PatientID, ds.PatientName = self.patient_id, self.patient_name
        ds.StudyInstanceUID, ds.StudyID = self.study_instance_uid, self.study_id
        ds.StudyDate, ds.StudyTime = self.study_date, self.study_time


@dataclass(frozen=True, eq=False)
class Grid:
    """A regular voxel grid in patient space.

    Parameters
    ----------
    shape : (3,) int
        ``(nk, nj, ni)``: slices, rows, columns.
    patient_from_index : (4, 4) float
        Maps the homogeneous index ``(i, j, k, 1)`` to ``(x, y, z, 1)`` in LPS mm; columns 0-2 are the
        voxel steps along i, j, k in mm.

    Raises
    ------
    ValueError
        A shape that is not three positive sizes, or a singular or non-homogeneous matrix.
    """

    shape: tuple[int, int, int]
    patient_from_index: FloatArray

    def __post_init__(self) -> None:
        if len(self.shape) != 3 or min(self.shape) < 1:
            raise ValueError(f"grid shape must be three positive sizes (nk, nj, ni), got {self.shape}")
        m = np.asarray(self.patient_from_index, dtype=float)
        _check_affine(m, "patient_from_index")
        m.setflags(write=False)
        object.__setattr__(self, "shape", tuple(int(s) for s in self.shape))
        object.__setattr__(self, "patient_from_index", m)

    @property
    def spacing_mm(self) -> FloatArray:
        """(3,) float, mm: voxel size along i (columns), j (rows), k (slices)."""
        return np.linalg.norm(self.patient_from_index[:3, :3], axis=0)

    @property
    def index_from_patient(self) -> FloatArray:
        """(4, 4) float: inverse of :attr:`patient_from_index`."""
        return np.linalg.inv(self.patient_from_index)

    def to_patient(self, ijk: np.ndarray) -> FloatArray:
        """Map continuous voxel indices to patient coordinates.

        Parameters
        ----------
        ijk : (n, 3) float
            Continuous indices ``(i, j, k)`` (column, row, slice); voxel centres at integers.

        Returns
        -------
        (n, 3) float, mm, LPS
        """
        ijk = np.asarray(ijk, dtype=float)
        return ijk @ self.patient_from_index[:3, :3].T + self.patient_from_index[:3, 3]

    def to_index(self, xyz_mm: np.ndarray) -> FloatArray:
        """Map patient coordinates to continuous voxel indices.

        Parameters
        ----------
        xyz_mm : (n, 3) float, mm, LPS

        Returns
        -------
        (n, 3) float
            Continuous indices ``(i, j, k)`` (column, row, slice); voxel centres at integers.
        """
        inv = self.index_from_patient
        return np.asarray(xyz_mm, dtype=float) @ inv[:3, :3].T + inv[:3, 3]


@dataclass(frozen=True, eq=False)
class Volume:
    """An image volume (CT in HU, MR in its own units) with its place in patient space.

    Parameters
    ----------
    array : (nk, nj, ni) float32
        Voxel values; CT already rescaled to Hounsfield units.
    grid : Grid
        Shape and ``patient_from_index`` of ``array``.
    modality : str
        ``"CT"``, ``"MR"``, ...
    series_instance_uid, frame_of_reference_uid : str
        Identity of the series it was read from.
    patient_study : PatientStudy
        Patient and study as written in the images; carried over to exports.
    slice_uids : tuple of (str, str)
        (SOP Class UID, SOP Instance UID) of the image holding each slice k, in slice order; empty when
        not known. Exports reference the images through them.

    Raises
    ------
    ValueError
        ``array.shape`` differs from ``grid.shape``, or ``slice_uids`` is given but not one per slice.
    """

    array: np.ndarray
    grid: Grid
    modality: str
    series_instance_uid: str
    frame_of_reference_uid: str
    patient_study: PatientStudy = field(default_factory=PatientStudy)
    slice_uids: tuple[tuple[str, str], ...] = ()

    def __post_init__(self) -> None:
        if tuple(self.array.shape) != self.grid.shape:
            raise ValueError(f"array shape {self.array.shape} does not match grid shape {self.grid.shape}")
        if self.slice_uids and len(self.slice_uids) != self.grid.shape[0]:
            raise ValueError(f"{len(self.slice_uids)} slice UIDs for {self.grid.shape[0]} slices")


@dataclass(frozen=True, eq=False)
class Contour:
    """One contour of a structure.

    Parameters
    ----------
    points_mm : (n, 3) float, mm, LPS
        The contour's points in order; a CLOSED_PLANAR contour closes from its last point back to its first.
    geometric_type : str
        ``"CLOSED_PLANAR"``, ``"OPEN_NONPLANAR"``, ``"OPEN_PLANAR"`` or ``"POINT"``.
    image : (str, str)
        (Referenced SOP Class UID, Instance UID) of the image slice the contour was drawn on, as read; ("", "")
        when not known.

    Raises
    ------
    ValueError
        Points that are not a non-empty finite ``(n, 3)`` array.
    """

    points_mm: FloatArray
    geometric_type: str = "CLOSED_PLANAR"
    image: tuple[str, str] = ("", "")

    def __post_init__(self) -> None:
        p = np.asarray(self.points_mm, dtype=float)
        if p.ndim != 2 or p.shape[1] != 3 or len(p) == 0:
            raise ValueError(f"contour points must be a non-empty (n, 3) array, got shape {p.shape}")
        if not np.all(np.isfinite(p)):
            raise ValueError("contour points must be finite")
        p.setflags(write=False)
        object.__setattr__(self, "points_mm", p)


@dataclass(frozen=True, eq=False)
class Roi:
    """A region of interest of an RT Structure Set.

    Parameters
    ----------
    number : int
        ROI Number (3006,0022) in the file.
    name : str
        The name as written in the file.
    contours : tuple of Contour
        In file order.
    normalized_name : str
        The standard name ``name`` maps to through the synonym table (``name`` when no synonym matched,
        or when left empty).
    interpreted_type : str
        RT ROI Interpreted Type (``"ORGAN"``, ``"CTV"``, ``"BRACHY_CHANNEL"``, ...); empty when not given.
    color : (int, int, int) or None
        ROI Display Color, RGB 0-255.
    """

    number: int
    name: str
    contours: tuple[Contour, ...]
    normalized_name: str = ""
    interpreted_type: str = ""
    color: tuple[int, int, int] | None = None

    def __post_init__(self) -> None:
        if not self.normalized_name:
            object.__setattr__(self, "normalized_name", self.name)


@dataclass(frozen=True, eq=False)
class StructureSet:
    """The ROIs of an RT Structure Set and what they refer to.

    Parameters
    ----------
    rois : tuple of Roi
        In file order.
    frame_of_reference_uid : str
        Frame of Reference of every contour.
    referenced_series_uid : str or None
        SeriesInstanceUID of the images the contours were drawn on, when the file names one.
    sop_instance_uid, label : str
        SOP Instance UID and Structure Set Label of the file; empty when not given.
    patient_study : PatientStudy
        Patient and study as written in the file.
    referenced_images : tuple of (str, str)
        (SOP Class UID, SOP Instance UID) of the images of the referenced series, as listed in the file's
        Contour Image Sequence; empty when not given.

    Attributes
    ----------
    names : tuple of str
        The normalised names of ``rois``, in order.
    """

    rois: tuple[Roi, ...]
    frame_of_reference_uid: str
    referenced_series_uid: str | None = None
    sop_instance_uid: str = ""
    label: str = ""
    patient_study: PatientStudy = field(default_factory=PatientStudy)
    referenced_images: tuple[tuple[str, str], ...] = ()
    names: tuple[str, ...] = field(init=False)

    def __post_init__(self) -> None:
        object.__setattr__(self, "names", tuple(r.normalized_name for r in self.rois))

    def get(self, name: str) -> Roi:
        """Return the ROI whose normalised (or original) name is ``name``, case-insensitively.

        Of ROIs whose names differ only in case (``B5.5`` and ``b5.5``) the one spelt as asked.

        Parameters
        ----------
        name : str
            The ROI name, normalised or original (any case).

        Returns
        -------
        Roi
            The ROI.

        Raises
        ------
        StructureError
            With the list of available names.
        """
        key = name.casefold()
        for same in ([r for r in self.rois if r.normalized_name.casefold() == key],
                     [r for r in self.rois if r.name.casefold() == key]):
            if same:  # several only when names differ in case: the one spelt as asked, else the first
                return next((r for r in same if name in (r.normalized_name, r.name)), same[0])
        raise StructureError(f"no ROI named {name!r}; available: {', '.join(self.names) or 'none'}")
