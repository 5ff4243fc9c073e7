"""The built-in dwell optimiser ``"lp"``: linear programmes on the model, and the needle selection at a budget.

Without a budget, the LP of :class:`reachplan.planner.implant.model._Model` (needle binaries, if any, relaxed to
[0, 1]): the dwell times of a chosen set, or the bound of every candidate loaded.

**Needle selection at a budget K: exact by enumeration where that is cheap, else a deterministic heuristic with a
bound.** When the selections of at most K needles (one per hole) number at most ``exhaustive_max``
(:class:`reachplan.planner.implant.optimiser.DwellProblem`; ``ImplantSettings.exhaustive_max_selections``), every
one's LP is solved and the best kept (:func:`_exhaustive`): the selection is the model's optimum (gap 0), and the
same needles get the same objective in every arm whose problem shares the rows
(:func:`reachplan.planner.implant.plan.plan_arms`); with many candidates (steered ones: several per hole) one
needle's LP is solved in the model of a few holes' needles alone, the same LP at a fraction of the cost
(:meth:`LinearProgramme._single`). Beyond that: the
model: each channel's dwells in ``segments_per_channel`` blocks of equal time, sampled target points, the needle
binaries (:mod:`reachplan.planner.implant.model`). Its LP relaxation (HiGHS dual simplex, warm from the last
budget's) bounds every selection of K needles from below. Starts: the relaxation rounded (its largest
``y`` first) with and without the previous budget's needles, that selection itself (so the objective never rises
with K); then a local search (:func:`_improved`): add a needle or swap one for another of the ``swap_pool`` needles
with the largest relaxed ``y``, the best move while it lowers the objective, each move an LP on the chosen needles'
columns alone. No wall-clock limit anywhere: the same input gives the same selection on a quiet or a loaded machine.
(Before, HiGHS's branch and bound ran for 1 s per budget and seldom left the root node: its selections depended on
the load and were worse than this search's.) The bound reported per budget is the LP relaxation's: the big-M
relaxation is weak, so gaps of 0.4-0.95 on the clinical case say that the selection is not proven optimal, not that
it is that far from it.
"""

from __future__ import annotations

import itertools
from collections.abc import Callable, Sequence

import numpy as np
from scipy import optimize as sopt

from reachplan.planner.implant.model import _Model
from reachplan.planner.implant.optimiser import SHARED, WARM_START, DwellProblem, DwellSolution, restricted

#: a selection's LP is solved in the model of a few needles (its hole's, or the local search's pool) when the problem
#: has at least this many needles (:meth:`LinearProgramme._subset`): 40 or more candidates have several per hole
#: (steered ones)
SINGLE_MODEL_MIN_NEEDLES = 40
#: ... and in the model of its hole's needles and those of the next holes, this many holes in all (in the order the
#: needles come): each new model's first LP is a cold solve, so four holes' models (some twelve needles) cost less
#: than one per hole (a fifth less CPU over a clinical case's single-needle LPs), the same LPs
SINGLE_MODEL_HOLES = 4


def _rounded(model: _Model, budget: int, kappa: np.ndarray, relaxed: sopt.OptimizeResult,
             keep: Sequence[int] = ()) -> sopt.OptimizeResult | None:
    """Return a feasible selection of at most ``budget`` needles by rounding the LP relaxation ``relaxed``.

    The needles ``keep`` (an incumbent's), then those with the largest relaxed ``y``, one per hole; their best
    loading (an LP). None when that fails.
    """
    picked = list(dict.fromkeys(int(i) for i in keep))[:budget]
    holes = {model.hole_of[i] for i in picked}
    if relaxed.x is not None:
        y = relaxed.x[model.i_y:model.i_u]
        for i in np.argsort(-y, kind="stable"):
            if len(picked) >= budget or y[i] <= 1e-6:
                break
            if model.hole_of[int(i)] not in holes:
                picked.append(int(i))
                holes.add(model.hole_of[int(i)])
    res = model.solve(budget, kappa=kappa, only=picked)
    return res if res.x is not None else None


