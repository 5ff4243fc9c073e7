"""Analytic solids with closed-form volumes: the building blocks of the pilot phantom.

Each solid (:class:`Cylinder`, :class:`EllipticCylinder`, :class:`Box`, :class:`Ellipsoid`,
:class:`TorusSection`) tells which points are inside, gives its axial cross-sections as closed polygons
(for an RT Structure Set) and its bounding box, and knows its exact volume, so a DICOM round trip can be
checked against exact numbers. Geometry in DICOM patient coordinates (LPS, mm).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

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
        """Tell which points are inside the cylinder.

        Parameters
        ----------
        p : (..., 3) float, mm, LPS
            Points to test against the cylinder (axis along z).

        Returns
        -------
        (...) bool
            True inside: within ``radius_mm`` of the axis and ``z0_mm <= z < z1_mm``.
        """
        cx, cy = self.center_xy_mm
        r2 = (p[..., 0] - cx) ** 2 + (p[..., 1] - cy) ** 2
        return (r2 <= self.radius_mm**2) & (p[..., 2] >= self.z0_mm) & (p[..., 2] < self.z1_mm)

    def cross_section(self, z0: float) -> list[np.ndarray]:
        """Return the closed polygons of the axial cut ``z = z0``.

        Parameters
        ----------
        z0 : float, mm
            LPS z of the plane cutting the cylinder (axis along z).

        Returns
        -------
        list of (n, 2) float, mm, LPS
            The cut's circle as one (x, y) polygon; none outside ``z0_mm <= z < z1_mm``.
        """
        if not self.z0_mm <= z0 < self.z1_mm:
            return []
        return [_ellipse(*self.center_xy_mm, self.radius_mm, self.radius_mm)]

    def bounds(self) -> np.ndarray:
        """Return the bounding box of the cylinder.

        Returns
        -------
        (2, 3) float, mm, LPS
            Lower and upper corner of the cylinder's box.
        """
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
        """Tell which points are inside the elliptic cylinder.

        Parameters
        ----------
        p : (..., 3) float, mm, LPS
            Points to test against the elliptic cylinder.

        Returns
        -------
        (...) bool
            True inside: ``(dx / a)² + (dy / b)² <= 1`` and ``z0_mm <= z < z1_mm``.
        """
        (cx, cy), (a, b) = self.center_xy_mm, self.semi_axes_xy_mm
        q = ((p[..., 0] - cx) / a) ** 2 + ((p[..., 1] - cy) / b) ** 2
        return (q <= 1.0) & (p[..., 2] >= self.z0_mm) & (p[..., 2] < self.z1_mm)

    def cross_section(self, z0: float) -> list[np.ndarray]:
        """Return the closed polygons of the axial cut ``z = z0``.

        Parameters
        ----------
        z0 : float, mm
            LPS z of the plane cutting the elliptic cylinder.

        Returns
        -------
        list of (n, 2) float, mm, LPS
            One polygon (x, y) per outline:
            an ellipse, none outside ``z0_mm <= z < z1_mm``.
        """
        if not self.z0_mm <= z0 < self.z1_mm:
            return []
        return [_ellipse(*self.center_xy_mm, *self.semi_axes_xy_mm)]

    def bounds(self) -> np.ndarray:
        """Return the bounding box of the elliptic cylinder.

        Returns
        -------
        (2, 3) float, mm, LPS
            Lower and upper corner of the elliptic cylinder's box.
        """
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
        """Tell which points are inside the box (lower faces included, upper ones not).

        Parameters
        ----------
        p : (..., 3) float, mm, LPS
            Points to test against the box from ``lo_mm`` to ``hi_mm``.

        Returns
        -------
        (...) bool
            True inside: ``lo_mm <= p < hi_mm`` on every axis.
        """
        return np.all((p >= self.lo_mm) & (p < self.hi_mm), axis=-1)

    def cross_section(self, z0: float) -> list[np.ndarray]:
        """Return the closed polygons of the axial cut ``z = z0``.

        Parameters
        ----------
        z0 : float, mm
            LPS z of the plane cutting the box from ``lo_mm`` to ``hi_mm``.

        Returns
        -------
        list of (n, 2) float, mm, LPS
            One polygon (x, y) per outline:
            the rectangle, none outside the box.
        """
        (x0, y0, za), (x1, y1, zb) = self.lo_mm, self.hi_mm
        if not za <= z0 < zb:
            return []
        return [np.array([[x0, y0], [x1, y0], [x1, y1], [x0, y1]], dtype=float)]

    def bounds(self) -> np.ndarray:
        """Return the bounding box: the box's own corners.

        Returns
        -------
        (2, 3) float, mm, LPS
            Lower and upper corner of the box's box.
        """
        return np.array([self.lo_mm, self.hi_mm], dtype=float)


def rotation_x(angle_deg: float) -> np.ndarray:
    """Return the rotation about patient x by ``angle_deg`` degrees (right-handed).

    Parameters
    ----------
    angle_deg : float, degrees
        The angle.

    Returns
    -------
    (3, 3) float
        The rotation matrix (LPS to LPS).
    """
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
        """Tell which points are inside the ellipsoid.

        Parameters
        ----------
        p : (..., 3) float, mm, LPS
            Points to test against the ellipsoid, its axes the columns of ``rotation``.

        Returns
        -------
        (...) bool
            True inside: the quadric form of the offset from the centre is at most 1.
        """
        d = p - np.asarray(self.center_mm)
        return np.einsum("...i,ij,...j->...", d, self._quad, d) <= 1.0

    def cross_section(self, z0: float) -> list[np.ndarray]:
        """Return the closed polygons of the axial cut ``z = z0``.

        Parameters
        ----------
        z0 : float, mm
            LPS z of the plane cutting the ellipsoid, its axes the columns of ``rotation``.

        Returns
        -------
        list of (n, 2) float, mm, LPS
            One polygon (x, y) per outline:
            the ellipse of the cut, none when the plane misses it.
        """
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
        """Return the bounding box (axis-aligned) of the rotated ellipsoid.

        Returns
        -------
        (2, 3) float, mm, LPS
            Lower and upper corner of the ellipsoid's box.
        """
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
        """Tell which points are inside the torus section (where its distance field is <= 0).

        Parameters
        ----------
        p : (..., 3) float, mm, LPS
            Points to test against the torus section, a tube around an arc.

        Returns
        -------
        (...) bool
            True inside: within ``minor_mm`` of the arc of radius ``major_mm``, inside the arc's angles.
        """
        return self._field(p) <= 0.0

    def cross_section(self, z0: float, step_mm: float = 0.2) -> list[np.ndarray]:
        """Return the closed polygons of the axial cut ``z = z0``, traced on a grid every ``step_mm`` mm.

        Parameters
        ----------
        z0 : float, mm
            LPS z of the plane cutting the torus section, a tube around an arc.
        step_mm : float, mm
            Sampling step of the distance field the outline is traced on.

        Returns
        -------
        list of (n, 2) float, mm, LPS
            One polygon (x, y) per outline:
            the zero level of the tube's distance field, none when the plane misses the tube.
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
        """Return the bounding box of the swept arc and its tube.

        Returns
        -------
        (2, 3) float, mm, LPS
            Lower and upper corner of the torus section's box.
        """
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
