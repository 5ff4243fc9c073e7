"""Source dwells and their TG-43 dose at points and on voxel grids.

Dwell sets, the dose-rate matrix, dose at points and on voxel grids, the source axis along a channel, and the
dwells of an existing plan.

Frames and units as :mod:`reachplan.planner.dose.tg43`: positions in mm, DICOM patient coordinates (LPS); dwell
``directions`` are unit vectors along the source axis pointing toward the needle tip; S_K in U
(= µGy m² h⁻¹ = cGy cm² h⁻¹); times in seconds; dose in Gy.
"""

from __future__ import annotations

import os
from collections.abc import Iterable, Mapping
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import Literal

import numpy as np

from reachplan._arrays import arc_length_mm
from reachplan.imaging.brachy_plan import RtPlan
from reachplan.imaging.types import Grid
from reachplan.planner.dose.tg43 import Tg43Kernel
from reachplan.planner.errors import PlanInputError


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
