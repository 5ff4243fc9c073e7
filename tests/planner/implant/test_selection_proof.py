"""Needle selection with a proof: every selection enumerated where that is cheap, checked against HiGHS's
branch and bound on the same mixed-integer programme, and one score per needle set whichever arm asks."""

from __future__ import annotations

import itertools
from dataclasses import replace

import numpy as np
import pytest
from scipy import optimize as sopt

from reachplan.planner.implant.model import _Model
from reachplan.planner.implant.optimiser import WARM_START, DwellProblem, Modulation, NeedleChoice, OrganRows
from reachplan.planner.implant.plan import _restricted
from reachplan.planner.implant.selection import LP, selections_at_most


def _problem(seed: int, exhaustive_max: int) -> DwellProblem:
    """Seven needles (two pairs share a hole) and one intracavitary channel, three dwells each; a target of 40
    points, an organ of 30 points that the needles near it dose strongly (so the choice is not the obvious one)."""
    rng = np.random.default_rng(seed)
    n_ch, per = 8, 3
    channel = np.repeat(np.arange(n_ch), per)
    target = rng.uniform(0.2, 1.0, (40, n_ch * per)) * rng.uniform(0.1, 1.0, n_ch * per)
    organ = rng.uniform(0.0, 0.3, (30, n_ch * per))
    organ[:, channel < 3] *= 6.0
    rows = OrganRows(organ, np.full(30, 0.2), limit_gy=3.0, volume_cc=2.0, name="Rectum")
    holes = ("A", "A", "B", "C", "C", "D", "E")
    units = tuple(np.flatnonzero(channel == c) for c in range(n_ch))
    return DwellProblem(target, np.full(40, 7.0), 7.0, (rows,), channel,
                        Modulation(1.0, float("inf"), 1e-3, 1e-3, 0.0), units,
                        NeedleChoice(tuple(range(7)), holes, rng.uniform(0.0, 1.0, 7)),
                        swap_pool=2, swap_passes=1, exhaustive_max=exhaustive_max)


def test_the_count_of_selections_is_the_brute_force_count() -> None:
    holes = ["A", "A", "B", "C", "C", "C", "D", "E", "E", "F"]
    for budget in range(0, 5):
        brute = sum(1 for k in range(1, budget + 1) for s in itertools.combinations(range(len(holes)), k)
                    if len({holes[i] for i in s}) == k)
        assert selections_at_most(holes, budget) == brute


def _branch_and_bound(problem: DwellProblem, budget: int) -> float:
    """The selection MIP solved by HiGHS's branch and bound to optimality (integral needle binaries)."""
    model = _Model(problem)
    ub = model.ub.copy()
    ub[-1] = budget
    integrality = np.zeros(model.n)
    integrality[model.i_y:model.i_u] = 1
    hi = np.full(model.n, np.inf)
    hi[model.i_y:model.i_u] = 1.0
    res = sopt.milp(model.c, constraints=[sopt.LinearConstraint(model.a, model.lb, ub)],
                    bounds=sopt.Bounds(np.zeros(model.n), hi), integrality=integrality,
                    options={"mip_rel_gap": 1e-9})
    assert res.status == 0, res.message
    return float(res.fun)


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("budget", [1, 2, 3])
def test_enumeration_finds_the_branch_and_bound_optimum(seed: int, budget: int) -> None:
    """The enumerated selection is optimal (HiGHS's branch and bound agrees to 1e-7) and says so (gap 0); the
    heuristic on the same problem is never better than it."""
    exact = LP.optimise(_problem(seed, 10_000), budget=budget)
    assert exact.times_s is not None and exact.status.startswith("exhaustive")
    assert exact.bound == exact.objective
    assert exact.objective == pytest.approx(_branch_and_bound(_problem(seed, 10_000), budget), rel=1e-7, abs=1e-9)
    heuristic = LP.optimise(_problem(seed, 0), budget=budget)
    assert not heuristic.status.startswith("exhaustive")
    assert heuristic.objective >= exact.objective - 1e-9
    holes = _problem(seed, 0).needles.holes  # type: ignore[union-attr]
    assert len({holes[i] for i in exact.needles}) == len(exact.needles) <= budget


