"""Implant planning: the needle set and the dwell times that cover the HR-CTV, chosen together (one arm, or several).

Candidates come from :mod:`reachplan.planner.implant.candidates`. Choice of needles and dwell times
(:func:`plan_implant`), for each needle budget K = 1, 2, ... (K = 0 too when an intracavitary channel is given),
meaning "at most K needles", by the dwell optimiser named in ``ImplantSettings.optimiser``
(:mod:`reachplan.planner.implant.optimiser`; the built-in ``"lp"``: :mod:`reachplan.planner.implant.selection`
on the model of :mod:`reachplan.planner.implant.model`):

1. **Needle selection** at budget K, on the selection problem: each channel's dwells in ``segments_per_channel``
   blocks of equal time, ``selection_target_points`` sampled target points, organ rows on a lattice of
   ``selection_oar_pitch_mm`` (each organ's planning aim less the headroom), the HR-CTV's V200 rows, one binary per
   needle, one needle per template hole; where the selections of at most K needles are few enough
   (``exhaustive_max_selections``), every one is solved and the selection is proven optimal (up to the first budget
   whose plan meets every aim; the budgets after it, which only extend the Pareto curve, are searched). The bound
   reported per budget is the optimiser's (the built-in's: the LP relaxation's) and the relative gap to the selection
   kept (:class:`reachplan.planner.implant.arms.BudgetResult`; plan.json ``selection``). The LP with every candidate
   loaded, its organ rows calibrated once, bounds every budget (``selection.all_candidates_objective``); every
   budget's model has those rows.
2. **Dwell times on the chosen channels** (:func:`reachplan.planner.implant.dwells._final`): the robust loading
   (:mod:`reachplan.planner.implant.robust`: hard limits and D90 >= 85 Gy with any one needle displaced), the
   empty-needle rule, the check on every organ voxel and in every scenario.

Each new selection's plan is a point of the arm's Pareto curve (:mod:`reachplan.planner.implant.arms`); the plan
chosen is the fewest needles that meet every planning aim with the headroom and keep the hard limits in every
scenario (or the Pareto point of ``ImplantSettings.needles``). The budgets stop as :func:`_budgets` says.

Aims (EQD2, α/β 10 tumour / 3 organs, 45 Gy / 25 fractions external beam + 4 fractions): EMBRACE II
(Pötter et al., Clin Transl Radiat Oncol 9:48, 2018), as :class:`reachplan.planner.dose.aims.Aims`: planning aims
HR-CTV D90 > 90 and < 95, D98 > 75, GTV D98 > 95 Gy, organ D2cm³ 1 Gy below their aims; hard limits HR-CTV D90 > 85
Gy and the organs' limits, kept with any one needle displaced.
"""

from __future__ import annotations

import dataclasses
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np

from reachplan.planner.dose.aims import Aims
from reachplan.planner.dose.coverage import voxel_volume_cc
from reachplan.planner.dose.structures import PlanningStructures, Structure
from reachplan.planner.dose.tg43 import Tg43Kernel
from reachplan.planner.implant.arms import BudgetResult, ImplantArm, ImplantPlan, _arm, with_subset
from reachplan.planner.implant.candidates import Channel
from reachplan.planner.implant.dwells import _final
from reachplan.planner.implant.optimiser import (
    DwellOptimiser,
    DwellProblem,
    DwellSolution,
    NeedleChoice,
    OrganRows,
    resolve,
)
from reachplan.planner.implant.optimiser import restricted as _restricted
from reachplan.planner.implant.problem import (
    PointLimit,
    _calibrate,
    _d2cc,
    _modulation,
    _organ_rows,
    _Problem,
    _rates,
    _sampled_problem,
    _target_rows,
    point_rows,
)
from reachplan.planner.implant.robust import V200_KAPPA_START, v200_points, v200_row_pct
from reachplan.planner.implant.settings import ImplantSettings

