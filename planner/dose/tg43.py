"""TG-43U1 dose from dwell positions, at points and on voxel grids.

Formalism (Rivard et al., Med. Phys. 31:633, 2004), 2D line source::

    D(r, θ) = S_K · Λ · G_L(r, θ) / G_L(r0, θ0) · g_L(r) · F(r, θ),  r0 = 1 cm, θ0 = 90°
    G_L = β / (L r sin θ) off the axis, 1 / (r² − L²/4) on it

and the 1D point-source option ``D(r) = S_K · Λ · G_L(r, θ0) / G_L(r0, θ0) · g_L(r) · φ_an(r)`` (TG-43U1
eq. 11 with the line-source g_L; identical to ``(r0/r)² g_P(r) φ_an(r)``), where φ_an(r) is the
solid-angle-weighted mean of the 2D dose over θ computed from F.

Interpolation and extrapolation (TG-43U1 §IV and Appendix):

* g_L: linear in r inside the table; below the first radius the first value (nearest neighbour);
  beyond the last radius log-linear extrapolation through the last two points, up to 100 cm, then
  held constant (dose there is below 10⁻⁴ of the 1 cm dose).
* F: bilinear in (r, θ) inside the table; outside the r range the nearest column (TG-43U1 recommends
  F(r_max, θ) beyond r_max and F(r_min, θ) below r_min).
* Near the source (line model) the geometry factor is evaluated at the point's own distance, as in the
  TG-43U1 formalism and the treatment planning systems that follow the consensus data (Perez-Calatayud et
  al. 2012, HEBD report §II: G_L is analytic, only g_L and F are tabulated and extrapolated): there is no
  cap on r; below the first tabulated radius g_L and F take their nearest values (TG-43U1 §IV.D,
  above). Only points inside the source itself, closer to its axis than ``Y_SOURCE_CM`` (0.4 mm: less than
  the radius of any needle lumen a 0.9 mm Ir-192 source fits in), are moved out to that distance from the
  axis at the same position along it, so that the dose is finite; everywhere outside the needle lumen the
  kernel is the formalism itself. On the axis beyond the source's ends the line-source G_L tends
  continuously to 1 / (r² − L²/4). (Until issue 17 every point within r_min = max(first g_L radius, 0.6 L)
  of the centre was evaluated at r_min, which capped the dose within about 2 mm of a dwell and set 0.8 % of
  the voxels of a Vitesse HDR export apart from the TPS by more than 2 %.)
* The 1D point-source option evaluates the dose at ``r_min = max(first g_L radius, 0.6 L)`` for closer points.

g_L · F is tabulated once per source on a regular (Δr = 0.05 cm, Δθ = 1°) grid. Every consensus table
node lies on that grid, so bilinear lookup in it reproduces bilinear interpolation of the published
table (up to the product of two linear factors inside a 0.05 cm cell, below 10⁻⁵ relative).

Frames and units: positions in mm, DICOM patient coordinates (LPS); dwell ``directions`` are unit
vectors along the source axis pointing toward the needle tip (θ = 0 on that side); S_K in U
(= µGy m² h⁻¹ = cGy cm² h⁻¹); times in seconds; dose in Gy.
"""

from __future__ import annotations

import math
import os
import re
from collections.abc import Iterable, Mapping
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import Literal

import numpy as np

from reachplan._arrays import arc_length_mm
from reachplan.imaging.rtplan import BrachySource, RtPlan
from reachplan.imaging.types import Grid
from reachplan.planner.errors import PlanInputError
from reachplan.plugins.sources import SourceData

R0_CM = 1.0
DR_CM = 0.05  # radial step of the internal table
DTHETA_DEG = 1.0  # polar step of the internal table
R_TABLE_MAX_CM = 100.0
_EPS_Y_CM = 1e-6
#: Points closer than this to a source's axis, within its length, are inside the source: they are evaluated at
#: this distance from the axis (cm). 0.04 cm < the 0.45 mm radius of a 0.9 mm source capsule (GammaMed Plus,
#: rtplan_conventions.md §5), so every point outside the needle lumen is computed as it is.
Y_SOURCE_CM = 0.04

SourceModel = Literal["line", "point"]


def geometry_factor_line(r_cm: np.ndarray, theta_rad: np.ndarray | float, length_cm: float) -> np.ndarray:
    """Line-source geometry function G_L(r, θ), cm⁻².

    Parameters
    ----------
    r_cm : array, cm
        Distance from the source centre (> L/2 on the axis).
    theta_rad : array, rad
        Polar angle from the source axis.
    length_cm : float
        Active length L, cm.

    Returns
    -------
    array, cm⁻²
        β / (L r sin θ); its continuous limit 1 / (r² − L²/4) on the axis.
    """
    r = np.asarray(r_cm, dtype=float)
    th = np.asarray(theta_rad, dtype=float)
    y = np.maximum(r * np.abs(np.sin(th)), _EPS_Y_CM)
    beta = np.arctan2(length_cm * y, r * r - 0.25 * length_cm**2)
    return beta / (length_cm * y)


