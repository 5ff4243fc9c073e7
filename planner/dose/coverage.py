"""Dose-volume metrics: cumulative DVH, D90, D98, D2cc, V100, V150, physical and EQD2.

Definitions (ICRU 89 / GEC-ESTRO):

* ``D_x%``: the minimum dose to the hottest x % of the structure; ``D_V`` (e.g. D2cc) the minimum dose
  to its hottest V cm³. On voxels (each of volume ``voxel_cc``) sorted hottest first, it is the dose of
  the voxel at which the accumulated volume first reaches the asked volume (no interpolation). When
  the structure is smaller than V, ``D_V`` is its minimum dose (the whole structure is the hottest V).
* ``V_x%``: the percentage of the structure's volume receiving at least x % of the prescribed dose.
* EQD2 (linear-quadratic, no repopulation): ``EQD2 = n d (d + α/β) / (2 + α/β)`` for n fractions of d Gy,
  plus an external-beam contribution already in EQD2 (e.g. 45 Gy in 25 fractions).

Dose arrays are in Gy *per fraction* unless a name says otherwise; volumes in cm³.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from reachplan.imaging.types import Grid


def voxel_volume_cc(grid: Grid) -> float:
    """Volume of one voxel of ``grid``, cm³.

    Parameters
    ----------
    grid : Grid
        The dose or mask grid.

    Returns
    -------
    float, cm³
        ``|det|`` of the grid's voxel steps (mm³) / 1000.
    """
    return abs(float(np.linalg.det(grid.patient_from_index[:3, :3]))) / 1000.0


def _doses(doses_gy: np.ndarray) -> np.ndarray:
    d = np.asarray(doses_gy, dtype=float).ravel()
    if len(d) == 0:
        raise ValueError("a structure needs at least one voxel to compute dose-volume metrics")
    if not np.all(np.isfinite(d)):
        raise ValueError("doses must be finite")
    return d


def _check_voxel(voxel_cc: float) -> None:
    if not (voxel_cc > 0 and math.isfinite(voxel_cc)):
        raise ValueError(f"voxel volume must be positive (cm³), got {voxel_cc}")


def _hottest_minimum(d: np.ndarray, voxels: float) -> float:
    """Minimum of the ``voxels`` largest values of ``d`` (Gy); ``voxels`` rounded up and kept within 1..len(d)."""
    k = min(len(d), max(1, math.ceil(voxels - 1e-9)))
    return float(np.partition(d, len(d) - k)[len(d) - k])


def dose_to_volume(doses_gy: np.ndarray, voxel_cc: float, volume_cc: float) -> float:
    """``D_V``: minimum dose to the hottest ``volume_cc`` of the structure, Gy.

    Parameters
    ----------
    doses_gy : (n,) float, Gy
        Dose at each voxel of the structure.
    voxel_cc : float, cm³
        Volume of one voxel.
    volume_cc : float, cm³
        The hottest volume asked for (> 0).

    Returns
    -------
    float, Gy
        The structure's minimum dose when it is smaller than ``volume_cc``.

    Raises
    ------
    ValueError
        No voxels, doses not finite, or a voxel or asked volume that is not positive.
    """
    d = _doses(doses_gy)
    _check_voxel(voxel_cc)
    if not volume_cc > 0:
        raise ValueError(f"volume must be > 0 cm³, got {volume_cc}")
    return _hottest_minimum(d, volume_cc / voxel_cc)


def dose_to_fraction(doses_gy: np.ndarray, fraction: float) -> float:
    """``D_x``: minimum dose to the hottest ``fraction`` (0-1] of the structure's voxels, Gy.

    Parameters
    ----------
    doses_gy : (n,) float, Gy
        Dose at each voxel of the structure.
    fraction : float
        Volume fraction in (0, 1] (0.9 for D90).

    Returns
    -------
    float, Gy

    Raises
    ------
    ValueError
        No voxels, doses not finite, or a fraction outside (0, 1].
    """
    d = _doses(doses_gy)
    if not 0 < fraction <= 1:
        raise ValueError(f"volume fraction must be in (0, 1], got {fraction}")
    return _hottest_minimum(d, fraction * len(d))


def volume_receiving(doses_gy: np.ndarray, threshold_gy: float) -> float:
    """Percentage (0-100) of the structure's voxels with dose >= ``threshold_gy``.

    Parameters
    ----------
    doses_gy : (n,) float, Gy
        Dose at each voxel of the structure.
    threshold_gy : float, Gy
        Dose threshold (e.g. the prescription for V100).

    Returns
    -------
    float, %
    """
    d = _doses(doses_gy)
    return 100.0 * float(np.count_nonzero(d >= threshold_gy)) / len(d)


@dataclass(frozen=True, eq=False)
class Dvh:
    """Cumulative dose-volume histogram.

    Parameters
    ----------
    dose_gy : (m,) float, Gy
        Increasing dose axis starting at 0.
    volume_cc : (m,) float, cm³
        Volume receiving at least ``dose_gy[i]`` (non-increasing; ``volume_cc[0]`` is the total).
    """

    dose_gy: np.ndarray
    volume_cc: np.ndarray

    def __post_init__(self) -> None:
        d = np.asarray(self.dose_gy, dtype=float)
        v = np.asarray(self.volume_cc, dtype=float)
        if d.shape != v.shape or d.ndim != 1 or len(d) < 2:
            raise ValueError("a DVH needs matching 1-D dose and volume axes of >= 2 points")
        if np.any(np.diff(d) <= 0) or np.any(np.diff(v) > 1e-12):
            raise ValueError("DVH dose axis must increase and volumes must not increase")
        for name, a in (("dose_gy", d), ("volume_cc", v)):
            a.setflags(write=False)
            object.__setattr__(self, name, a)

    @property
    def total_cc(self) -> float:
        """Volume of the whole structure, cm³."""
        return float(self.volume_cc[0])

    @property
    def volume_percent(self) -> np.ndarray:
        """(m,) float, % of the structure's volume."""
        return 100.0 * self.volume_cc / self.total_cc