#: a new plan that raises the arm's best HR-CTV D90 by less than this (Gy EQD2) is no gain (two such end the budgets)
MIN_GAIN_GY = 0.5


def plan_implant(name: str, channels: Sequence[Channel], planning: PlanningStructures, kernel: Tg43Kernel,
                 air_kerma_strength_u: float, aims: Aims | None = None, settings: ImplantSettings | None = None, *,
                 gtv: Structure | None = None, points: Sequence[PointLimit] = ()) -> ImplantArm:
    """Return the Pareto curve of needle count against HR-CTV D90 and the chosen implant of one arm.

    One arm of :func:`plan_arms`.

    Parameters
    ----------
    name : str
        The arm's name (e.g. ``"straight"``, ``"steered"``).
    channels : sequence of Channel
        Candidate needles and intracavitary channels (:func:`reachplan.planner.implant.candidates.needle_candidates`,
        :func:`reachplan.planner.implant.candidates.intracavitary_channel`); paths mm, LPS.
    planning : PlanningStructures
        Target and organ masks on the planning grid.
    kernel : Tg43Kernel
        TG-43 dose kernel of the source.
    air_kerma_strength_u : float, U
        Source strength.
    aims : Aims, optional
        EMBRACE II by default.
    settings : ImplantSettings, optional
        Its ``optimiser`` names the dwell optimiser.
    gtv : Structure, optional
        The GTV mask on the planning grid, when there is one (its D98 is then an aim).
    points : sequence of PointLimit
        Dose points with a planning aim and a hard limit.

    Returns
    -------
    ImplantArm
        ``plan`` None (with ``reason``) when there is no candidate or no budget gives a plan.

    Raises
    ------
    reachplan.plugins.errors.PluginError
        No dwell optimiser is registered under ``settings.optimiser`` (the message lists the available ones).
    """
    return plan_arms([(name, channels)], planning, kernel, air_kerma_strength_u, aims, settings, gtv=gtv,
                     workers=1, points=points)[0]


def load_implant(channels: Sequence[Channel], planning: PlanningStructures, kernel: Tg43Kernel,
                 air_kerma_strength_u: float, aims: Aims | None = None, settings: ImplantSettings | None = None, *,
                 gtv: Structure | None = None, points: Sequence[PointLimit] = ()) -> ImplantPlan | None:
    """Return the plan of exactly ``channels``: no selection, their robust dwell times (the empty-needle rule).

    The organ rows are calibrated on these channels loaded, then the final step of :func:`plan_arms` loads them.

    Parameters
    ----------
    channels : sequence of Channel
        The implant's needles and intracavitary channels (paths mm, LPS).
    planning : PlanningStructures
        Target and organ masks on the planning grid.
    kernel : Tg43Kernel
        TG-43 dose kernel of the source.
    air_kerma_strength_u : float, U
        Source strength.
    aims : Aims, optional
        EMBRACE II by default.
    settings : ImplantSettings, optional
        Its ``optimiser`` loads the channels.
    gtv : Structure, optional
        The GTV mask on the planning grid, when there is one.
    points : sequence of PointLimit
        Dose points with a planning aim and a hard limit.

    Returns
    -------
    ImplantPlan or None
        None when no channel has a dwell or the optimiser finds no loading.
    """
    aims = aims or Aims()
    settings = settings or ImplantSettings()
    optimiser = resolve(settings.optimiser)
    channels = tuple(c for c in channels if len(c.dwell_positions_mm) >= 1)
    if not channels:
        return None
    shared = _shared(channels, planning, kernel, air_kerma_strength_u, aims, settings, gtv, optimiser, points)
    final = _Final(shared.prob, *shared.final_rows, aims, settings, shared.vox_cc, optimiser, shared.kappa)
    return final(np.arange(len(channels)), "the given channels loaded (no selection)", None)