def _moves(model: _Model, pool: Sequence[int], sel: Sequence[int], budget: int) -> list[list[int]]:
    """Return the selections one move from ``sel``: a needle of ``pool`` added (under ``budget``) or swapped in."""
    moves = []
    for j in pool:
        if j in sel:
            continue
        outs: list[int | None] = [None] if len(sel) < budget else []
        for out in [*outs, *sel]:
            rest = [i for i in sel if i != out]
            if model.hole_of[j] not in {model.hole_of[i] for i in rest}:
                moves.append([*rest, j])
    return moves


def _improved(model: _Model, budget: int, kappa: np.ndarray, relaxed: sopt.OptimizeResult,
              start: sopt.OptimizeResult, pool_size: int, passes: int,
              subset: Callable[[Sequence[int]], tuple[_Model, dict[int, int]]] | None = None,
              ) -> tuple[sopt.OptimizeResult, int]:
    """Improve the selection ``start`` by swaps (a deterministic local search); return it and the LPs solved.

    Moves: add a needle (when under ``budget``) or swap one for another, each drawn from the ``pool_size`` needles
    with the largest relaxed ``y`` (``relaxed``, the LP relaxation at this budget); the best move is taken while it
    lowers the objective, for at most ``passes`` passes. Every move is a feasible selection, so the objective never
    rises; the LP relaxation still bounds the optimum from below. ``subset``: for needles, a smaller model holding
    them (and their indices there) in which their selections have the same LPs (:func:`restricted`): the moves
    (among the pool and the start's needles) are solved there, and a better selection again in ``model``.
    """
    best = start
    n_lp = 0
    if relaxed.x is None or passes == 0:
        return best, n_lp
    y = relaxed.x[model.i_y:model.i_u]
    pool = [int(i) for i in np.argsort(-y, kind="stable")[:pool_size] if y[i] > 1e-6]
    best_sel = list(model.selected(start.x))
    where, index = model, {i: i for i in range(model.n_y)}
    if subset is not None:
        where, index = subset(sorted({*pool, *best_sel}))
    tried: set[frozenset[int]] = set()
    # each move's LP starts from the incumbent's optimal basis (one swap away) rather than the last move's (two): a
    # sixth less LP time over a clinical case's swap searches, the same moves
    where.solve(budget, kappa=kappa, only=[index[i] for i in best_sel])
    basis = where.selection_basis()
    for _ in range(passes):
        tried.add(frozenset(best_sel))
        step, step_sel, step_basis = best, best_sel, basis
        for move in _moves(model, pool, best_sel, budget):
            if frozenset(move) in tried:
                continue
            tried.add(frozenset(move))
            where.start_selection_from(basis)
            res = where.solve(budget, kappa=kappa, only=[index[i] for i in move])
            n_lp += 1
            if res.x is not None and float(res.fun) < float(step.fun) - 1e-9 * max(1.0, abs(float(step.fun))):
                step, step_sel, step_basis = res, sorted(move), where.selection_basis()
        if step is best:
            break
        best, best_sel, basis = step, step_sel, step_basis
    if best is not start and where is not model:  # the selection's columns in the whole model
        again = model.solve(budget, kappa=kappa, only=best_sel)
        best = again if again.x is not None else start
    return best, n_lp


def selections_at_most(holes: Sequence[str], budget: int) -> int:
    """Return how many selections of 1 to ``budget`` needles there are, one needle per template hole at most.

    Parameters
    ----------
    holes : sequence of str
        The template hole of each needle.
    budget : int
        The most needles a selection holds.

    Returns
    -------
    int
        The sum over sizes 1..``budget`` of the elementary symmetric polynomials of the needles per hole.
    """
    e = [1] + [0] * budget  # e[j]: selections of j needles over the holes seen so far
    for n_h in np.unique(np.asarray(holes, dtype=object), return_counts=True)[1]:
        for j in range(budget, 0, -1):
            e[j] += e[j - 1] * int(n_h)
    return sum(e[1:])