@dataclass(frozen=True, eq=False)
class Tg43Kernel:
    """Dose-rate kernel of one source model.

    Parameters
    ----------
    source : SourceData
        Consensus data.
    model : {"line", "point"}
        2D line-source formalism (default) or the 1D point-source approximation.

    ``r_min_cm`` is the distance below which the point model holds the dose at its value there.
    """

    source: SourceData
    model: SourceModel = "line"
    r_min_cm: float = field(init=False)
    _table: np.ndarray = field(init=False, repr=False)  # (nr, nθ) g_L·F (line) or (nr,) 1D rate factor
    _table32: np.ndarray = field(init=False, repr=False)  # the same in float32
    _table32_2d: np.ndarray = field(init=False, repr=False)
    _g0: float = field(init=False, repr=False)

    def __post_init__(self) -> None:
        if self.model not in ("line", "point"):
            raise ValueError(f"source model must be 'line' or 'point', got {self.model!r}")
        src = self.source
        length = src.active_length_cm
        object.__setattr__(self, "r_min_cm", max(float(src.radial_r_cm[0]), 0.6 * length))
        r = np.arange(0.0, R_TABLE_MAX_CM + DR_CM / 2, DR_CM)
        theta = np.arange(0.0, 180.0 + DTHETA_DEG / 2, DTHETA_DEG)
        g = radial_dose(src, r)
        f = anisotropy(src, r[:, None], theta[None, :])
        object.__setattr__(self, "_g0", float(geometry_factor_line(np.array(R0_CM), np.pi / 2, length)))
        if self.model == "line":
            table = g[:, None] * f
        else:
            table = g * phi_an(src, r) * geometry_factor_line(r, np.pi / 2, length) / self._g0
        table.setflags(write=False)
        object.__setattr__(self, "_table", table)
        table32 = table.astype(np.float32)
        table32.setflags(write=False)
        object.__setattr__(self, "_table32", table32)
        # the same, 2-D for the compiled kernel ((nr, 1) for the point model), C-contiguous
        object.__setattr__(self, "_table32_2d", np.ascontiguousarray(table32.reshape(len(r), -1)))

    def _rate_factor(self) -> float:
        """Constant that turns the compiled kernel's output into cGy h⁻¹ U⁻¹."""
        if self.model == "point":
            return float(self.source.dose_rate_constant)
        return float(self.source.dose_rate_constant / (self.length_cm * self._g0))

    def compiled_rates(self, points_mm: np.ndarray, positions_mm: np.ndarray, directions: np.ndarray) -> np.ndarray:
        """Rate matrix from the compiled float32 kernel (threads over the points).

        Parameters
        ----------
        points_mm : (m, 3) float, mm, LPS
        positions_mm : (n, 3) float, mm, LPS
        directions : (n, 3) float, unit vectors toward the needle tip

        Returns
        -------
        (m, n) float64, cGy h⁻¹ U⁻¹; within 1e-4 of :meth:`rate_per_u` (polynomial arctangent, float32).
        """
        from reachplan.planner.dose import _tg43_numba as nb

        p = np.ascontiguousarray(np.asarray(points_mm, dtype=float).reshape(-1, 3) * 0.1, dtype=np.float32)
        s = np.ascontiguousarray((np.asarray(positions_mm, dtype=float).reshape(-1, 3) * 0.1).T, dtype=np.float32)
        u = np.ascontiguousarray(np.asarray(directions, dtype=float).reshape(-1, 3).T, dtype=np.float32)
        out = np.empty((len(p), s.shape[1]))
        if out.size:
            nb.pair_matrix(p, s, u, self._table32_2d, *self._scalars(), out)
            out *= self._rate_factor()
        return out

    def compiled_dose(self, points_mm: np.ndarray, positions_mm: np.ndarray, directions: np.ndarray,
                      weights: np.ndarray) -> np.ndarray:
        """``compiled_rates(points_mm, positions_mm, directions) @ weights`` without forming the matrix.

        Parameters
        ----------
        points_mm : (m, 3) float, mm, LPS
            Where the dose is computed.
        positions_mm : (n, 3) float, mm, LPS
            Source centre at each dwell.
        directions : (n, 3) float, unit vectors, LPS
            Source axis at each dwell, toward the needle tip.
        weights : (n,) float
            Weight of each dwell (e.g. dwell times).

        Returns
        -------
        (m,) float64, cGy h⁻¹ U⁻¹ × the weights' unit
            The float32 pair rates summed in float64.
        """
        from reachplan.planner.dose import _tg43_numba as nb

        p = np.ascontiguousarray(np.asarray(points_mm, dtype=float).reshape(-1, 3) * 0.1, dtype=np.float32)
        s = np.ascontiguousarray((np.asarray(positions_mm, dtype=float).reshape(-1, 3) * 0.1).T, dtype=np.float32)
        u = np.ascontiguousarray(np.asarray(directions, dtype=float).reshape(-1, 3).T, dtype=np.float32)
        w = np.ascontiguousarray(np.asarray(weights, dtype=float).reshape(-1))
        out = np.zeros(len(p))
        if len(p) and s.shape[1]:
            nb.pair_dose(p, s, u, w, self._table32_2d, *self._scalars(), out)
            out *= self._rate_factor()
        return out

    def _scalars(self) -> tuple[np.float32, np.float32, np.float32, np.float32, np.float32, bool]:
        f = np.float32
        return (f(1.0 / DR_CM), f(self.r_min_cm), f(self.length_cm), f(_EPS_Y_CM), f(Y_SOURCE_CM),
                self.model == "point")

    @property
    def length_cm(self) -> float:
        """Active length of the source, cm."""
        return self.source.active_length_cm

    def rate_per_u(self, r_cm: np.ndarray, cos_theta: np.ndarray, dtype: type = np.float64) -> np.ndarray:
        """Dose rate per unit air-kerma strength, cGy h⁻¹ U⁻¹, at distance ``r_cm`` and polar cosine.

        Parameters
        ----------
        r_cm : array, cm
            Distance from the source centre.
        cos_theta : array
            Cosine of the angle between the source axis (toward the tip) and the point; broadcast with ``r_cm``.
        dtype : type
            Float type of the computation (``np.float32`` for grids).

        Returns
        -------
        array of ``dtype``, cGy h⁻¹ U⁻¹
            The broadcast shape of ``r_cm`` and ``cos_theta``.
        """
        r, c = np.broadcast_arrays(np.asarray(r_cm, dtype=dtype), np.asarray(cos_theta, dtype=dtype))
        r = np.array(r, dtype=dtype)  # a private copy: the kernel works in place
        c = np.clip(c, -1.0, 1.0)
        return self._rate(r, c, dtype)

    def _rate(self, r: np.ndarray, c: np.ndarray, dtype: type) -> np.ndarray:
        """Kernel on arrays (modified in place where possible); ``c`` already in [-1, 1]."""
        L = dtype(self.length_cm)
        one = dtype(1.0)
        table: np.ndarray = self._table32 if dtype is np.float32 else self._table
        nr = self._table.shape[0]
        if self.model == "point":
            rc = np.maximum(r, dtype(self.r_min_cm), out=r)
            ri = rc * dtype(1.0 / DR_CM)
            i0 = np.minimum(ri.astype(np.intp), nr - 2)
            fr = np.minimum(ri - i0, one, out=ri)
            v = table[i0] * (one - fr)
            v += table[i0 + 1] * fr
            return v * dtype(self.source.dose_rate_constant)
        # Line source at the point's own distance (no cap): only points beside the source and closer to
        # its axis than Y_SOURCE_CM are moved out to it (see the module docstring). Only arctan (no
        # arctan2/arccos: those are 3-4x slower in numpy): β from atan(L y / |r² − L²/4|), mirrored to
        # π − β inside the sphere of diameter L, and θ from the half-angle formula, well conditioned on both
        # sides of the axis.
        ac = np.abs(c)
        s = one - ac
        s *= one + ac
        s = np.sqrt(s, out=s)  # sin θ >= 0
        z = r * ac  # |z| along the axis
        y = r * s
        near = y < dtype(Y_SOURCE_CM)
        if near.any():  # beside the source: keep clear of its axis; beyond its ends: the on-axis limit
            near &= z < dtype(0.5) * L
            y[near] = dtype(Y_SOURCE_CM)
        np.maximum(y, dtype(_EPS_Y_CM), out=y)
        rc = np.hypot(y, z, out=r)  # the distance, moved out of the source (θ for F stays the point's own)
        d = rc * rc
        d -= dtype(0.25) * L * L
        neg = d < 0
        np.abs(d, out=d)
        np.maximum(d, dtype(1e-12), out=d)
        np.divide(y, d, out=d)
        d *= L
        gfac = np.arctan(d, out=d)
        if neg.any():
            gfac[neg] = dtype(math.pi) - gfac[neg]  # β > 90° inside the sphere of diameter L
        gfac /= y  # β / y ; divided by L and G0 in the constant below
        ri = rc * dtype(1.0 / DR_CM)
        i0 = np.minimum(ri.astype(np.intp), nr - 2)
        fr = np.minimum(ri - i0, one, out=ri)
        ac += one
        np.divide(s, ac, out=s)
        phi = np.arctan(s, out=s)  # α/2, α = angle to the nearer axis direction (tan α/2 = sin α/(1+cos α))
        phi *= dtype(-2.0 * 180.0 / (math.pi * DTHETA_DEG))
        phi += dtype(90.0 / DTHETA_DEG)  # 90° − α, in table steps
        th = np.copysign(phi, c, out=phi)
        np.subtract(dtype(90.0 / DTHETA_DEG), th, out=th)  # θ = 90° − sign(cos θ)·(90° − α)
        nt = self._table.shape[1]
        t0 = np.minimum(th.astype(np.intp), nt - 2)
        ft = th
        ft -= t0
        k = i0 * nt + t0
        flat = table.reshape(-1)
        a = flat[k] * (one - ft)
        a += flat[k + 1] * ft
        k += nt
        b = flat[k] * (one - ft)
        b += flat[k + 1] * ft
        b -= a
        b *= fr
        a += b
        a *= gfac
        a *= dtype(self.source.dose_rate_constant / (self.length_cm * self._g0))
        return a


