"""The TG-43U1 dose-rate kernel of a source: the formalism, its tables, interpolation and extrapolation.

The dwells it is applied to (dose at points and on voxel grids) are :mod:`reachplan.planner.dose.dwells`; the
checks of an existing plan :mod:`reachplan.planner.dose.plan_check`.

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
from dataclasses import dataclass, field
from typing import Literal

import numpy as np

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
        Consensus TG-43 data of the source model.
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