def _exhaustive(model: _Model, budget: int, kappa: np.ndarray,
                memo: dict[tuple[int, ...], tuple[_Model, sopt.OptimizeResult]], channels: Sequence[int],
                single: Callable[[int], tuple[_Model, int]] | None = None) -> tuple[sopt.OptimizeResult | None, int]:
    """Return the best selection of 1 to ``budget`` needles (one per hole) over all of them, and the LPs solved.

    Every selection's LP is solved (those in ``memo``, by their ``channels``, a smaller budget's or another
    restriction's of the problem, are read from it): the result is the selection model's optimum at this budget,
    proven by enumeration. ``single``: for a needle, a smaller model that holds it (and its index there) in which its
    selection alone has the same LP (:func:`restricted`): one needle's LP is solved there. A best result solved in
    another model is solved again in ``model`` for its columns. A selection solved in ``model`` starts from the optimal
    basis of its needles but the last when that was solved there (``model.selection_bases``): one needle away and
    primal feasible, where the last selection's is two away (a third less time over a clinical case's pairs); one
    needle's LP in a smaller model starts from ``model``'s optimal basis of no needle matched there
    (:meth:`_Model.basis_onto`; budget 0's, :meth:`LinearProgramme._none`).
    """
    by_hole: dict[str, list[int]] = {}
    for i, h in enumerate(model.hole_of):
        by_hole.setdefault(h, []).append(i)
    groups = list(by_hole.values())
    best: sopt.OptimizeResult | None = None
    best_key: tuple[int, ...] = ()
    best_in: _Model | None = None
    n_lp = 0
    for size in range(1, budget + 1):
        for combo in itertools.combinations(groups, size):
            for pick in itertools.product(*combo):
                key = tuple(sorted(pick))
                ident = tuple(sorted(int(channels[i]) for i in key))
                held = memo.get(ident)
                if held is None:
                    if size == 1 and single is not None:
                        sub, j = single(key[0])
                        if () not in sub.selection_bases:  # no needle's optimal basis, there
                            sub.selection_bases[()] = model.basis_onto(model.selection_bases.get(()), sub)
                        sub.start_selection_from(sub.selection_bases[()])
                        held = memo[ident] = (sub, sub.solve(budget, kappa=kappa, only=[j]))
                    else:
                        model.start_selection_from(model.selection_bases.get(key[:-1]))
                        held = memo[ident] = (model, model.solve(budget, kappa=kappa, only=key))
                        model.selection_bases[key] = model.selection_basis()
                    n_lp += 1
                solved_in, res = held
                if res.x is not None and (best is None or float(res.fun) < float(best.fun) - 1e-12):
                    best, best_key, best_in = res, key, solved_in
    if best is not None and best_in is not model:  # its columns are another model's
        again = model.solve(budget, kappa=kappa, only=best_key)
        best = again if again.x is not None else None
    return best, n_lp


def _min_time(model: _Model, kappa: np.ndarray, lp: sopt.OptimizeResult) -> tuple[sopt.OptimizeResult, str]:
    """Return the LP solution ``lp`` with no unit loaded below ``model.min_time_s``, and how it was made.

    Rounding and one re-solve: a unit the LP left under half the minimum is emptied, one between half the minimum and
    the minimum is held at the minimum or more, and every unit the LP loaded keeps at least the minimum (the others
    stay empty), so the re-solved LP has no short unit. Should that LP fail, the short units are emptied instead (the
    LP's loading with them emptied keeps every organ row).
    """
    t = lp.x[:model.n_u]
    lo_t = model.min_time_s
    short = (t > 1e-9) & (t < lo_t * (1 - 1e-9))
    if not short.any():
        return lp, "solved"
    on = (t >= lo_t * (1 - 1e-9)) | (short & (t >= 0.5 * lo_t))
    res = model.solve(None, kappa=kappa, units=(np.where(on, lo_t, 0.0), np.where(on, np.inf, 0.0)))
    if res.x is not None:
        return res, f"solved; {int(short.sum())} short dwells rounded to 0 or {lo_t:g} s and re-solved"
    x = lp.x.copy()
    x[:model.n_u][short] = 0.0
    lp.x = x
    return lp, f"solved; {int(short.sum())} short dwells emptied"