def cumulative_dvh(
    doses_gy: np.ndarray, voxel_cc: float, dose_axis_gy: np.ndarray | None = None
) -> Dvh:
    """Cumulative DVH from voxel doses (exact counts, no binning of the voxels).

    Parameters
    ----------
    doses_gy : (n,) float, Gy
        Dose at each voxel of the structure, in any order.
    voxel_cc : float, cm³
        Volume of one voxel (every voxel the same size).
    dose_axis_gy : (m,) float, Gy, optional
        Increasing axis starting at 0; default 0 to the maximum dose in 1001 points.

    Returns
    -------
    Dvh
        Volume (cm³) receiving at least each dose of the axis.
    """
    d = np.sort(_doses(doses_gy))
    _check_voxel(voxel_cc)
    if dose_axis_gy is None:
        top = float(d[-1]) if d[-1] > 0 else 1.0
        dose_axis_gy = np.linspace(0.0, top, 1001)
    axis = np.asarray(dose_axis_gy, dtype=float)
    counts = len(d) - np.searchsorted(d, axis, side="left")
    return Dvh(axis, counts * voxel_cc)


# --- EQD2 ---------------------------------------------------------------------------------------------


def eqd2(dose_per_fraction_gy: np.ndarray | float, n_fractions: int, alpha_beta_gy: float) -> np.ndarray:
    """EQD2 (Gy) of ``n_fractions`` fractions of ``dose_per_fraction_gy`` (linear-quadratic model).

    Parameters
    ----------
    dose_per_fraction_gy : float or array, Gy
        Physical dose per fraction.
    n_fractions : int
        Number of fractions (>= 1).
    alpha_beta_gy : float, Gy
        α/β of the tissue (> 0).

    Returns
    -------
    ndarray, Gy
        EQD2, the shape of ``dose_per_fraction_gy`` (0-d for a number).

    Raises
    ------
    ValueError
        Fewer than one fraction or α/β not positive.
    """
    _check_lq(n_fractions, alpha_beta_gy)
    d = np.asarray(dose_per_fraction_gy, dtype=float)
    return n_fractions * d * (d + alpha_beta_gy) / (2.0 + alpha_beta_gy)


