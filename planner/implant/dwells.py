"""Dwell times of a chosen set of channels: the implant's final LP, and the per-target plan of given needles.

**Dwell times on the chosen channels of an implant** (:func:`_final`): the robust loading of
:func:`reachplan.planner.implant.robust.robust_times` (nominal organ rows at the planning aim less the headroom,
V200 rows, the rows of every one-needle-displaced scenario over a hard limit, calibrated until they hold; no loaded
dwell under ``min_dwell_time_s``); a needle left with fewer than ``min_dwells`` loaded dwells is not part of the
implant: it is dropped and the rest re-solved. The plan is checked on every organ voxel near the implant and in
every scenario, all times scaled down when a D2cm³ still exceeds its limit (or D90 its upper aim), and the aims it
misses and the limits it stands on are named (:func:`_plan`).

**Dwell times on given needles** (:func:`optimise_dwell_times`, the per-target delivery), a linear programme (scipy
HiGHS, deterministic)::

    minimise   (1/m) Σ_i u_i + ε Σ_j t_j / t_ref
    subject to A_T t + u >= P          (target points: dose plus underdose slack reaches the prescription)
               A_O t <= L_o             (OAR points outside their hottest 2 cm³)
               t >= 0, u >= 0

``A`` holds TG-43 dose per second of dwell (Gy s⁻¹, per fraction), ``P`` is the per-fraction dose that
brings HR-CTV D90 to the aim in EQD2 (α/β 10, with the external-beam course), ``L_o`` the per-fraction
D2cm³ limit of each organ (α/β 3). D2cm³ ≤ L is not linear; it is handled by constraining every
candidate OAR point at first (max dose ≤ L, which implies D2cm³ ≤ L), then releasing the points in the
hottest 2 cm³ of each organ and solving again (twice). The final plan is checked on every voxel of every
organ; if a D2cm³ still exceeds its limit all times are scaled down until none does, and the result
says so. Organ limits are therefore always respected. Aims: :class:`reachplan.planner.dose.aims.Aims`.

Needle paths are ``(k, 3)`` polylines in mm, LPS, ordered from the template (base) to the tip.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy import optimize as sopt
from scipy import sparse

from reachplan.planner.dose.aims import Aims
from reachplan.planner.dose.coverage import (
    Dvh,
    StructureMetrics,
    cumulative_dvh,
    dose_to_fraction,
    dose_to_volume,
    structure_metrics,
    voxel_volume_cc,
)
from reachplan.planner.dose.dwells import DwellSet, dwells_along_path, grid_points_mm
from reachplan.planner.dose.structures import PlanningStructures
from reachplan.planner.dose.tg43 import Tg43Kernel
from reachplan.planner.implant.arms import ImplantPlan
from reachplan.planner.implant.optimiser import DwellOptimiser
from reachplan.planner.implant.problem import (
    _aims_failed,
    _metrics,
    _Problem,
    _stride,
    point_doses,
)
from reachplan.planner.implant.robust import (
    ScenarioCheck,
    robust_failed,
    robust_times,
    robustness_json,
    worst,
    worst_points,
)
from reachplan.planner.implant.settings import ImplantSettings


def _clip_share(t: np.ndarray, share: float) -> np.ndarray:
    """Clip times to ``min(t, c)`` with the largest ``c`` such that no time exceeds ``share`` of the total.

    Exact: with the m largest clipped, ``c = share · R_m / (1 - share · m)``, R_m the sum of the others.
    """
    order = np.sort(t)[::-1]
    if order[0] <= share * order.sum():
        return t
    rest = order.sum()
    for m in range(1, len(order) + 1):
        rest -= order[m - 1]
        if share * m >= 1:
            break
        c = share * rest / (1 - share * m)
        if m == len(order) or order[m] <= c:
            return np.minimum(t, c * (1 - 1e-12))
    return t


@dataclass(frozen=True)
class OptimizerSettings:
    """Dwell placement and problem size (lengths in mm).

    Parameters
    ----------
    dwell_step_mm, tip_offset_mm, active_length_mm : float, mm
        Distance between candidate dwells along a needle; of the first dwell from the needle tip; length along
        each needle (from the first dwell) where dwells may be placed.
    max_target_points, max_oar_points : int
        Target voxels used in the LP (an even stride through them) and candidate voxels per organ (those
        with the highest dose for equal dwell times, i.e. nearest to the needles).
    time_weight : float, unitless
        ε: weight of the mean target dose against the mean underdose (both Gy); breaks ties toward shorter
        plans.
    relax_iterations : int
        Re-solves that release each organ's hottest 2 cm³ from the point constraints.
    """

    dwell_step_mm: float = 5.0
    tip_offset_mm: float = 6.0
    active_length_mm: float = 60.0
    max_target_points: int = 3000
    max_oar_points: int = 1500
    time_weight: float = 1e-3
    relax_iterations: int = 2

    def __post_init__(self) -> None:
        if not (self.dwell_step_mm > 0 and self.tip_offset_mm >= 0 and self.active_length_mm >= 0):
            raise ValueError("dwell step must be > 0 mm; tip offset and active length >= 0 mm")
        if self.max_target_points < 1 or self.max_oar_points < 1 or self.relax_iterations < 0:
            raise ValueError("point limits must be >= 1 and relax iterations >= 0")


@dataclass(frozen=True, eq=False)
class OptimisationResult:
    """Optimised dwell times and the resulting metrics (per fraction; EQD2 totals in the metrics).

    ``success`` is False with a ``reason`` when the LP did not solve; ``scaled`` tells that the times
    were scaled down by ``scale`` after the LP so that every organ limit holds on all its voxels;
    ``aim_met`` that HR-CTV D90 (EQD2) reached its aim.

    Parameters
    ----------
    dwells : DwellSet
        Dwell positions (mm, LPS) and times (s per fraction); channel = needle index + 1.
    target : StructureMetrics
        HR-CTV metrics on its voxels (Gy per fraction; EQD2 totals).
    oars : tuple of StructureMetrics
        Each organ's metrics on all its voxels (organs without voxels left out).
    success : bool
        The LP solved (else the times are zero).
    reason : str
        ``"solved"``, the scaling note, or why the LP did not solve.
    scaled : bool
        ``scale`` < 1.
    scale : float
        Factor (<= 1) applied to the LP's times.
    dvhs : tuple of (name, Dvh)
        Cumulative DVH of each structure (Gy per fraction).
    aim_met : bool
        HR-CTV D90 (EQD2) reached its aim.
    """

    dwells: DwellSet
    target: StructureMetrics
    oars: tuple[StructureMetrics, ...]
    success: bool
    reason: str
    scaled: bool = False
    scale: float = 1.0
    dvhs: tuple[tuple[str, Dvh], ...] = ()
    aim_met: bool = False


def candidate_dwells(needles: Sequence[np.ndarray], settings: OptimizerSettings) -> DwellSet:
    """Candidate dwells on every needle (channel number = needle index + 1), times zero.

    Parameters
    ----------
    needles : sequence of (k, 3) float, mm, LPS, ordered base → tip
        Each needle's path.
    settings : OptimizerSettings
        Dwell step, tip offset and active length.

    Returns
    -------
    DwellSet
        Dwell positions (mm, LPS), directions toward each tip, zero times, channels 1-based.

    Raises
    ------
    ValueError
        A path that is not a finite (k >= 2, 3) array.
    """
    parts = []
    for i, path in enumerate(needles):
        p = np.asarray(path, dtype=float)
        if p.ndim != 2 or p.shape[1] != 3 or len(p) < 2 or not np.all(np.isfinite(p)):
            raise ValueError(f"needle {i + 1}: path must be a finite (k >= 2, 3) array in mm")
        pos, dirs = dwells_along_path(
            p[::-1],
            step_mm=settings.dwell_step_mm,
            tip_offset_mm=settings.tip_offset_mm,
            active_length_mm=settings.active_length_mm,
        )
        parts.append(DwellSet(pos, dirs, np.zeros(len(pos)), np.full(len(pos), i + 1)))
    return DwellSet.concatenate(parts)


@dataclass(frozen=True, eq=False)
class _NeedleProblem:
    """Dose-rate matrices (Gy per second of dwell, per fraction) of one arm's candidate dwells."""

    dwells: DwellSet
    target_idx: np.ndarray  # flat voxel indices of the target
    a_target: np.ndarray  # (n_target_voxels, n_dwells)
    oar_idx: tuple[np.ndarray, ...]
    a_oar: tuple[np.ndarray, ...]  # (n_oar_voxels, n_dwells) each
    lp_target_rows: np.ndarray
    lp_oar_rows: tuple[np.ndarray, ...]


