"""The sampled problem of one arm: its channels' dwells, the structures' points, dose rates and the plan's metrics.

Organ points for a D2cm³ row (:func:`_organ_rows`): the organ's voxels on a lattice of ``*_oar_pitch_mm``, each
weighted by the volume it stands for, nearest to the dwells until they hold ``oar_sample_cc``. The rows' limit is
calibrated to the exact D2cm³ on the organ's 20 cm³ nearest the loaded dwells (:func:`_d2cc`, :func:`_calibrate`).
The final metrics of the target are computed on sub-voxels of at most :data:`SUBVOXEL_MM`; organs on their voxels
within ``oar_eval_radius_mm`` of a loaded dwell (:func:`_metrics`).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial import cKDTree

from reachplan.imaging.types import Grid
from reachplan.planner.dose.aims import Aims
from reachplan.planner.dose.coverage import (
    Dvh,
    StructureMetrics,
    cumulative_dvh,
    dose_to_volume,
    structure_metrics,
)
from reachplan.planner.dose.dwells import grid_points_mm
from reachplan.planner.dose.structures import PlanningStructures, Structure
from reachplan.planner.dose.tg43 import Tg43Kernel
from reachplan.planner.implant.candidates import Channel
from reachplan.planner.implant.optimiser import Modulation, OrganRows
from reachplan.planner.implant.settings import ImplantSettings


@dataclass(frozen=True, eq=False)
class PointLimit:
    """A dose point with a planning aim and a hard limit (the ICRU recto-vaginal point of EMBRACE II).

    Parameters
    ----------
    name : str
        The protocol's name of the point (``"ICRU recto-vaginal"``).
    position_mm : (3,) float, mm, LPS
        Where the point lies (:func:`reachplan.planner.geometry.reference_points.place_reference_points`).
    planning_gy : float, Gy per fraction
        The nominal plan's limit: the aim less the protocol's headroom.
    hard_gy : float, Gy per fraction
        The hard limit, kept with any one needle displaced.
    alpha_beta_gy : float, Gy
        The α/β of its EQD2 (3 for an organ point).
    """

    name: str
    position_mm: np.ndarray
    planning_gy: float
    hard_gy: float
    alpha_beta_gy: float = 3.0


def point_limits(aims: Aims, placed: Sequence[tuple[str, np.ndarray]]) -> tuple[PointLimit, ...]:
    """Return the protocol's dose points with an upper aim that the placed reference points stand for.

    Parameters
    ----------
    aims : Aims
        The protocol (its ``points``, fractionation, headroom).
    placed : sequence of (str, (3,) float)
        The case's reference points by name, mm, LPS.

    Returns
    -------
    tuple of PointLimit
        One per placed point matched by a protocol point with an upper aim; the hard limit is the aim when the
        protocol gives none.
    """
    out = []
    for point in aims.points:
        if point.aim_max_eqd2_gy is None:
            continue
        ab = aims.alpha_beta_target_gy if point.tissue == "target" else aims.alpha_beta_oar_gy
        planning = aims.fractionation.per_fraction_for(point.aim_max_eqd2_gy - aims.headroom_eqd2_gy, ab)
        hard = aims.fractionation.per_fraction_for(point.limit_max_eqd2_gy or point.aim_max_eqd2_gy, ab)
        out += [PointLimit(point.name, np.asarray(pos, dtype=float), planning, hard, ab)
                for name, pos in placed if point.matches(name)]
    return tuple(out)


@dataclass(frozen=True, eq=False)
class _Problem:
    """One arm's channels and dwells (mm, LPS), the structures' voxel points, organ limits and the dose kernel.

    Built once per arm (:func:`_sampled_problem`); the organ lattices (:meth:`lattice`) are cached on it.
    """

    channels: tuple[Channel, ...]
    positions: np.ndarray  # (D, 3)
    directions: np.ndarray  # (D, 3)
    channel_of: np.ndarray  # (D,) 0-based
    target_pts: np.ndarray  # all target voxel centres (n, 3)
    gtv_pts: np.ndarray | None
    oar_pts: tuple[np.ndarray, ...]  # all voxels of each organ
    oar_limits: tuple[float | None, ...]  # nominal: each organ's planning aim less the headroom, Gy per fraction
    gy_per_s: float
    kernel: Tg43Kernel
    oar_names: tuple[str, ...]
    eval_radius_mm: float
    target_fine: tuple[np.ndarray, np.ndarray]  # points and weights of the final metrics (_supersampled)
    gtv_fine: tuple[np.ndarray, np.ndarray] | None
    # each organ's voxels within ``eval_radius_mm`` of any candidate dwell (every loading's organ dose is read there)
    oar_near: tuple[np.ndarray, ...] = ()
    oar_hard: tuple[float | None, ...] = ()  # each organ's hard limit (every scenario), Gy per fraction
    points: tuple[PointLimit, ...] = ()  # dose points with a planning aim (nominal) and a hard limit (scenarios)
    lattices: dict[tuple[int, float], tuple[np.ndarray, np.ndarray]] = field(default_factory=dict, repr=False)

    def near_organ(self, o: int, pos: np.ndarray, radius_mm: float, vox_cc: float, times_2cc: int = 4) -> np.ndarray:
        """:func:`_near_organ` of organ ``o`` for dwells ``pos`` (a subset of the candidates' dwells).

        Read from ``oar_near`` when that provably holds the answer (every voxel of the organ outside it is farther
        than ``eval_radius_mm`` from every candidate dwell), else from all the organ's voxels.

        Parameters
        ----------
        o : int
            The organ (index into ``oar_pts``, the planning structures' organs).
        pos : (d, 3) float, mm, LPS
            The dwells.
        radius_mm : float, mm
            Voxels within this distance of a dwell are kept.
        vox_cc : float, cm³
            Voxel volume of the planning grid.
        times_2cc : int
            At least the organ's nearest ``times_2cc`` × 2 cm³ are kept (all of it when smaller).

        Returns
        -------
        (n, 3) float, mm, LPS
            The organ's voxel centres kept.
        """
        if self.oar_near and radius_mm <= self.eval_radius_mm:
            near = self.oar_near[o]
            n_min = min(len(self.oar_pts[o]), times_2cc * math.ceil(2.0 / vox_cc))
            if len(near) >= n_min and len(pos):
                dist = cKDTree(pos).query(near)[0]
                if n_min == 0 or np.partition(dist, n_min - 1)[n_min - 1] <= self.eval_radius_mm:
                    return _near_organ(near, pos, radius_mm, vox_cc, times_2cc, dist, n_min)
        return _near_organ(self.oar_pts[o], pos, radius_mm, vox_cc, times_2cc)

    def lattice(self, o: int, pitch_mm: float, vox_cc: float) -> tuple[np.ndarray, np.ndarray]:
        """Return organ ``o``'s voxels binned on a lattice of ``pitch_mm`` (cached per organ and pitch).

        Parameters
        ----------
        o : int
            The organ (index into ``oar_pts``).
        pitch_mm : float, mm
            Edge of the lattice's cubic bins (LPS axes).
        vox_cc : float, cm³
            Voxel volume of the planning grid.

        Returns
        -------
        points : (b, 3) float, mm, LPS
            One voxel centre per occupied bin (the first in the organ's voxel order).
        volume_cc : (b,) float, cm³
            Volume of the organ's voxels in each bin.
        """
        key = (o, float(pitch_mm))
        if key not in self.lattices:
            pts = self.oar_pts[o]
            b = np.floor(pts / pitch_mm).astype(np.int64)
            b -= b.min(axis=0) if len(b) else 0
            span = b.max(axis=0) + 1 if len(b) else np.ones(3, np.int64)
            # one integer per bin, in the bins' lexicographic order (as np.unique's rows, at a fraction of the cost)
            _, first, counts = np.unique((b[:, 0] * span[1] + b[:, 1]) * span[2] + b[:, 2], return_index=True,
                                         return_counts=True)
            self.lattices[key] = (pts[first], counts * vox_cc)
        return self.lattices[key]


def _rates(points: np.ndarray, pos: np.ndarray, dirs: np.ndarray, prob: _Problem) -> np.ndarray:
    """(m, d) Gy per second of dwell (per fraction)."""
    if len(points) == 0 or len(pos) == 0:
        return np.zeros((len(points), len(pos)))
    out = np.empty((len(points), len(pos)))
    step = max(1, (1 << 20) // len(pos))
    for s0 in range(0, len(points), step):
        out[s0:s0 + step] = prob.kernel.compiled_rates(points[s0:s0 + step], pos, dirs)
    return out * prob.gy_per_s


def _dose(points: np.ndarray, pos: np.ndarray, dirs: np.ndarray, times: np.ndarray, prob: _Problem) -> np.ndarray:
    """(m,) dose, Gy per fraction, at ``points`` from dwells with ``times`` (s), by chunks of points."""
    return prob.kernel.compiled_dose(points, pos, dirs, times) * prob.gy_per_s


#: largest sub-voxel size (mm) at which the final metrics of the target (and GTV) are computed
SUBVOXEL_MM = 0.7


def _supersampled(grid: Grid, mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Points (mm, LPS) and weights at which a structure's final metrics are computed.

    Each voxel split along each axis into ``ceil(spacing / SUBVOXEL_MM)`` sub-voxels (:data:`SUBVOXEL_MM`). The dose
    falls steeply across a target's edge, where D90 and D98 are decided: voxel centres alone are 1-3 % off on a 2 mm
    grid; the tests check the result against a grid six times finer than 2 mm.
    """
    n_axis = [max(1, math.ceil(float(h) / SUBVOXEL_MM - 1e-9)) for h in grid.spacing_mm]  # (i, j, k)
    k, j, i = np.nonzero(mask)
    ijk = np.column_stack([i, j, k]).astype(float)
    ax = [(np.arange(n) + 0.5) / n - 0.5 for n in n_axis]
    off = np.array([[a, b, c] for a in ax[0] for b in ax[1] for c in ax[2]])
    subs = grid.to_patient((ijk[:, None, :] + off[None]).reshape(-1, 3))
    return subs, np.ones(len(subs), dtype=int)


def _stride(n: int, k: int) -> np.ndarray:
    return np.arange(n) if n <= k else np.linspace(0, n - 1, k).round().astype(int)


def _organ_sample(lattice: tuple[np.ndarray, np.ndarray], near_mm: np.ndarray,
                  volume_cc: float) -> tuple[np.ndarray, np.ndarray]:
    """Return an organ's representative points for its D2cm³ row, and the volume (cm³) each stands for.

    ``lattice``: the organ's voxel centres binned on a lattice, one point ((n, 3) mm LPS) per bin and the volume
    (cm³) of its voxels (:meth:`_Problem.lattice`); of those, the ones nearest to the dwells ``near_mm``
    ((d, 3) mm) until they hold ``volume_cc``.
    """
    reps, w = lattice
    if len(reps) == 0 or len(near_mm) == 0:
        return np.zeros((0, 3)), np.zeros(0)
    order = np.argsort(cKDTree(near_mm).query(reps)[0], kind="stable")
    n = min(len(order), int(np.searchsorted(np.cumsum(w[order]), volume_cc)) + 1)
    keep = np.sort(order[:n])
    return reps[keep], w[keep]


@dataclass(frozen=True, eq=False)
class _Doses:
    """A loading's dose where :func:`_metrics` reads it (Gy per fraction), kept to re-read a scaled loading.

    Parameters
    ----------
    times_s : (c,) float, s
        The loading (of the metrics' columns).
    oar_points : tuple of (n_o, 3) float, mm, LPS
        Each organ's voxels within ``eval_radius_mm`` of a loaded dwell.
    oar : tuple of (n_o,) float, Gy per fraction
        The dose there.
    target, gtv : (n,) float, Gy per fraction
        The dose at the HR-CTV's (and GTV's, None without one) sub-voxel points (before their weights).
    """

    times_s: np.ndarray
    oar_points: tuple[np.ndarray, ...]
    oar: tuple[np.ndarray, ...]
    target: np.ndarray
    gtv: np.ndarray | None


def _rescaled(prob: _Problem, cols: np.ndarray, times: np.ndarray, base: _Doses, factor: float,
              points: np.ndarray, dose: np.ndarray) -> np.ndarray:
    """Return the dose at ``points`` of the loading ``times`` from ``base``'s dose there, ``dose``.

    ``factor`` × ``dose`` plus the dose of what is left, ``times - factor × base.times_s`` (the few dwells a minimum
    dwell time held up). The same pair rates either way, summed in another order: the direct computation to the
    compiled kernel's float32 rounding (1e-8 relative; the kernel is within 1e-4 of the float64 table).
    """
    rest = times - factor * base.times_s
    on = rest != 0.0
    out: np.ndarray = factor * dose
    if on.any() and len(points):
        out = out + _dose(points, prob.positions[cols][on], prob.directions[cols][on], rest[on], prob)
    return out


def _metrics(prob: _Problem, cols: np.ndarray, times: np.ndarray, aims: Aims, vox_cc: float,
             max_scale: float = 1.0, base: tuple[_Doses, float] | None = None,
             ) -> tuple[StructureMetrics, float, StructureMetrics | None, tuple[StructureMetrics, ...],
                        tuple[tuple[str, Dvh], ...], float, _Doses]:
    """Compute target, V200, GTV and organ metrics of a loading on every voxel.

    Organs: voxels within ``oar_eval_radius`` of a loaded dwell. Also returns the factor <= ``max_scale`` (the
    scenarios' own, <= 1) that keeps every nominal D2cm³ within its planning limit, and the doses of the loading
    scaled by it. ``base``: the doses of an earlier loading with the same loaded dwells and the factor this one is
    of it (but for dwells held at a minimum time): the doses are then that factor times the earlier ones plus the
    dose of the difference (:func:`_rescaled`), not computed again on every sub-voxel.
    """
    loaded = times > 0
    pos, dirs, t = prob.positions[cols][loaded], prob.directions[cols][loaded], times[loaded]
    rx = aims.prescription_gy
    if base is not None and not np.array_equal(base[0].times_s > 0, loaded):
        base = None
    pts_oar = base[0].oar_points if base is not None else tuple(
        prob.near_organ(o, pos, prob.eval_radius_mm, vox_cc) for o in range(len(prob.oar_limits)))
    dose_oar = []
    scale = max_scale
    for o, limit in enumerate(prob.oar_limits):
        d = (_rescaled(prob, cols, times, base[0], base[1], pts_oar[o], base[0].oar[o]) if base is not None
             else _dose(pts_oar[o], pos, dirs, t, prob))
        dose_oar.append(d)
        if limit is not None and len(d):
            d2 = dose_to_volume(d, vox_cc, 2.0)
            if d2 > limit:
                scale = min(scale, limit / d2 * (1 - 1e-9))
    sub_cc = vox_cc * len(prob.target_pts) / max(len(prob.target_fine[0]), 1)  # target and GTV on sub-voxels

    def fine(points: np.ndarray, earlier: np.ndarray | None) -> np.ndarray:
        if base is None or earlier is None:
            return _dose(points, pos, dirs, t * scale, prob)
        return scale * _rescaled(prob, cols, times, base[0], base[1], points, earlier)

    d_t = fine(prob.target_fine[0], None if base is None else base[0].target)
    dt = np.repeat(d_t, prob.target_fine[1])
    target = structure_metrics("HR-CTV", dt, sub_cc, rx, aims.alpha_beta_target_gy, aims.fractionation)
    v200 = 100.0 * float(np.count_nonzero(dt >= 2.0 * rx)) / len(dt)
    dvhs = [("HR-CTV", cumulative_dvh(dt, sub_cc))]
    gtv, d_g = None, None
    if prob.gtv_fine is not None and len(prob.gtv_fine[0]):
        d_g = fine(prob.gtv_fine[0], None if base is None else base[0].gtv)
        dg = np.repeat(d_g, prob.gtv_fine[1])
        gtv = structure_metrics("GTV", dg, sub_cc, rx, aims.alpha_beta_target_gy, aims.fractionation)
        dvhs.append(("GTV", cumulative_dvh(dg, sub_cc)))
    oars = []
    for name, d in zip(prob.oar_names, dose_oar, strict=True):
        d = d * scale if len(d) else np.zeros(1)
        oars.append(structure_metrics(name, d, vox_cc, rx, aims.alpha_beta_oar_gy, aims.fractionation))
        dvhs.append((name, cumulative_dvh(d, vox_cc)))
    doses = _Doses(times * scale, pts_oar, tuple(d * scale for d in dose_oar), d_t, d_g)
    return target, v200, gtv, tuple(oars), tuple(dvhs), scale, doses


def point_rows(prob: _Problem, pos: np.ndarray, dirs: np.ndarray) -> list[OrganRows]:
    """Return one row per dose point of the problem: its dose from the dwells ``pos`` within its planning value.

    A row of one point whose weight is its volume: the tail mean is the point's dose, so κ = 1 is exact.

    Parameters
    ----------
    prob : _Problem
        Its ``points``.
    pos : (c, 3) float, mm, LPS
        Dwell positions (the columns of the rows).
    dirs : (c, 3) float
        Source directions (unit).

    Returns
    -------
    list of OrganRows
        One per point, in the order of ``prob.points``.
    """
    return [OrganRows(_rates(p.position_mm[None], pos, dirs, prob), np.ones(1), p.planning_gy, 1.0, p.name)
            for p in prob.points]


def point_doses(prob: _Problem, pos: np.ndarray, dirs: np.ndarray, times: np.ndarray) -> np.ndarray:
    """Return the dose (Gy per fraction) at each of the problem's points from the dwells ``pos`` loaded ``times``.

    Parameters
    ----------
    prob : _Problem
        Its ``points``.
    pos : (c, 3) float, mm, LPS
        Dwell positions.
    dirs : (c, 3) float
        Source directions (unit).
    times : (c,) float, s
        Dwell times.

    Returns
    -------
    (n_points,) float, Gy per fraction
    """
    if not prob.points:
        return np.zeros(0)
    out: np.ndarray = _dose(np.array([p.position_mm for p in prob.points]), pos, dirs, times, prob)
    return out


def _aims_failed(target: StructureMetrics, gtv: StructureMetrics | None, oars: Sequence[StructureMetrics],
                 aims: Aims, v200_pct: float | None = None, v200_max_pct: float | None = None,
                 points: Sequence[tuple[PointLimit, float]] = ()) -> list[str]:
    """Return the planning aims the nominal plan misses (empty: every one met), each with its value.

    HR-CTV D90 (within its upper aim too) and D98, GTV D98, each organ's D2cm³ and each dose point (``points``:
    each with its dose, Gy per fraction) at least ``headroom_eqd2_gy`` below its aim, and V200 within its limit (when
    both are given).
    """
    out = []
    if target.d90_eqd2_gy < aims.target_d90_eqd2_gy - 1e-6:
        out.append(f"HR-CTV D90 {target.d90_eqd2_gy:.1f} < {aims.target_d90_eqd2_gy:g} Gy")
    if aims.target_d90_max_eqd2_gy is not None and target.d90_eqd2_gy > aims.target_d90_max_eqd2_gy + 0.05:
        out.append(f"HR-CTV D90 {target.d90_eqd2_gy:.1f} > {aims.target_d90_max_eqd2_gy:g} Gy")
    if target.d98_eqd2_gy < aims.target_d98_eqd2_gy - 1e-6:
        out.append(f"HR-CTV D98 {target.d98_eqd2_gy:.1f} < {aims.target_d98_eqd2_gy:g} Gy")
    if gtv is not None and gtv.d98_eqd2_gy < aims.gtv_d98_eqd2_gy - 1e-6:
        out.append(f"GTV D98 {gtv.d98_eqd2_gy:.1f} < {aims.gtv_d98_eqd2_gy:g} Gy")
    for o in oars:
        aim = aims.oar_eqd2_gy(o.name)
        if aim is not None and o.d2cc_eqd2_gy > aim - aims.headroom_eqd2_gy + 1e-6:
            out.append(f"{o.name} D2cm³ {o.d2cc_eqd2_gy:.1f} > {aim - aims.headroom_eqd2_gy:g} Gy "
                       f"(aim {aim:g} less {aims.headroom_eqd2_gy:g} headroom)")
    for p, dose_gy in points:
        value, limit = aims.fractionation.total_eqd2(dose_gy, p.alpha_beta_gy), \
            aims.fractionation.total_eqd2(p.planning_gy, p.alpha_beta_gy)
        if value > limit + 1e-6:
            out.append(f"{p.name} {value:.1f} > {limit:.3g} Gy (aim less {aims.headroom_eqd2_gy:g} headroom)")
    if v200_pct is not None and v200_max_pct is not None and v200_pct > v200_max_pct + 1e-6:
        out.append(f"HR-CTV V200 {v200_pct:.1f} % > {v200_max_pct:g} %")
    return out


def _organ_samples(prob: _Problem, pos: np.ndarray, pitch_mm: float, volume_cc: float,
                   vox_cc: float) -> list[tuple[int, np.ndarray, np.ndarray]]:
    """Return each organ with a limit, its representative points and their volumes for the dwells ``pos``.

    Points (p, 3) mm, LPS; volumes (p,) cm³ (module docstring).
    """
    return [(o, *_organ_sample(prob.lattice(o, pitch_mm, vox_cc), pos, volume_cc))
            for o, limit in enumerate(prob.oar_limits) if limit is not None]


def _organ_rows(prob: _Problem, pos: np.ndarray, dirs: np.ndarray, pitch_mm: float, volume_cc: float,
                vox_cc: float) -> list[OrganRows]:
    """Return the D2cm³ rows of every organ with a limit, for the dwells ``pos``/``dirs`` (module docstring)."""
    return [OrganRows(_rates(reps, pos, dirs, prob), w, float(prob.oar_limits[o]), 2.0, prob.oar_names[o])  # type: ignore[arg-type]
            for o, reps, w in _organ_samples(prob, pos, pitch_mm, volume_cc, vox_cc)]


def _d2cc(prob: _Problem, pos: np.ndarray, dirs: np.ndarray, t: np.ndarray, vox_cc: float) -> np.ndarray:
    """Return the D2cm³ (Gy per fraction) of every organ with a limit, on its 20 cm³ nearest the loaded dwells."""
    on = t > 0
    out = []
    for o, (pts, limit) in enumerate(zip(prob.oar_pts, prob.oar_limits, strict=True)):
        if limit is None:
            continue
        if not on.any() or len(pts) == 0:
            out.append(0.0)
            continue
        near = prob.near_organ(o, pos[on], 0.0, vox_cc, 10)  # the nearest 20 cm³ hold the hottest 2 cm³
        out.append(dose_to_volume(_dose(near, pos[on], dirs[on], t[on], prob), vox_cc, 2.0))
    return np.array(out)


def _near_organ(pts: np.ndarray, pos: np.ndarray, radius_mm: float, vox_cc: float, times_2cc: int = 4,
                dist: np.ndarray | None = None, n_min: int | None = None) -> np.ndarray:
    """Return an organ's voxels within ``radius_mm`` of a dwell, and at least its nearest ``times_2cc`` × 2 cm³.

    ``dist``: each voxel's distance to the dwells when known; ``n_min``: the voxel count of ``times_2cc`` × 2 cm³
    (of the whole organ when ``pts`` is a part of it).
    """
    if dist is None:
        dist = cKDTree(pos).query(pts)[0] if len(pos) else np.zeros(len(pts))
    if n_min is None:
        n_min = min(len(pts), times_2cc * math.ceil(2.0 / vox_cc))
    keep = dist <= radius_mm
    if n_min > 0:
        # the ``n_min`` nearest, the first of equal distances first (a stable sort's first ``n_min``), found by a
        # partition: the voxels nearer than the ``n_min``-th distance and the first of those at it
        kth = np.partition(dist, n_min - 1)[n_min - 1]
        if kth > radius_mm:
            nearer = dist < kth
            keep |= nearer
            keep[np.flatnonzero(dist == kth)[:n_min - int(np.count_nonzero(nearer))]] = True
    out: np.ndarray = pts[keep]
    return out


def _calibrate(kappa: np.ndarray, d2: np.ndarray, tails: np.ndarray, limits: np.ndarray) -> np.ndarray:
    """Calibrate each organ's mean-tail-dose row to its D2cm³.

    An organ whose row binds (or whose exact D2cm³ is over its limit) gets ``kappa × limit / D2cm³``: the mean
    over the hottest 2 cm³ exceeds D2cm³ by a factor that changes little between nearby loadings, so the next
    solution's D2cm³ lands on the limit (within 1 % in two rounds on the clinical case). The same for any tail row
    against its exact value (the V200 rows: the dose at which the HR-CTV's hottest ``v200_max_pct`` begins, whose
    tail mean is several times that dose, hence the wide clip).
    """
    out = kappa.copy()
    binds = (tails >= 0.98 * limits * kappa) | (d2 > limits * (1 + 1e-3))
    ok = binds & (d2 > 0)
    out[ok] = np.clip(kappa[ok] * limits[ok] / d2[ok] * (1 - 2e-3), 0.25, 10.0)
    return out


def _sampled_problem(channels: Sequence[Channel], planning: PlanningStructures, kernel: Tg43Kernel,
                     air_kerma_strength_u: float, aims: Aims, settings: ImplantSettings,
                     gtv: Structure | None, points: Sequence[PointLimit] = ()) -> _Problem:
    """Return the sampled problem of ``channels`` (each with at least one dwell) on the planning structures.

    ``oar_near`` holds each organ's voxels within ``oar_eval_radius_mm`` of any candidate dwell: every voxel of an
    organ outside it is farther than the radius from every dwell of every loading.
    """
    grid = planning.grid
    positions = np.concatenate([c.dwell_positions_mm for c in channels])
    directions = np.concatenate([c.dwell_directions for c in channels])
    channel_of = np.repeat(np.arange(len(channels)), [len(c.dwell_positions_mm) for c in channels])
    prob = _Problem(
        tuple(channels), positions, directions, channel_of,
        grid_points_mm(grid, np.flatnonzero(planning.target.mask.ravel())),
        None if gtv is None else grid_points_mm(grid, np.flatnonzero(gtv.mask.ravel())),
        tuple(grid_points_mm(grid, np.flatnonzero(o.mask.ravel())) for o in planning.oars),
        tuple(aims.oar_gy(o.name, "planning") for o in planning.oars), air_kerma_strength_u / 360000.0, kernel,
        tuple(o.name for o in planning.oars), settings.oar_eval_radius_mm, _supersampled(grid, planning.target.mask),
        None if gtv is None else _supersampled(grid, gtv.mask),
        oar_hard=tuple(aims.oar_gy(o.name, "limit") for o in planning.oars), points=tuple(points))
    tree = cKDTree(positions)
    return dataclasses.replace(prob, oar_near=tuple(
        pts[np.isfinite(tree.query(pts, distance_upper_bound=settings.oar_eval_radius_mm * (1 + 1e-6) + 1e-6)[0])]
        for pts in prob.oar_pts))


def _target_rows(prob: _Problem, n_pts: int, p_t: float, p_g: float) -> tuple[np.ndarray, np.ndarray]:
    """Return the target sample points ((m, 3) mm, LPS) and the dose each should reach ((m,) Gy per fraction).

    ``n_pts`` HR-CTV voxels (an even stride through them) at ``p_t``, and a quarter as many GTV voxels at ``p_g``.
    """
    pts = [prob.target_pts[_stride(len(prob.target_pts), n_pts)]]
    p = [np.full(len(pts[0]), p_t)]
    if prob.gtv_pts is not None and len(prob.gtv_pts):
        pts.append(prob.gtv_pts[_stride(len(prob.gtv_pts), max(1, n_pts // 4))])
        p.append(np.full(len(pts[1]), p_g))
    return np.concatenate(pts), np.concatenate(p)


def _modulation(settings: ImplantSettings) -> Modulation:
    """Return the modulation rules and objective weights of ``settings``."""
    ratio = float("inf") if settings.neighbour_ratio is None else settings.neighbour_ratio
    return Modulation(settings.max_dwell_share, ratio, settings.time_weight,
                      settings.invasiveness_weight, settings.smoothness_weight)
