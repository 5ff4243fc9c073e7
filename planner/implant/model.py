"""The linear model of a loading, as an LP or, with needle binaries, a MIP (solved by HiGHS through scipy).

**The model** (:class:`_Model`), linear in the dwell times ``t``: target points ``A t + u >= P`` (``u``
underdose, ``P`` the per-fraction dose that brings D90 to its aim, plus ``coverage_margin``; GTV points at the
GTV D98 aim); for each organ a **mean-tail-dose row**: the mean dose over its hottest 2 cm³ within ``κ`` × its
D2cm³ limit, written linearly as ``ζ + Σ w_i s_i / 2 cm³ <= κ L``, ``s_i >= (A t)_i - ζ``, ``s, ζ >= 0``
(Rockafellar & Uryasev, J Risk 2(3):21, 2000; as mean-tail-dose in radiotherapy planning, Romeijn et al.,
Oper Res 54(2):201, 2006). The mean over the hottest 2 cm³ is at least D2cm³, so with ``κ`` = 1 the row implies
D2cm³ <= L; ``κ`` is then calibrated to the exact D2cm³ on the organ's 20 cm³ nearest the loaded dwells
(:func:`reachplan.planner.implant.problem._calibrate`), which puts D2cm³ on the limit instead of below it.
Clinical loading: a **dwell-time gradient term** in the objective, ``smoothness_weight`` × the sum over neighbouring
dwells of a channel of ``|t_a - t_b|`` (auxiliary ``g >= ±(t_a - t_b)``), as a target dose in units of the
prescription; it is the linear form of IPSA's dwell-time modulation restriction and HIPO's dwell-time gradient
restriction (Balvert et al., Phys Med Biol 60(2):537, 2015, who also show what it costs in coverage; Mosleh-Shirazi
et al., J Contemp Brachytherapy 11(3):265, 2019, for cervix HDR): plateaus instead of one peak with halvings. The
older hard rule, neighbouring dwells within ``neighbour_ratio`` of each other, is kept when that is finite (a
channel is then loaded on all its dwells or on none). No dwell over ``max_dwell_share`` of the total. With
``min_time_s`` (:class:`reachplan.planner.implant.optimiser.DwellProblem`) a loaded dwell carries at least that
time: the LP first, then its short dwells rounded to 0 or the minimum and the LP solved again with every loaded
dwell at the minimum or more and the empty ones held empty
(:func:`reachplan.planner.implant.selection._min_time`). Objective: mean
underdose (in units of the prescription) + ``time_weight`` × mean target dose (shorter plans) + the gradient term
+ ``invasiveness_weight`` × each used needle's normalised hole distance and tissue length ("least invasive").

The rows of a structure's tail (:class:`reachplan.planner.implant.optimiser.OrganRows`) hold the mean over its
hottest ``volume_cc``: an organ's D2cm³ (2 cm³) in the nominal plan or with one needle displaced (a robustness
scenario, :mod:`reachplan.planner.implant.robust`), or the HR-CTV's hottest ``v200_max_pct`` of volume under
twice the prescription (its V200).

With needle binaries (the selection model): binary ``y_n`` per needle with each unit's time ``<= M y_n`` (``M``: the
time at which the unit alone brings every target point to ``P``, or fills an organ's row), one needle per template
hole, ``Σ y_n <= K``.

A selection's LP (its needles used, the others empty: :meth:`_Model.solve` with ``only``) is solved by a HiGHS
instance kept with the model (``highspy``), warm-started from the last selection's basis: only column bounds change
between selections, so the primal simplex starts from a basis that is primal feasible but for the needles taken
out (2-3 times fewer milliseconds per selection than a cold ``scipy.optimize.milp`` with the dual simplex warm, and
40-45 % fewer again with the primal; the same optimum to 1e-12). An enumerated selection starts from the optimal basis
of its needles but the last, which is primal feasible for it; a model of a few holes' needles
(:func:`reachplan.planner.implant.optimiser.restricted`) starts its first selection from the whole model's optimal
basis of no needle, its rows and columns matched by what they stand for (:meth:`_Model.basis_onto`), instead of a
cold solve (about 100 primal iterations instead of 400-1500 dual ones on a clinical case). The whole LP (no
``only``: the relaxation at a budget, the loading of chosen channels) has a second instance: a new budget changes one
row bound, a minimum dwell time column bounds, and the next round of a robust loading (a new model with more row sets,
:data:`reachplan.planner.implant.optimiser.WARM_START`) takes over the last round's instance with the added row sets
appended (:meth:`_Model._adopted`); the dual simplex then goes on from the last round's optimum and needs a fraction
of a cold solve's iterations (2-2.5 times less time over a clinical case's robust loadings, the same dwell times to
1e-9 s). Without ``highspy`` every solve goes through ``scipy.optimize.milp``. The rows are built block by block in
:mod:`reachplan.planner.implant.rows`.
"""