def _build(
    dwells: DwellSet, structures: PlanningStructures, kernel: Tg43Kernel, sk: float, settings: OptimizerSettings
) -> _NeedleProblem:
    to_gy_per_s = sk / 360000.0

    def rates(idx: np.ndarray) -> np.ndarray:
        # the compiled float32 kernel (within 1e-4 of the float64 table; threads over voxels)
        out = kernel.compiled_rates(grid_points_mm(structures.grid, idx), dwells.positions_mm, dwells.directions)
        out *= to_gy_per_s
        return out

    t_idx = np.flatnonzero(structures.target.mask.ravel())
    a_t = rates(t_idx)
    o_idx = tuple(np.flatnonzero(o.mask.ravel()) for o in structures.oars)
    a_o = tuple(rates(i) for i in o_idx)
    lp_t = _stride(len(t_idx), settings.max_target_points)
    lp_o = []
    for a in a_o:
        k = min(len(a), settings.max_oar_points)
        near = np.argsort(-a.sum(axis=1), kind="stable")[:k] if len(a) else np.zeros(0, dtype=int)
        lp_o.append(np.sort(near))
    return _NeedleProblem(dwells, t_idx, a_t, o_idx, a_o, lp_t, tuple(lp_o))


def _solve_lp(
    prob: _NeedleProblem, cols: np.ndarray, limits: Sequence[float | None], released: Sequence[np.ndarray],
    prescription: float, settings: OptimizerSettings,
) -> tuple[np.ndarray | None, str]:
    n = len(cols)
    at = prob.a_target[prob.lp_target_rows][:, cols]
    m = len(at)
    # variables x = [t (n), u (m)]
    # objective: mean underdose + ε · mean target dose (both Gy), so ε is unit-free
    c = np.concatenate([settings.time_weight * at.mean(axis=0), np.full(m, 1.0 / m)])
    rows = [sparse.hstack([sparse.csr_matrix(-at), -sparse.identity(m, format="csr")])]
    rhs = [np.full(m, -prescription)]
    for a, lp_rows, limit, free in zip(prob.a_oar, prob.lp_oar_rows, limits, released, strict=True):
        if limit is None:
            continue
        keep = np.setdiff1d(lp_rows, free, assume_unique=False)
        if len(keep):
            rows.append(sparse.hstack([sparse.csr_matrix(a[keep][:, cols]), sparse.csr_matrix((len(keep), m))]))
            rhs.append(np.full(len(keep), limit))
    res = sopt.linprog(
        c, A_ub=sparse.vstack(rows, format="csr"), b_ub=np.concatenate(rhs), bounds=(0, None), method="highs",
    )
    if res.status != 0 or res.x is None:
        return None, f"linear programme did not solve: {res.message}"
    return np.maximum(res.x[:n], 0.0), "solved"


