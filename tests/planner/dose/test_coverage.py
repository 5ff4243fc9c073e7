"""Dose-volume metrics against closed-form cases."""

from __future__ import annotations

import math

import numpy as np
import pytest

from reachplan.imaging.types import Grid
from reachplan.planner.dose.coverage import (
    Dvh,
    Fractionation,
    cumulative_dvh,
    dose_per_fraction_for_eqd2,
    dose_to_fraction,
    dose_to_volume,
    eqd2,
    structure_metrics,
    volume_receiving,
    voxel_volume_cc,
)


def test_ramp_percentiles() -> None:
    """Doses 1..1000 Gy, one voxel each, shuffled: hottest k voxels have minimum 1001 − k."""
    d = np.random.default_rng(0).permutation(np.arange(1.0, 1001.0))
    assert dose_to_fraction(d, 0.90) == 101.0
    assert dose_to_fraction(d, 0.98) == 21.0
    assert dose_to_fraction(d, 1.0) == 1.0
    assert dose_to_volume(d, 0.01, 2.0) == 801.0  # 2 cc = 200 voxels of 0.01 cc
    assert dose_to_volume(d, 0.01, 50.0) == 1.0  # more than the structure: its minimum
    assert volume_receiving(d, 500.0) == pytest.approx(50.1)
    assert volume_receiving(d, 1500.0) == 0.0


def test_dvh_counts() -> None:
    d = np.array([0.0, 1.0, 1.0, 2.0, 3.0])
    dvh = cumulative_dvh(d, 0.5, np.array([0.0, 1.0, 1.5, 3.0, 4.0]))
    assert dvh.volume_cc == pytest.approx([2.5, 2.0, 1.0, 0.5, 0.0])
    assert dvh.total_cc == 2.5
    assert dvh.volume_percent[1] == pytest.approx(80.0)
    with pytest.raises(ValueError, match="increase"):
        Dvh(np.array([0.0, 1.0]), np.array([1.0, 2.0]))


def test_inverse_square_sphere_closed_form() -> None:
    """D = A/r² in a sphere of radius R: the hottest fraction f is the concentric sphere of radius
    R f^(1/3), so D_f = A / (R² f^(2/3)) and V(D) = (4/3)π (A/D)^(3/2)."""
    h = 0.5  # mm
    R = 20.0  # mm
    ax = np.arange(-R, R + h / 2, h)
    x, y, z = np.meshgrid(ax, ax, ax, indexing="ij")
    r = np.sqrt(x**2 + y**2 + z**2)
    inside = (r <= R) & (r >= 2.0)  # leave out the singular centre (volume fraction 0.1 %)
    dose = 100.0 / np.maximum(r, 1e-9) ** 2
    d = dose[inside]
    vox = h**3 / 1000.0
    vol = inside.sum() * vox
    shell = lambda f: 100.0 / (R**2 * (f + (1 - f) * (2.0 / R) ** 3) ** (2 / 3))  # noqa: E731
    for f in (0.9, 0.98):
        assert dose_to_fraction(d, f) == pytest.approx(shell(f), rel=0.01)
    # D2cc: the hottest 2 cm³ is the shell between 2 mm and ρ with (4/3)π(ρ³ − 2³) = 2000 mm³
    rho = (2000.0 / (4 / 3 * math.pi) + 8.0) ** (1 / 3)
    assert dose_to_volume(d, vox, 2.0) == pytest.approx(100.0 / rho**2, rel=0.01)
    dvh = cumulative_dvh(d, vox)
    mid = np.searchsorted(dvh.dose_gy, 1.0)  # D = 1 Gy ↔ radius 10 mm
    expect = (4 / 3 * math.pi * (10.0**3 - 2.0**3)) / 1000.0
    assert dvh.volume_cc[mid] == pytest.approx(expect, rel=0.02)
    assert dvh.total_cc == pytest.approx(vol)


def test_eqd2_closed_forms() -> None:
    assert eqd2(2.0, 25, 10.0) == pytest.approx(50.0)  # 2 Gy fractions: EQD2 = physical
    assert eqd2(7.0, 4, 10.0) == pytest.approx(28.0 * 17.0 / 12.0)
    assert eqd2(7.0, 4, 3.0) == pytest.approx(28.0 * 10.0 / 5.0)
    for ab in (3.0, 10.0):
        assert dose_per_fraction_for_eqd2(float(eqd2(6.3, 4, ab)), 4, ab) == pytest.approx(6.3)
    fr = Fractionation()  # EMBRACE II: 45 Gy / 25 + 4 BT fractions
    assert fr.total_eqd2(7.0, 10.0) == pytest.approx(45 * 11.8 / 12 + 28 * 17 / 12)
    assert fr.total_eqd2(fr.per_fraction_for(85.0, 10.0), 10.0) == pytest.approx(85.0)
    with pytest.raises(ValueError, match="α/β"):
        eqd2(1.0, 1, 0.0)


def test_structure_metrics_and_voxel_volume() -> None:
    g = Grid((2, 2, 2), np.diag([2.0, 2.5, 4.0, 1.0]))
    assert voxel_volume_cc(g) == pytest.approx(0.02)
    d = np.arange(1.0, 1001.0)
    m = structure_metrics("HR-CTV", d, 0.01, 500.0, 10.0, Fractionation(n_fractions=1, ebrt_dose_gy=0.0))
    assert (m.d90_gy, m.d98_gy, m.d2cc_gy) == (101.0, 21.0, 801.0)
    assert m.v100_pct == pytest.approx(50.1) and m.v150_pct == pytest.approx(25.1)
    assert m.d90_eqd2_gy == pytest.approx(float(eqd2(101.0, 1, 10.0)))
    assert m.volume_cc == pytest.approx(10.0)
    with pytest.raises(ValueError, match="at least one voxel"):
        structure_metrics("x", np.zeros(0), 0.01, 7.0, 10.0)
    with pytest.raises(ValueError, match="finite"):
        dose_to_fraction(np.array([1.0, np.nan]), 0.9)