@dataclass(frozen=True, eq=False)
class _Shared:
    """What every arm of a case shares, so that one needle set gets one score whichever arm evaluates it.

    The sampled problem of every arm's channels together, the selection problem on all of them (rows: target points,
    organ lattices near every candidate dwell, V200), the calibration of its organ rows from every candidate loaded,
    the final step's target rows, and the needles' invasiveness normalised over all candidates; ``loaded``: the plan
    of each channel set loaded so far (by any arm: the same set gets the same plan, so it is loaded once).
    """

    prob: _Problem
    selection: DwellProblem
    free: DwellSolution
    kappa: np.ndarray
    final_rows: tuple[np.ndarray, np.ndarray]
    vox_cc: float
    loaded: dict[tuple[int, ...], ImplantPlan | None] = field(default_factory=dict, repr=False)


def _shared(channels: Sequence[Channel], planning: PlanningStructures, kernel: Tg43Kernel, air_kerma_u: float,
            aims: Aims, settings: ImplantSettings, gtv: Structure | None, optimiser: DwellOptimiser,
            points: Sequence[PointLimit]) -> _Shared:
    """Return the problem every arm of ``channels`` shares (:class:`_Shared`), its rows calibrated once."""
    vox_cc = voxel_volume_cc(planning.grid)
    prob = _sampled_problem(channels, planning, kernel, air_kerma_u, aims, settings, gtv, points)
    p_t = aims.prescription_gy * (1.0 + settings.coverage_margin)
    p_g = aims.fractionation.per_fraction_for(aims.gtv_d98_eqd2_gy, aims.alpha_beta_target_gy) * (
        1.0 + settings.coverage_margin)
    selection = _selection_problem(prob, settings, _target_rows(prob, settings.selection_target_points, p_t, p_g),
                                   aims, vox_cc)
    # every candidate loaded, no budget; its solution calibrates the organ rows (of every arm)
    n_org = sum(limit is not None for limit in prob.oar_limits)
    kappa = np.ones(len(selection.organs))  # the dose points' rows are exact: κ = 1
    kappa[n_org:n_org + (settings.v200_max_pct is not None)] = V200_KAPPA_START
    free = optimiser.optimise(selection, limit_factor=kappa)
    if free.times_s is not None:
        kappa[:n_org] = _calibrate(kappa[:n_org], _d2cc(prob, prob.positions, prob.directions, free.times_s, vox_cc),
                                   selection.tail_means(free.times_s)[:n_org], selection.limits_gy[:n_org])
        free = optimiser.optimise(selection, limit_factor=kappa)
    return _Shared(prob, selection, free, kappa, _target_rows(prob, settings.final_target_points, p_t, p_g), vox_cc)


def _plan_arm(name: str, allowed: Sequence[int], shared: _Shared, aims: Aims, settings: ImplantSettings,
              optimiser: DwellOptimiser, given: _Published | None = None,
              publish: _Published | None = None) -> ImplantArm:
    """Return one arm's Pareto curve and chosen implant, its candidates the shared problem's ``allowed`` channels.

    ``given``: per budget, another arm's selected needles (channels of the shared problem) as a start of this arm's
    search at that budget, where all of them are among ``allowed``, and the budget at which it first met every aim
    (this arm takes in its implants: its budgets stop as past its own first plan meeting every aim); ``publish``:
    where this arm's selections and budgets go (the caller closes it).
    """
    t0 = time.perf_counter()
    prob = shared.prob
    whole = len(allowed) == len(prob.channels)
    selection = shared.selection if whole else _restricted(shared.selection, allowed)
    assert selection.needles is not None
    needles = list(selection.needles.channels)
    free = shared.free if whole else optimiser.optimise(selection, limit_factor=shared.kappa)
    bound = free.objective if free.times_s is not None else float("nan")
    final = _Final(prob, *shared.final_rows, aims, settings, shared.vox_cc, optimiser, shared.kappa, shared.loaded)
    rank: list[int] = []  # needles (indices into ``needles``) by their time in the all-candidates loading
    if free.times_s is not None:
        ch_time = np.bincount(prob.channel_of, weights=free.times_s, minlength=len(prob.channels))
        rank = [int(i) for i in np.argsort(-ch_time[needles], kind="stable") if ch_time[needles[i]] > 0]
    where = {c: i for i, c in enumerate(needles)}

    def starts(k: int) -> list[int] | None:
        sel = None if given is None else given.get(k)
        return None if sel is None or not all(c in where for c in sel) else [where[c] for c in sel]

    budgets, plans = _budgets(selection, needles, optimiser, shared.kappa, bound, final, rank, starts,
                              publish, None if given is None else given.met_before)
    record: dict[str, object] = {
        "model": getattr(optimiser, "description", "") or optimiser.name,
        "all_candidates_objective": None if not np.isfinite(bound) else round(bound, 6),
        "exhaustive_max_selections": settings.exhaustive_max_selections,
        "budgets": [b.to_json() for b in budgets]}
    return _arm(name, len(needles), plans, time.perf_counter() - t0, tuple(budgets), record, settings.needles)