def _evaluate(
    prob: _NeedleProblem, cols: np.ndarray, times: np.ndarray, structures: PlanningStructures, aims: Aims,
) -> tuple[StructureMetrics, tuple[StructureMetrics, ...], tuple[tuple[str, Dvh], ...]]:
    vox = voxel_volume_cc(structures.grid)
    rx = aims.prescription_gy
    dt = prob.a_target[:, cols] @ times
    target = structure_metrics(structures.target.name, dt, vox, rx, aims.alpha_beta_target_gy, aims.fractionation)
    dvhs = [(structures.target.name, cumulative_dvh(dt, vox))]
    oars = []
    for s, a in zip(structures.oars, prob.a_oar, strict=True):
        if len(a) == 0:
            continue
        d = a[:, cols] @ times
        oars.append(structure_metrics(s.name, d, vox, rx, aims.alpha_beta_oar_gy, aims.fractionation))
        dvhs.append((s.name, cumulative_dvh(d, vox)))
    return target, tuple(oars), tuple(dvhs)


def _optimise_columns(
    prob: _NeedleProblem, cols: np.ndarray, structures: PlanningStructures, aims: Aims, settings: OptimizerSettings,
) -> OptimisationResult:
    vox = voxel_volume_cc(structures.grid)
    limits = [aims.oar_gy(o.name) for o in structures.oars]
    released: list[np.ndarray] = [np.zeros(0, dtype=int) for _ in structures.oars]
    n_hot = max(1, math.ceil(2.0 / vox - 1e-9) - 1)  # voxels allowed above the limit
    reason = "no dwells"
    best: tuple[np.ndarray, float, float] | None = None  # (LP times, scale to the limits, D90)
    for _ in range(settings.relax_iterations + 1):
        t, reason = _solve_lp(prob, cols, limits, released, aims.prescription_gy, settings)
        if t is None:
            break
        scale = _limit_scale(prob, cols, t, limits, vox)
        d90 = dose_to_fraction(prob.a_target[:, cols] @ (t * scale), 0.9)
        if best is None or d90 > best[2] + 1e-12:
            best = (t, scale, d90)
        released = [
            lp_rows[np.argsort(-(a[lp_rows][:, cols] @ t), kind="stable")[:n_hot]]
            for a, lp_rows in zip(prob.a_oar, prob.lp_oar_rows, strict=True)
        ]
    dwells = prob.dwells.select(np.isin(np.arange(len(prob.dwells)), cols))
    if best is None:
        zero = np.zeros(len(cols))
        target, oars, dvhs = _evaluate(prob, cols, zero, structures, aims)
        return OptimisationResult(dwells.with_times(zero), target, oars, False, reason, dvhs=dvhs)
    t, scale, _ = best
    final = t * scale
    target, oars, dvhs = _evaluate(prob, cols, final, structures, aims)
    scaled = scale < 1.0
    note = "solved" if not scaled else "solved; times scaled down so every organ D2cm³ meets its limit"
    return OptimisationResult(
        dwells.with_times(final), target, oars, True, note, scaled=scaled, scale=scale, dvhs=dvhs,
        aim_met=target.d90_eqd2_gy >= aims.target_d90_eqd2_gy - 1e-9,
    )


