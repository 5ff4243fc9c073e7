"""A deterministic synthetic pelvis for gynecologic interstitial brachytherapy, written as DICOM.

The phantom follows the OncoReach pilot phantom (reference ``oncoreach.md``, "Tissue and phantom": SimuGel
tissue, a uterus, 10 mm target cylinders, 15 mm tall every 60 degrees on a 65 mm circle and 5 mm tall on
an 80 mm circle) and the clinical case it stands for: an anteverted uterus tilted toward the bladder, a
cervix with a vaginal obturator, an HR-CTV reaching laterally into the parametria, bladder, rectum,
sigmoid colon, a bowel loop and pelvic bones.

Every structure is a union of disjoint analytic solids (:class:`Cylinder`, :class:`EllipticCylinder`,
:class:`Box`, :class:`Ellipsoid`, :class:`TorusSection`) with a closed-form volume, so the DICOM round
trip (write -> read -> mask -> mesh) can be checked against exact numbers. Geometry in DICOM patient
coordinates (LPS, mm): patient supine, +x patient left, +y posterior, +z superior; the perineal template
plane is ``z = 0`` with its centre on the obturator axis ``(0, 0, 0)`` and needles go in along +z.

CT slices are 2.5 mm thick with centres at ``z = -28.75 + 2.5 k``, so slab boundaries fall on multiples of
2.5 mm, where every flat end of a solid is placed (a contour stack then represents them exactly).

Geometry (LPS mm; exact values in :func:`phantom_spec`)
--------------------------------------------------------
* CT: 84 slices z -30..180, 256 x 256 pixels of 1 mm centred on the z axis; air -1000 HU, an 8 mm
  subcutaneous fat layer -90 HU, SimuGel +30 HU.
* Body: elliptic cylinder semi-axes (95, 90), z -30..180 (EXTERNAL).
* Obturator: cylinder r 15 on the z axis, z -30..60, +100 HU (BRACHY_ACCESSORY).
* Cervix: cylinder r 15, z 60..85, +50 HU. Uterus: ellipsoid semi (25, 18, 38) centred (0, -25, 115), long
  axis tilted 45 degrees from +z toward anterior (anteverted, toward the bladder), +45 HU.
* HR-CTV: ellipsoid semi (45, 20, 18) centred (0, 0, 75), +55 HU (CTV).
* Bladder: ellipsoid semi (40, 18, 25) centred (0, -65, 100), +10 HU.
* Rectum: cylinder r 12 at (0, 60), z -20..100, +40 HU. Sigmoid: tube r 10 on a quarter circle of radius 35
  from the rectum top (0, 60, 100) toward patient left and up to (35, 60, 135), +40 HU.
* Bowel: torus R 25, r 10 centred (0, -10, 160), axis along z, +35 HU.
* Bone (AVOIDANCE, +700 HU): side walls |x| 62..75, y -40..30, z -10..120; pubic symphysis x -15..15,
  y -75..-60, z -10..30.
* Targets (PTV, +80 HU): cylinders r 5, axes along z: ``Target_65_aaa`` 15 mm tall (z 67.5..82.5) on a 65 mm
  circle at angles 0, 60, ..., 300; ``Target_80_aaa`` 5 mm tall (z 77.5..82.5) on an 80 mm circle at
  30, 90, ..., 330; angle 0 = patient left (+x), 90 = anterior (-y).
* ``patient_from_template`` is the identity: template plane z = 0, centre on the obturator axis.
"""

from __future__ import annotations

import hashlib
import math
import re
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from reachplan.imaging.errors import OutputExistsError
from reachplan.imaging.files import atomic_write_files
from reachplan.imaging.sweep import Sweep, Union

#: target spacing (mm) between polygon vertices written for a cross-section
VERTEX_SPACING_MM = 0.75
MIN_VERTICES = 64


def _ring(n_perimeter_mm: float) -> np.ndarray:
    """Angles of ``n`` evenly spaced vertices for a closed curve of the given perimeter."""
    n = max(MIN_VERTICES, math.ceil(n_perimeter_mm / VERTEX_SPACING_MM))
    return np.linspace(0.0, 2.0 * np.pi, n, endpoint=False)


def _ellipse_perimeter(a: float, b: float) -> float:
    """Ramanujan's approximation of an ellipse's perimeter (mm)."""
    h = ((a - b) / (a + b)) ** 2
    return math.pi * (a + b) * (1 + 3 * h / (10 + math.sqrt(4 - 3 * h)))


def _ellipse(cx: float, cy: float, a: float, b: float, rot: np.ndarray | None = None) -> np.ndarray:
    t = _ring(_ellipse_perimeter(a, b))
    pts = np.column_stack([a * np.cos(t), b * np.sin(t)])
    if rot is not None:
        pts = pts @ rot.T
    return pts + np.array([cx, cy])


def _check_positive(obj: object, *names: str) -> None:
    for name in names:
        v = getattr(obj, name)
        if not (np.isfinite(v) and v > 0):
            raise ValueError(f"{type(obj).__name__}.{name} must be a positive number of mm, got {v}")