from __future__ import annotations

import threading
from collections.abc import Sequence
from typing import Any, NamedTuple

import numpy as np
from scipy import optimize as sopt
from scipy import sparse

from reachplan.planner.implant.optimiser import DwellProblem
from reachplan.planner.implant.rows import (
    _big_m,
    _Eye,
    _gradient_rows,
    _modulation_rows,
    _needle_rows,
    _neighbour_pairs,
    _organ_tail_rows,
    _Rows,
    _unit_sums,
    keys,
)

#: HiGHS instances of several threads do not run (or go) at once: two arms' instances solving on two threads crashed
#: the process (its task scheduler is the process's; cf. HiGHS issues 810 and 3141). Re-entrant: a model collected
#: while its own thread holds the lock may take it again.
_HIGHS_LOCK = threading.RLock()
_highs: Any  # HiGHS's own bindings: a solver object that keeps its basis between solves (optional)
try:
    from highspy import _core as _highs
except ImportError:  # pragma: no cover - exercised only without highspy
    _highs = None


class _Held(NamedTuple):
    """A model's HiGHS instance and the bounds it holds, in its own order of rows and columns.

    ``col`` and ``row``: the instance's column (row) of each of the model's (None: the same order); an instance
    taken over from an earlier model (:meth:`_Model._adopted`) has the rows and columns that model had in their
    place there and the added ones after them.
    """

    highs: Any
    col: np.ndarray | None
    row: np.ndarray | None
    row_lo: np.ndarray
    row_hi: np.ndarray
    col_lo: np.ndarray
    col_hi: np.ndarray


def _placed(index: np.ndarray, values: np.ndarray) -> np.ndarray:
    """Return ``values`` (one per model row or column) in an instance's order: ``out[index] = values``."""
    out = np.empty(len(values), dtype=values.dtype)
    out[index] = values
    return out


def _carried_index(came_from: np.ndarray, old_index: np.ndarray | None, old_count: int) -> np.ndarray:
    """Return the instance index of each row (or column) of a model taking over an earlier model's instance.

    ``came_from``: the earlier model's row of each (-1: added, appended in order); ``old_index``: the earlier model's
    instance index of each of its rows (None: the same); ``old_count``: how many it had.
    """
    out = np.empty(len(came_from), dtype=np.int64)
    kept = came_from >= 0
    out[kept] = came_from[kept] if old_index is None else old_index[came_from[kept]]
    out[~kept] = old_count + np.arange(int((~kept).sum()))
    return out


