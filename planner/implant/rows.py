"""The constraint rows of the linear model of a loading (:mod:`reachplan.planner.implant.model`), block by block.

Columns in the model's order ``[t (units), y (needles), u (target points), T, ζ (organs), s (organ points),
g (gradients)]``. :class:`reachplan.planner.implant.model._Model` adds the blocks in this order: target, total time
and shares, neighbour ratios, gradients, each organ's tail rows, needle rows (the budget row last); :func:`keys`
names its columns and rows in the same order.
"""

from __future__ import annotations

import itertools
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, NamedTuple

import numpy as np
from scipy import sparse

from reachplan.planner.implant.optimiser import OrganRows, tail_mean


@dataclass(frozen=True)
class _Eye:
    """A part of a row block: ``value`` times the identity of ``size`` rows (:meth:`_Rows.cols`).

    Parameters
    ----------
    size : int
        Rows (and columns) of the part.
    value : float
        Its diagonal.
    """

    size: int
    value: float = 1.0


class _Block(NamedTuple):
    """A row block as coordinate triplets (its entries in the order given) and its row count."""

    row: np.ndarray
    col: np.ndarray
    data: np.ndarray
    n_rows: int


class _Rows:
    """The constraint rows of a model with ``n`` variables, block by block, with their lower and upper bounds.

    The blocks are kept as coordinate triplets and assembled once (:meth:`matrix`): the same matrix as stacking
    sparse blocks, at a fraction of the cost (a model is built per selection problem and per robust round).

    Parameters
    ----------
    n : int
        Number of variables (columns) of the model.
    """

    def __init__(self, n: int) -> None:
        self.n = n
        self.blocks: list[_Block] = []
        self.lb: list[np.ndarray] = []
        self.ub: list[np.ndarray] = []
        self._count = 0

    @property
    def count(self) -> int:
        """Rows added so far."""
        return self._count

    def add(self, rows: sparse.spmatrix | _Block, lo: float | np.ndarray, hi: float | np.ndarray) -> None:
        """Add the block ``lo <= rows x <= hi``.

        Parameters
        ----------
        rows : (r, n) sparse matrix or _Block
            The block's coefficients, in the unit of its bounds per unit of each variable (:meth:`cols`).
        lo : float or (r,) float
            Lower bound of each row (``-inf``: none), broadcast to the block's rows.
        hi : float or (r,) float
            Upper bound of each row (``inf``: none).
        """
        if not isinstance(rows, _Block):
            m = sparse.coo_matrix(rows)
            rows = _Block(m.row, m.col, m.data, m.shape[0])
        self.blocks.append(rows)
        self.lb.append(np.broadcast_to(lo, rows.n_rows).astype(float))
        self.ub.append(np.broadcast_to(hi, rows.n_rows).astype(float))
        self._count += rows.n_rows

    def cols(self, parts: Sequence[tuple[int, sparse.spmatrix | np.ndarray | _Eye]], n_rows: int) -> _Block:
        """Return a row block holding each ``(first column, matrix)`` part, zeros elsewhere.

        Parameters
        ----------
        parts : sequence of (int, (r, c) matrix)
            The first column of each part and its coefficients (sparse, dense, a dense part's zeros left out, or a
            scaled identity), not overlapping.
        n_rows : int
            ``r``, the rows of the block.

        Returns
        -------
        _Block
            Its entries part by part, each part's in row-major order (a sparse part's in its coordinate order).
        """
        r_i, c_i, v = [], [], []
        for start, mat in parts:
            if isinstance(mat, _Eye):
                r = c = np.arange(mat.size)
                d = np.full(mat.size, float(mat.value))
            elif sparse.issparse(mat):
                m = sparse.coo_matrix(mat)
                r, c, d = m.row, m.col, m.data
            else:
                dense = np.asarray(mat, dtype=float)
                r, c = np.nonzero(dense)
                d = dense[r, c]
            r_i.append(r)
            c_i.append(c + start)
            v.append(d)
        return _Block(np.concatenate(r_i), np.concatenate(c_i), np.concatenate(v), n_rows)

    def matrix(self) -> sparse.csr_matrix:
        """Return every block stacked, in the order added.

        Returns
        -------
        (rows, n) scipy.sparse CSR matrix
        """
        offsets = np.cumsum([0] + [b.n_rows for b in self.blocks])
        rows = np.concatenate([b.row + o for b, o in zip(self.blocks, offsets, strict=False)])
        cols = np.concatenate([b.col for b in self.blocks])
        vals = np.concatenate([b.data for b in self.blocks]).astype(float)
        return sparse.csr_matrix((vals, (rows, cols)), shape=(int(offsets[-1]), self.n))