def _selection_problem(prob: _Problem, settings: ImplantSettings, target: tuple[np.ndarray, np.ndarray],
                       aims: Aims, vox_cc: float) -> DwellProblem:
    """Return the selection problem: every candidate's dwells in blocks, a binary per needle, its invasiveness.

    Its rows: the target points, each organ's nominal D2cm³ rows (planning aim less the headroom), the HR-CTV's
    V200 rows and each dose point's row (its planning value); the scenarios are the final step's
    (:func:`reachplan.planner.implant.robust.robust_times`). A needle's invasiveness is its hole distance and tissue
    length, each over the largest of every candidate.
    """
    p_t = aims.prescription_gy * (1.0 + settings.coverage_margin)
    channels = prob.channels
    needles = [i for i, c in enumerate(channels) if c.is_needle]
    cost = np.zeros(len(needles))
    if needles:
        dmax = max(max(channels[i].hole_distance_mm for i in needles), 1e-9)
        lmax = max(max(channels[i].tissue_length_mm for i in needles), 1e-9)
        cost = np.array([0.5 * channels[i].hole_distance_mm / dmax + 0.5 * channels[i].tissue_length_mm / lmax
                         for i in needles])
    units = []
    for c in range(len(channels)):
        on_c = np.flatnonzero(prob.channel_of == c)
        units += np.array_split(on_c, min(settings.segments_per_channel, len(on_c)))
    organs = _organ_rows(prob, prob.positions, prob.directions, settings.selection_oar_pitch_mm,
                         settings.oar_sample_cc, vox_cc)
    rates = _rates(target[0], prob.positions, prob.directions, prob)
    if settings.v200_max_pct is not None:
        rows = v200_points(len(prob.target_pts), settings.selection_target_points)
        volume = len(prob.target_pts) * vox_cc
        organs.append(OrganRows(rates[rows], np.full(len(rows), volume / len(rows)), 2.0 * aims.prescription_gy,
                                volume * v200_row_pct(settings) / 100.0, "HR-CTV V200"))
    organs += point_rows(prob, prob.positions, prob.directions)
    return DwellProblem(
        rates, target[1], p_t, tuple(organs), prob.channel_of,
        _modulation(settings), tuple(units),
        NeedleChoice(tuple(needles), tuple(channels[i].name for i in needles), cost),
        settings.swap_pool, settings.swap_passes, exhaustive_max=settings.exhaustive_max_selections)