def _limit_scale(
    prob: _NeedleProblem, cols: np.ndarray, times: np.ndarray, limits: Sequence[float | None], vox: float
) -> float:
    """Largest factor <= 1 that keeps every organ's D2cm³ (all its voxels) within its limit."""
    scale = 1.0
    for a, limit in zip(prob.a_oar, limits, strict=True):
        if limit is None or len(a) == 0:
            continue
        d2 = dose_to_volume(a[:, cols] @ times, vox, 2.0)
        if d2 > limit:
            scale = min(scale, limit / d2 * (1 - 1e-9))
    return scale


def optimise_dwell_times(
    needles: Sequence[np.ndarray],
    structures: PlanningStructures,
    kernel: Tg43Kernel,
    air_kerma_strength_u: float,
    aims: Aims | None = None,
    settings: OptimizerSettings | None = None,
) -> OptimisationResult:
    """Optimise dwell times on the given needles (straight or steered).

    Parameters
    ----------
    needles : sequence of (k, 3) float, mm, LPS, ordered base → tip
        Every needle is offered (channel = needle index + 1).
    structures : PlanningStructures
        Target and organ masks; the organs' limits hold on all their voxels.
    kernel : Tg43Kernel
        TG-43 dose-rate kernel of the source, cGy h⁻¹ U⁻¹.
    air_kerma_strength_u : float, U
        Source strength S_K (converts the kernel's cGy h⁻¹ U⁻¹ to Gy s⁻¹).
    aims : Aims, optional
        EMBRACE II when None; the prescription and organ limits per fraction follow from it.
    settings : OptimizerSettings, optional
        Defaults when None.

    Returns
    -------
    OptimisationResult
        Per-fraction dwell times; organ D2cm³ limits always hold; ``aim_met`` says whether HR-CTV D90
        reached its aim.
    """
    aims = Aims() if aims is None else aims
    settings = OptimizerSettings() if settings is None else settings
    dwells = candidate_dwells(needles, settings)
    prob = _build(dwells, structures, kernel, air_kerma_strength_u, settings)
    return _optimise_columns(prob, np.arange(len(dwells)), structures, aims, settings)