def dose_per_fraction_for_eqd2(eqd2_gy: float, n_fractions: int, alpha_beta_gy: float) -> float:
    """Inverse of :func:`eqd2`: the dose per fraction (Gy) giving ``eqd2_gy`` in ``n_fractions``.

    Parameters
    ----------
    eqd2_gy : float, Gy
        EQD2 to deliver.
    n_fractions : int
        Fractions that share it (>= 1).
    alpha_beta_gy : float, Gy
        The tissue's α/β (> 0).

    Returns
    -------
    float, Gy
        Dose per fraction; 0 when ``eqd2_gy`` <= 0.

    Raises
    ------
    ValueError
        Fewer than one fraction or α/β not positive.
    """
    _check_lq(n_fractions, alpha_beta_gy)
    if eqd2_gy <= 0:
        return 0.0
    c = eqd2_gy * (2.0 + alpha_beta_gy) / n_fractions  # d² + (α/β) d − c = 0
    return 0.5 * (-alpha_beta_gy + math.sqrt(alpha_beta_gy**2 + 4.0 * c))


def _check_lq(n_fractions: int, alpha_beta_gy: float) -> None:
    if n_fractions < 1:
        raise ValueError(f"number of fractions must be >= 1, got {n_fractions}")
    if not alpha_beta_gy > 0:
        raise ValueError(f"α/β must be > 0 Gy, got {alpha_beta_gy}")


@dataclass(frozen=True)
class Fractionation:
    """How the brachytherapy dose is delivered, for EQD2.

    Parameters
    ----------
    n_fractions : int, >= 1
        Brachytherapy fractions (the plan's dose is per fraction).
    ebrt_dose_gy : float, Gy
        External-beam dose added to every structure (EMBRACE II: 45 Gy); 0 for none.
    ebrt_fractions : int
        Fractions of the external-beam course (EMBRACE II: 25).

    Raises
    ------
    ValueError
        Fewer than one fraction, or a negative external-beam dose.
    """

    n_fractions: int = 4
    ebrt_dose_gy: float = 45.0
    ebrt_fractions: int = 25

    def __post_init__(self) -> None:
        if self.n_fractions < 1 or self.ebrt_fractions < 1 or self.ebrt_dose_gy < 0:
            raise ValueError("fractions must be >= 1 and the external-beam dose >= 0 Gy")

    def total_eqd2(self, dose_per_fraction_gy: float, alpha_beta_gy: float) -> float:
        """EQD2 of brachytherapy (per-fraction dose × n) plus the external-beam course, Gy.

        Parameters
        ----------
        dose_per_fraction_gy : float, Gy
            Brachytherapy dose per fraction.
        alpha_beta_gy : float, Gy
            α/β of the tissue.

        Returns
        -------
        float, Gy
            Total EQD2.
        """
        ebrt = float(eqd2(self.ebrt_dose_gy / self.ebrt_fractions, self.ebrt_fractions, alpha_beta_gy))
        return float(eqd2(dose_per_fraction_gy, self.n_fractions, alpha_beta_gy)) + ebrt

    def per_fraction_for(self, total_eqd2_gy: float, alpha_beta_gy: float) -> float:
        """Brachytherapy dose per fraction (Gy) that brings the total to ``total_eqd2_gy``.

        Parameters
        ----------
        total_eqd2_gy : float, Gy
            Total EQD2 aimed at (external beam included).
        alpha_beta_gy : float, Gy
            α/β of the tissue.

        Returns
        -------
        float, Gy
            Dose per brachytherapy fraction; 0 when the external beam alone reaches the total.
        """
        ebrt = float(eqd2(self.ebrt_dose_gy / self.ebrt_fractions, self.ebrt_fractions, alpha_beta_gy))
        return dose_per_fraction_for_eqd2(total_eqd2_gy - ebrt, self.n_fractions, alpha_beta_gy)