def radial_dose(source: SourceData, r_cm: np.ndarray) -> np.ndarray:
    """g_L(r) with TG-43U1 interpolation and extrapolation (see module docstring).

    Parameters
    ----------
    source : SourceData
        Consensus data of the source.
    r_cm : array, cm
        Distances from the source centre.

    Returns
    -------
    array
        Radial dose function (dimensionless), the shape of ``r_cm``.
    """
    r = np.asarray(r_cm, dtype=float)
    rt, gt = source.radial_r_cm, source.radial_g
    g = np.interp(r, rt, gt)
    beyond = r > rt[-1]
    if np.any(beyond):
        k = math.log(gt[-1] / gt[-2]) / (rt[-1] - rt[-2])
        g = np.where(beyond, gt[-1] * np.exp(k * (np.minimum(r, R_TABLE_MAX_CM) - rt[-1])), g)
    return g


def anisotropy(source: SourceData, r_cm: np.ndarray, theta_deg: np.ndarray) -> np.ndarray:
    """F(r, θ): bilinear in (r, θ), nearest column outside the tabulated r range.

    Parameters
    ----------
    source : SourceData
        The source's consensus tables (F is read from them).
    r_cm : array, cm
        Distance of each point from the source centre.
    theta_deg : array, degrees
        Polar angle from the source axis (toward the tip), clipped to [0, 180]; broadcast with ``r_cm``.

    Returns
    -------
    array
        2D anisotropy function (dimensionless), the broadcast shape.
    """
    fr, ft, f = source.anisotropy_r_cm, source.anisotropy_theta_deg, source.anisotropy_f
    r, th = np.broadcast_arrays(np.asarray(r_cm, float), np.asarray(theta_deg, float))
    rr = np.clip(r, fr[0], fr[-1]).ravel()
    tt = np.clip(th, 0.0, 180.0).ravel()
    i = np.clip(np.searchsorted(fr, rr, side="right") - 1, 0, len(fr) - 2)
    j = np.clip(np.searchsorted(ft, tt, side="right") - 1, 0, len(ft) - 2)
    wr = (rr - fr[i]) / (fr[i + 1] - fr[i])
    wt = (tt - ft[j]) / (ft[j + 1] - ft[j])
    out = (
        f[j, i] * (1 - wr) * (1 - wt)
        + f[j, i + 1] * wr * (1 - wt)
        + f[j + 1, i] * (1 - wr) * wt
        + f[j + 1, i + 1] * wr * wt
    )
    return out.reshape(r.shape)