class LinearProgramme:
    """The built-in dwell optimiser: the LP of the model, and at a budget the rounded relaxation improved by swaps.

    Registered as ``"lp"`` (entry-point group ``reachplan.optimisers``). The model is built once per problem and
    kept in the problem's cache; every solve on it only changes bounds.
    """

    name = "lp"
    description = ("needle selection: LP relaxation (HiGHS through scipy.optimize.milp) on sampled target points and "
                   "organ mean-tail-dose rows, dwells in blocks, rounded and improved by swaps; dwell times: LP on "
                   "every dwell of the selection")

    def model(self, problem: DwellProblem) -> _Model:
        """Return the problem's linear model (built on first use, then cached on the problem).

        Parameters
        ----------
        problem : DwellProblem
            The problem to model.

        Returns
        -------
        _Model
            The LP (or, with needle binaries, the MIP) of the problem.
        """
        model = problem.cache.get(self.name)
        if not isinstance(model, _Model):
            last = problem.cache.pop(WARM_START, None)  # a similar problem solved before (a robust loading's round)
            warm = last.cache.get(self.name) if isinstance(last, DwellProblem) else None
            model = problem.cache[self.name] = _Model(problem, warm if isinstance(warm, _Model) else None)
        return model

    def optimise(self, problem: DwellProblem, *, budget: int | None = None, limit_factor: np.ndarray | None = None,
                 start: Sequence[Sequence[int]] = ()) -> DwellSolution:
        """Solve the LP (no budget) or select at most ``budget`` needles (:meth:`DwellOptimiser.optimise`).

        With a budget: the rounded LP relaxation (with each of ``start`` and without), each of ``start`` itself, then
        swaps; the bound is the relaxation's. At budget 0 the one selection (no needle) is solved. Without: one LP
        (needle binaries relaxed to [0, 1]), its own bound.

        Parameters
        ----------
        problem : DwellProblem
            Its model is built on the first call and kept in ``problem.cache``.
        budget : int, optional
            The most needles the selection may use; None: the LP alone.
        limit_factor : (n_organs,) float, unitless, optional
            The organ rows' calibration ``κ`` (None: 1 for every organ).
        start : sequence of sequence of int
            Selections to start from, e.g. the previous budget's needles and another arm's selection at this budget
            (each indices into ``problem.needles.channels``); read with a budget only.

        Returns
        -------
        DwellSolution
            Times per column (s), status, objective, bound and the needles used.
        """
        model = self.model(problem)
        kappa = np.ones(len(problem.organs)) if limit_factor is None else np.asarray(limit_factor, dtype=float)
        if budget is not None and budget >= 1 and \
                selections_at_most(model.hole_of, budget) <= problem.exhaustive_max:
            return self._enumerate(problem, model, budget, kappa)
        if budget == 0 and problem.needles is not None:
            return self._none(model, kappa)
        if budget is None:
            res = model.solve(None, kappa=kappa)
            if res.x is None:
                return DwellSolution(None, f"linear programme did not solve: {res.message}")
            bound, status = float(res.fun), "solved"
            if problem.min_time_s > 0:
                res, status = _min_time(model, kappa, res)
            return DwellSolution(model.dwell_times(res.x), status, float(res.fun), bound, model.selected(res.x))
        return self._select(problem, model, budget, kappa, start)

    @staticmethod
    def _none(model: _Model, kappa: np.ndarray) -> DwellSolution:
        """Return the selection of no needle (the other channels loaded): the only one at budget 0, its own bound."""
        res = model.solve(0, kappa=kappa, only=[])
        model.selection_bases[()] = model.selection_basis()  # where a budget's first selections start
        if res.x is None:
            return DwellSolution(None, f"no loading without needles: {res.message}", float("inf"), None)
        value = float(res.fun)
        return DwellSolution(model.dwell_times(res.x), "the only selection of no needle", value, value, ())

    def _single(self, problem: DwellProblem, model: _Model) -> Callable[[int], tuple[_Model, int]] | None:
        """Return, for a needle of ``model``, the model of the needles of its hole's group and its index there.

        A group: :data:`SINGLE_MODEL_HOLES` holes in the order of the problem's needles. None when the problem has
        few needles (few per hole: its own model is as small). One needle's LP in the model of every candidate (100
        needles and more with steered ones) costs several times its LP among a few holes' needles; the models are
        built once and kept in the problem's cache.
        """
        choice = problem.needles
        subset = self._subset(problem)
        if choice is None or subset is None:
            return None

        group = {h: k // SINGLE_MODEL_HOLES for k, h in enumerate(dict.fromkeys(choice.holes))}

        def single(i: int) -> tuple[_Model, int]:
            held, index = subset([j for j, h in enumerate(choice.holes) if group[h] == group[choice.holes[i]]])
            return held, index[i]

        return single

    def _subset(self, problem: DwellProblem) -> Callable[[Sequence[int]], tuple[_Model, dict[int, int]]] | None:
        """Return, for some needles of ``problem``, the model of them alone and each one's index there.

        The model keeps the other channels (intracavitary); None when the problem has fewer than
        :data:`SINGLE_MODEL_MIN_NEEDLES` needles. A selection of those needles has the same LP there as in the whole
        model (:func:`restricted`), at a fraction of its cost. The models are kept in the problem's cache by needle
        set.
        """
        choice = problem.needles
        if choice is None or len(choice.channels) < SINGLE_MODEL_MIN_NEEDLES:
            return None
        others = sorted({int(c) for c in problem.channel} - set(choice.channels))

        def subset(needles: Sequence[int]) -> tuple[_Model, dict[int, int]]:
            chosen = sorted({int(i) for i in needles})
            key = f"{self.name}:needles:{','.join(map(str, chosen))}"
            held = problem.cache.get(key)
            if not isinstance(held, _Model):
                held = problem.cache[key] = self.model(restricted(problem, [*(choice.channels[i] for i in chosen),
                                                                           *others]))
            return held, {i: k for k, i in enumerate(chosen)}

        return subset

    def _enumerate(self, problem: DwellProblem, model: _Model, k: int, kappa: np.ndarray) -> DwellSolution:
        """Select at most ``k`` needles by solving every selection's LP (:func:`_exhaustive`); the bound is its value.

        The LPs of one calibration ``kappa`` are kept by channels in the problem's :data:`SHARED` cache, so budget
        ``k`` solves only the selections of ``k`` needles, and none another restriction of the problem solved (the
        straight arm's selections, in the straight + steered arm).
        """
        memo = problem.cache.setdefault(SHARED, {}).setdefault(f"{self.name}:selections:{kappa.tobytes().hex()}", {})
        n_all = selections_at_most(model.hole_of, k)
        assert problem.needles is not None
        best, n_lp = _exhaustive(model, k, kappa, memo, problem.needles.channels, self._single(problem, model))
        if best is None:
            return DwellSolution(None, f"no feasible selection among all {n_all} of at most {k} needles",
                                 float("inf"), None)
        value = float(best.fun)
        return DwellSolution(model.dwell_times(best.x), f"exhaustive: optimal over all {n_all} selections of at most "
                             f"{k} needles ({n_lp} LPs solved here)", value, value, model.selected(best.x))

    def _select(self, problem: DwellProblem, model: _Model, k: int, kappa: np.ndarray,
                keep: Sequence[Sequence[int]]) -> DwellSolution:
        """Select at most ``k`` needles: the LP relaxation rounded with each of ``keep`` kept, then swaps.

        The objective never rises with ``k`` when ``keep`` holds the last budget's selection (every budget's model
        has the same organ rows), and is no higher than any selection of ``keep`` (another arm's at this budget).
        """
        relaxed = model.solve(k, kappa=kappa)  # its optimum bounds every selection of k needles from below
        given = list(dict.fromkeys(tuple(int(i) for i in sel) for sel in keep if 0 < len(sel) <= k))
        starts = [*(_rounded(model, k, kappa, relaxed, sel) for sel in given), _rounded(model, k, kappa, relaxed, ())]
        for sel in given:  # each given selection itself (a needle added to it costs its invasiveness)
            last = model.solve(k, kappa=kappa, only=sel)
            starts.append(last if last.x is not None else None)
        inc = min((r for r in starts if r is not None), key=lambda r: float(r.fun), default=None)
        lower = float(relaxed.fun) if relaxed.x is not None else None
        if inc is None:
            return DwellSolution(None, "no feasible selection (the rounded LP relaxation failed)", float("inf"), lower)
        best, n_lp = _improved(model, k, kappa, relaxed, inc, problem.swap_pool, problem.swap_passes,
                               self._subset(problem))
        status = (f"rounded LP relaxation improved by {n_lp} swap LPs" if best is not inc else
                  f"rounded LP relaxation, no better swap in {n_lp} LPs")
        return DwellSolution(model.dwell_times(best.x), status, float(best.fun), lower, model.selected(best.x))


#: The built-in optimiser (entry point ``lp`` of ``reachplan.optimisers``).
LP = LinearProgramme()