def _final(prob: _Problem, chosen: np.ndarray, fin_pts: np.ndarray, fin_p: np.ndarray, aims: Aims,
           settings: ImplantSettings, vox_cc: float, kappa: np.ndarray, status: str, gap: float | None,
           optimiser: DwellOptimiser) -> ImplantPlan | None:
    """Return the implant of the chosen channels: their robust dwell times (the empty-needle rule) and its metrics.

    Parameters
    ----------
    prob : _Problem
        The arm's sampled problem.
    chosen : (c,) int
        The chosen channels (indices into ``prob.channels``), ascending.
    fin_pts, fin_p : (m, 3) float, mm, LPS; (m,) float, Gy per fraction
        The final model's target points and the dose each should reach.
    aims, settings : Aims, ImplantSettings
    vox_cc : float, cm³
        Voxel volume of the planning grid.
    kappa : (n_organs + n_v200,) float
        The calibration of the nominal organ rows and the V200 rows to start from; updated in place to the one
        reached (the next plan's start).
    status : str
        How the selection was made (the plan's ``mip_status``).
    gap : float or None
        The selection's relative gap (the plan's ``mip_gap``).
    optimiser : DwellOptimiser
        Loads the chosen channels (without a budget).

    Returns
    -------
    ImplantPlan or None
        None when the optimiser finds no loading, or no channel keeps enough loaded dwells.
    """
    t = np.zeros(0)
    cols = np.zeros(0, dtype=int)
    check = None
    for _ in range(3):
        cols = np.flatnonzero(np.isin(prob.channel_of, chosen))
        loaded = robust_times(prob, cols, fin_pts, fin_p, aims, settings, vox_cc, kappa, optimiser)
        if loaded is None:
            return None
        times, check, reached = loaded
        kappa[:len(reached)] = reached
        t = np.where(times >= settings.min_dwell_time_s * (1 - 1e-6), times, 0.0)
        n_loaded = np.bincount(prob.channel_of[cols], weights=(t > 0).astype(float), minlength=len(prob.channels))
        need = np.array([settings.min_dwells if prob.channels[c].is_needle else 1 for c in range(len(prob.channels))])
        loaded_ch = np.array([c for c in chosen if n_loaded[c] >= need[c]], dtype=int)
        if len(loaded_ch) == 0:
            return None
        t = np.where(np.isin(prob.channel_of[cols], loaded_ch), t, 0.0)
        t = _clip_share(t, settings.max_dwell_share)  # the dropped short dwells raised the others' shares
        if len(loaded_ch) == len(chosen):
            break
        chosen = loaded_ch  # a needle the optimum leaves (almost) empty is not part of the implant: re-solve
    assert check is not None
    return _plan(prob, chosen, cols, t, check, aims, settings, vox_cc, status, gap)