class _Final:
    """The final dwell-time step of one arm (:func:`reachplan.planner.implant.dwells._final`), its inputs bound.

    Parameters
    ----------
    prob : _Problem
        The arm's sampled problem.
    fin_pts : (m, 3) float, mm, LPS
        Target (and GTV) sample points of the final model.
    fin_p : (m,) float, Gy per fraction
        The dose each of them should reach.
    aims : Aims
        The aims the plan's metrics are checked against.
    settings : ImplantSettings
        The arm's settings (final model, empty-needle rule).
    vox_cc : float, cm³
        Voxel volume of the planning grid.
    optimiser : DwellOptimiser
        Loads each chosen set (without a budget).
    kappa : (n_organs + n_v200,) float, unitless
        The calibration every plan starts from (the shared one: a needle set's plan does not depend on the arm or
        on the plans made before it).
    loaded : dict, optional
        The plans already made by channel set, shared by the arms (:attr:`_Shared.loaded`): a set another arm
        loaded is not loaded again (its plan is the same; only its selection's status and gap are this arm's).
    """

    def __init__(self, prob: _Problem, fin_pts: np.ndarray, fin_p: np.ndarray, aims: Aims, settings: ImplantSettings,
                 vox_cc: float, optimiser: DwellOptimiser, kappa: np.ndarray,
                 loaded: dict[tuple[int, ...], ImplantPlan | None] | None = None) -> None:
        self.prob, self.fin_pts, self.fin_p, self.aims, self.settings = prob, fin_pts, fin_p, aims, settings
        self.vox_cc, self.optimiser, self.kappa = vox_cc, optimiser, kappa
        self.loaded = {} if loaded is None else loaded

    def __call__(self, chosen: np.ndarray, status: str, gap: float | None) -> ImplantPlan | None:
        """Return the plan of the channels ``chosen``, its selection's ``status`` and ``gap`` recorded.

        Parameters
        ----------
        chosen : (c,) int
            Indices into ``prob.channels``, ascending.
        status : str
            How the selection was made.
        gap : float or None
            The selection's relative gap.

        Returns
        -------
        ImplantPlan or None
            None when the chosen channels give no plan.
        """
        key = tuple(int(c) for c in chosen)
        if key not in self.loaded:
            self.loaded[key] = _final(self.prob, chosen, self.fin_pts, self.fin_p, self.aims, self.settings,
                                      self.vox_cc, self.kappa.copy(), status, gap, self.optimiser)
        plan = self.loaded[key]
        return None if plan is None else dataclasses.replace(plan, mip_status=status, mip_gap=gap)