@dataclass(frozen=True)
class Cylinder:
    """A circular cylinder with its axis along patient z, ``z0_mm <= z < z1_mm``.

    Parameters
    ----------
    center_xy_mm : (float, float), mm, LPS
        The axis' x and y.
    radius_mm, z0_mm, z1_mm : float, mm
        Radius and axial extent (LPS z).

    Raises
    ------
    ValueError
        A radius that is not positive, or ``z1_mm <= z0_mm``.
    """

    center_xy_mm: tuple[float, float]
    radius_mm: float
    z0_mm: float
    z1_mm: float

    def __post_init__(self) -> None:
        _check_positive(self, "radius_mm")
        if not self.z1_mm > self.z0_mm:
            raise ValueError(f"Cylinder needs z1_mm > z0_mm, got {self.z0_mm}, {self.z1_mm}")

    @property
    def analytic_volume_mm3(self) -> float:
        """Exact volume, mm³."""
        return math.pi * self.radius_mm**2 * (self.z1_mm - self.z0_mm)

    def contains(self, p: np.ndarray) -> np.ndarray:
        """Tell which of the points ``p``, ``(..., 3)`` float in LPS mm, are inside: ``(...)`` bool."""
        cx, cy = self.center_xy_mm
        r2 = (p[..., 0] - cx) ** 2 + (p[..., 1] - cy) ** 2
        return (r2 <= self.radius_mm**2) & (p[..., 2] >= self.z0_mm) & (p[..., 2] < self.z1_mm)

    def cross_section(self, z0: float) -> list[np.ndarray]:
        """Return the closed polygons, each ``(n, 2)`` float (x, y) in LPS mm, of the axial cut ``z = z0``."""
        if not self.z0_mm <= z0 < self.z1_mm:
            return []
        return [_ellipse(*self.center_xy_mm, self.radius_mm, self.radius_mm)]

    def bounds(self) -> np.ndarray:
        """Return the bounding box, (2, 3) float, LPS mm: lower and upper corner."""
        cx, cy = self.center_xy_mm
        r = self.radius_mm
        return np.array([[cx - r, cy - r, self.z0_mm], [cx + r, cy + r, self.z1_mm]])


@dataclass(frozen=True)
class EllipticCylinder:
    """An elliptic cylinder (semi-axes along patient x and y), axis along z, ``z0_mm <= z < z1_mm``.

    Parameters
    ----------
    center_xy_mm, semi_axes_xy_mm : (float, float), mm, LPS
        The axis' x and y, and the semi-axes along x and y.
    z0_mm, z1_mm : float, mm
        Axial extent (LPS z).

    Raises
    ------
    ValueError
        A semi-axis that is not positive, or ``z1_mm <= z0_mm``.
    """

    center_xy_mm: tuple[float, float]
    semi_axes_xy_mm: tuple[float, float]
    z0_mm: float
    z1_mm: float

    def __post_init__(self) -> None:
        if min(self.semi_axes_xy_mm) <= 0 or not self.z1_mm > self.z0_mm:
            raise ValueError("EllipticCylinder needs positive semi-axes and z1_mm > z0_mm")

    @property
    def analytic_volume_mm3(self) -> float:
        """Exact volume, mm³."""
        a, b = self.semi_axes_xy_mm
        return math.pi * a * b * (self.z1_mm - self.z0_mm)

    def contains(self, p: np.ndarray) -> np.ndarray:
        """Tell which of the points ``p``, ``(..., 3)`` float in LPS mm, are inside: ``(...)`` bool."""
        (cx, cy), (a, b) = self.center_xy_mm, self.semi_axes_xy_mm
        q = ((p[..., 0] - cx) / a) ** 2 + ((p[..., 1] - cy) / b) ** 2
        return (q <= 1.0) & (p[..., 2] >= self.z0_mm) & (p[..., 2] < self.z1_mm)

    def cross_section(self, z0: float) -> list[np.ndarray]:
        """Return the closed polygons, each ``(n, 2)`` float (x, y) in LPS mm, of the axial cut ``z = z0``."""
        if not self.z0_mm <= z0 < self.z1_mm:
            return []
        return [_ellipse(*self.center_xy_mm, *self.semi_axes_xy_mm)]

    def bounds(self) -> np.ndarray:
        """Return the bounding box, (2, 3) float, LPS mm: lower and upper corner."""
        (cx, cy), (a, b) = self.center_xy_mm, self.semi_axes_xy_mm
        return np.array([[cx - a, cy - b, self.z0_mm], [cx + a, cy + b, self.z1_mm]])


@dataclass(frozen=True)
class Box:
    """An axis-aligned box ``lo_mm <= p < hi_mm``.

    Parameters
    ----------
    lo_mm, hi_mm : (float, float, float), mm, LPS
        Lower and upper corner.

    Raises
    ------
    ValueError
        ``hi_mm <= lo_mm`` on some axis.
    """

    lo_mm: tuple[float, float, float]
    hi_mm: tuple[float, float, float]

    def __post_init__(self) -> None:
        if not all(h > lo for lo, h in zip(self.lo_mm, self.hi_mm, strict=True)):
            raise ValueError(f"Box needs hi_mm > lo_mm on every axis, got {self.lo_mm}, {self.hi_mm}")

    @property
    def analytic_volume_mm3(self) -> float:
        """Exact volume, mm³."""
        return float(np.prod(np.subtract(self.hi_mm, self.lo_mm)))

    def contains(self, p: np.ndarray) -> np.ndarray:
        """Tell which of the points ``p``, ``(..., 3)`` float in LPS mm, are inside: ``(...)`` bool."""
        return np.all((p >= self.lo_mm) & (p < self.hi_mm), axis=-1)

    def cross_section(self, z0: float) -> list[np.ndarray]:
        """Return the closed polygons, each ``(n, 2)`` float (x, y) in LPS mm, of the axial cut ``z = z0``."""
        (x0, y0, za), (x1, y1, zb) = self.lo_mm, self.hi_mm
        if not za <= z0 < zb:
            return []
        return [np.array([[x0, y0], [x1, y0], [x1, y1], [x0, y1]], dtype=float)]

    def bounds(self) -> np.ndarray:
        """Return the bounding box, (2, 3) float, LPS mm: lower and upper corner."""
        return np.array([self.lo_mm, self.hi_mm], dtype=float)