def phi_an(source: SourceData, r_cm: np.ndarray) -> np.ndarray:
    """1D anisotropy function φ_an(r) = ½ ∫ F(r,θ) G_L(r,θ)/G_L(r,90°) sin θ dθ (trapezoidal, 0.25°).

    Parameters
    ----------
    source : SourceData
        Its active length and F table give the integrand.
    r_cm : array, cm
        Distances from the source centre (held at 0.6 L below it).

    Returns
    -------
    array
        φ_an (dimensionless), the shape of ``r_cm``.
    """
    r = np.maximum(np.asarray(r_cm, dtype=float), 0.6 * source.active_length_cm)
    theta = np.radians(np.arange(0.0, 180.0 + 0.125, 0.25))
    L = source.active_length_cm
    f = anisotropy(source, r[..., None], np.degrees(theta))
    ratio = geometry_factor_line(r[..., None], theta, L) / geometry_factor_line(r[..., None], np.pi / 2, L)
    integrand = f * ratio * np.sin(theta)
    return 0.5 * np.trapezoid(integrand, theta, axis=-1)


@dataclass(frozen=True, eq=False)
class DwellSet:
    """Source dwells.

    Parameters
    ----------
    positions_mm : (n, 3) float, mm, LPS
        Centre of the active source at each dwell.
    directions : (n, 3) float, unit, LPS
        Source axis at each dwell, pointing toward the needle tip (θ = 0). Normalised on construction.
    times_s : (n,) float, s
        Dwell times (>= 0).
    channels : (n,) int
        Channel (needle) number of each dwell; zeros when not given.
    """

    positions_mm: np.ndarray
    directions: np.ndarray
    times_s: np.ndarray
    channels: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=int))

    def __post_init__(self) -> None:
        p = np.asarray(self.positions_mm, dtype=float).reshape(-1, 3)
        d = np.asarray(self.directions, dtype=float).reshape(-1, 3)
        t = np.asarray(self.times_s, dtype=float).reshape(-1)
        ch = np.asarray(self.channels, dtype=int).reshape(-1)
        if len(ch) == 0:
            ch = np.zeros(len(p), dtype=int)
        if not (len(p) == len(d) == len(t) == len(ch)):
            raise ValueError(
                f"dwell arrays disagree in length: positions {len(p)}, directions {len(d)}, "
                f"times {len(t)}, channels {len(ch)}"
            )
        if not (np.all(np.isfinite(p)) and np.all(np.isfinite(d)) and np.all(np.isfinite(t))):
            raise ValueError("dwell positions, directions and times must be finite")
        if np.any(t < 0):
            raise ValueError("dwell times must be >= 0 s")
        norm = np.linalg.norm(d, axis=1)
        if np.any(norm < 1e-9):
            raise ValueError("every dwell needs a non-zero source direction")
        d = d / norm[:, None]
        for name, arr in (("positions_mm", p), ("directions", d), ("times_s", t), ("channels", ch)):
            arr.setflags(write=False)
            object.__setattr__(self, name, arr)

    def __len__(self) -> int:
        return len(self.times_s)

    def with_times(self, times_s: np.ndarray) -> DwellSet:
        """Return the same dwells with other times.

        Parameters
        ----------
        times_s : (n,) float, s
            New dwell times (>= 0).

        Returns
        -------
        DwellSet
            Same positions, directions and channels.
        """
        return DwellSet(self.positions_mm, self.directions, times_s, self.channels)

    def select(self, mask: np.ndarray) -> DwellSet:
        """Return the dwells where ``mask`` is true.

        Parameters
        ----------
        mask : (n,) bool
            Which dwells to keep.

        Returns
        -------
        DwellSet
            The kept dwells, in order.
        """
        m = np.asarray(mask, dtype=bool)
        return DwellSet(self.positions_mm[m], self.directions[m], self.times_s[m], self.channels[m])

    @staticmethod
    def concatenate(parts: Iterable[DwellSet]) -> DwellSet:
        """Join dwell sets in order into one (an empty set when there are none).

        Parameters
        ----------
        parts : iterable of DwellSet
            The sets to join.

        Returns
        -------
        DwellSet
            Their dwells one after the other.
        """
        ps = list(parts)
        if not ps:
            return DwellSet(np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0), np.zeros(0, dtype=int))
        return DwellSet(
            np.concatenate([p.positions_mm for p in ps]),
            np.concatenate([p.directions for p in ps]),
            np.concatenate([p.times_s for p in ps]),
            np.concatenate([p.channels for p in ps]),
        )