@dataclass(frozen=True)
class StructureMetrics:
    """Dose-volume metrics of one structure.

    Physical values are Gy per brachytherapy fraction; ``*_eqd2_gy`` are totals (brachytherapy
    fractions + external beam) with the structure's α/β. V100/V150 are % of the volume receiving at
    least 100 %/150 % of the prescription.

    Parameters
    ----------
    name : str
        The structure's name.
    volume_cc : float, cm³
        Its volume (voxels × voxel volume).
    d90_gy, d98_gy : float, Gy per fraction
        Minimum dose to the hottest 90 % and 98 %.
    d2cc_gy : float, Gy per fraction
        Minimum dose to the hottest 2 cm³.
    v100_pct, v150_pct : float, %
        Volume receiving at least 100 % and 150 % of the prescription.
    d90_eqd2_gy, d98_eqd2_gy, d2cc_eqd2_gy : float, Gy
        The same doses as total EQD2.
    alpha_beta_gy : float, Gy
        The α/β used.
    d0_1cc_gy, d0_1cc_eqd2_gy : float, Gy
        Minimum dose to the hottest 0.1 cm³, per fraction and as total EQD2 (what is reported for an organ smaller
        than 2 cm³, whose D2cm³ is not applicable); NaN when not computed.
    """

    name: str
    volume_cc: float
    d90_gy: float
    d98_gy: float
    d2cc_gy: float
    v100_pct: float
    v150_pct: float
    d90_eqd2_gy: float
    d98_eqd2_gy: float
    d2cc_eqd2_gy: float
    alpha_beta_gy: float
    d0_1cc_gy: float = math.nan
    d0_1cc_eqd2_gy: float = math.nan


def structure_metrics(
    name: str,
    doses_gy: np.ndarray,
    voxel_cc: float,
    prescription_gy: float,
    alpha_beta_gy: float,
    fractionation: Fractionation | None = None,
) -> StructureMetrics:
    """All metrics of one structure.

    Parameters
    ----------
    name : str
        The structure's name.
    doses_gy : (n,) float, Gy per fraction
        Dose at the structure's voxels.
    voxel_cc : float, cm³
        Volume of one voxel.
    prescription_gy : float, Gy per fraction
        Prescribed dose (> 0), for V100 and V150.
    alpha_beta_gy : float, Gy
        α/β of the structure (10 for tumour, 3 for organs at risk).
    fractionation : Fractionation, optional
        Default: EMBRACE II, 4 fractions + 45 Gy / 25.

    Returns
    -------
    StructureMetrics
        D90, D98, D2cc, D0.1cc, V100, V150, physical and EQD2.

    Raises
    ------
    ValueError
        A prescription that is not positive, or no voxels.
    """
    fr = Fractionation() if fractionation is None else fractionation
    if not prescription_gy > 0:
        raise ValueError(f"prescription must be > 0 Gy, got {prescription_gy}")
    d = _doses(doses_gy)
    d90 = dose_to_fraction(d, 0.90)
    d98 = dose_to_fraction(d, 0.98)
    d2cc = dose_to_volume(d, voxel_cc, 2.0)
    d0_1cc = dose_to_volume(d, voxel_cc, 0.1)
    return StructureMetrics(
        name=name,
        volume_cc=len(d) * voxel_cc,
        d90_gy=d90,
        d98_gy=d98,
        d2cc_gy=d2cc,
        v100_pct=volume_receiving(d, prescription_gy),
        v150_pct=volume_receiving(d, 1.5 * prescription_gy),
        d90_eqd2_gy=fr.total_eqd2(d90, alpha_beta_gy),
        d98_eqd2_gy=fr.total_eqd2(d98, alpha_beta_gy),
        d2cc_eqd2_gy=fr.total_eqd2(d2cc, alpha_beta_gy),
        alpha_beta_gy=alpha_beta_gy,
        d0_1cc_gy=d0_1cc,
        d0_1cc_eqd2_gy=fr.total_eqd2(d0_1cc, alpha_beta_gy),
    )
