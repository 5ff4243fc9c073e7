"""The description of a built-in case: its structures (unions of analytic solids) and its image geometry.

The data types the phantom (:mod:`reachplan.imaging.phantom`) and the clinical case build, and the DICOM encoding
(:mod:`reachplan.imaging.case_dicom`) writes. Geometry in DICOM patient coordinates (LPS, mm).
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field

import numpy as np

from reachplan.imaging.solids import Shape


@dataclass(frozen=True)
class PhantomStructure:
    """One ROI of the phantom, made of disjoint solids (their union).

    Parameters
    ----------
    name : str
        ROI name, as written to the file.
    interpreted_type : str
        RT ROI Interpreted Type written to the file.
    shapes : tuple of Cylinder, EllipticCylinder, Box, Ellipsoid or TorusSection
        Disjoint solids, LPS mm; at least one.
    hu : float, HU
        CT number painted inside.
    color : (int, int, int)
        ROI Display Color, RGB 0-255.
    is_oar : bool
        An organ at risk a needle must avoid (bone included).

    Raises
    ------
    ValueError
        No shapes.
    """

    name: str
    interpreted_type: str
    shapes: tuple[Shape, ...]
    hu: float
    color: tuple[int, int, int]
    is_oar: bool = False

    def __post_init__(self) -> None:
        if not self.shapes:
            raise ValueError(f"structure {self.name!r} needs at least one shape")

    @property
    def primitive(self) -> str:
        """The kind of solid(s), e.g. ``"Ellipsoid"`` or ``"Box x3"``."""
        kinds = sorted({type(s).__name__ for s in self.shapes})
        return " + ".join(kinds) + (f" x{len(self.shapes)}" if len(self.shapes) > 1 else "")

    @property
    def analytic_volume_mm3(self) -> float:
        """Exact volume (mm³) of the union (the shapes are disjoint)."""
        return float(sum(s.analytic_volume_mm3 for s in self.shapes))

    def contains(self, p: np.ndarray) -> np.ndarray:
        """Tell which points are inside any of the structure's shapes.

        Parameters
        ----------
        p : (..., 3) float, mm, LPS
            The points to test.

        Returns
        -------
        (...) bool
            True where one shape holds the point.
        """
        inside = np.zeros(p.shape[:-1], dtype=bool)
        for s in self.shapes:
            inside |= s.contains(p)
        return inside

    def cross_section(self, z_mm: float) -> list[np.ndarray]:
        """Return the closed polygons of every shape on the axial plane ``z = z_mm``.

        Parameters
        ----------
        z_mm : float, mm
            The plane's LPS z.

        Returns
        -------
        list of (n, 2) float, mm, LPS
            The x, y outlines, shape by shape.
        """
        return [poly for s in self.shapes for poly in s.cross_section(z_mm)]

    def bounds(self) -> np.ndarray:
        """Return the box around all the shapes.

        Returns
        -------
        (2, 3) float, mm, LPS
            Lowest and highest corner over the shapes' bounding boxes.
        """
        b = np.array([s.bounds() for s in self.shapes])
        return np.array([b[:, 0].min(axis=0), b[:, 1].max(axis=0)])


@dataclass(frozen=True, eq=False)
class PhantomSpec:
    """The analytic phantom and its CT geometry.

    Parameters
    ----------
    structures : tuple of PhantomStructure
        Every ROI, in the order written (targets last); names unique.
    slice_thickness_mm, pixel_mm : float, mm
        CT slice spacing and in-plane pixel size.
    z_range_mm : (float, float), mm, LPS z
        ``(z0, z1)`` extent of the CT slabs, a whole number of slices; slice centres at
        ``z0 + (k + 0.5) * slice_thickness_mm``.
    matrix : int
        Rows = columns of the CT.
    air_hu, fat_hu : float, HU
        CT numbers outside the body and of a subcutaneous fat layer under the body outline (the body's own
        ``hu`` is the gel inside it); painted only, not a ROI.
    fat_thickness_mm : float, mm
        Thickness of that fat layer.
    patient_from_template : (4, 4) float
        Template frame (origin at the obturator axis on the perineal plane, x/y in the template plane, +z the
        insertion direction; mm) to LPS mm.
    case_id : str
        Empty for the reference phantom; a variant's id (e.g. ``case_003``) gives it its own DICOM UIDs and
        Patient ID, so variants are distinct patients, studies and Frames of Reference.
    tissues : tuple of PhantomStructure
        Structures painted into the image but not written as ROIs (fat, muscle, urine, gas, marrow).
    paint_order : tuple of str
        Names of structures and tissues in paint order (later wins); empty: the pilot's order.
    modality : str
        ``"CT"`` (HU) or ``"MR"`` (the ``hu`` of each structure is then its signal, arbitrary units).
    description : str
        The DICOM StudyDescription.

    Raises
    ------
    ValueError
        A bad ``case_id``, duplicate names, non-positive sizes, a z range that is not whole slices, or a
        ``patient_from_template`` that is not 4x4.
    """

    structures: tuple[PhantomStructure, ...]
    slice_thickness_mm: float = 2.5
    pixel_mm: float = 1.0
    z_range_mm: tuple[float, float] = (-30.0, 180.0)
    matrix: int = 256
    air_hu: float = -1000.0
    fat_hu: float = -90.0
    fat_thickness_mm: float = 8.0
    patient_from_template: np.ndarray = field(default_factory=lambda: np.eye(4))
    case_id: str = ""
    tissues: tuple[PhantomStructure, ...] = ()
    paint_order: tuple[str, ...] = ()
    modality: str = "CT"
    description: str = "reachplan synthetic pelvis (gyn ISBT)"

    def __post_init__(self) -> None:
        if self.case_id and not re.fullmatch(r"[A-Za-z0-9_.-]{1,40}", self.case_id):
            raise ValueError(f"case_id must be 1-40 characters of [A-Za-z0-9_.-], got {self.case_id!r}")
        names = [s.name for s in self.structures]
        if len(set(names)) != len(names):
            raise ValueError(f"phantom structure names must be unique, got {names}")
        if not (self.slice_thickness_mm > 0 and self.pixel_mm > 0 and self.matrix > 0):
            raise ValueError("slice_thickness_mm, pixel_mm and matrix must be positive")
        n = (self.z_range_mm[1] - self.z_range_mm[0]) / self.slice_thickness_mm
        if n < 1 or abs(n - round(n)) > 1e-9:
            raise ValueError(f"z_range_mm {self.z_range_mm} must span a whole number of slices")
        if self.modality not in ("CT", "MR"):
            raise ValueError(f"modality must be 'CT' or 'MR', got {self.modality!r}")
        known = {*names, *(t.name for t in self.tissues)}
        if set(self.paint_order) - known:
            raise ValueError(f"paint_order names unknown structures: {sorted(set(self.paint_order) - known)}")
        m = np.asarray(self.patient_from_template, dtype=float)
        if m.shape != (4, 4):
            raise ValueError("patient_from_template must be a 4x4 matrix")

    @property
    def organs(self) -> tuple[PhantomStructure, ...]:
        """Every structure that is not a ``Target_*`` cylinder."""
        return tuple(s for s in self.structures if not s.name.startswith("Target_"))

    @property
    def targets(self) -> tuple[PhantomStructure, ...]:
        """The reference phantom's target cylinders."""
        return tuple(s for s in self.structures if s.name.startswith("Target_"))

    @property
    def oars(self) -> tuple[PhantomStructure, ...]:
        """The organs at risk (``is_oar``), bone included."""
        return tuple(s for s in self.structures if s.is_oar)

    def get(self, name: str) -> PhantomStructure:
        """Return the structure called ``name`` (exact match), among the ROIs and the painted tissues.

        Parameters
        ----------
        name : str
            The ROI or tissue name, exactly as in the spec.

        Returns
        -------
        PhantomStructure
            The structure.

        Raises
        ------
        KeyError
            When there is none.
        """
        for s in (*self.structures, *self.tissues):
            if s.name == name:
                return s
        raise KeyError(name)

    @property
    def n_slices(self) -> int:
        """Number of CT slices."""
        return round((self.z_range_mm[1] - self.z_range_mm[0]) / self.slice_thickness_mm)

    @property
    def slice_z_mm(self) -> np.ndarray:
        """(n_slices,) float, mm: z of each CT slice centre."""
        return self.z_range_mm[0] + (np.arange(self.n_slices) + 0.5) * self.slice_thickness_mm

    @property
    def first_pixel_xy_mm(self) -> float:
        """Coordinate x (= y) of the centre of the first pixel, LPS mm; the field of view is centred on the z axis."""
        return -0.5 * (self.matrix - 1) * self.pixel_mm