def _budgets(selection: DwellProblem, needles: Sequence[int], optimiser: DwellOptimiser, kappa: np.ndarray,
             bound: float, final: _Final, rank: Sequence[int],
             given: Callable[[int], Sequence[int] | None] | None = None,
             publish: _Published | None = None,
             their_met: Callable[[int], int | None] | None = None,
             ) -> tuple[list[BudgetResult], list[ImplantPlan]]:
    """Select at budgets K = 1, 2, ... (0 with an intracavitary channel); return every budget and the new plans.

    Each budget's search starts from the last budget's selection and from ``given(K)`` (another arm's selection at
    K, indices into ``needles``, or None), so it is never worse on the selection model than either; ``publish``
    receives each budget's selected needles (indices into ``prob.channels``; None: no selection) and, once the budget
    is done, whether a plan meets every aim by then.

    The selection model holds the nominal rows only: when its selection at K is one already planned (or has fewer
    than K needles) and no plan meets every aim yet (the V200 limit or a scenario asks for more needles than the
    selection model sees), the needle with the most time in the all-candidates loading (``rank``, indices into
    ``needles``) whose hole is free is added. The budgets stop ``extra_after_aims`` after the first plan that meets
    every aim (or at ``settings.needles``), after two budgets without a new selection, when the selection reaches the
    all-candidates bound with every aim met, or after two new plans that do not raise the best D90 by
    :data:`MIN_GAIN_GY` (a plan of ``given``'s selection at its budget not counted). ``their_met(K)``: the first
    budget below K at which the arm whose implants this arm takes in met every aim (None: none), which stops this
    arm's budgets as its own would stop them (``extra_after_aims`` past it, or at ``settings.needles``): a budget past
    it cannot give a plan chosen over that arm's (:func:`reachplan.planner.implant.arms._arm`: the fewest needles
    that meet every aim).
    """
    prob, settings = final.prob, final.settings
    channels = prob.channels
    intracavitary = [c for c in range(len(channels)) if not channels[c].is_needle]
    budgets: list[BudgetResult] = []
    plans: list[ImplantPlan] = []
    seen: dict[tuple[int, ...], ImplantPlan | None] = {}
    keep: list[int] = []  # the last budget's needles (indices into ``needles``): a start for the next
    met_at: int | None = None
    stall = no_gain = 0
    best_d90 = -np.inf
    for k in range(0 if intracavitary else 1, min(settings.max_needles, len(needles)) + 1):
        k_met = None if their_met is None else their_met(k)
        if k_met is not None and k > max(k_met + settings.extra_after_aims, settings.needles or 0):
            break
        t_k = time.perf_counter()
        # past the first plan that meets every aim a budget only extends the Pareto curve: searched, not enumerated
        # (the same problem and cache, so the same model)
        problem = selection if met_at is None else dataclasses.replace(selection, exhaustive_max=0)
        theirs = None if given is None else given(k)
        sol = optimiser.optimise(problem, budget=k, limit_factor=kappa, start=[keep, *([theirs] if theirs else [])])
        value, lower, status = sol.objective, sol.bound, sol.status
        if sol.times_s is None:
            if publish is not None:
                publish.put(k, None)
            budgets.append(BudgetResult(k, 0, value, None, None, status, time.perf_counter() - t_k, False))
            if publish is not None:
                publish.planned(k, met_at is not None)
            continue
        ch_time = np.bincount(prob.channel_of, weights=sol.times_s, minlength=len(channels))
        keep = [i for i in sol.needles if ch_time[needles[i]] > 0]
        picked = tuple(sorted([needles[i] for i in keep] + intracavitary))
        if met_at is None and len(keep) < k and picked in seen:
            extra = _forced(keep, rank, channels, needles)
            if extra is not None:
                keep.append(extra)
                picked = tuple(sorted([needles[i] for i in keep] + intracavitary))
                status += f"; needle {channels[needles[extra]].name} added (no plan meets every aim yet)"
        if publish is not None:
            publish.put(k, tuple(needles[i] for i in keep))
        gap = None if lower is None else max(0.0, (value - lower) / max(abs(value), 1e-12))
        new = bool(picked) and picked not in seen
        if new:
            seen[picked] = final(np.array(picked, dtype=int),
                                 f"budget {k}: selection objective {value:.6g}, {status}", gap)
        budgets.append(BudgetResult(k, len(keep), value, lower, gap, status, time.perf_counter() - t_k, new,
                                    tuple(channels[c] for c in picked), seen.get(picked) if new else None))
        stall = 0 if new else stall + 1
        plan = seen[picked] if new else None
        if plan is not None:
            plans.append(plan)
            # a plan of the other arm's selection says nothing of whether this arm's own search has stalled
            same = theirs is not None and sorted(keep) == sorted(theirs)
            no_gain = 0 if plan.target.d90_eqd2_gy > best_d90 + MIN_GAIN_GY else no_gain + (not same)
            best_d90 = max(best_d90, plan.target.d90_eqd2_gy)
            if plan.aims_met and met_at is None:
                met_at = k
        if publish is not None:
            publish.planned(k, met_at is not None)
        if met_at is not None and k >= max(met_at + settings.extra_after_aims, settings.needles or 0):
            break
        at_bound = value <= bound + 1e-9 * max(1.0, abs(bound))
        if stall >= 2 or no_gain >= 2 or (at_bound and met_at is not None):
            break  # nothing new twice, no better plan twice, or the selection reaches the all-candidates bound
    return budgets, plans