def _check_points(points_mm: np.ndarray) -> np.ndarray:
    p = np.asarray(points_mm, dtype=float)
    if p.ndim != 2 or p.shape[1] != 3 or not np.all(np.isfinite(p)):
        raise ValueError(f"points must be a finite (m, 3) array in mm, got shape {p.shape}")
    return p


def rate_matrix(
    points_mm: np.ndarray,
    positions_mm: np.ndarray,
    directions: np.ndarray,
    kernel: Tg43Kernel,
    dtype: type = np.float64,
) -> np.ndarray:
    """Dose rate per unit air-kerma strength from each dwell at each point.

    Parameters
    ----------
    points_mm : (m, 3) float, mm, LPS
    positions_mm : (n, 3) float, mm, LPS
    directions : (n, 3) float, unit vectors toward the needle tip
    kernel : Tg43Kernel
    dtype : numpy float type of the computation (float32 for grids)

    Returns
    -------
    (m, n) array of ``dtype``, cGy h⁻¹ U⁻¹
    """
    p = np.asarray(points_mm, dtype=dtype) * dtype(0.1)
    s = np.asarray(positions_mm, dtype=dtype) * dtype(0.1)
    u: np.ndarray = np.asarray(directions, dtype=dtype)
    dx = p[:, 0:1] - s[None, :, 0]
    dy = p[:, 1:2] - s[None, :, 1]
    dz = p[:, 2:3] - s[None, :, 2]
    z = dx * u[None, :, 0]
    z += dy * u[None, :, 1]
    z += dz * u[None, :, 2]
    dx *= dx
    dy *= dy
    dz *= dz
    dx += dy
    dx += dz
    r = np.sqrt(dx, out=dx)
    np.maximum(r, dtype(1e-9), out=dy)
    z /= dy
    np.clip(z, -1.0, 1.0, out=z)
    return kernel._rate(r, z, dtype)