def _unit_sums(rates: np.ndarray, units: Sequence[np.ndarray]) -> np.ndarray:
    """Return each unit's column: the sum of its dwells' columns of ``rates``, in the order of its dwells.

    Only the units' columns are read (a restricted problem's few, not all of its rates). The sum runs from the unit's
    first dwell to its last, one column added at a time: the same floating-point sums, bit for bit, as the product
    with the units' 0/1 membership matrix (which adds each dwell's column to its unit's in dwell order).

    Parameters
    ----------
    rates : (p, D) float
        A column per dwell (any unit: Gy s⁻¹ per fraction for the models' rates).
    units : sequence of (k_u,) int
        Each unit's dwells (indices into ``rates``' columns), ascending.

    Returns
    -------
    (p, n_u) float
        In the unit of ``rates``.
    """
    sizes = np.array([len(u) for u in units], dtype=int)
    if len(units) == 0:
        return np.zeros((rates.shape[0], 0))
    first = np.array([int(u[0]) for u in units], dtype=int)
    out: np.ndarray = np.asarray(rates, dtype=float)[:, first]  # a copy (fancy indexing)
    for k in range(1, int(sizes.max())):
        on = np.flatnonzero(sizes > k)
        out[:, on] += rates[:, np.array([int(units[int(u)][k]) for u in on], dtype=int)]
    return out


def _modulation_rows(rows: _Rows, sizes: np.ndarray, unit_ch: np.ndarray, i_T: int, share: float,
                     ratio: float) -> None:
    """Add the total time ``T = Σ sizes·t``, no unit over ``share`` of it, and the neighbour rows of each channel."""
    n_u = len(sizes)
    rows.add(rows.cols([(0, sizes[None, :]), (i_T, -np.ones((1, 1)))], 1), 0.0, 0.0)
    share = share * (1 - 1e-3)
    rows.add(rows.cols([(0, _Eye(n_u)), (i_T, -share * np.ones((n_u, 1)))], n_u), -np.inf, 0.0)
    if not np.isfinite(ratio):
        return
    groups = [np.flatnonzero(unit_ch == ch) for ch in np.unique(unit_ch)]
    for rowset in _neighbour_rows(groups, n_u, ratio):
        rows.add(rows.cols([(0, rowset)], rowset.shape[0]), -np.inf, 0.0)


def _neighbour_pairs(unit_ch: np.ndarray) -> np.ndarray:
    """Return the (q, 2) int pairs of consecutive units of one channel (units of a channel are consecutive)."""
    a = np.flatnonzero(unit_ch[1:] == unit_ch[:-1])
    return np.column_stack([a, a + 1]).astype(int)


def _gradient_rows(rows: _Rows, pairs: np.ndarray, i_g: int) -> None:
    """Add ``g_k >= t_a - t_b`` and ``g_k >= t_b - t_a`` for each pair (a, b) of neighbouring units."""
    q = len(pairs)
    if q == 0:
        return
    r = np.arange(q)
    for sign in (1.0, -1.0):
        block = sparse.csr_matrix((np.concatenate([np.full(q, sign), np.full(q, -sign), np.full(q, -1.0)]),
                                   (np.concatenate([r, r, r]), np.concatenate([pairs[:, 0], pairs[:, 1], i_g + r]))),
                                  shape=(q, rows.n))
        rows.add(block, -np.inf, 0.0)


def _organ_tail_rows(rows: _Rows, organs: Sequence[OrganRows], ao: Sequence[np.ndarray], i_z: int,
                     i_s: int) -> list[int]:
    """Add each organ's mean-tail-dose rows; return the index of each organ's limit row.

    Each organ's mean dose over its hottest 2 cm³ within its limit (it implies D2cm³ <= limit):
    ``ζ + Σ w_i s_i / 2 cm³ <= limit``, ``s_i >= (A t)_i - ζ``, ``s >= 0``, ``ζ >= 0``.
    """
    start = 0
    limit_rows = []
    for k, (o, a) in enumerate(zip(organs, ao, strict=True)):
        q = len(o.weight_cc)
        rows.add(rows.cols([(0, a), (i_z + k, -np.ones((q, 1))), (i_s + start, _Eye(q, -1.0))], q),
                 -np.inf, 0.0)
        limit_rows.append(rows.count)
        rows.add(rows.cols([(i_z + k, np.ones((1, 1))), (i_s + start, o.weight_cc[None, :] / o.volume_cc)], 1), -np.inf,
                 o.limit_gy)
        start += q
    return limit_rows


def _big_m(p: np.ndarray, at: np.ndarray, organs: Sequence[OrganRows], ao: Sequence[np.ndarray]) -> np.ndarray:
    """Return each unit's big-M (s).

    A unit's time is at most what brings every target point to its dose alone (more only adds time; scaling the
    whole loading down keeps every row) and at most what alone fills an organ's limit.
    """
    big_m = p.max() / np.maximum(at.min(axis=0), 1e-30)
    for o, a in zip(organs, ao, strict=True):
        big_m = np.minimum(big_m, o.limit_gy / np.maximum(tail_mean(a, o.weight_cc, o.volume_cc), 1e-30))
    out: np.ndarray = big_m
    return out