def _forced(keep: Sequence[int], rank: Sequence[int], channels: Sequence[Channel],
            needles: Sequence[int]) -> int | None:
    """Return the first needle of ``rank`` not in ``keep`` whose hole ``keep`` leaves free (None: there is none)."""
    holes = {channels[needles[i]].name for i in keep}
    return next((j for j in rank if j not in keep and channels[needles[j]].name not in holes), None)


def plan_arms(arms: Sequence[tuple[str, Sequence[Channel]]], planning: PlanningStructures, kernel: Tg43Kernel,
              air_kerma_strength_u: float, aims: Aims | None = None, settings: ImplantSettings | None = None, *,
              gtv: Structure | None = None, workers: int = 2,
              points: Sequence[PointLimit] = ()) -> tuple[ImplantArm, ...]:
    """Plan several arms on one shared problem, each arm's search on its own, in up to ``workers`` threads.

    The arms share the sampled problem of all their channels (:class:`_Shared`: rows, organ-row calibration, the
    invasiveness scale, the final step's start): a needle set gets the same selection objective and the same plan
    whichever arm evaluates it, so an arm whose candidates include another's is never worse where both enumerate.
    The first arm's selection at each budget is a start of the search at that budget of every later arm whose
    candidates include the first arm's (the straight arm's for the steered arms: a steered arm's selection is then
    never worse than the straight arm's on the selection model); a later arm waits for it (:class:`_Published`).
    Such an arm takes in the first arm's implants (:func:`reachplan.planner.implant.arms.with_subset`: never worse
    than it), and its budgets stop past the first arm's first budget that meets every aim as they stop past its own
    (``settings.extra_after_aims``; a budget past it cannot give the arm a plan with fewer needles that meets every
    aim: a fifth of a study case's CPU time, spent on plans never chosen).
    HiGHS and the compiled dose kernels release the GIL, so two arms run on two cores. Threads only when the compiled
    kernels' threading layer allows calls from several threads at once (``omp`` or ``tbb``; numba's ``workqueue``
    does not); else one after the other, with the same result.

    Parameters
    ----------
    arms : sequence of (name, channels)
        Each arm's candidate channels (paths mm, LPS).
    planning : PlanningStructures
        Target and organ masks, shared by the arms.
    kernel : Tg43Kernel
        The source's TG-43 kernel, shared by the arms (numba's threading layer decides whether they run at once).
    air_kerma_strength_u : float, U
        Source strength S_K.
    aims : Aims, optional
        EMBRACE II when None.
    settings : ImplantSettings, optional
        Defaults when None; the same for every arm.
    gtv : Structure, optional
        As in :func:`plan_implant`.
    workers : int
        Threads at most.
    points : sequence of PointLimit
        Dose points with a planning aim and a hard limit (:func:`reachplan.planner.implant.problem.point_limits`):
        rows of the selection, the nominal loading and every scenario.

    Returns
    -------
    tuple of ImplantArm
        In the order of ``arms``; a later arm whose candidates include the first arm's with the first arm's implants.
    """
    aims = aims or Aims()
    settings = settings or ImplantSettings()
    optimiser = resolve(settings.optimiser)
    union: list[Channel] = []
    index: dict[int, int] = {}
    members: list[tuple[int, ...]] = []
    for _, channels in arms:
        for c in channels:
            if len(c.dwell_positions_mm) >= 1 and id(c) not in index:
                index[id(c)] = len(union)
                union.append(c)
        members.append(tuple(sorted({index[id(c)] for c in channels if id(c) in index})))
    t0 = time.perf_counter()
    shared = _shared(union, planning, kernel, air_kerma_strength_u, aims, settings, gtv, optimiser,
                     points) if union else None

    first = _Published()  # the first arm's selections, by budget, as its search makes them
    # the later arms whose candidates include the first arm's: they start from its selections and take in its implants
    over_first = [i > 0 and bool(members[0]) and set(members[0]) <= set(members[i]) for i in range(len(arms))]

    def one(i: int) -> ImplantArm:
        try:
            if shared is None or not members[i]:
                return ImplantArm(arms[i][0], 0, (), None, time.perf_counter() - t0, "no candidate channel")
            return _plan_arm(arms[i][0], members[i], shared, aims, settings, optimiser,
                             first if over_first[i] else None, first if i == 0 else None)
        finally:
            if i == 0:  # done (or failed): the arms waiting on it go on
                first.close()

    if workers < 2 or len(arms) < 2 or not _threads_safe(kernel):
        out = tuple(one(i) for i in range(len(arms)))
    else:
        from concurrent.futures import ThreadPoolExecutor

        with ThreadPoolExecutor(min(workers, len(arms))) as pool:  # the first arm starts first: the others wait on it
            out = tuple(pool.map(one, range(len(arms))))
    return tuple(with_subset(arm, out[0]) if over_first[i] else arm for i, arm in enumerate(out))