def test_beyond_the_limit_the_heuristic_runs_with_its_bound() -> None:
    problem = _problem(0, selections_at_most(_problem(0, 0).needles.holes, 2) - 1)  # type: ignore[union-attr]
    assert LP.optimise(problem, budget=1).status.startswith("exhaustive")
    sol = LP.optimise(problem, budget=2)
    assert not sol.status.startswith("exhaustive") and sol.bound is not None and sol.bound <= sol.objective


def test_a_needle_set_gets_one_score_whichever_arm_evaluates_it() -> None:
    """An arm whose candidates are a part of the others' (the straight arm) is the same problem restricted to
    its channels: each of its selections has the objective it has in the whole problem, and its enumerated
    optimum is the whole problem's best among those needles."""
    whole = _problem(3, 10_000)
    part = _restricted(whole, [0, 2, 3, 5, 7])  # needles 0, 2, 3, 5 and the intracavitary channel 7
    m_whole, m_part = LP.model(whole), LP.model(part)
    idx = {c: i for i, c in enumerate(whole.needles.channels)}  # type: ignore[union-attr]
    for k in (1, 2):
        for sel in itertools.combinations(range(4), k):
            a = m_part.solve(k, only=list(sel))
            b = m_whole.solve(k, only=[idx[part.needles.channels[i]] for i in sel])  # type: ignore[union-attr]
            assert a.x is not None and b.x is not None
            assert float(a.fun) == pytest.approx(float(b.fun), rel=1e-9, abs=1e-12)
    best_part = LP.optimise(part, budget=2)
    best_whole_among = min(float(m_whole.solve(2, only=[idx[c] for c in s]).fun)
                           for k in (1, 2) for s in itertools.combinations([0, 2, 3, 5], k))
    assert best_part.objective == pytest.approx(best_whole_among, rel=1e-9)


def test_warm_started_selection_lps_agree_with_cold_ones() -> None:
    """The model's HiGHS instance, warm-started from the last selection (or an earlier one's basis), gives the cold
    solver's optimum."""
    problem = _problem(4, 0)
    model = LP.model(problem)
    order = [[0], [3, 5], [1], [2, 4, 6], [6]]
    assert model.selection_basis() is None  # no LP solved yet
    first = None
    for k, only in enumerate(order):
        if k >= 3:  # from an earlier selection's basis instead of the last one's (the swap search's start)
            model.start_selection_from(first)
        warm = model.solve(3, only=only)
        if k == 0:
            first = model.selection_basis()
            assert first is not None and first.valid
        cold = _cold(model, only)
        assert warm.x is not None and cold.x is not None
        assert float(warm.fun) == pytest.approx(float(cold.fun), rel=1e-9, abs=1e-12)
        assert np.allclose(model.dwell_times(warm.x) @ problem.target_rates.T,
                           model.dwell_times(cold.x) @ problem.target_rates.T, rtol=0, atol=1e-6) or \
            float(warm.fun) == pytest.approx(float(cold.fun), rel=1e-12)


def _cold(model: _Model, only: list[int]) -> sopt.OptimizeResult:
    """The selection's LP by scipy's milp from scratch (no basis kept)."""
    lo, hi = model._on_columns(np.array(only))
    ub = model.ub.copy()
    ub[-1] = 3
    return sopt.milp(model.c, constraints=[sopt.LinearConstraint(model.a, model.lb, ub)], bounds=sopt.Bounds(lo, hi))


