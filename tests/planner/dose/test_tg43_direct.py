"""Every dose path against the TG-43U1 formula written out here, from the consensus tables as published (CSV).

One dwell of a tilted source; points on and off its axis at 0-180° and 1-120 mm, so beyond the tabulated radial and
anisotropy range (10 cm) too. The formula (Rivard et al., Med. Phys. 31:633, 2004, eq. 1, 4, 10 and §IV.D):
D = S_K Λ G_L(r,θ)/G_L(1 cm, 90°) g_L(r) F(r,θ); G_L = β/(L r sin θ) off the axis, 1/(r² − L²/4) on it; g_L linear
between nodes, its first value below the table, log-linear through the last two nodes beyond it; F bilinear in
(r, θ), the nearest tabulated radius outside the r range. The paths: the compiled grid kernel (the planner's RT Dose,
``reachplan dose``), the compiled point kernel (dose-volume metrics and the optimiser's rows), and the float64 point
evaluation (reference point doses).
"""

from __future__ import annotations

import csv
import json
import math
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

from reachplan.imaging.types import Grid
from reachplan.planner.dose.dwells import DwellSet, dose_at_points, dose_on_grid, grid_points_mm
from reachplan.planner.dose.tg43 import Tg43Kernel
from reachplan.planner.lookup import get_source

SK = 40700.0
AXIS = np.array([0.3, -0.5, 0.81]) / np.linalg.norm([0.3, -0.5, 0.81])
CENTRE = np.array([4.2, -7.9, 31.3])


def _tables(reference_file: Callable[[str], Path], name: str) -> dict:
    params = json.loads(reference_file(f"tg43/{name}/params.json").read_text())
    with reference_file(f"tg43/{name}/radial_dose_gL.csv").open() as f:
        rows = [r for r in csv.reader(f)][1:]
    rg = np.array([[float(x) for x in r[:2]] for r in rows if r and r[0].strip()])
    with reference_file(f"tg43/{name}/anisotropy_F.csv").open() as f:
        table = [r for r in csv.reader(f)]
    fr = np.array([float(h.split("=")[1].rstrip("cm")) for h in table[0][1:]])
    ft = np.array([float(r[0]) for r in table[1:] if r and r[0].strip()])
    f = np.array([[float(x) for x in r[1:]] for r in table[1:] if r and r[0].strip()])
    return {"lam": float(params["dose_rate_constant_cGy_per_h_per_U"]), "L": float(params["active_length_cm"]),
            "rg": rg[:, 0], "g": rg[:, 1], "fr": fr, "ft": ft, "f": f}


def _direct(t: dict, points_mm: np.ndarray) -> np.ndarray:
    """Dose rate per U (cGy h⁻¹ U⁻¹) of one line source at CENTRE along AXIS, the formula written out."""
    d = (points_mm - CENTRE) / 10.0  # cm
    r = np.linalg.norm(d, axis=1)
    z = d @ AXIS
    y = np.linalg.norm(d - np.outer(z, AXIS), axis=1)
    length = t["L"]
    on_axis = y < 1e-7
    tip, tail = 0.5 * length, -0.5 * length  # β = the angle the source subtends: atan2 from each end
    beta = np.arctan2(y, z - tip) - np.arctan2(y, z - tail)
    g_geom = np.where(on_axis, 1.0 / np.maximum(r**2 - length**2 / 4, 1e-12),
                      np.abs(beta) / (length * np.maximum(y, 1e-12)))
    g0 = 2.0 * math.atan(length / 2.0) / length
    rg, g = t["rg"], t["g"]
    gl = np.interp(r, rg, g)  # linear inside, the first value below (np.interp holds the end values)
    k = math.log(g[-1] / g[-2]) / (rg[-1] - rg[-2])
    gl = np.where(r > rg[-1], g[-1] * np.exp(k * (r - rg[-1])), gl)  # log-linear beyond the last node
    theta = np.degrees(np.arccos(np.clip(z / r, -1.0, 1.0)))
    rc = np.clip(r, t["fr"][0], t["fr"][-1])  # the nearest tabulated radius outside the r range
    per_row = np.array([np.interp(rc, t["fr"], row) for row in t["f"]])  # (nθ, m): linear in r on every θ row
    f = np.array([np.interp(theta[m], t["ft"], per_row[:, m]) for m in range(len(r))])  # then linear in θ
    return t["lam"] * g_geom / g0 * gl * f