class _Published:
    """One arm's selected needles by budget, published as its search makes them, for the arms that start from them.

    :meth:`get` waits until the budget's selection is published or the arm is done, :meth:`met_before` until the arm
    is past the budgets below (so an arm on another thread reads the same as one planned after it: the same result
    either way).
    """

    def __init__(self) -> None:
        self._cond = threading.Condition()
        self._by_budget: dict[int, tuple[int, ...] | None] = {}
        self._done = False
        self._last = -1  # the last budget done
        self._met: int | None = None  # the first budget by which a plan met every aim

    def put(self, budget: int, channels: tuple[int, ...] | None) -> None:
        """Publish the selection at ``budget``.

        Parameters
        ----------
        budget : int
            The needle budget.
        channels : tuple of int or None
            The selected needles (channels of the shared problem); None: no selection there.
        """
        with self._cond:
            self._by_budget[budget] = channels
            self._cond.notify_all()

    def planned(self, budget: int, aims_met: bool) -> None:
        """Record that the arm is done with ``budget``, and whether a plan of it meets every aim by then.

        Parameters
        ----------
        budget : int
            The needle budget.
        aims_met : bool
            A plan of this budget or a lower one meets every aim.
        """
        with self._cond:
            self._last = budget
            if aims_met and self._met is None:
                self._met = budget
            self._cond.notify_all()

    def met_before(self, budget: int) -> int | None:
        """Wait until the arm is past every budget below ``budget``; return the first of them that met every aim.

        Parameters
        ----------
        budget : int
            The budget the asking arm is about to search (the arm published from is waited for up to the one below).

        Returns
        -------
        int or None
            The first budget below ``budget`` with a plan (of it or a lower one) that meets every aim; None: no such
            budget.
        """
        with self._cond:
            self._cond.wait_for(lambda: self._last >= budget - 1 or self._done)
            return self._met if self._met is not None and self._met < budget else None

    def close(self) -> None:
        """Mark the arm done: a budget not published by now has no selection."""
        with self._cond:
            self._done = True
            self._cond.notify_all()

    def get(self, budget: int) -> tuple[int, ...] | None:
        """Return the selection at ``budget`` once known.

        Parameters
        ----------
        budget : int
            The needle budget.

        Returns
        -------
        tuple of int or None
            The selected needles (channels of the shared problem); None: the arm has none there.
        """
        with self._cond:
            self._cond.wait_for(lambda: budget in self._by_budget or self._done)
            return self._by_budget.get(budget)


def _threads_safe(kernel: Tg43Kernel) -> bool:
    """Return True when numba's threading layer runs parallel kernels called from several threads at once."""
    import numba

    kernel.compiled_dose(np.zeros((1, 3)), np.ones((1, 3)), np.array([[0.0, 0.0, 1.0]]), np.ones(1))  # loads it
    try:
        return str(numba.threading_layer()) in ("omp", "tbb")
    except ValueError:  # no parallel kernel has run
        return False