def rotation_x(angle_deg: float) -> np.ndarray:
    """Return the (3, 3) rotation about patient x by ``angle_deg`` degrees (right-handed)."""
    a = math.radians(angle_deg)
    c, s = math.cos(a), math.sin(a)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


@dataclass(frozen=True)
class Ellipsoid:
    """An ellipsoid with semi-axes along the columns of ``rotation``.

    Parameters
    ----------
    center_mm : (float, float, float), mm, LPS
    semi_axes_mm : (float, float, float), mm
        Along the columns of ``rotation``.
    rotation : (3, 3) float
        ``patient_from_local``: orthonormal; its columns are the ellipsoid's axes in LPS.

    Raises
    ------
    ValueError
        A rotation that is not orthonormal, or a semi-axis that is not positive.
    """

    center_mm: tuple[float, float, float]
    semi_axes_mm: tuple[float, float, float]
    rotation: tuple[tuple[float, ...], ...] = ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0))
    _quad: np.ndarray = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        r = np.asarray(self.rotation, dtype=float)
        if r.shape != (3, 3) or not np.allclose(r.T @ r, np.eye(3), atol=1e-9):
            raise ValueError("Ellipsoid.rotation must be an orthonormal 3x3 matrix")
        if min(self.semi_axes_mm) <= 0:
            raise ValueError(f"Ellipsoid semi-axes must be positive, got {self.semi_axes_mm}")
        object.__setattr__(self, "_quad", r @ np.diag(1.0 / np.square(self.semi_axes_mm)) @ r.T)

    @property
    def analytic_volume_mm3(self) -> float:
        """Exact volume, mm³."""
        a, b, c = self.semi_axes_mm
        return 4.0 / 3.0 * math.pi * a * b * c

    def contains(self, p: np.ndarray) -> np.ndarray:
        """Tell which of the points ``p``, ``(..., 3)`` float in LPS mm, are inside: ``(...)`` bool."""
        d = p - np.asarray(self.center_mm)
        return np.einsum("...i,ij,...j->...", d, self._quad, d) <= 1.0

    def cross_section(self, z0: float) -> list[np.ndarray]:
        """Return the closed polygons, each ``(n, 2)`` float (x, y) in LPS mm, of the axial cut ``z = z0``."""
        q = self._quad
        dz = z0 - self.center_mm[2]
        a2, b = q[:2, :2], q[:2, 2] * dz
        m = -np.linalg.solve(a2, b)  # in-plane centre offset
        s = 1.0 - q[2, 2] * dz * dz + b @ np.linalg.solve(a2, b)
        if s <= 1e-12:
            return []
        w, v = np.linalg.eigh(a2 / s)
        semi = 1.0 / np.sqrt(w)
        return [_ellipse(self.center_mm[0] + m[0], self.center_mm[1] + m[1], semi[0], semi[1], v)]

    def bounds(self) -> np.ndarray:
        """Return the bounding box, (2, 3) float, LPS mm: lower and upper corner."""
        half = np.sqrt(np.diag(np.linalg.inv(self._quad)))
        c = np.asarray(self.center_mm)
        return np.array([c - half, c + half])