def _points() -> np.ndarray:
    """On and off the axis: 0-180° (finely near the axis, where F is steep) × 1-120 mm, outside the source."""
    theta = np.radians([0, 0.5, 1, 2, 5, 10, 20, 30, 45, 60, 90, 120, 135, 150, 160, 170, 175, 178, 179.5, 180])
    r = np.array([1.0, 1.5, 2.0, 3.0, 5.0, 7.5, 10.0, 15.0, 20.0, 30.0, 40.0, 50.0, 70.0, 85.0, 100.0, 120.0])
    rr, tt = np.meshgrid(r, theta)
    side = np.cross(AXIS, [1.0, 0.0, 0.0])
    side /= np.linalg.norm(side)
    pts = CENTRE + rr.ravel()[:, None] * (np.outer(np.cos(tt.ravel()), AXIS) + np.outer(np.sin(tt.ravel()), side))
    y = rr.ravel() * np.sin(tt.ravel())
    z = rr.ravel() * np.abs(np.cos(tt.ravel()))
    return pts[(y >= 0.5) | (z >= 1.8 + 0.5)]  # outside a 0.5 mm lumen around the 3.5 mm source


@pytest.fixture(scope="module", params=["gammamed_plus_hdr", "flexisource_hdr"])
def source(request: pytest.FixtureRequest, reference_file: Callable[[str], Path]) -> tuple[dict, Tg43Kernel]:
    return _tables(reference_file, request.param), Tg43Kernel(get_source(request.param))


def test_points_on_and_off_the_axis_beyond_the_tables(source: tuple[dict, Tg43Kernel]) -> None:
    t, kernel = source
    pts = _points()
    assert len(pts) > 250 and np.linalg.norm(pts - CENTRE, axis=1).max() > 10 * t["fr"][-1]  # beyond the tables
    dwell = DwellSet(CENTRE[None], AXIS[None], np.array([3600.0]))
    expect = _direct(t, pts) * SK / 100.0  # Gy in one hour
    got = dose_at_points(pts, dwell, kernel, SK)  # float64: reference point doses
    assert np.allclose(got, expect, rtol=2e-5), np.max(np.abs(got / expect - 1))
    compiled = kernel.compiled_dose(pts, dwell.positions_mm, dwell.directions, dwell.times_s) * SK / 360000.0
    assert np.allclose(compiled, expect, rtol=2e-4), np.max(np.abs(compiled / expect - 1))  # float32 kernel


@pytest.mark.parametrize("spacing", [1.3, 9.7])
def test_the_grid_kernel_of_every_rt_dose(source: tuple[dict, Tg43Kernel], spacing: float) -> None:
    """The voxel grid of the planner's RT Dose and of ``reachplan dose``, oblique, 1.3 mm (to 20 mm) and 9.7 mm
    (to 120 mm from the dwell)."""
    t, kernel = source
    c, s = math.cos(0.4), math.sin(0.4)
    affine = np.eye(4)
    affine[:3, :3] = spacing * np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    n = 25
    affine[:3, 3] = CENTRE - affine[:3, :3] @ np.full(3, (n - 1) / 2 + 0.37)  # the dwell between voxel centres
    grid = Grid((n, n, n), affine)
    dwell = DwellSet(CENTRE[None], AXIS[None], np.array([3600.0]))
    dose = dose_on_grid(grid, dwell, kernel, SK).ravel()
    pts = grid_points_mm(grid)
    d = pts - CENTRE
    z = np.abs(d @ AXIS)
    y = np.linalg.norm(d - np.outer(d @ AXIS, AXIS), axis=1)
    keep = (y >= 0.5) | (z >= 1.8 + 0.5)
    expect = _direct(t, pts[keep]) * SK / 100.0
    assert np.allclose(dose[keep], expect, rtol=2e-4), np.max(np.abs(dose[keep] / expect - 1))