def _plan(prob: _Problem, chosen: np.ndarray, cols: np.ndarray, t: np.ndarray, check: ScenarioCheck, aims: Aims,
          settings: ImplantSettings, vox_cc: float, status: str, gap: float | None) -> ImplantPlan:
    """Return the plan of the loading ``t`` of ``cols``: its metrics, every scenario's, and the aims met.

    All times are scaled down (by one factor) when a nominal D2cm³ exceeds its planning limit or a scenario's its
    hard limit, and when HR-CTV D90 is over its upper planning aim (down to the aim less the headroom, or to the
    factor that keeps every scenario's D90 at its hard limit: :func:`_down_to_upper_aim`); a dwell the scaling takes
    under ``min_dwell_time_s`` is set to that minimum.
    """
    hard = np.array([prob.oar_hard[o] for o in check.organs], dtype=float)
    results = check.evaluate(t)
    d2_worst, _ = worst(results, hard)
    over = d2_worst > hard
    max_scale = float(np.min(hard[over] / d2_worst[over])) * (1 - 1e-9) if over.any() else 1.0
    target, v200, gtv, oars, dvhs, scale, doses = _metrics(prob, cols, t, aims, vox_cc, max_scale)
    if scale < 1.0:
        t = np.where(t > 0, np.maximum(t * scale, settings.min_dwell_time_s), 0.0)
        results = check.evaluate(t)
    # the scenarios' D90 on their target voxels, shifted by the nominal's difference to the final sub-voxels
    bias = target.d90_gy - check.nominal(t)[1]
    results = [dataclasses.replace(r, d90_gy=r.d90_gy + bias) for r in results]
    down = _down_to_upper_aim(target.d90_gy, min((r.d90_gy for r in results), default=np.inf), aims)
    if down < 1.0:  # over the D90 upper aim: every time scaled down to it (as far as the scenarios' D90 allows)
        t = np.where(t > 0, np.maximum(t * down, settings.min_dwell_time_s), 0.0)
        target, v200, gtv, oars, dvhs, _, _ = _metrics(prob, cols, t, aims, vox_cc, base=(doses, down))
        scale *= down
        bias = target.d90_gy - check.nominal(t)[1]
        results = [dataclasses.replace(r, d90_gy=r.d90_gy + bias) for r in check.evaluate(t)]
    names = tuple(prob.oar_names[o] for o in check.organs)
    pt_worst = worst_points(check, t)
    robustness = robustness_json(results, names, aims, settings.shift_mm, settings.shift_directions,
                                 [(p, v, sc) for p, (v, sc) in zip(prob.points, pt_worst, strict=True)])
    pt_nominal = point_doses(prob, prob.positions[cols], prob.directions[cols], t)
    keep = t > 0
    new_index = {int(c): i + 1 for i, c in enumerate(chosen)}
    dwells = DwellSet(prob.positions[cols][keep], prob.directions[cols][keep], t[keep],
                      np.array([new_index[int(c)] for c in prob.channel_of[cols][keep]], dtype=int))
    failed = _aims_failed(target, gtv, oars, aims, v200, settings.v200_max_pct,
                          list(zip(prob.points, pt_nominal, strict=True))) + robust_failed(robustness)
    return ImplantPlan(tuple(prob.channels[int(c)] for c in chosen), dwells, target, v200, oars, not failed, gtv,
                       scale, gap, status, dvhs, robustness, tuple(failed), _limited_by(oars, v200, aims, settings))


def _down_to_upper_aim(d90_gy: float, worst_d90_gy: float, aims: Aims) -> float:
    """Return the factor (<= 1) that brings HR-CTV D90 (Gy per fraction) down below its upper planning aim.

    A D90 over the upper aim comes down to the aim less the protocol's headroom (no lower than the middle of the
    D90 range): a plan scaled to the aim itself sits on it, and an independent recomputation, which lands within a
    fraction of a Gy on either side (:mod:`reachplan.planner.dose.aims`), finds it over (0.4 Gy on a clinical
    seed's plan). No lower than what keeps the lowest scenario D90 (``worst_d90_gy``) at its hard limit; 1 without
    an upper aim.
    """
    top = aims.target_d90_max_eqd2_gy
    if top is None or d90_gy <= 0:
        return 1.0
    if d90_gy <= aims.per_fraction_target_gy(top):
        return 1.0
    goal = max(top - aims.headroom_eqd2_gy, 0.5 * (top + aims.target_d90_eqd2_gy))
    down = aims.per_fraction_target_gy(goal) / d90_gy
    if np.isfinite(worst_d90_gy) and worst_d90_gy > 0:
        down = max(down, aims.per_fraction_target_gy(aims.target_d90_limit_eqd2_gy) / worst_d90_gy)
    return min(1.0, down)


def _limited_by(oars: Sequence[StructureMetrics], v200_pct: float, aims: Aims,
                settings: ImplantSettings) -> tuple[str, ...]:
    """Return the limits a plan stands on (EQD2 Gy, %).

    Organs within 0.3 Gy of their planning aim less the headroom, V200 within 1.5 % of its limit.
    """
    out = []
    for o in oars:
        aim = aims.oar_eqd2_gy(o.name)
        if aim is not None and o.d2cc_eqd2_gy >= aim - aims.headroom_eqd2_gy - 0.3:
            out.append(f"{o.name} D2cm³ {o.d2cc_eqd2_gy:.1f} Gy (aim {aim:g} less {aims.headroom_eqd2_gy:g} headroom)")
    if settings.v200_max_pct is not None and v200_pct >= settings.v200_max_pct - 1.5:
        out.append(f"HR-CTV V200 {v200_pct:.1f} % (limit {settings.v200_max_pct:g} %)")
    return tuple(out)