class _Model:
    """The linear model of a loading (module docstring), as an LP or, with needle binaries, a MIP.

    Variables ``[t (units), y (needles), u (target points), T, ζ (organs), s (organ points)]``. A unit is a run
    of consecutive dwells of one channel with a common time (a block in the selection model, one dwell in the
    final one); ``t`` is its time per dwell (s).

    Parameters
    ----------
    problem : DwellProblem
        Its ``units`` (None: one unit per column), rates, organ rows, needle binaries and modulation.
    warm : _Model or None
        A model of the same units, target points and needles whose organ row sets are a subset of this one's (the
        same :class:`OrganRows` objects), already solved without ``only``: this model's first LP takes over its
        HiGHS instance (:meth:`_adopted`), which the warm model then no longer has.
    """

    def __init__(self, problem: DwellProblem, warm: _Model | None = None) -> None:
        units = problem.units if problem.units is not None else tuple(
            np.array([j]) for j in range(problem.n_columns))
        unit_ch = np.array([int(problem.channel[u[0]]) for u in units], dtype=int)
        choice = problem.needles
        needles = [] if choice is None else list(choice.channels)
        a_t, p, organs = problem.target_rates, problem.target_dose_gy, problem.organs
        n_u, n_y, m = len(units), len(needles), len(a_t)
        sizes = np.array([len(u) for u in units], dtype=float)
        member = sparse.csr_matrix((np.ones(int(sizes.sum())), (np.concatenate(units),
                                                                np.repeat(np.arange(n_u), sizes.astype(int)))),
                                   shape=(a_t.shape[1], n_u))
        at = _unit_sums(a_t, units)
        ao = [_unit_sums(o.rates, units) for o in organs]
        n_p = sum(len(o.weight_cc) for o in organs)
        i_y, i_u, i_T, i_z, i_s = n_u, n_u + n_y, n_u + n_y + m, n_u + n_y + m + 1, n_u + n_y + m + 1 + len(organs)
        pairs = _neighbour_pairs(unit_ch)
        mod = problem.modulation
        i_g = i_s + n_p
        n = i_g + (len(pairs) if mod.smoothness_weight > 0 else 0)
        c = np.zeros(n)
        # the weights' scales are the whole problem's (every column), not the units', so that a selection's LP is
        # the same in a problem restricted to some channels' units (another arm's) as in the whole one
        n_cols = max(problem.n_columns, 1)
        c[:n_u] = mod.time_weight * sizes * at.mean(axis=0) / (problem.reference_dose_gy * n_cols)
        c[i_y:i_u] = mod.invasiveness_weight * (np.zeros(0) if choice is None else choice.cost)
        c[i_u:i_T] = 1.0 / (m * problem.reference_dose_gy)
        c[i_g:] = mod.smoothness_weight * float(a_t.mean()) / problem.reference_dose_gy
        rows = _Rows(n)
        rows.add(rows.cols([(0, at), (i_u, _Eye(m))], m), p, np.inf)  # target: A t + u >= p
        _modulation_rows(rows, sizes, unit_ch, i_T, mod.max_dwell_share, mod.neighbour_ratio)
        if n > i_g:
            _gradient_rows(rows, pairs, i_g)
        limit_rows = _organ_tail_rows(rows, organs, ao, i_z, i_s)
        self.big_m = _big_m(p, at, organs, ao)
        if n_y and choice is not None:
            _needle_rows(rows, unit_ch, needles, list(choice.holes), self.big_m, i_y)
        self.a = rows.matrix()
        self.a_csc = self.a.tocsc()
        y_index = {ch: i for i, ch in enumerate(needles)}
        self.unit_y = np.array([y_index.get(int(ch), -1) for ch in unit_ch], dtype=int)  # -1: not a needle
        self.lb, self.ub = np.concatenate(rows.lb), np.concatenate(rows.ub)
        self.limit_rows = np.array(limit_rows, dtype=int)
        self.limits = np.array([o.limit_gy for o in organs])
        self.c, self.n, self.n_u, self.n_y, self.i_y, self.i_u = c, n, n_u, n_y, i_y, i_u
        self.member = member
        self.hole_of = [] if choice is None else list(choice.holes)
        self.unit_ch, self.needles, self.neighbour_rows = unit_ch, needles, bool(np.isfinite(mod.neighbour_ratio))
        self.min_time_s = problem.min_time_s
        # what a later model needs to start from this one's basis: the organ row sets (by identity), their first
        # columns and rows; the rows before the organs' (target, modulation, gradient) and after them (needles)
        self.organs = tuple(organs)
        self.i_z, self.i_s, self.i_g, self.m = i_z, i_s, i_g, m
        q = np.array([len(o.weight_cc) for o in organs], dtype=int)
        self.organ_s = i_s + np.concatenate([[0], np.cumsum(q)[:-1]]).astype(int) if len(q) else q
        self.organ_q = q
        self.organ_row = (np.array(limit_rows, dtype=int) - q) if len(q) else q
        self.n_head_rows = int(self.organ_row[0]) if len(q) else self.a.shape[0]
        # HiGHS instances kept for warm starts, each with the bounds it holds: "selection" (the LPs of selections,
        # :meth:`_warm`), "full" (the whole LP, :meth:`_full`)
        self._highs: dict[str, _Held] = {}
        # the optimal basis of each selection solved here by enumeration (needle indices, ascending): a selection one
        # needle larger starts from it (:func:`reachplan.planner.implant.selection._exhaustive`)
        self.selection_bases: dict[tuple[int, ...], Any] = {}
        self._first_basis: Any = None  # the first selection's start (:meth:`start_selection_from` before any)
        self._warm_from = warm

    def solve(self, budget: int | None = None, kappa: np.ndarray | None = None,
              only: Sequence[int] | None = None, units: tuple[np.ndarray, np.ndarray] | None = None,
              ) -> sopt.OptimizeResult:
        """Solve the LP (the needle binaries relaxed to [0, 1]) with at most ``budget`` needles (None: no budget).

        Parameters
        ----------
        budget : int, optional
            The budget row's bound (None: no budget).
        kappa : (n_organs,) float, unitless, optional
            Each organ's mean-tail-dose row may reach ``kappa`` × its limit (the calibration of that row to D2cm³).
        only : sequence of int, optional
            The needles (indices into the needles) used (``y`` = 1), the others held empty: the LP is then solved on
            their columns alone (and the intracavitary channels').
        units : ((n_u,) float, (n_u,) float), optional
            Lower and upper bounds of each unit's time (s); None: ``t >= 0``.

        Returns
        -------
        scipy.optimize.OptimizeResult
            HiGHS's result; ``x`` (None when it failed) in the full model's columns.
        """
        ub = self.ub.copy()
        if kappa is not None and len(self.limit_rows):
            ub[self.limit_rows] = self.limits * kappa
        if self.n_y and budget is not None:
            ub[-1] = float(budget)
        lo = np.zeros(self.n)
        hi = np.full(self.n, np.inf)
        hi[self.i_y:self.i_u] = 1.0
        if units is not None:
            lo[:self.n_u], hi[:self.n_u] = units[0], units[1]
        cols = np.arange(self.n)
        if only is not None and units is None and _highs is not None:
            return self._warm(ub, np.asarray(only, dtype=int))
        if only is None and _highs is not None:
            res = self._full(ub, lo, hi)
            if res.x is not None:
                return res
        if only is not None:
            on = np.zeros(self.n_y, dtype=bool)
            on[np.asarray(only, dtype=int)] = True
            lo[self.i_y:self.i_u] = on
            keep = np.ones(self.n, dtype=bool)
            keep[:self.n_u] = self.unit_y < 0
            keep[:self.n_u][self.unit_y >= 0] = on[self.unit_y[self.unit_y >= 0]]
            keep[self.i_y:self.i_u] = on
            cols = np.flatnonzero(keep)
        a = self.a if only is None else self.a_csc[:, cols]
        res = sopt.milp(self.c[cols], constraints=[sopt.LinearConstraint(a, self.lb, ub)],
                        bounds=sopt.Bounds(lo[cols], hi[cols]), options={"disp": False})
        if only is not None and res.x is not None:
            x = np.zeros(self.n)
            x[cols] = res.x
            res.x = x
        return res

    def __del__(self) -> None:
        """Let the HiGHS instances go under the lock (see :data:`_HIGHS_LOCK`)."""
        if getattr(self, "_highs", None):
            with _HIGHS_LOCK:
                self._highs = {}

    def selection_basis(self) -> Any:
        """Return the basis the last selection's LP ended on (a HiGHS basis), None before any or without ``highspy``.

        Returns
        -------
        highspy.HighsBasis or None
        """
        with _HIGHS_LOCK:
            held = self._highs.get("selection")
            return None if held is None else held.highs.getBasis()

    def start_selection_from(self, basis: Any) -> None:
        """Start the next selection's LP from ``basis`` (:meth:`selection_basis`) instead of the last LP's.

        Before the model's first selection: its first LP starts there, with the primal simplex (as the later ones),
        instead of the dual simplex from the slack basis.

        Parameters
        ----------
        basis : highspy.HighsBasis or None
            A basis of this model's selection LPs (or :meth:`basis_onto` this model); None: nothing changes.
        """
        with _HIGHS_LOCK:
            held = self._highs.get("selection")
            if basis is not None and held is not None:
                held.highs.setBasis(basis)
            elif basis is not None:
                self._first_basis = basis

    def basis_onto(self, basis: Any, other: _Model) -> Any:
        """Return ``basis``, one of this model's selection LPs, as a basis of ``other``'s, or None.

        Rows and columns are matched by what they stand for (:func:`reachplan.planner.implant.rows.keys`): a unit,
        needle, target point, organ row set (by identity) and its points. The other model's own rows are basic and its
        own columns nonbasic at their lower bounds. Made for a model of some of this one's needles
        (:func:`reachplan.planner.implant.optimiser.restricted`): the basis of a selection of those needles (e.g. of
        none) is then one of the same selection's LP there, and primal feasible for a selection one needle larger.
        None without ``highspy``, when the basis is not of this model's selection instance, or when the matched basis
        would not hold one basic variable per row.

        Parameters
        ----------
        basis : highspy.HighsBasis or None
            From :meth:`selection_basis`.
        other : _Model
            The model to start.

        Returns
        -------
        highspy.HighsBasis or None
        """
        if basis is None or _highs is None:
            return None
        col_status, row_status = list(basis.col_status), list(basis.row_status)
        mine, theirs = self._keys(), other._keys()
        if mine is None or theirs is None or (len(col_status), len(row_status)) != (self.n, self.a.shape[0]):
            return None
        at_col = {k: i for i, k in enumerate(mine[0])}
        at_row = {k: i for i, k in enumerate(mine[1])}
        basic, lower = _highs.HighsBasisStatus.kBasic, _highs.HighsBasisStatus.kLower
        cols = [col_status[at_col[k]] if k in at_col else lower for k in theirs[0]]
        rows = [row_status[at_row[k]] if k in at_row else basic for k in theirs[1]]
        if sum(s == basic for s in cols) + sum(s == basic for s in rows) != len(rows):
            return None
        out = _highs.HighsBasis()
        out.col_status, out.row_status, out.valid = cols, rows, True
        return out

    def _keys(self) -> tuple[list[tuple[Any, ...]], list[tuple[Any, ...]]] | None:
        """Return :func:`~reachplan.planner.implant.rows.keys` of this model; None if they do not fit its shape."""
        cols, rows = keys(self.unit_ch, self.needles, self.hole_of, self.m, self.organs, self.n > self.i_g,
                          self.neighbour_rows)
        return (cols, rows) if (len(cols), len(rows)) == (self.n, self.a.shape[0]) else None

    def _on_columns(self, only: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Return the column bounds (lower, upper) with the needles ``only`` used and every other needle empty."""
        on = np.zeros(self.n_y, dtype=bool)
        on[only] = True
        lo = np.zeros(self.n)
        hi = np.full(self.n, np.inf)
        lo[self.i_y:self.i_u] = hi[self.i_y:self.i_u] = on
        is_needle = self.unit_y >= 0
        hi[:self.n_u][is_needle] = np.where(on[self.unit_y[is_needle]], np.inf, 0.0)
        return lo, hi

    def _warm(self, row_ub: np.ndarray, only: np.ndarray) -> sopt.OptimizeResult:
        """Solve :meth:`_warm_locked` holding :data:`_HIGHS_LOCK`.

        Parameters
        ----------
        row_ub : (rows,) float
            The rows' upper bounds.
        only : (k,) int
            The needles used.

        Returns
        -------
        scipy.optimize.OptimizeResult
        """
        with _HIGHS_LOCK:
            return self._warm_locked(row_ub, only)

    def _warm_locked(self, row_ub: np.ndarray, only: np.ndarray) -> sopt.OptimizeResult:
        """Solve the LP of the selection ``only`` on the model's HiGHS instance, from the last solve's basis.

        Parameters
        ----------
        row_ub : (rows,) float
            The rows' upper bounds (the organ rows' calibration applied).
        only : (k,) int
            The needles used (indices into the needles).

        Returns
        -------
        scipy.optimize.OptimizeResult
            ``x`` (None when HiGHS does not report an optimum), ``fun``, ``status`` (0: optimal) and ``message``.
        """
        lo, hi = self._on_columns(only)
        return self._run("selection", row_ub, lo, hi)

    def _full(self, row_ub: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> sopt.OptimizeResult:
        """Solve the whole LP on the model's own HiGHS instance, from its last basis (or the warm model's).

        The rounds of a robust loading add row sets and change bounds (calibration, coverage aim, minimum times):
        each solve is the dual simplex from the last basis, which stays dual feasible (an added row set's rows are
        basic, its columns nonbasic at 0 with zero reduced cost), instead of a cold solve. The optimum is the same
        LP's (the tests compare it with a cold ``scipy.optimize.milp``).

        Parameters
        ----------
        row_ub : (rows,) float
            The rows' upper bounds (the organ rows' calibration applied).
        lo, hi : (n,) float
            The columns' bounds.

        Returns
        -------
        scipy.optimize.OptimizeResult
            ``x`` None when HiGHS does not report an optimum.
        """
        with _HIGHS_LOCK:
            res = self._run("full", row_ub, lo, hi)
            if res.x is None:
                self._highs.pop("full", None)
            return res

    def _run(self, key: str, row_ub: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> sopt.OptimizeResult:
        """Solve the LP with these bounds on the HiGHS instance ``key``, from its last basis; the caller holds the lock.

        The instance is built on first use, without presolve (it costs more than it saves on these LPs: a third of
        a cold solve), and solves first with the dual simplex; ``"full"`` first takes over the warm model's instance
        when there is one (:meth:`_adopted`). ``"selection"`` then runs the primal simplex: a new selection changes
        column bounds only, and its last basis stays primal feasible but for the needles taken out (40-45 % less
        time than the dual simplex on the clinical cases, the same optima to 1e-10 s of dwell time).

        Parameters
        ----------
        key : str
            ``"selection"`` or ``"full"``.
        row_ub : (rows,) float
            The rows' upper bounds.
        lo, hi : (n,) float
            The columns' bounds.

        Returns
        -------
        scipy.optimize.OptimizeResult
            ``x`` (None when HiGHS does not report an optimum), ``fun``, ``status`` (0: optimal) and ``message``.
        """
        inf = _highs.kHighsInf
        row_lo = np.where(np.isfinite(self.lb), self.lb, -inf)
        row_hi = np.where(np.isfinite(row_ub), row_ub, inf)
        col_hi = np.where(np.isfinite(hi), hi, inf)
        held = self._highs.get(key)
        if held is None and key == "full":
            held = self._adopted()
        if held is None:
            h: Any = _highs._Highs()
            h.setOptionValue("output_flag", False)
            h.setOptionValue("threads", 1)
            # presolve costs more than it saves here (a third of a cold solve of a robust loading's LP)
            h.setOptionValue("presolve", "off")
            lp = _highs.HighsLp()
            lp.num_col_, lp.num_row_ = self.n, self.a.shape[0]
            lp.col_cost_, lp.col_lower_, lp.col_upper_ = self.c, lo, col_hi
            lp.row_lower_, lp.row_upper_ = row_lo, row_hi
            lp.a_matrix_.format_ = _highs.MatrixFormat.kColwise
            lp.a_matrix_.start_, lp.a_matrix_.index_ = self.a_csc.indptr, self.a_csc.indices
            lp.a_matrix_.value_ = self.a_csc.data
            h.passModel(lp)
            held = _Held(h, None, None, row_lo, row_hi, lo.copy(), col_hi)
            if key == "selection" and self._first_basis is not None:  # from a basis given: primal, as the next ones
                h.setBasis(self._first_basis)
                h.setOptionValue("simplex_strategy", 4)
                self._first_basis = None
        else:
            h = held.highs
            if held.row is not None and held.col is not None:  # into the instance's order
                row_lo, row_hi = _placed(held.row, row_lo), _placed(held.row, row_hi)
                lo, col_hi = _placed(held.col, lo), _placed(held.col, col_hi)
            changed = np.flatnonzero((row_lo != held.row_lo) | (row_hi != held.row_hi)).astype(np.int32)
            if len(changed):
                h.changeRowsBounds(len(changed), changed, row_lo[changed], row_hi[changed])
            moved = np.flatnonzero((lo != held.col_lo) | (col_hi != held.col_hi)).astype(np.int32)
            if len(moved):
                h.changeColsBounds(len(moved), moved, lo[moved], col_hi[moved])
            held = held._replace(row_lo=row_lo, row_hi=row_hi, col_lo=lo.copy(), col_hi=col_hi)
        first = key not in self._highs
        self._highs[key] = held
        h.run()
        if key == "selection" and first:
            h.setOptionValue("simplex_strategy", 4)  # the next selections: primal, from this basis
        status = h.getModelStatus()
        if status != _highs.HighsModelStatus.kOptimal:
            return sopt.OptimizeResult(x=None, fun=np.inf, status=1, message=f"HiGHS: {h.modelStatusToString(status)}")
        x = np.asarray(h.getSolution().col_value, dtype=float)
        if held.col is not None:
            x = x[held.col]
        return sopt.OptimizeResult(x=x, fun=float(h.getInfo().objective_function_value), status=0,
                                   message="Optimization terminated successfully. (HiGHS Status 7: Optimal)")

    def _adopted(self) -> _Held | None:
        """Take over the warm model's ``"full"`` instance, this model's added row sets appended; or None.

        The warm model (the last round of a robust loading) holds every row and column of this one but those of the
        organ row sets it lacks: they are added to its instance (the columns at 0 and nonbasic, the rows basic), so
        the instance keeps its basis, and the dual simplex goes on from the last round's optimum,
        which stays dual feasible (an added set's columns have zero cost and no entry in the other rows). Before, each
        round passed its whole model to a new instance and set the last round's basis on it (15-20 ms a round more on
        a clinical case's robust loadings). Shared rows and columns keep their place in the instance; added ones come
        after them (:class:`_Held`). None when there is no such model (or it has no instance, or the models differ
        otherwise): the caller then builds a new instance.

        Returns
        -------
        _Held or None
        """
        old, self._warm_from = self._warm_from, None  # no chain of models kept alive
        held = None if old is None else old._highs.get("full")
        carried = None if old is None or held is None else self._carried(old)
        if old is None or held is None or carried is None:
            return None
        col_from, row_from = carried
        new_c, new_r = np.flatnonzero(col_from < 0), np.flatnonzero(row_from < 0)
        added = self.a[new_r]
        if self.a.nnz != old.a.nnz + added.nnz:  # a shared row or column with other entries: not the same model
            return None
        del old._highs["full"]
        inf = _highs.kHighsInf
        col = _carried_index(col_from, held.col, old.n)
        row = _carried_index(row_from, held.row, old.a.shape[0])
        h = held.highs
        zeros, no_hi = np.zeros(len(new_c)), np.full(len(new_c), inf)
        h.addCols(len(new_c), self.c[new_c], zeros, no_hi, 0, np.zeros(len(new_c), dtype=np.int32),
                  np.zeros(0, dtype=np.int32), np.zeros(0))
        r_lo = np.where(np.isfinite(self.lb[new_r]), self.lb[new_r], -inf)
        r_hi = np.where(np.isfinite(self.ub[new_r]), self.ub[new_r], inf)
        h.addRows(len(new_r), r_lo, r_hi, added.nnz, added.indptr[:-1].astype(np.int32),
                  col[added.indices].astype(np.int32), added.data)
        shared = np.flatnonzero(col_from >= 0)
        cost = self.c[shared]
        moved = np.flatnonzero(cost != old.c[col_from[shared]])
        if len(moved):
            h.changeColsCost(len(moved), col[shared[moved]].astype(np.int32), cost[moved])
        return _Held(h, col, row, np.concatenate([held.row_lo, r_lo]), np.concatenate([held.row_hi, r_hi]),
                     np.concatenate([held.col_lo, zeros]), np.concatenate([held.col_hi, no_hi]))

    def _carried(self, old: _Model) -> tuple[np.ndarray, np.ndarray] | None:
        """Return the column and row of ``old`` each of this model's columns and rows is (-1: only this model has it).

        Shared: the blocks both models have (times, binaries, underdoses, total time, gradients; the target,
        modulation, gradient and needle rows) and each organ row set of ``old`` (by identity), which must all be this
        model's too. None when the models differ otherwise.
        """
        same = (old.n_u, old.n_y, old.m, old.n_head_rows, old.n - old.i_g, old.a.shape[0] - old.n_head_rows
                - int((old.organ_q + 1).sum())) == (self.n_u, self.n_y, self.m, self.n_head_rows, self.n - self.i_g,
                                                    self.a.shape[0] - self.n_head_rows - int((self.organ_q + 1).sum()))
        where = {id(o): j for j, o in enumerate(self.organs)}
        if not same or any(id(o) not in where for o in old.organs):
            return None
        if self.n_y and not np.array_equal(self.big_m, old.big_m):  # the needle rows' coefficients
            return None
        col = np.full(self.n, -1, dtype=np.int64)
        row = np.full(self.a.shape[0], -1, dtype=np.int64)
        col[:self.i_z] = np.arange(old.i_z)
        col[self.i_g:] = old.i_g + np.arange(self.n - self.i_g)
        row[:self.n_head_rows] = np.arange(old.n_head_rows)
        tail = self.a.shape[0] - self.n_head_rows - int((self.organ_q + 1).sum())
        if tail:
            row[len(row) - tail:] = old.a.shape[0] - tail + np.arange(tail)
        for j, o in enumerate(old.organs):
            k, q = where[id(o)], int(old.organ_q[j])
            col[self.i_z + k] = old.i_z + j
            col[self.organ_s[k]:self.organ_s[k] + q] = old.organ_s[j] + np.arange(q)
            row[self.organ_row[k]:self.organ_row[k] + q + 1] = old.organ_row[j] + np.arange(q + 1)
        return col, row

    def dwell_times(self, x: np.ndarray) -> np.ndarray:
        """Return the dwell times of a solution.

        Parameters
        ----------
        x : (n,) float
            A solution in the model's columns.

        Returns
        -------
        (D,) float, s
        """
        out: np.ndarray = self.member @ np.maximum(x[:self.n_u], 0.0)
        return out

    def selected(self, x: np.ndarray) -> tuple[int, ...]:
        """Return the needles a solution uses.

        Parameters
        ----------
        x : (n,) float
            :meth:`solve`'s ``x``; only its needle binaries ``y`` are read.

        Returns
        -------
        tuple of int
            The needles with ``y`` > 0.5, as indices into the problem's needles (ascending).
        """
        return tuple(int(i) for i in np.flatnonzero(x[self.i_y:self.i_u] > 0.5))