def test_a_robust_rounds_lp_starts_from_the_last_round_and_gives_the_cold_optimum() -> None:
    """The next round's model (more row sets) goes on in the last round's HiGHS instance; budgets' relaxations from
    the last budget's; every optimum is the cold solver's."""
    base = _problem(6, 0)
    loading = replace(base, needles=None, units=None, min_time_s=0.0)
    rng = np.random.default_rng(7)
    extra = OrganRows(rng.uniform(0.0, 0.4, (25, base.n_columns)), np.full(25, 0.2), 2.5, 2.0, "Rectum, shifted")
    first = replace(loading, cache={})
    LP.optimise(first, limit_factor=np.ones(1))
    second = replace(loading, organs=(*loading.organs, extra), cache={WARM_START: first})
    model = LP.model(second)
    assert WARM_START not in second.cache  # the hint is read once, not kept
    instance = LP.model(first)._highs["full"].highs
    kappa = np.array([0.9, 1.1])
    warm = model.solve(None, kappa=kappa)
    assert model._highs["full"].highs is instance  # the last round's instance, the added rows appended
    assert "full" not in LP.model(first)._highs
    ub = model.ub.copy()
    ub[model.limit_rows] = model.limits * kappa
    cold = sopt.milp(model.c, constraints=[sopt.LinearConstraint(model.a, model.lb, ub)],
                     bounds=sopt.Bounds(np.zeros(model.n), np.full(model.n, np.inf)))
    assert warm.x is not None and cold.x is not None
    assert float(warm.fun) == pytest.approx(float(cold.fun), rel=1e-9, abs=1e-12)
    assert np.allclose(model.dwell_times(warm.x), model.dwell_times(cold.x), rtol=0, atol=1e-6)
    # a third round: a row set inserted before the last one, a higher coverage aim, then minimum dwell times
    middle = OrganRows(rng.uniform(0.0, 0.4, (15, base.n_columns)), np.full(15, 0.3), 2.0, 2.0, "Bladder, shifted")
    third = replace(loading, target_dose_gy=loading.target_dose_gy * 1.05, organs=(*loading.organs, middle, extra),
                    cache={WARM_START: second})
    model3 = LP.model(third)
    kappa3 = np.array([0.95, 1.05, 1.1])
    lo = np.zeros(model3.n_u)
    lo[::3] = 0.5
    for units in (None, (lo, np.full(model3.n_u, np.inf))):
        warm = model3.solve(None, kappa=kappa3, units=units)
        assert model3._highs["full"].highs is instance
        ub = model3.ub.copy()
        ub[model3.limit_rows] = model3.limits * kappa3
        col_lo = np.zeros(model3.n)
        if units is not None:
            col_lo[:model3.n_u] = units[0]
        cold = sopt.milp(model3.c, constraints=[sopt.LinearConstraint(model3.a, model3.lb, ub)],
                         bounds=sopt.Bounds(col_lo, np.full(model3.n, np.inf)))
        assert warm.x is not None and cold.x is not None
        assert float(warm.fun) == pytest.approx(float(cold.fun), rel=1e-9, abs=1e-12)
        assert np.allclose(model3.dwell_times(warm.x), model3.dwell_times(cold.x), rtol=0, atol=1e-6)
    selection = LP.model(_problem(6, 0))
    for budget in (1, 3, 2):  # one relaxation after the other on the model's instance
        relaxed = selection.solve(budget)
        ub = selection.ub.copy()
        ub[-1] = budget
        hi = np.full(selection.n, np.inf)
        hi[selection.i_y:selection.i_u] = 1.0
        cold = sopt.milp(selection.c, constraints=[sopt.LinearConstraint(selection.a, selection.lb, ub)],
                         bounds=sopt.Bounds(np.zeros(selection.n), hi))
        assert float(relaxed.fun) == pytest.approx(float(cold.fun), rel=1e-9, abs=1e-12)