def dose_at_points(
    points_mm: np.ndarray, dwells: DwellSet, kernel: Tg43Kernel, air_kerma_strength_u: float
) -> np.ndarray:
    """Dose (Gy) at points, float64.

    Parameters
    ----------
    points_mm : (m, 3) float, mm, LPS
    dwells : DwellSet
    kernel : Tg43Kernel
    air_kerma_strength_u : float, U (cGy cm² h⁻¹)

    Returns
    -------
    (m,) float, Gy
    """
    p = _check_points(points_mm)
    _check_sk(air_kerma_strength_u)
    if len(dwells) == 0 or len(p) == 0:
        return np.zeros(len(p))
    w = dwells.times_s * (air_kerma_strength_u / 3600.0 / 100.0)  # cGy/h → Gy over t seconds
    return rate_matrix(p, dwells.positions_mm, dwells.directions, kernel) @ w


def _check_sk(sk: float) -> None:
    if not (np.isfinite(sk) and sk > 0):
        raise ValueError(f"air-kerma strength must be positive and finite (U), got {sk}")


def grid_points_mm(grid: Grid, flat_index: np.ndarray | None = None) -> np.ndarray:
    """Voxel centres, float, mm, LPS.

    Parameters
    ----------
    grid : Grid
    flat_index : (n,) int, optional
        Indices into the C-ordered (k, j, i) array; default all voxels.

    Returns
    -------
    (n, 3) float, mm, LPS (n = nk·nj·ni without ``flat_index``)
    """
    flat = np.arange(int(np.prod(grid.shape))) if flat_index is None else np.asarray(flat_index)
    k, j, i = np.unravel_index(flat, grid.shape)
    return grid.to_patient(np.stack([i, j, k], axis=1))