@dataclass(frozen=True)
class TorusSection:
    """A tube of radius ``minor_mm`` around a circular arc (a section of a torus).

    The arc is ``centre + major (cos φ u + sin φ v)`` for ``φ0 <= φ <= φ1`` (degrees); ``u`` and ``v``
    are orthonormal (LPS). Its volume is exact by Pappus: ``π r² · R · Δφ``.

    Parameters
    ----------
    center_mm : (float, float, float), mm, LPS
        Centre of the arc's circle.
    major_mm, minor_mm : float, mm
        Radius of the arc and of the tube, ``0 < minor_mm < major_mm``.
    u, v : (float, float, float), LPS
        Orthonormal directions spanning the arc's plane.
    phi0_deg, phi1_deg : float, degrees
        The arc, ``0 < phi1_deg - phi0_deg <= 360``.

    Raises
    ------
    ValueError
        Radii, directions or angles out of range.
    """

    center_mm: tuple[float, float, float]
    major_mm: float
    minor_mm: float
    u: tuple[float, float, float]
    v: tuple[float, float, float]
    phi0_deg: float = 0.0
    phi1_deg: float = 360.0

    def __post_init__(self) -> None:
        _check_positive(self, "major_mm", "minor_mm")
        if self.minor_mm >= self.major_mm:
            raise ValueError("TorusSection needs minor_mm < major_mm")
        u, v = np.asarray(self.u, float), np.asarray(self.v, float)
        if not (np.isclose(u @ u, 1) and np.isclose(v @ v, 1) and abs(u @ v) < 1e-9):
            raise ValueError("TorusSection u and v must be orthonormal")
        if not 0 < self.phi1_deg - self.phi0_deg <= 360:
            raise ValueError("TorusSection needs 0 < phi1_deg - phi0_deg <= 360")

    @property
    def full(self) -> bool:
        """The arc is a whole circle (a full torus)."""
        return self.phi1_deg - self.phi0_deg >= 360

    @property
    def analytic_volume_mm3(self) -> float:
        """Exact volume, mm³."""
        return math.pi * self.minor_mm**2 * self.major_mm * math.radians(self.phi1_deg - self.phi0_deg)

    def _field(self, p: np.ndarray) -> np.ndarray:
        """Signed distance-like field (mm): negative inside."""
        u, v = np.asarray(self.u), np.asarray(self.v)
        n = np.cross(u, v)
        d = p - np.asarray(self.center_mm)
        a, b, w = d @ u, d @ v, d @ n
        rho = np.hypot(a, b)
        f = np.hypot(rho - self.major_mm, w) - self.minor_mm
        if self.full:
            return f
        phi = np.degrees(np.arctan2(b, a))
        mid = 0.5 * (self.phi0_deg + self.phi1_deg)
        dphi = (phi - mid + 180.0) % 360.0 - 180.0  # angle from the middle of the arc, (-180, 180]
        out = np.radians(np.abs(dphi) - 0.5 * (self.phi1_deg - self.phi0_deg)) * np.maximum(rho, 1e-9)
        return np.maximum(f, out)

    def contains(self, p: np.ndarray) -> np.ndarray:
        """Tell which of the points ``p``, ``(..., 3)`` float in LPS mm, are inside: ``(...)`` bool."""
        return self._field(p) <= 0.0

    def cross_section(self, z0: float, step_mm: float = 0.2) -> list[np.ndarray]:
        """Return the closed polygons, each ``(n, 2)`` float (x, y) in LPS mm, of the axial cut ``z = z0``.

        The cut is traced as the zero level of the tube's distance field sampled every ``step_mm`` mm.
        """
        from skimage.measure import find_contours

        lo, hi = self.bounds()
        if not lo[2] < z0 < hi[2]:
            return []
        xs = np.arange(lo[0] - 2 * step_mm, hi[0] + 2 * step_mm, step_mm)
        ys = np.arange(lo[1] - 2 * step_mm, hi[1] + 2 * step_mm, step_mm)
        gx, gy = np.meshgrid(xs, ys, indexing="ij")
        f = self._field(np.stack([gx, gy, np.full_like(gx, z0)], axis=-1))
        if f.min() >= 0:
            return []
        out = []
        for c in find_contours(f, 0.0):
            c = c[:-1] if np.allclose(c[0], c[-1]) else c
            seg = np.linalg.norm(np.diff(c, axis=0), axis=1).mean() * step_mm
            k = max(1, min(round(VERTEX_SPACING_MM / max(seg, 1e-9)), len(c) // MIN_VERTICES))
            c = c[::k]
            if len(c) >= 3:
                out.append(np.column_stack([xs[0] + c[:, 0] * step_mm, ys[0] + c[:, 1] * step_mm]))
        return out

    def bounds(self) -> np.ndarray:
        """Return the bounding box, (2, 3) float, LPS mm: lower and upper corner."""
        c = np.asarray(self.center_mm)
        ext = self.major_mm + self.minor_mm
        if self.full:
            u, v = np.asarray(self.u), np.asarray(self.v)
            n = np.cross(u, v)
            half = ext * np.sqrt(u**2 + v**2) + self.minor_mm * np.abs(n)
            return np.array([c - half, c + half])
        phi = np.radians(np.linspace(self.phi0_deg, self.phi1_deg, 721))
        arc = c + self.major_mm * (np.outer(np.cos(phi), self.u) + np.outer(np.sin(phi), self.v))
        return np.array([arc.min(axis=0) - self.minor_mm, arc.max(axis=0) + self.minor_mm])


Shape = Cylinder | EllipticCylinder | Box | Ellipsoid | TorusSection | Sweep | Union


# --------------------------------------------------------------------------------------------------
# The phantom's description
# --------------------------------------------------------------------------------------------------


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
        """Tell which of the points ``p``, ``(..., 3)`` float in LPS mm, are inside: ``(...)`` bool."""
        inside = np.zeros(p.shape[:-1], dtype=bool)
        for s in self.shapes:
            inside |= s.contains(p)
        return inside

    def cross_section(self, z_mm: float) -> list[np.ndarray]:
        """Return the closed polygons, each ``(n, 2)`` float (x, y) in LPS mm, of the axial cut ``z = z_mm``."""
        return [poly for s in self.shapes for poly in s.cross_section(z_mm)]

    def bounds(self) -> np.ndarray:
        """Return the bounding box, (2, 3) float, LPS mm: lower and upper corner."""
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
        """Return the structure called ``name`` (exact match); KeyError when there is none."""
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


def _targets() -> list[PhantomStructure]:
    """Build the reference target cylinders (10 mm diameter, axes along z); angle 0 = patient left, 90 = anterior."""
    out = []
    for diameter, height, z_centre, angles in ((65.0, 15.0, 75.0, range(0, 360, 60)),
                                               (80.0, 5.0, 80.0, range(30, 360, 60))):
        r = diameter / 2
        for a in angles:
            x, y = r * math.cos(math.radians(a)), -r * math.sin(math.radians(a))
            out.append(PhantomStructure(
                f"Target_{diameter:.0f}_{a:03d}", "PTV",
                (Cylinder((round(x, 6), round(y, 6)), 5.0, z_centre - height / 2, z_centre + height / 2),),
                hu=80.0, color=(255, 0, 0)))
    return out


def phantom_spec() -> PhantomSpec:
    """Describe the built-in phantom analytically (see the module docstring for frames and values)."""
    tilt = rotation_x(45.0)  # uterus long axis: +z tilted 45 degrees toward anterior (-y)
    structures = [
        PhantomStructure("Body", "EXTERNAL", (EllipticCylinder((0.0, 0.0), (95.0, 90.0), -30.0, 180.0),),
                         hu=30.0, color=(200, 180, 140)),
        PhantomStructure("Bone", "AVOIDANCE", (
            Box((-75.0, -40.0, -10.0), (-62.0, 30.0, 120.0)),  # right pelvic side wall
            Box((62.0, -40.0, -10.0), (75.0, 30.0, 120.0)),  # left pelvic side wall
            Box((-15.0, -75.0, -10.0), (15.0, -60.0, 30.0)),  # pubic symphysis
        ), hu=700.0, color=(240, 240, 220), is_oar=True),
        PhantomStructure("Rectum", "ORGAN", (Cylinder((0.0, 60.0), 12.0, -20.0, 100.0),),
                         hu=40.0, color=(150, 90, 40), is_oar=True),
        PhantomStructure("Sigmoid", "ORGAN", (TorusSection(
            (35.0, 60.0, 100.0), 35.0, 10.0, u=(-1.0, 0.0, 0.0), v=(0.0, 0.0, 1.0), phi0_deg=0.0, phi1_deg=90.0),),
            hu=40.0, color=(200, 120, 60), is_oar=True),
        PhantomStructure("Bowel", "ORGAN", (TorusSection(
            (0.0, -10.0, 160.0), 25.0, 10.0, u=(1.0, 0.0, 0.0), v=(0.0, 1.0, 0.0)),),
            hu=35.0, color=(230, 180, 60), is_oar=True),
        PhantomStructure("Bladder", "ORGAN", (Ellipsoid((0.0, -65.0, 100.0), (40.0, 18.0, 25.0)),),
                         hu=10.0, color=(250, 230, 50), is_oar=True),
        PhantomStructure("Uterus", "ORGAN", (Ellipsoid(
            (0.0, -25.0, 115.0), (25.0, 18.0, 38.0), tuple(tuple(float(v) for v in row) for row in tilt)),),
            hu=45.0, color=(230, 130, 170)),
        PhantomStructure("Cervix", "ORGAN", (Cylinder((0.0, 0.0), 15.0, 60.0, 85.0),),
                         hu=50.0, color=(200, 90, 140)),
        PhantomStructure("HR-CTV", "CTV", (Ellipsoid((0.0, 0.0, 75.0), (45.0, 20.0, 18.0)),),
                         hu=55.0, color=(255, 60, 60)),
        PhantomStructure("Obturator", "BRACHY_ACCESSORY", (Cylinder((0.0, 0.0), 15.0, -30.0, 60.0),),
                         hu=100.0, color=(120, 120, 255)),
        *_targets(),
    ]
    return PhantomSpec(tuple(structures))


# Paint order of the CT (later wins): tissue first, then organs, target complex, applicator, bone.
_PAINT_ORDER = ("Body", "Rectum", "Sigmoid", "Bowel", "Bladder", "Uterus", "Cervix", "HR-CTV")


def phantom_ct_hu(spec: PhantomSpec) -> np.ndarray:
    """Paint the CT of the phantom in HU, sampled at the voxel centres (later structures in the paint order win).

    Parameters
    ----------
    spec : PhantomSpec
        The phantom (structures, CT geometry and CT numbers).

    Returns
    -------
    hu : (n_slices, matrix, matrix) int16, HU
        Indexed ``[k, j, i]`` (slice, row = y, column = x); voxel centres at LPS ``z = spec.slice_z_mm[k]``,
        ``y = x0 + j * pixel_mm``, ``x = x0 + i * pixel_mm`` with ``x0 = spec.first_pixel_xy_mm``.
    """
    n, z = spec.matrix, spec.slice_z_mm
    xy = spec.first_pixel_xy_mm + np.arange(n) * spec.pixel_mm
    hu = np.full((len(z), n, n), spec.air_hu, dtype=np.float32)
    if spec.paint_order:
        for name in spec.paint_order:
            _paint(hu, spec.get(name), z, xy)
        return np.round(hu).astype(np.int16)
    order = [*_PAINT_ORDER, *(s.name for s in spec.targets), "Obturator", "Bone"]
    painted = {s.name for s in spec.structures if s.name in order}
    order += [s.name for s in spec.structures if s.name not in painted]
    body = spec.get("Body") if "Body" in {s.name for s in spec.structures} else None
    fat_inner = None
    if body is not None and isinstance(body.shapes[0], EllipticCylinder) and spec.fat_thickness_mm > 0:
        outer = body.shapes[0]
        (a, b), t = outer.semi_axes_xy_mm, spec.fat_thickness_mm
        fat_inner = PhantomStructure("gel", "", (EllipticCylinder(outer.center_xy_mm, (a - t, b - t), outer.z0_mm,
                                                                  outer.z1_mm),), hu=body.hu, color=body.color)
        body = PhantomStructure("fat", "", body.shapes, hu=spec.fat_hu, color=body.color)
    for name in order:
        if name == "Body" and body is not None and fat_inner is not None:
            shapes = [body, fat_inner]
        else:
            shapes = [spec.get(name)]
        for s in shapes:
            _paint(hu, s, z, xy)
    return np.round(hu).astype(np.int16)


def _paint(hu: np.ndarray, s: PhantomStructure, z: np.ndarray, xy: np.ndarray) -> None:
    """Set ``hu`` to ``s.hu`` at the voxel centres inside ``s`` (in place)."""
    lo, hi = s.bounds()
    ks = np.flatnonzero((z >= lo[2]) & (z <= hi[2]))
    js = np.flatnonzero((xy >= lo[1]) & (xy <= hi[1]))
    is_ = np.flatnonzero((xy >= lo[0]) & (xy <= hi[0]))
    if not (len(ks) and len(js) and len(is_)):
        return
    parts = [sh for sh in s.shapes if isinstance(sh, Sweep | Union)]
    if len(parts) == len(s.shapes):  # slice by slice, in each part's window
        for sh in parts:
            for k in ks:
                win = sh.slice_window(float(z[k]))
                if win is None:
                    continue
                j = np.flatnonzero((xy >= win[0][1]) & (xy <= win[1][1]))
                i = np.flatnonzero((xy >= win[0][0]) & (xy <= win[1][0]))
                if not (len(j) and len(i)):
                    continue
                gy, gx = np.meshgrid(xy[j], xy[i], indexing="ij")
                inside = sh.contains(np.stack([gx, gy, np.full_like(gx, z[k])], axis=-1))
                hu[k, j[0]:j[-1] + 1, i[0]:i[-1] + 1][inside] = s.hu
        return
    gz, gy, gx = np.meshgrid(z[ks], xy[js], xy[is_], indexing="ij")
    inside = s.contains(np.stack([gx, gy, gz], axis=-1))
    sub = hu[ks[0]:ks[-1] + 1, js[0]:js[-1] + 1, is_[0]:is_[-1] + 1]
    sub[inside] = s.hu


# --------------------------------------------------------------------------------------------------
# Writing DICOM
# --------------------------------------------------------------------------------------------------

#: Identity of the phantom's files; changing the geometry must change PHANTOM_VERSION (new UIDs).
PHANTOM_VERSION = "2"
MANUFACTURER = "reachplan"
MODEL_NAME = "reachplan pelvic phantom"
CT_IMAGE_STORAGE = "1.2.840.10008.5.1.4.1.1.2"
MR_IMAGE_STORAGE = "1.2.840.10008.5.1.4.1.1.4"
RT_STRUCTURE_SET_STORAGE = "1.2.840.10008.5.1.4.1.1.481.3"


@dataclass(frozen=True)
class PhantomFiles:
    """Where :func:`write_phantom` put the phantom.

    The image series folder (CT or MR) and the RT Structure Set file.
    """

    ct_dir: Path
    rtstruct_path: Path


def _uid(*parts: str, case_id: str = "") -> str:
    """Derive a deterministic UID ``2.25.<128-bit hash>`` (ISO/IEC 9834-8 UUID arc).

    The hash covers the phantom version, the case id (when not empty) and ``parts``.
    """
    case = ["case", case_id] if case_id else []
    digest = hashlib.sha256("\0".join(["reachplan phantom", PHANTOM_VERSION, *case, *parts]).encode()).hexdigest()
    return f"2.25.{int(digest[:32], 16)}"


def _base_dataset(sop_class: str, sop_instance: str, modality: str, series_uid: str,
                  series_number: int, description: str, case_id: str = "",
                  study_description: str = "reachplan synthetic pelvis (gyn ISBT)") -> Any:
    from pydicom.dataset import FileDataset, FileMetaDataset
    from pydicom.uid import PYDICOM_IMPLEMENTATION_UID, UID, ExplicitVRLittleEndian

    meta = FileMetaDataset()
    meta.MediaStorageSOPClassUID = UID(sop_class)
    meta.MediaStorageSOPInstanceUID = UID(sop_instance)
    meta.TransferSyntaxUID = ExplicitVRLittleEndian
    meta.ImplementationClassUID = PYDICOM_IMPLEMENTATION_UID
    ds = FileDataset("", {}, file_meta=meta, preamble=b"\0" * 128)
    ds.SpecificCharacterSet = "ISO_IR 100"
    ds.SOPClassUID = sop_class
    ds.SOPInstanceUID = sop_instance
    ds.StudyDate = ds.SeriesDate = "20260101"
    ds.StudyTime = ds.SeriesTime = "120000"
    ds.AccessionNumber = ""
    ds.Modality = modality
    ds.Manufacturer = MANUFACTURER
    ds.ManufacturerModelName = MODEL_NAME
    ds.SoftwareVersions = f"phantom {PHANTOM_VERSION}"
    ds.ReferringPhysicianName = ""
    ds.StudyDescription = study_description
    ds.SeriesDescription = description
    ds.PatientName = "Phantom^Pelvis"
    ds.PatientID = f"REACHPLAN-PHANTOM-{case_id}" if case_id else "REACHPLAN-PHANTOM"
    ds.PatientBirthDate = ""
    ds.PatientSex = "F"
    ds.StudyInstanceUID = _uid("study", case_id=case_id)
    ds.SeriesInstanceUID = series_uid
    ds.StudyID = "1"
    ds.SeriesNumber = series_number
    return ds


@dataclass(frozen=True)
class _ImageRef:
    """What the structure set references of one written image."""

    SOPClassUID: str
    SOPInstanceUID: str
    SeriesInstanceUID: str
    StudyInstanceUID: str
    FrameOfReferenceUID: str


def _ct_files(spec: PhantomSpec) -> Iterator[tuple[str, bytes, _ImageRef]]:
    """Return the image slices, (file name, DICOM bytes, reference) each: CT (HU), or MR (T2-weighted-like).

    MR when ``spec.modality == "MR"``. One dataset holds everything the slices share; per slice only the instance
    UID, number, position and pixels are set before it is encoded.
    """
    values = phantom_ct_hu(spec)
    mr = spec.modality == "MR"
    tag = "mr" if mr else "ct"
    series_uid = _uid(f"{tag} series", case_id=spec.case_id)
    for_uid = _uid("frame of reference", case_id=spec.case_id)
    x0 = spec.first_pixel_xy_mm
    sop = MR_IMAGE_STORAGE if mr else CT_IMAGE_STORAGE
    ds = _base_dataset(sop, _uid(tag, "0", case_id=spec.case_id), spec.modality, series_uid, 1,
                       f"phantom {spec.modality}", spec.case_id, spec.description)
    ds.ImageType = ["DERIVED", "SECONDARY", "AXIAL"] if not mr else ["DERIVED", "SECONDARY", "OTHER"]
    ds.InstanceNumber = 1
    ds.FrameOfReferenceUID = for_uid
    ds.PositionReferenceIndicator = ""
    ds.PatientPosition = "HFS"
    ds.BodyPartExamined = "PELVIS"
    if mr:  # MR Image module (PS3.3 C.8.3.1): a T2-weighted turbo spin echo, described not simulated
        ds.ScanningSequence = "SE"
        ds.SequenceVariant = "SK"
        ds.ScanOptions = ""
        ds.MRAcquisitionType = "2D"
        ds.RepetitionTime = 4000
        ds.EchoTime = 100
        ds.EchoTrainLength = 16
        ds.MagneticFieldStrength = 1.5
        ds.ImagedNucleus = "1H"
        ds.SpacingBetweenSlices = spec.slice_thickness_mm
    else:
        ds.KVP = ""
    ds.AcquisitionNumber = 1
    ds.ImageOrientationPatient = [1, 0, 0, 0, 1, 0]
    ds.SliceThickness = spec.slice_thickness_mm
    ds.PixelSpacing = [spec.pixel_mm, spec.pixel_mm]
    ds.SamplesPerPixel = 1
    ds.PhotometricInterpretation = "MONOCHROME2"
    ds.Rows = ds.Columns = spec.matrix
    ds.BitsAllocated = 16
    ds.BitsStored = 16
    ds.HighBit = 15
    ds.PixelRepresentation = 0 if mr else 1
    if mr:
        ds.WindowCenter = 700
        ds.WindowWidth = 1600
        pixels = np.clip(values, 0, None).astype(np.uint16)
    else:
        ds.RescaleIntercept = 0
        ds.RescaleSlope = 1
        ds.RescaleType = "HU"
        ds.WindowCenter = 40
        ds.WindowWidth = 400
        pixels = values
    for k, z in enumerate(spec.slice_z_mm):
        uid = _uid(tag, str(k), case_id=spec.case_id)
        ds.file_meta.MediaStorageSOPInstanceUID = uid
        ds.SOPInstanceUID = uid
        ds.InstanceNumber = k + 1
        ds.ImagePositionPatient = [f"{x0:.3f}", f"{x0:.3f}", f"{z:.3f}"]
        ds.SliceLocation = f"{z:.3f}"
        ds.PixelData = pixels[k].tobytes()
        yield (f"{spec.modality}.{k + 1:04d}.dcm", _encode(ds),
               _ImageRef(sop, uid, series_uid, ds.StudyInstanceUID, for_uid))


def _rtstruct_dataset(spec: PhantomSpec, ct: list[_ImageRef]) -> Any:
    from pydicom.dataset import Dataset
    from pydicom.sequence import Sequence

    first = ct[0]
    ds = _base_dataset(RT_STRUCTURE_SET_STORAGE, _uid("rtstruct", case_id=spec.case_id), "RTSTRUCT",
                       _uid("rtstruct series", case_id=spec.case_id), 2, "phantom structures", spec.case_id)
    ds.InstanceNumber = 1
    ds.OperatorsName = ""
    ds.FrameOfReferenceUID = first.FrameOfReferenceUID
    ds.PositionReferenceIndicator = ""
    ds.StructureSetLabel = "PHANTOM"
    ds.StructureSetName = "reachplan phantom"
    ds.StructureSetDate = "20260101"
    ds.StructureSetTime = "120000"

    def image_ref(img: _ImageRef) -> Dataset:
        r = Dataset()
        r.ReferencedSOPClassUID = img.SOPClassUID
        r.ReferencedSOPInstanceUID = img.SOPInstanceUID
        return r

    series = Dataset()
    series.SeriesInstanceUID = first.SeriesInstanceUID
    series.ContourImageSequence = Sequence([image_ref(img) for img in ct])
    study = Dataset()
    study.ReferencedSOPClassUID = "1.2.840.10008.3.1.2.3.1"  # Detached Study Management (retired, as TPSs write)
    study.ReferencedSOPInstanceUID = first.StudyInstanceUID
    study.RTReferencedSeriesSequence = Sequence([series])
    for_ref = Dataset()
    for_ref.FrameOfReferenceUID = first.FrameOfReferenceUID
    for_ref.RTReferencedStudySequence = Sequence([study])
    ds.ReferencedFrameOfReferenceSequence = Sequence([for_ref])

    rois, contours, observations = [], [], []
    z_all = spec.slice_z_mm
    for number, s in enumerate(spec.structures, start=1):
        roi = Dataset()
        roi.ROINumber = number
        roi.ReferencedFrameOfReferenceUID = first.FrameOfReferenceUID
        roi.ROIName = s.name
        roi.ROIGenerationAlgorithm = "AUTOMATIC"
        rois.append(roi)
        items = []
        for k, z in enumerate(z_all):
            for poly in s.cross_section(float(z)):
                c = Dataset()
                c.ContourImageSequence = Sequence([image_ref(ct[k])])
                c.ContourGeometricType = "CLOSED_PLANAR"
                c.NumberOfContourPoints = len(poly)
                pts = np.column_stack([poly, np.full(len(poly), z)])
                c[0x30060050] = _raw_ds(0x30060050, pts.ravel())  # ContourData
                c.set_original_encoding(False, True, "iso8859")  # lets pydicom write the raw bytes as they are
                items.append(c)
        rc = Dataset()
        rc.ROIDisplayColor = list(s.color)
        rc.ReferencedROINumber = number
        rc.ContourSequence = Sequence(items)
        contours.append(rc)
        obs = Dataset()
        obs.ObservationNumber = number
        obs.ReferencedROINumber = number
        obs.RTROIInterpretedType = s.interpreted_type
        obs.ROIInterpreter = ""
        observations.append(obs)
    ds.StructureSetROISequence = Sequence(rois)
    ds.ROIContourSequence = Sequence(contours)
    ds.RTROIObservationsSequence = Sequence(observations)
    return ds


def _raw_ds(tag: int, values: np.ndarray) -> Any:
    """Build a DS element holding ``values`` (3 decimals) as raw bytes (pydicom's per-value checks are slow)."""
    from pydicom.dataelem import RawDataElement
    from pydicom.tag import Tag

    text = "\\".join([f"{v:.3f}" for v in values.tolist()]).encode("ascii")  # Python floats: 5x faster
    if len(text) % 2:
        text += b" "
    return RawDataElement(Tag(tag), "DS", len(text), text, 0, False, True)


def _is_phantom_file(path: Path) -> bool:
    """Tell whether ``path`` is a DICOM file this module wrote (any version)."""
    from pydicom import dcmread

    try:
        ds = dcmread(path, stop_before_pixels=True, specific_tags=["Manufacturer", "ManufacturerModelName"])
    except Exception:  # any unreadable file is not ours
        return False
    return ds.get("Manufacturer") == MANUFACTURER and ds.get("ManufacturerModelName") == MODEL_NAME


def _encode(ds: Any) -> bytes:
    """Return the DICOM file of a dataset as bytes."""
    import io

    buf = io.BytesIO()
    ds.save_as(buf, enforce_file_format=True)
    return buf.getvalue()


def write_phantom(out_dir: Path, spec: PhantomSpec | None = None) -> PhantomFiles:
    """Write the phantom as a DICOM CT series and an RT Structure Set.

    Files: ``out_dir/CT/CT.0001.dcm ...`` (``out_dir/MR/MR.0001.dcm ...`` for an MR spec) and
    ``out_dir/RS.phantom.dcm``. The output is deterministic
    (fixed UIDs derived from the phantom version). Existing phantom files are replaced (atomically,
    file by file); any other file in the way is left untouched and :class:`OutputExistsError` is raised
    before anything is written.

    Parameters
    ----------
    out_dir : Path
        Folder to create or reuse.
    spec : PhantomSpec, optional
        The phantom to write (default :func:`phantom_spec`).

    Returns
    -------
    PhantomFiles

    Raises
    ------
    OutputExistsError
        ``out_dir`` is a file, or a file that is not a reachplan phantom file is in the way.
    """
    spec = spec or phantom_spec()
    out_dir = Path(out_dir)
    ct_dir, rs_path = out_dir / spec.modality, out_dir / "RS.phantom.dcm"
    if out_dir.exists() and not out_dir.is_dir():
        raise OutputExistsError(f"{out_dir} is a file; give a folder for the phantom")
    names = [f"{spec.modality}.{k + 1:04d}.dcm" for k in range(spec.n_slices)]
    in_the_way = [p for p in [rs_path, *(ct_dir / n for n in names)] if p.exists() and not _is_phantom_file(p)]
    stale = []
    if ct_dir.is_dir():
        extra = [p for p in sorted(ct_dir.iterdir()) if p.name not in names and not p.name.startswith(".")]
        in_the_way += [p for p in extra if not _is_phantom_file(p)]
        stale = [p for p in extra if p not in in_the_way]
    if in_the_way:
        raise OutputExistsError(
            f"{in_the_way[0]} (and {len(in_the_way) - 1} more) is not a reachplan phantom file; "
            "refusing to overwrite: choose an empty or new --out folder"
        )
    ct_dir.mkdir(parents=True, exist_ok=True)
    for p in stale:  # slices of an older phantom version would form a second series
        p.unlink()
    ct, encoded = [], []
    for name, data, ref in _ct_files(spec):
        encoded.append((ct_dir / name, data))
        ct.append(ref)
    encoded.append((rs_path, _encode(_rtstruct_dataset(spec, ct))))
    atomic_write_files(encoded)  # each file atomic, one batch of disk flushes for the series
    return PhantomFiles(ct_dir=ct_dir, rtstruct_path=rs_path)