def test_one_needles_lps_in_its_holes_model_give_the_same_selection(monkeypatch: pytest.MonkeyPatch) -> None:
    """With many candidates each single needle's LP is solved among a few holes' needles alone: the same optimum,
    returned in the whole model's columns, and the same selection at the next budget from the kept results."""
    from reachplan.planner.implant import selection

    problem = _problem(8, 0)
    plain = _Model(problem)
    kappa = np.ones(1)
    monkeypatch.setattr(selection, "SINGLE_MODEL_MIN_NEEDLES", 1)
    monkeypatch.setattr(selection, "SINGLE_MODEL_HOLES", 2)
    model = LP.model(problem)
    single = LP._single(problem, model)
    assert single is not None and single(3)[0].n_y == 3  # holes C and D hold needles 3, 4 and 5
    memo: dict[tuple[int, ...], tuple[_Model, sopt.OptimizeResult]] = {}
    channels = problem.needles.channels if problem.needles else ()
    for budget in (1, 2):
        best, _ = selection._exhaustive(model, budget, kappa, memo, channels, single)
        ref, _ = selection._exhaustive(plain, budget, kappa, {}, channels)
        assert best is not None and ref is not None
        assert float(best.fun) == pytest.approx(float(ref.fun), rel=1e-9)
        assert model.selected(best.x) == plain.selected(ref.x)
        assert np.allclose(model.dwell_times(best.x), plain.dwell_times(ref.x), atol=1e-6)


def test_a_models_unit_columns_are_the_membership_products_bit_for_bit() -> None:
    """Each unit's column (its dwells' columns summed, only the units' columns read) equals the product with the 0/1
    membership matrix exactly: the models, and so every LP, are those of before."""
    from scipy import sparse

    from reachplan.planner.implant.rows import _unit_sums

    rng = np.random.default_rng(3)
    rates = rng.uniform(0.0, 1.0, (50, 40)) * 10.0 ** rng.uniform(-6, 2, 40)
    units = [u for u in np.split(np.arange(40), [3, 4, 9, 17, 18, 30]) if u[0] != 9]  # one left out (restricted)
    sizes = [len(u) for u in units]
    member = sparse.csr_matrix((np.ones(sum(sizes)), (np.concatenate(units), np.repeat(np.arange(len(units)), sizes))),
                               shape=(40, len(units)))
    assert np.array_equal(_unit_sums(rates, units), np.asarray((member.T @ rates.T).T))


def test_an_organs_voxels_near_the_dwells_are_those_a_stable_sort_keeps() -> None:
    """The voxels within the radius and the nearest n (the first of equal distances first), found by a partition,
    are those of a stable sort, ties included."""
    from reachplan.planner.implant.problem import _near_organ

    rng = np.random.default_rng(4)
    for radius, n_min in ((0.0, 7), (1.0, 40), (3.0, 5), (0.0, 0)):
        pts = rng.uniform(0.0, 1.0, (200, 3))
        dist = np.round(rng.uniform(0.0, 4.0, 200), 1)  # ties
        keep = dist <= radius
        keep[np.argsort(dist, kind="stable")[:n_min]] = True
        assert np.array_equal(_near_organ(pts, np.zeros((1, 3)), radius, 0.1, 4, dist, n_min), pts[keep])


def test_a_restrictions_enumerated_lps_are_not_solved_again_in_the_whole_problem() -> None:
    """The straight arm's selections, enumerated in its restricted problem, are read by the straight + steered arm's
    enumeration (the same LPs, by channels): it solves only the others, and selects what it selects alone."""
    problem = _problem(5, 100)
    part = _restricted(problem, [0, 2, 3, 7])  # needles 0, 2, 3 (holes A, B, C) and the intracavitary channel
    kappa = np.ones(1)
    alone = LP.optimise(_problem(5, 100), budget=2, limit_factor=kappa)
    LP.optimise(part, budget=2, limit_factor=kappa)  # 3 singles and 3 pairs
    whole = LP.optimise(problem, budget=2, limit_factor=kappa)
    n_all = selections_at_most(("A", "A", "B", "C", "C", "D", "E"), 2)  # the holes of _problem's needles
    assert f"({n_all - 6} LPs solved here)" in whole.status, whole.status
    assert f"({n_all} LPs solved here)" in alone.status, alone.status
    assert whole.needles == alone.needles and whole.objective == pytest.approx(alone.objective, rel=1e-9)
    assert np.allclose(whole.times_s, alone.times_s, atol=1e-6)


