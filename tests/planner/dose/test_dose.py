"""TG-43U1 kernel and dose sums against closed forms and independent evaluations."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy import integrate

from reachplan.imaging.types import Grid
from reachplan.planner.dose.dwells import (
    DwellSet,
    dose_at_points,
    dose_on_grid,
    dwell_directions,
    dwells_along_path,
    grid_points_mm,
)
from reachplan.planner.dose.tg43 import Tg43Kernel, anisotropy, geometry_factor_line, radial_dose
from reachplan.planner.lookup import all_sources, get_source
from reachplan.plugins.errors import PluginError
from reachplan.plugins.sources import BUILTIN
from reachplan.plugins.sources.identify import recognise_source

NAMES = sorted(BUILTIN)


@pytest.fixture(scope="module")
def kernels() -> dict[str, Tg43Kernel]:
    return {n: Tg43Kernel(BUILTIN[n]()) for n in NAMES}


def test_geometry_factor_reference_value() -> None:
    assert geometry_factor_line(np.array(1.0), math.pi / 2, 0.35) == pytest.approx(0.98998, abs=5e-6)
    # closed form 2·atan(L/2r)/(L r) at 90°, and 1/(r² − L²/4) on the axis
    r = np.array([0.5, 2.0, 7.0])
    assert np.allclose(geometry_factor_line(r, math.pi / 2, 0.5), 2 * np.arctan(0.25 / r) / (0.5 * r))
    assert np.allclose(geometry_factor_line(r, 0.0, 0.5), 1 / (r**2 - 0.0625), rtol=1e-9)
    assert np.allclose(geometry_factor_line(r, math.pi, 0.5), 1 / (r**2 - 0.0625), rtol=1e-9)


@pytest.mark.parametrize("name", NAMES)
def test_rate_at_reference_point_is_lambda(kernels: dict[str, Tg43Kernel], name: str) -> None:
    k = kernels[name]
    assert k.rate_per_u(np.array([1.0]), np.array([0.0]))[0] == pytest.approx(
        k.source.dose_rate_constant, rel=1e-12
    )


@pytest.mark.parametrize("name", NAMES)
def test_table_nodes_reproduced(kernels: dict[str, Tg43Kernel], name: str) -> None:
    """At every published (r, θ) node: Λ · G_L/G_L0 · g_L · F with the table values themselves."""
    k, src = kernels[name], kernels[name].source
    r = src.anisotropy_r_cm[src.anisotropy_r_cm >= k.r_min_cm]
    rr, tt = np.meshgrid(r, src.anisotropy_theta_deg)
    g_node = np.interp(rr, src.radial_r_cm, src.radial_g)  # nodes of g_L inside its table
    inside = rr <= src.radial_r_cm[-1]
    f_node = src.anisotropy_f[:, np.isin(src.anisotropy_r_cm, r)]
    g0 = geometry_factor_line(np.array(1.0), math.pi / 2, src.active_length_cm)
    expect = (
        src.dose_rate_constant
        * geometry_factor_line(rr, np.radians(tt), src.active_length_cm) / g0 * g_node * f_node
    )
    got = k.rate_per_u(rr, np.cos(np.radians(tt)))
    assert np.allclose(got[inside], expect[inside], rtol=2e-6)


def test_bilinear_between_nodes(kernels: dict[str, Tg43Kernel]) -> None:
    """Midway between published nodes F is the mean of the four corners (GammaMed Plus HDR)."""
    k = kernels["gammamed_plus_hdr"]
    src = k.source
    i = int(np.flatnonzero(src.anisotropy_r_cm == 2.0)[0])
    j = int(np.flatnonzero(src.anisotropy_theta_deg == 30.0)[0])
    f_mid = src.anisotropy_f[j : j + 2, i : i + 2].mean()
    r, th = 2.25, 35.0
    g = np.interp(r, src.radial_r_cm, src.radial_g)
    g0 = geometry_factor_line(np.array(1.0), math.pi / 2, 0.35)
    expect = src.dose_rate_constant * geometry_factor_line(np.array(r), math.radians(th), 0.35) / g0 * g * f_mid
    assert k.rate_per_u(np.array([r]), np.array([math.cos(math.radians(th))]))[0] == pytest.approx(
        float(expect), rel=1e-5
    )


def test_inverse_square_far_field(kernels: dict[str, Tg43Kernel]) -> None:
    """Far from the source, rate · r² / (Λ g_L) → 1/G_L(r0) (the line looks like a point)."""
    for name in NAMES:
        k = kernels[name]
        src = k.source
        g0 = float(geometry_factor_line(np.array(1.0), math.pi / 2, src.active_length_cm))
        for r in (5.0, 8.0, 10.0):
            g = np.interp(r, src.radial_r_cm, src.radial_g)
            rate = k.rate_per_u(np.array([r]), np.array([0.0]))[0]
            assert rate * r**2 * g0 / (src.dose_rate_constant * g) == pytest.approx(1.0, abs=2e-3)


def test_radial_extrapolation_log_linear() -> None:
    src = BUILTIN["gammamed_plus_hdr"]()
    r8, r10 = 8.0, 10.0
    g8, g10 = (np.interp(x, src.radial_r_cm, src.radial_g) for x in (r8, r10))
    expect = g10 * (g10 / g8) ** ((14.0 - r10) / (r10 - r8))
    assert radial_dose(src, np.array([14.0]))[0] == pytest.approx(expect, rel=1e-12)
    assert radial_dose(src, np.array([0.01]))[0] == src.radial_g[0]  # nearest neighbour below the table
    # F outside the r range: nearest column
    assert anisotropy(src, np.array(30.0), np.array(10.0)) == pytest.approx(
        anisotropy(src, np.array(10.0), np.array(10.0))
    )


@pytest.mark.parametrize("name", ["gammamed_plus_hdr", "varisource_vs2000_hdr", "gammamed_plus_pdr"])
def test_near_source_follows_the_formalism_outside_the_lumen(kernels: dict[str, Tg43Kernel], name: str) -> None:
    """Within 3 mm of a dwell, outside a 0.5 mm lumen: the TG-43U1 line-source dose at the point's own distance
    (β from the source's two ends, g_L and F bilinear inside their tables, nearest value below them), no cap."""
    k, src = kernels[name], kernels[name].source
    half = 10 * src.active_length_cm / 2  # mm
    rng = np.random.default_rng(7)
    pts = rng.uniform(-3.0, 3.0, size=(400, 3))
    y = np.hypot(pts[:, 0], pts[:, 1])
    pts = pts[(y > 0.5) | (np.abs(pts[:, 2]) > half + 0.5)]  # outside the lumen (source axis = +z)
    tip, tail = np.array([0, 0, half]), np.array([0, 0, -half])
    a, b = pts - tip, pts - tail
    beta = np.arccos(np.sum(a * b, 1) / np.linalg.norm(a, axis=1) / np.linalg.norm(b, axis=1))
    r = np.linalg.norm(pts, axis=1) / 10  # cm
    yc = np.hypot(pts[:, 0], pts[:, 1]) / 10
    lc = src.active_length_cm
    on_axis = yc < 1e-9
    g_geom = np.where(on_axis, 1 / (r**2 - lc**2 / 4), beta / (lc * np.maximum(yc, 1e-12)))
    g0 = 2 * np.arctan(lc / 2) / lc
    theta = np.degrees(np.arccos(pts[:, 2] / 10 / r))
    gl = np.interp(r, src.radial_r_cm, src.radial_g)
    fr = np.clip(r, src.anisotropy_r_cm[0], src.anisotropy_r_cm[-1])
    f = np.array([np.interp(t, src.anisotropy_theta_deg,
                            [np.interp(x, src.anisotropy_r_cm, row) for row in src.anisotropy_f]) for t, x
                  in zip(theta, fr, strict=True)])
    expect = src.dose_rate_constant * g_geom / g0 * gl * f
    got = k.rate_per_u(r, pts[:, 2] / 10 / r)
    assert np.allclose(got, expect, rtol=1e-4)
    # inside the source the dose stays finite (evaluated at Y_SOURCE_CM from the axis), and rises toward it
    inside = k.rate_per_u(np.array([0.0, 0.02, 0.04, 0.1]), np.zeros(4))
    assert np.all(np.isfinite(inside)) and inside[0] == inside[1] == inside[2] > inside[3]


def _rotation(axis: np.ndarray, angle: float) -> np.ndarray:
    a = axis / np.linalg.norm(axis)
    kx = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + math.sin(angle) * kx + (1 - math.cos(angle)) * kx @ kx


def test_symmetry_about_source_axis(kernels: dict[str, Tg43Kernel]) -> None:
    rng = np.random.default_rng(1)
    k = kernels["gammamed_plus_hdr"]
    pos = np.array([[10.0, -5.0, 3.0]])
    axis = np.array([0.3, -0.5, 0.8])
    dw = DwellSet(pos, axis[None, :], [10.0])
    pts = pos + rng.normal(scale=20.0, size=(50, 3))
    base = dose_at_points(pts, dw, k, 40000.0)
    for angle in (0.7, 2.0, 4.5):
        rot = (pts - pos) @ _rotation(axis, angle).T + pos
        assert np.allclose(dose_at_points(rot, dw, k, 40000.0), base, rtol=1e-9)
    # reversing the source direction mirrors the dose through the transverse plane
    n = axis / np.linalg.norm(axis)
    mirrored = pts - 2 * ((pts - pos) @ n)[:, None] * n
    flipped = DwellSet(pos, -axis[None, :], [10.0])
    assert np.allclose(dose_at_points(mirrored, flipped, k, 40000.0), base, rtol=1e-9)


def test_dose_units_and_linearity(kernels: dict[str, Tg43Kernel]) -> None:
    """1 h at S_K = 40 700 U gives S_K·Λ cGy at (1 cm, 90°); dose is linear in time and S_K."""
    k = kernels["gammamed_plus_hdr"]
    dw = DwellSet([[0.0, 0.0, 0.0]], [[0.0, 0.0, 1.0]], [3600.0])
    d = dose_at_points(np.array([[10.0, 0.0, 0.0]]), dw, k, 40700.0)[0]
    assert d == pytest.approx(40700.0 * 1.1165 / 100.0, rel=1e-12)
    assert dose_at_points(np.array([[10.0, 0.0, 0.0]]), dw.with_times([1800.0]), k, 81400.0)[0] == (
        pytest.approx(d)
    )


def test_channel_is_sum_of_dwells(kernels: dict[str, Tg43Kernel]) -> None:
    rng = np.random.default_rng(2)
    k = kernels["flexisource_hdr"]
    path = np.array([[0.0, 0.0, 60.0], [5.0, 0.0, 30.0], [15.0, 3.0, 0.0]])  # tip first
    pos, dirs = dwells_along_path(path, step_mm=5.0, tip_offset_mm=5.0, active_length_mm=40.0)
    times = rng.uniform(1.0, 20.0, len(pos))
    channel = DwellSet(pos, dirs, times)
    pts = rng.uniform(-30.0, 60.0, size=(40, 3))
    total = dose_at_points(pts, channel, k, 30000.0)
    parts = sum(dose_at_points(pts, DwellSet(pos[i : i + 1], dirs[i : i + 1], times[i : i + 1]), k, 30000.0)
                for i in range(len(pos)))
    assert np.allclose(total, parts, rtol=1e-12)


def test_point_model(kernels: dict[str, Tg43Kernel]) -> None:
    """1D option: isotropic, Λ·φ_an(r)·G_L(r,90°)/G_L0·g_L(r), φ_an integrated independently."""
    src = BUILTIN["gammamed_plus_hdr"]()
    kp = Tg43Kernel(src, "point")
    r = 3.0
    g0 = float(geometry_factor_line(np.array(1.0), math.pi / 2, 0.35))
    gl90 = float(geometry_factor_line(np.array(r), math.pi / 2, 0.35))

    def integrand(t: float) -> float:
        f = float(anisotropy(src, np.array(r), np.array(math.degrees(t))))
        return f * float(geometry_factor_line(np.array(r), t, 0.35)) / gl90 * math.sin(t)

    phi = 0.5 * integrate.quad(integrand, 0.0, math.pi, limit=400, points=[math.radians(x) for x in (10, 20)])[0]
    assert 0.9 < phi < 1.0
    expect = src.dose_rate_constant * gl90 / g0 * float(radial_dose(src, np.array(r))) * phi
    rates = kp.rate_per_u(np.full(3, r), np.array([1.0, 0.0, -0.5]))
    assert np.allclose(rates, expect, rtol=2e-4)
    # far field: inverse square up to g_L and φ_an
    assert kp.rate_per_u(np.array([8.0]), np.array([0.0]))[0] * 64 / (
        kp.rate_per_u(np.array([4.0]), np.array([0.0]))[0] * 16
    ) == pytest.approx(float(radial_dose(src, np.array(8.0)) / radial_dose(src, np.array(4.0))), rel=5e-3)
    with pytest.raises(ValueError, match="line"):
        Tg43Kernel(src, "sphere")  # type: ignore[arg-type]


def test_grid_matches_points(kernels: dict[str, Tg43Kernel]) -> None:
    k = kernels["gammamed_plus_hdr"]
    affine = np.array([[2.0, 0, 0, -20.0], [0, 2.5, 0, -15.0], [0, 0, 3.0, -10.0], [0, 0, 0, 1]])
    grid = Grid((8, 12, 20), affine)
    path = np.array([[1.0, 2.0, 20.0], [0.0, 0.0, -20.0]])
    pos, dirs = dwells_along_path(path, step_mm=5.0, tip_offset_mm=3.0, active_length_mm=30.0)
    dw = DwellSet(pos, dirs, np.linspace(5, 20, len(pos)))
    ref = dose_at_points(grid_points_mm(grid), dw, k, 40000.0).reshape(grid.shape)
    for method in ("compiled", "numpy"):
        for workers in (1, 2):
            got = dose_on_grid(grid, dw, k, 40000.0, chunk_pairs=997, workers=workers, method=method)
            assert got.dtype == np.float32 and got.shape == grid.shape
            assert np.allclose(got, ref, rtol=2e-4)


@pytest.mark.parametrize("name", NAMES)
@pytest.mark.parametrize("model", ["line", "point"])
def test_compiled_kernel_within_0p1_percent_of_direct_formula(name: str, model: str) -> None:
    """The compiled float32 kernel against g_L·F·G_L evaluated straight from the consensus tables (no internal
    table), at random points 2-150 mm from the source in every direction (incl. near the axis)."""
    k = Tg43Kernel(BUILTIN[name](), model)  # type: ignore[arg-type]
    src, length = k.source, k.length_cm
    rng = np.random.default_rng(7)
    u = rng.normal(size=(20000, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    u[:200] = [0.0, 0.0, 1.0]  # on the axis, both sides
    u[200:400] = [0.0, 0.0, -1.0]
    r_cm = np.exp(rng.uniform(math.log(max(0.2, k.r_min_cm)), math.log(15.0), len(u)))
    pts_cm = u * r_cm[:, None]
    theta = np.arccos(np.clip(u[:, 2], -1, 1))
    if model == "line":
        direct = (src.dose_rate_constant * radial_dose(src, r_cm) * anisotropy(src, r_cm, np.degrees(theta))
                  * geometry_factor_line(r_cm, theta, length) / geometry_factor_line(np.array(1.0), math.pi / 2,
                                                                                     length))
    else:
        direct = k.rate_per_u(r_cm, u[:, 2])  # φ_an is an integral: the float64 table is its direct form
    got = k.compiled_rates(pts_cm * 10.0, np.zeros((1, 3)), np.array([[0.0, 0.0, 1.0]]))[:, 0]
    assert got.shape == direct.shape
    assert np.max(np.abs(got / direct - 1.0)) < 1e-3


def test_compiled_dose_is_the_rate_matrix_times_the_weights() -> None:
    # the implant metrics sum the pair rates without forming the matrix; checked against the float64 direct form
    k = Tg43Kernel(get_source("gammamed_plus_hdr"))
    rng = np.random.default_rng(3)
    pts = rng.uniform(-40.0, 40.0, (3000, 3))
    pos = rng.uniform(-10.0, 10.0, (25, 3))
    dirs = rng.normal(size=(25, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    w = rng.uniform(0.0, 20.0, 25)
    got = k.compiled_dose(pts, pos, dirs, w)
    r = np.linalg.norm(pts[:, None, :] - pos[None], axis=2)
    cos = np.einsum("mnk,nk->mn", pts[:, None, :] - pos[None], dirs) / r
    direct = k.rate_per_u(r * 0.1, cos) @ w
    far = np.min(r, axis=1) > 2.0
    assert got.shape == (3000,)
    assert np.max(np.abs(got[far] / direct[far] - 1.0)) < 1e-3
    assert np.allclose(k.compiled_dose(pts[:0], pos, dirs, w), 0.0)


def test_dwell_directions_follow_tangent() -> None:
    # a circular arc of radius 50 mm in the x-z plane, tip first
    s = np.linspace(0.0, 1.0, 200)
    path = np.stack([50 * np.cos(s), np.zeros_like(s), 50 * np.sin(s)], axis=1)
    q = np.array([0.2, 0.5, 0.8])
    pos = np.stack([50 * np.cos(q), np.zeros(3), 50 * np.sin(q)], axis=1)
    tangent = np.stack([np.sin(q), np.zeros(3), -np.cos(q)], axis=1)  # toward decreasing s (the tip)
    got = dwell_directions(path, pos)
    assert np.all(np.einsum("ij,ij->i", got, tangent) > math.cos(math.radians(0.5)))
    with pytest.raises(ValueError, match="two distinct"):
        dwell_directions(np.zeros((3, 3)), pos)


def test_dwells_along_path_spacing() -> None:
    path = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, -100.0]])
    pos, dirs = dwells_along_path(path, step_mm=5.0, tip_offset_mm=2.0, active_length_mm=20.0)
    assert np.allclose(pos[:, 2], -np.array([2.0, 7.0, 12.0, 17.0, 22.0]))
    assert np.allclose(dirs, [0.0, 0.0, 1.0])


def test_dwellset_validation() -> None:
    with pytest.raises(ValueError, match="disagree"):
        DwellSet(np.zeros((2, 3)), np.ones((2, 3)), [1.0])
    with pytest.raises(ValueError, match=">= 0"):
        DwellSet(np.zeros((1, 3)), np.ones((1, 3)), [-1.0])
    with pytest.raises(ValueError, match="non-zero"):
        DwellSet(np.zeros((1, 3)), np.zeros((1, 3)), [1.0])


def test_source_lookup() -> None:
    assert get_source("gammamed_plus_pdr").kind == "PDR"
    with pytest.raises(PluginError, match="available"):
        get_source("no_such_source")
    assert recognise_source(all_sources(), "GammaMed Plus HDR source 0.9 mm") == "gammamed_plus_hdr"
    assert recognise_source(all_sources(), "", "GammaMed PlusPDR") == "gammamed_plus_pdr"
    assert recognise_source(all_sources(), "mHDR-v2") is None