def dose_on_grid(
    grid: Grid,
    dwells: DwellSet,
    kernel: Tg43Kernel,
    air_kerma_strength_u: float,
    *,
    chunk_pairs: int = 1 << 16,
    workers: int | None = None,
    method: Literal["compiled", "numpy"] = "compiled",
) -> np.ndarray:
    """Dose (Gy) on every voxel centre of ``grid``, float32, computed in float32.

    Parameters
    ----------
    grid : Grid
        Voxel grid (any orientation).
    dwells : DwellSet
    kernel : Tg43Kernel
    air_kerma_strength_u : float, U
    chunk_pairs : int
        ``method="numpy"`` only: voxel-dwell pairs per chunk (memory about ``chunk_pairs × 40`` bytes per worker).
    workers : int, optional
        Threads; default ``min(2, os.cpu_count())``.
    method : {"compiled", "numpy"}
        The compiled kernel (numba, one pair at a time, no temporaries; the default) or the chunked numpy
        evaluation of :meth:`Tg43Kernel.rate_per_u` (kept as the benchmark's reference).

    Returns
    -------
    (nk, nj, ni) float32, Gy
    """
    _check_sk(air_kerma_strength_u)
    n_vox = int(np.prod(grid.shape))
    out = np.zeros(n_vox, dtype=np.float32)
    active = dwells.select(dwells.times_s > 0)
    if len(active) == 0:
        return out.reshape(grid.shape)
    w = (active.times_s * (air_kerma_strength_u / 360000.0)).astype(np.float32)
    n_workers = workers if workers is not None else min(2, os.cpu_count() or 1)
    a = grid.patient_from_index
    if method == "compiled":
        import numba

        from reachplan.planner.dose import _tg43_numba as nb

        f32 = np.float32
        cm = a[:3] * 0.1
        pos = np.ascontiguousarray((active.positions_mm * 0.1).T, dtype=f32)
        dirs = np.ascontiguousarray(active.directions.T, dtype=f32)
        w *= f32(kernel._rate_factor())
        before = numba.get_num_threads()
        numba.set_num_threads(max(1, min(n_workers, int(numba.config.NUMBA_NUM_THREADS))))  # type: ignore[attr-defined]
        try:
            nb.grid_dose(cm[:, 3].astype(f32), cm[:, 0].astype(f32), cm[:, 1].astype(f32), cm[:, 2].astype(f32),
                         np.asarray(grid.shape, dtype=np.int64), pos, dirs, w, kernel._table32_2d,
                         *kernel._scalars(), out)
        finally:
            numba.set_num_threads(before)
        return out.reshape(grid.shape)
    if method != "numpy":
        raise ValueError(f"method must be 'compiled' or 'numpy', got {method!r}")
    pos = active.positions_mm.astype(np.float32)
    dirs = active.directions.astype(np.float32)
    m = max(1, chunk_pairs // len(active))
    _, nj, ni = grid.shape
    ii = np.arange(ni, dtype=np.float64)
    jj = np.arange(nj, dtype=np.float64)

    def work(start: int) -> None:
        stop = min(start + m, n_vox)
        flat = np.arange(start, stop)
        k, rem = np.divmod(flat, nj * ni)
        j, i = np.divmod(rem, ni)
        pts = (ii[i, None] * a[:3, 0] + jj[j, None] * a[:3, 1] + k[:, None] * a[:3, 2] + a[:3, 3]).astype(
            np.float32
        )
        out[start:stop] = rate_matrix(pts, pos, dirs, kernel, np.float32) @ w

    starts = range(0, n_vox, m)
    if n_workers <= 1:
        for s0 in starts:
            work(s0)
    else:
        with ThreadPoolExecutor(max_workers=n_workers) as pool:
            list(pool.map(work, starts))
    return out.reshape(grid.shape)


# --- source orientation -------------------------------------------------------------------------------


def dwell_directions(path_mm: np.ndarray, positions_mm: np.ndarray) -> np.ndarray:
    """Source axis at each dwell from the channel path's tangent.

    Parameters
    ----------
    path_mm : (k, 3) float, mm, LPS
        Channel centre line ordered from the needle tip to its base (as Eclipse writes channel ROIs).
    positions_mm : (n, 3) float, mm, LPS
        Dwell positions (on or near the path).

    Returns
    -------
    (n, 3) float
        Unit tangent of the path segment nearest to each dwell, pointing toward the tip. At a vertex
        (dwell within 1e-6 mm of the joint of two segments) the mean of both segment directions.
    """
    path = np.asarray(path_mm, dtype=float)
    pos = np.asarray(positions_mm, dtype=float).reshape(-1, 3)
    seg = path[:-1] - path[1:]  # toward the tip
    seg_len = np.linalg.norm(seg, axis=1)
    keep = seg_len > 1e-9
    if len(path) < 2 or not np.any(keep):
        raise ValueError("a channel path needs at least two distinct points")
    a, seg, seg_len = path[1:][keep], seg[keep], seg_len[keep]
    u = seg / seg_len[:, None]
    # distance of each dwell to each segment (from its base-side end a, along u)
    rel = pos[:, None, :] - a[None, :, :]
    t = np.clip(np.einsum("nsk,sk->ns", rel, u), 0.0, seg_len[None, :])
    foot = a[None, :, :] + t[..., None] * u[None, :, :]
    dist = np.linalg.norm(pos[:, None, :] - foot, axis=2)
    best = np.argmin(dist, axis=1)
    out = u[best].copy()
    # dwell at a joint: average the two segments meeting there
    tb = t[np.arange(len(pos)), best]
    at_tip_end = (tb >= seg_len[best] - 1e-6) & (best + 1 < len(u))
    at_base_end = (tb <= 1e-6) & (best > 0)
    out[at_tip_end] += u[best[at_tip_end] + 1]
    out[at_base_end] += u[best[at_base_end] - 1]
    return out / np.linalg.norm(out, axis=1, keepdims=True)


def dwells_along_path(
    path_mm: np.ndarray,
    *,
    step_mm: float = 5.0,
    tip_offset_mm: float = 6.0,
    active_length_mm: float = 50.0,
) -> tuple[np.ndarray, np.ndarray]:
    """Candidate dwell positions every ``step_mm`` along a needle, starting ``tip_offset_mm`` from the tip.

    Parameters
    ----------
    path_mm : (k, 3) float, mm, LPS
        Needle centre line ordered from the tip to the base.
    step_mm : float, mm
        Dwell step along the path (> 0).
    tip_offset_mm : float, mm
        Distance of the first dwell from the tip (>= 0).
    active_length_mm : float, mm
        Length (from the first dwell) over which dwells are placed (>= 0); positions beyond the path's length
        are dropped.

    Returns
    -------
    positions : (n, 3) float, mm, LPS
        Dwell positions on the path.
    directions : (n, 3) float, unit, LPS
        Source axis at each, toward the tip.

    Raises
    ------
    ValueError
        A step, offset or length out of range, or a path of fewer than two distinct points.
    """
    if not (step_mm > 0 and tip_offset_mm >= 0 and active_length_mm >= 0):
        raise ValueError("dwell step must be > 0 mm, tip offset and active length >= 0 mm")
    path = np.asarray(path_mm, dtype=float)
    s = arc_length_mm(path)
    if len(path) < 2 or s[-1] <= 0:
        raise ValueError("a needle path needs at least two distinct points")
    arc = tip_offset_mm + np.arange(0.0, active_length_mm + 1e-9, step_mm)
    arc = arc[arc <= s[-1] + 1e-9]
    if len(arc) == 0:
        return np.zeros((0, 3)), np.zeros((0, 3))
    pos = np.stack([np.interp(arc, s, path[:, c]) for c in range(3)], axis=1)
    return pos, dwell_directions(path, pos)


# --- isotope check -------------------------------------------------------------------------------


_ISOTOPE = re.compile(r"(?<![a-z])([a-z]{1,2})\s*-?\s*(\d{2,3})(?!\d)|(?<!\d)(\d{2,3})\s*-?\s*([a-z]{1,2})(?![a-z])")
#: Brachytherapy isotopes (element symbol, mass number) that a Source Isotope Name may name.
_KNOWN_ISOTOPES = frozenset({"ir192", "co60", "cs137", "i125", "pd103", "yb169", "cs131", "se75", "au198", "ra226"})


def isotope_of(text: str) -> str | None:
    """Return the isotope named in ``text`` as ``"ir192"`` (``"Ir-192"``, ``"192Ir"``, ``"GammaMed Ir192 HDR"``).

    Parameters
    ----------
    text : str
        A Source Isotope Name, a source's name or any label.

    Returns
    -------
    str or None
        Element symbol and mass number in lower case; None when it names no known brachytherapy isotope.
    """
    for m in _ISOTOPE.finditer(text.lower()):
        key = f"{m.group(1)}{m.group(2)}" if m.group(1) else f"{m.group(4)}{m.group(3)}"
        if key in _KNOWN_ISOTOPES:
            return key
    return None


def check_isotope(source: BrachySource, data: SourceData, where: str) -> None:
    """Refuse TG-43 data of another isotope than the plan's source.

    Parameters
    ----------
    source : BrachySource
        The plan's source.
    data : SourceData
        The TG-43 data to compute with.
    where : str
        What is being checked (starts the error message).

    Raises
    ------
    PlanInputError
        The plan's Source Isotope Name names another isotope than ``data.isotope``.
    """
    ours, theirs = isotope_of(data.isotope), isotope_of(source.isotope_name)
    if ours and theirs and ours != theirs:
        raise PlanInputError(
            f"{where}: the plan's source is {source.isotope_name!r} but the TG-43 data {data.name!r} are for "
            f"{data.isotope}; choose data of the plan's isotope with --source (see `reachplan plugins`)")


# --- existing plans (secondary check) -----------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class PointCheck:
    """Our dose and the TPS's at one dose reference point.

    Doses are in Gy over the whole plan (all fractions and pulses).

    Parameters
    ----------
    number : int
        Dose Reference Number.
    name : str
        Dose Reference Description.
    position_mm : (3,) float, mm, LPS
        The point.
    dose_gy : float, Gy
        Our dose there.
    tps_gy : float or None, Gy
        The TPS's dose; None when the plan carries none for the point.
    diff_percent : float or None, %
        ``100 (dose_gy / tps_gy − 1)``; None without a TPS dose.
    """

    number: int
    name: str
    position_mm: np.ndarray
    dose_gy: float
    tps_gy: float | None
    diff_percent: float | None


def plan_dwells(plan: RtPlan, paths: Mapping[int, np.ndarray]) -> DwellSet:
    """All dwells of a brachy plan, oriented along their channel paths.

    Parameters
    ----------
    plan : RtPlan
    paths : mapping channel number -> (k, 3) float, mm, LPS
        Channel centre lines ordered tip first (see :func:`reachplan.imaging.rtplan.channel_paths`).

    Returns
    -------
    DwellSet
        Times are the whole plan's: per-fraction (per-pulse for PDR) dwell times × fractions × pulses.

    Raises
    ------
    PlanInputError
        A channel with dwells has no path.
    """
    scale = plan.n_fractions * plan.n_pulses
    parts = []
    for ch in plan.channels:
        if ch.n_dwells == 0:
            continue
        if ch.number not in paths:
            raise PlanInputError(
                f"channel {ch.number} refers to ROI {ch.roi_number}, which has no channel path in the "
                "structure set; pass the RT Structure Set the plan was made on"
            )
        dirs = dwell_directions(paths[ch.number], ch.dwell_positions_mm)
        parts.append(
            DwellSet(ch.dwell_positions_mm, dirs, ch.dwell_times_s * scale, np.full(ch.n_dwells, ch.number))
        )
    return DwellSet.concatenate(parts)


def check_points(
    plan: RtPlan, dwells: DwellSet, kernel: Tg43Kernel, air_kerma_strength_u: float
) -> tuple[PointCheck, ...]:
    """Recompute the dose at every point dose reference of ``plan`` and set it beside the TPS's.

    Parameters
    ----------
    plan : RtPlan
        The plan; references without a position are skipped.
    dwells : DwellSet
        The plan's dwells with whole-plan times (see :func:`plan_dwells`).
    kernel : Tg43Kernel
        The source's dose-rate kernel.
    air_kerma_strength_u : float, U
        Source strength (cGy cm² h⁻¹).

    Returns
    -------
    tuple of PointCheck
        One per point reference with a position, in the plan's order.
    """
    refs = [r for r in plan.dose_references if r.position_mm is not None]
    if not refs:
        return ()
    pts = np.array([r.position_mm for r in refs])
    doses = dose_at_points(pts, dwells, kernel, air_kerma_strength_u)
    out = []
    for r, p, d in zip(refs, pts, doses, strict=True):
        diff = None if not r.tps_dose_gy else 100.0 * (float(d) / r.tps_dose_gy - 1.0)
        out.append(PointCheck(r.number, r.description, p, float(d), r.tps_dose_gy, diff))
    return tuple(out)