@pytest.mark.parametrize("ratio, smooth", [(float("inf"), 0.0), (float("inf"), 1e-3), (3.0, 1e-3)])
def test_a_smaller_models_first_selection_starts_from_the_whole_models_basis(ratio: float, smooth: float) -> None:
    """The whole model's basis of no needle, matched onto a model of some of its needles, is that model's optimal
    basis of no needle (no simplex iteration); each single needle's LP there from it gives the cold optimum, and the
    whole model's optimal basis of that needle is its optimal basis there. A basis of another model's size is not
    matched."""
    base = _problem(9, 0)
    per_dwell = tuple(np.array([j]) for j in range(base.n_columns))  # neighbouring units: gradient, ratio rows
    problem = replace(base, units=per_dwell, modulation=Modulation(1.0, ratio, 1e-3, 1e-3, smooth))
    whole = _Model(problem)
    assert whole.solve(0, only=[]).x is not None
    none = whole.selection_basis()
    part = _Model(_restricted(problem, [3, 4, 5, 7]))  # holes C and D, and the intracavitary channel
    assert part.n < whole.n and part.a.shape[0] < whole.a.shape[0]
    start = whole.basis_onto(none, part)
    assert start is not None and start.valid
    assert part.basis_onto(none, whole) is None  # not a basis of ``part``
    part.start_selection_from(start)
    assert float(part.solve(0, only=[]).fun) == pytest.approx(float(whole.solve(0, only=[]).fun), rel=1e-12)
    assert part._highs["selection"].highs.getInfo().simplex_iteration_count == 0
    for j in range(part.n_y):
        part.start_selection_from(start)
        warm = part.solve(1, only=[j])
        lo, hi = part._on_columns(np.array([j]))
        ub = part.ub.copy()
        ub[-1] = 1
        cold = sopt.milp(part.c, constraints=[sopt.LinearConstraint(part.a, part.lb, ub)], bounds=sopt.Bounds(lo, hi))
        assert warm.x is not None and cold.x is not None
        assert float(warm.fun) == pytest.approx(float(cold.fun), rel=1e-9, abs=1e-12)
        assert whole.solve(1, only=[[3, 4, 5][j]]).x is not None
        optimal = whole.basis_onto(whole.selection_basis(), part)
        assert optimal is not None
        part.start_selection_from(optimal)
        assert float(part.solve(1, only=[j]).fun) == pytest.approx(float(cold.fun), rel=1e-9, abs=1e-12)
        assert part._highs["selection"].highs.getInfo().simplex_iteration_count == 0


def test_enumerated_selections_start_from_their_needles_but_the_last() -> None:
    """Budget 0's basis, then each single's, are kept in the model; every pair starts from its first needle's, and
    the enumeration's optimum is branch and bound's."""
    problem = _problem(2, 10_000)
    assert LP.optimise(problem, budget=0).times_s is not None
    model = LP.model(problem)
    assert set(model.selection_bases) == {()}
    LP.optimise(problem, budget=1)
    assert set(model.selection_bases) == {()} | {(i,) for i in range(7)}
    best = LP.optimise(problem, budget=2)
    pairs = {k for k in model.selection_bases if len(k) == 2}
    holes = problem.needles.holes  # type: ignore[union-attr]
    assert pairs == {(i, j) for i, j in itertools.combinations(range(7), 2) if holes[i] != holes[j]}
    assert best.objective == pytest.approx(_branch_and_bound(_problem(2, 10_000), 2), rel=1e-7, abs=1e-9)