def _needle_rows(rows: _Rows, unit_ch: np.ndarray, needles: Sequence[int], hole_of: Sequence[str],
                 big_m: np.ndarray, i_y: int) -> None:
    """Add ``t <= M y`` for every needle unit, one needle per hole, and the budget row (last)."""
    n_y = len(needles)
    y_of = {ch: i for i, ch in enumerate(needles)}
    r_i, c_i, v = [], [], []
    r = 0
    for u_i, ch in enumerate(unit_ch):
        if int(ch) in y_of:
            r_i += [r, r]
            c_i += [u_i, i_y + y_of[int(ch)]]
            v += [1.0, -float(big_m[u_i])]
            r += 1
    rows.add(sparse.csr_matrix((v, (r_i, c_i)), shape=(r, rows.n)), -np.inf, 0.0)
    holes = sorted(set(hole_of))
    h_of = {h: i for i, h in enumerate(holes)}
    per_hole = sparse.csr_matrix((np.ones(n_y), ([h_of[h] for h in hole_of], np.arange(n_y))),
                                 shape=(len(holes), n_y))
    rows.add(rows.cols([(i_y, per_hole)], len(holes)), -np.inf, 1.0)
    rows.add(rows.cols([(i_y, np.ones((1, n_y)))], 1), -np.inf, np.inf)  # the budget row (last)


def _neighbour_rows(groups: Sequence[np.ndarray], n_cols: int, ratio: float) -> list[sparse.csr_matrix]:
    """Rows ``x_a - r x_b <= 0`` and ``x_b - r x_a <= 0`` for consecutive columns a, b of each group."""
    rows, cols, vals = [], [], []
    r = 0
    for g in groups:
        for a, b in itertools.pairwise(g):
            rows += [r, r, r + 1, r + 1]
            cols += [a, b, b, a]
            vals += [1.0, -ratio, 1.0, -ratio]
            r += 2
    if r == 0:
        return []
    return [sparse.csr_matrix((vals, (rows, cols)), shape=(r, n_cols))]


def keys(unit_ch: np.ndarray, needles: Sequence[int], hole_of: Sequence[str], m: int, organs: Sequence[OrganRows],
         gradient: bool, ratio_rows: bool) -> tuple[list[tuple[Any, ...]], list[tuple[Any, ...]]]:
    """Return a key per column and per row of a model, naming what it stands for, in the order the model adds them.

    A unit is its channel and its rank among that channel's units; a needle its channel; a target point its index; an
    organ row set its object's identity (its points by index). Two models' rows and columns with equal keys are the
    same variable or constraint (:meth:`reachplan.planner.implant.model._Model.basis_onto`).

    Parameters
    ----------
    unit_ch : (n_u,) int
        Each unit's channel (a channel's units consecutive).
    needles : sequence of int
        The needles' channels (empty: no needle rows).
    hole_of : sequence of str
        Each needle's template hole.
    m : int
        Target points.
    organs : sequence of OrganRows
        The organ row sets, in order.
    gradient : bool
        Whether the model has gradient columns and rows (:func:`_gradient_rows`).
    ratio_rows : bool
        Whether it has neighbour-ratio rows (:func:`_neighbour_rows`).

    Returns
    -------
    cols, rows : list of tuple
        The keys, in the model's order of columns and of rows.
    """
    rank = np.zeros(len(unit_ch), dtype=int)
    for i in range(1, len(unit_ch)):
        rank[i] = rank[i - 1] + 1 if unit_ch[i] == unit_ch[i - 1] else 0
    unit = [(int(c), int(r)) for c, r in zip(unit_ch, rank, strict=True)]
    pairs = _neighbour_pairs(unit_ch)
    cols: list[tuple[Any, ...]] = [("t", *u) for u in unit]
    cols += [("y", int(c)) for c in needles]
    cols += [("u", k) for k in range(m)] + [("T",)] + [("z", id(o)) for o in organs]
    cols += [("s", id(o), i) for o in organs for i in range(len(o.weight_cc))]
    cols += [("g", *unit[a]) for a in pairs[:, 0]] if gradient else []
    rows: list[tuple[Any, ...]] = [("target", k) for k in range(m)] + [("T",)] + [("share", *u) for u in unit]
    if ratio_rows:  # by channel, two per pair of neighbouring units
        rows += [("ratio", *unit[int(a)], side) for ch in np.unique(unit_ch)
                 for a in np.flatnonzero(unit_ch == ch)[:-1] for side in (0, 1)]
    if gradient:
        rows += [("g", sign, *unit[a]) for sign in (1, -1) for a in pairs[:, 0]]
    for o in organs:
        rows += [("s", id(o), i) for i in range(len(o.weight_cc))] + [("z", id(o))]
    if len(needles):
        on = {int(c) for c in needles}
        rows += [("M", *u) for u, ch in zip(unit, unit_ch, strict=True) if int(ch) in on]
        rows += [("hole", h) for h in sorted(set(hole_of))] + [("budget",)]
    return cols, rows
