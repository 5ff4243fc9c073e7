"""What implant planning returns: the plans, the needle selection at each budget, and an arm's Pareto curve.

Each new selection's plan is a point of the arm's Pareto curve of needle count against HR-CTV D90 with the organ
limits held; a plan no better than one with fewer needles is dominated and left out, so the curve rises and has
one point per count (:func:`_pareto`). The plan chosen is the one with the fewest needles that meets every aim
(HR-CTV D90 and D98, GTV D98 when a GTV is given, organ D2cm³), else the one with the highest D90 (:func:`_arm`).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from reachplan.imaging.types import Grid
from reachplan.planner.dose.aims import Aims
from reachplan.planner.dose.coverage import Dvh, StructureMetrics, structure_metrics, voxel_volume_cc
from reachplan.planner.dose.dwells import DwellSet, dose_on_grid
from reachplan.planner.dose.tg43 import Tg43Kernel
from reachplan.planner.implant.candidates import Channel, NeedleCheck


@dataclass(frozen=True, eq=False)
class ImplantPlan:
    """One implant: its loaded channels, dwell times (per fraction) and metrics (EQD2 totals in the metrics).

    ``dwells.channels`` are 1-based indices into ``channels``. ``scale`` < 1 tells that the LP times were
    scaled down so that every organ D2cm³ meets its limit. ``mip_gap`` is the relative gap between the selection of the
    budget that gave this plan and that budget's LP relaxation (None when there is none); ``mip_status`` says
    which budget and how the selection was made.

    Parameters
    ----------
    channels : tuple of Channel
        The loaded channels (needles and intracavitary), paths mm, LPS.
    dwells : DwellSet
        Loaded dwells (positions mm, LPS; times s per fraction); ``channels`` 1-based into ``channels``.
    target : StructureMetrics
        HR-CTV metrics on sub-voxels (Gy per fraction; EQD2 totals).
    v200_pct : float, %
        HR-CTV volume receiving twice the prescription.
    oars : tuple of StructureMetrics
        Each organ's metrics on its voxels near the implant.
    aims_met : bool
        Every aim met (HR-CTV D90 and D98, GTV D98, organ D2cm³).
    gtv : StructureMetrics or None
        GTV metrics when a GTV was given.
    scale : float
        Factor (<= 1) applied to the optimiser's times so that every organ limit holds.
    mip_gap : float or None
        Relative gap of the selection that gave this plan.
    mip_status : str
        Which budget and how the selection was made.
    dvhs : tuple of (name, Dvh)
        Cumulative DVH of each structure (Gy per fraction).
    failed : tuple of str
        The aims the plan misses (empty when ``aims_met``), e.g. ``"HR-CTV V200 36.1 % > 35 %"``.
    limited_by : tuple of str
        The limits the plan stands on (an organ's D2cm³ within 0.3 Gy of its planning aim less the headroom, V200
        within 1.5 % of its limit): why the coverage is no higher.
    robustness : dict
        plan.json's ``robustness``: the one-needle-displaced scenarios, each organ's worst D2cm³ and the lowest
        HR-CTV D90 over them, and whether every hard limit holds in every scenario
        (:func:`reachplan.planner.implant.robust.robustness_json`).
    """

    channels: tuple[Channel, ...]
    dwells: DwellSet
    target: StructureMetrics
    v200_pct: float
    oars: tuple[StructureMetrics, ...]
    aims_met: bool
    gtv: StructureMetrics | None = None
    scale: float = 1.0
    mip_gap: float | None = None
    mip_status: str = ""
    dvhs: tuple[tuple[str, Dvh], ...] = ()
    robustness: dict[str, object] = field(default_factory=dict)
    failed: tuple[str, ...] = ()
    limited_by: tuple[str, ...] = ()

    @property
    def n_needles(self) -> int:
        """Number of template needles (intracavitary channels not counted)."""
        return sum(c.is_needle for c in self.channels)

    @property
    def total_time_s(self) -> float:
        """Total dwell time (s per fraction)."""
        return float(self.dwells.times_s.sum())

    @property
    def max_dwell_share(self) -> float:
        """Largest single dwell time over the total."""
        total = self.total_time_s
        return float(self.dwells.times_s.max() / total) if total > 0 else 0.0

    @property
    def needle_time_share(self) -> float:
        """Share of the total dwell time (dwell weight) carried by needles (the rest: intracavitary)."""
        total = self.total_time_s
        needle = [i + 1 for i, c in enumerate(self.channels) if c.is_needle]
        return float(self.dwells.times_s[np.isin(self.dwells.channels, needle)].sum() / total) if total > 0 else 0.0

    @property
    def loaded_dwells(self) -> tuple[int, ...]:
        """Dwells with time, per channel (in ``channels`` order)."""
        return tuple(int(np.count_nonzero((self.dwells.channels == i + 1) & (self.dwells.times_s > 0)))
                     for i in range(len(self.channels)))


@dataclass(frozen=True)
class ParetoPoint:
    """One needle budget: needles loaded, HR-CTV D90 (EQD2) with the organ limits held, and the aims.

    Parameters
    ----------
    n_needles : int
        Needles of the plan (intracavitary channels not counted).
    hrctv_d90_eqd2_gy : float, Gy EQD2
        HR-CTV D90 (total with the external beam).
    aims_met : bool
        Every aim met.
    """

    n_needles: int
    hrctv_d90_eqd2_gy: float
    aims_met: bool


@dataclass(frozen=True, eq=False)
class ImplantArm:
    """One arm (e.g. straight only, straight + steered): its candidates, Pareto curve and chosen plan.

    ``budgets``: the needle selection at each budget tried; ``selection``: how the selection was made and the
    bound of every candidate loaded (plan.json ``selection``); ``plans``: the implant of each Pareto point.

    Parameters
    ----------
    name : str
        The arm's name.
    n_candidates : int
        Candidate needles offered to the arm.
    pareto : tuple of ParetoPoint
        The Pareto curve, needle count rising.
    plan : ImplantPlan or None
        The chosen plan (None with ``reason`` when there is none).
    seconds : float, s
        Wall time of the arm's planning.
    reason : str
        Why there is no plan, or why it does not meet every aim.
    budgets : tuple of BudgetResult
        The selection at each budget tried.
    selection : dict
        plan.json's ``selection`` record (the optimiser's description, the all-candidates bound, the budgets).
    plans : tuple of ImplantPlan
        The plan of each Pareto point.
    needle_check : dict
        plan.json's ``needle_check`` record: how the chosen implant's needles were checked (reference model,
        tension reserve, re-load, rejected needles; :func:`reachplan.planner.implant.needles.check_arm`); empty when
        they were not.
    wanted_needles : int or None
        The needle count asked for (``--needles``): the Pareto point chosen; None: the fewest needles that meet
        every aim.
    """

    name: str
    n_candidates: int
    pareto: tuple[ParetoPoint, ...]
    plan: ImplantPlan | None
    seconds: float
    reason: str = ""
    budgets: tuple[BudgetResult, ...] = ()
    selection: dict[str, object] = field(default_factory=dict)
    plans: tuple[ImplantPlan, ...] = ()
    needle_check: dict[str, object] = field(default_factory=dict)
    wanted_needles: int | None = None

    def to_json(self) -> dict[str, object]:
        """Return the arm for plan.json.

        Returns
        -------
        dict
            The candidates, wall time (s), reason, Pareto curve and ``needle_check`` record; with a plan, also its
            needles (hole, kind, design, model, tension schedule as [depth mm, tension N, roll °] rows, dwell
            positions mm, LPS, dwell times s per fraction, and the needle's check: peak tension and limit N, the
            reserve, worst-case reach and clearance mm, :meth:`NeedleCheck.to_json`, None where not checked), its
            metrics (EQD2 totals, Gy; volumes %), total time (s per fraction) and the ``selection`` record with the
            chosen plan's status.
        """
        doc: dict[str, object] = {
            "candidates": self.n_candidates, "seconds": round(self.seconds, 3), "reason": self.reason,
            "pareto": [{"n_needles": p.n_needles, "hrctv_d90_eqd2_gy": round(p.hrctv_d90_eqd2_gy, 3),
                        "aims_met": p.aims_met} for p in self.pareto],
            "needle_check": self.needle_check,
        }
        pl = self.plan
        if pl is None:
            return {**doc, "needles": [], "aims_met": False, "selection": self.selection}
        needles = []
        for ch, c in enumerate(pl.channels, start=1):
            keep = pl.dwells.channels == ch
            needles.append({
                "hole_id": c.name, "kind": c.kind, "design": c.design, "model": c.model or None,
                "schedule": None if c.schedule is None else [
                    [round(float(d), 3), round(float(t), 3), round(float(r), 3)] for d, t, r in
                    zip(c.schedule.depth_mm, c.schedule.tension_n, c.schedule.roll_deg, strict=True)],
                "hole_distance_mm": round(c.hole_distance_mm, 3), "tissue_length_mm": round(c.tissue_length_mm, 3),
                "clearance_mm": round(c.clearance_mm, 3) if np.isfinite(c.clearance_mm) else None,
                "dwell_positions_mm": np.round(pl.dwells.positions_mm[keep], 3).tolist(),
                "dwell_times_s": np.round(pl.dwells.times_s[keep], 3).tolist(),
                **(NeedleCheck.NOT_CHECKED if c.check is None else c.check.to_json()),
                "tissue_band": None if c.tissue_band is None else c.tissue_band.to_json(),
            })
        return {
            **doc,
            "n_needles": pl.n_needles,
            "needles": needles,
            "aims_met": pl.aims_met,
            "hrctv_d90_eqd2_gy": round(pl.target.d90_eqd2_gy, 3),
            "hrctv_d98_eqd2_gy": round(pl.target.d98_eqd2_gy, 3),
            "hrctv_v100_percent": round(pl.target.v100_pct, 3),
            "hrctv_v150_percent": round(pl.target.v150_pct, 3),
            "hrctv_v200_percent": round(pl.v200_pct, 3),
            "gtv_d98_eqd2_gy": None if pl.gtv is None else round(pl.gtv.d98_eqd2_gy, 3),
            "oar_d2cc_eqd2_gy": {o.name: round(o.d2cc_eqd2_gy, 3) for o in pl.oars},
            "max_dwell_share": round(pl.max_dwell_share, 5),
            "needle_time_share": round(pl.needle_time_share, 5),
            "loaded_dwells": {c.name: n for c, n in zip(pl.channels, pl.loaded_dwells, strict=True)},
            "total_time_s": round(pl.total_time_s, 3),
            "scale": round(pl.scale, 6),
            "selection_gap": None if pl.mip_gap is None else round(pl.mip_gap, 4),
            "selection": {**self.selection, "chosen": pl.mip_status},
            "aims_failed": list(pl.failed),
            "limited_by": list(pl.limited_by),
            "robustness": pl.robustness,
            "time_balance": time_balance(pl),
            "loading": {"min_loaded_dwell_s": round(float(pl.dwells.times_s.min()), 3) if len(pl.dwells.times_s)
                        else None, "wanted_needles": self.wanted_needles},
        }


@dataclass(frozen=True)
class BudgetResult:
    """The needle selection at one budget ("at most ``budget`` needles").

    ``objective``: the selection model's value at the selection kept; ``dual_bound``: the LP relaxation's (a
    lower bound of every selection of ``budget`` needles), ``mip_gap``: the relative gap between the two (None when
    the relaxation failed); ``n_needles``: the
    needles selected; ``new``: False when the selection equals a smaller budget's (no new Pareto point).

    Parameters
    ----------
    budget : int
        At most this many needles.
    n_needles : int
        Needles selected (and loaded).
    objective : float
        The optimiser's objective at the selection (inf when it found none).
    dual_bound : float or None
        The optimiser's lower bound at this budget (the built-in's: its LP relaxation's).
    mip_gap : float or None
        ``(objective - dual_bound) / |objective|``.
    status : str
        How the optimiser made the selection.
    seconds : float, s
        Wall time of the budget (selection and final plan).
    new : bool
        The selection differs from every smaller budget's.
    selected : tuple of Channel
        The selected channels (with the intracavitary ones).
    plan : ImplantPlan or None
        The new selection's plan.
    """

    budget: int
    n_needles: int
    objective: float
    dual_bound: float | None
    mip_gap: float | None
    status: str
    seconds: float
    new: bool = True
    selected: tuple[Channel, ...] = field(default=(), repr=False, compare=False)
    plan: ImplantPlan | None = field(default=None, repr=False, compare=False)  # the new selection's plan

    def to_json(self) -> dict[str, object]:
        """Return the record for plan.json ``selection.budgets``.

        Returns
        -------
        dict
            The fields, rounded (``seconds`` in s); ``selected`` and ``plan`` left out, ``new`` as
            ``new_selection``.
        """
        return {"budget": self.budget, "n_needles": self.n_needles, "objective": round(self.objective, 6),
                "dual_bound": None if self.dual_bound is None else round(self.dual_bound, 6),
                "mip_gap": None if self.mip_gap is None else round(self.mip_gap, 5), "status": self.status,
                "seconds": round(self.seconds, 3), "new_selection": self.new}


def _arm(name: str, n_candidates: int, plans: Sequence[ImplantPlan], seconds: float,
         budgets: tuple[BudgetResult, ...], record: dict[str, object], wanted: int | None = None) -> ImplantArm:
    """Return an arm from its plans: the Pareto curve and the plan chosen from it (``plan.plan_implant``).

    The plan chosen: with ``wanted`` (a needle count), the Pareto point with that many needles, else the one with the
    most needles under it (the fewest above it when there is none); without, the fewest needles that meet every aim
    (planning aims with the headroom, hard limits in every scenario), else the highest D90.
    """
    pareto_plans = _pareto(plans)
    pareto = tuple(ParetoPoint(p.n_needles, p.target.d90_eqd2_gy, p.aims_met) for p in pareto_plans)
    if not pareto_plans:
        return ImplantArm(name, n_candidates, (), None, seconds, "no needle budget gave a plan (every LP failed)",
                          budgets, record, wanted_needles=wanted)
    meeting = [p for p in pareto_plans if p.aims_met]
    if wanted is not None:
        under = [p for p in pareto_plans if p.n_needles <= wanted]
        chosen = max(under, key=lambda p: p.n_needles) if under else min(pareto_plans, key=lambda p: p.n_needles)
        reason = "" if chosen.n_needles == wanted else \
            f"no Pareto point has {wanted} needles; the one with {chosen.n_needles} is kept"
    else:
        chosen = (min(meeting, key=lambda p: (p.n_needles, -p.target.d90_eqd2_gy)) if meeting
                  else max(pareto_plans, key=lambda p: (p.target.d90_eqd2_gy, -p.n_needles)))
        reason = "" if meeting else "no needle budget meets every aim; the plan with the highest D90 is kept"
    if not chosen.aims_met and chosen.failed:
        why = "" if not chosen.limited_by else "; limited by " + ", ".join(chosen.limited_by)
        reason = "; ".join([r for r in (reason, "missed: " + ", ".join(chosen.failed) + why) if r])
    return ImplantArm(name, n_candidates, pareto, chosen, seconds, reason, budgets, record, tuple(pareto_plans),
                      wanted_needles=wanted)


def time_balance(plan: ImplantPlan) -> dict[str, object]:
    """Return the intracavitary/interstitial time balance of a plan (plan.json ``time_balance``).

    Parameters
    ----------
    plan : ImplantPlan
        Its dwell times (s per fraction) and channels.

    Returns
    -------
    dict
        ``intracavitary_s``, ``interstitial_s`` (s per fraction) and ``interstitial_share`` (of the total time).
    """
    total = plan.total_time_s
    needle = total * plan.needle_time_share
    return {"intracavitary_s": round(total - needle, 3), "interstitial_s": round(needle, 3),
            "interstitial_share": round(plan.needle_time_share, 5)}


def with_subset(arm: ImplantArm, subset: ImplantArm) -> ImplantArm:
    """Return ``arm`` with the implants of ``subset`` (an arm planned on a subset of its candidates) added.

    Every implant of the subset arm is one of this arm's too, so the result is never worse than ``subset``: its
    Pareto curve and chosen plan are taken over both arms' plans (two arms planned independently, e.g. at once).

    Parameters
    ----------
    arm : ImplantArm
        The arm (its name, candidates, budgets and selection record are kept).
    subset : ImplantArm
        An arm planned on a subset of ``arm``'s candidates.

    Returns
    -------
    ImplantArm
    """
    return _arm(arm.name, arm.n_candidates, [*arm.plans, *subset.plans], arm.seconds, arm.budgets, arm.selection,
                arm.wanted_needles)


def with_straight_plans(straight: ImplantArm, steered: ImplantArm) -> ImplantArm:
    """Return the straight arm with every plan of the steered arm that holds no steered needle taken in (fair arms).

    Such a plan is one the straight arm could have made: with it the straight arm's search is as strong as the
    steered arm's, and a needle saved by steering always comes from a steered needle.

    Parameters
    ----------
    straight : ImplantArm
        The straight arm (its name, candidates, budgets and selection record are kept).
    steered : ImplantArm
        The straight + steered arm planned on a superset of its candidates.

    Returns
    -------
    ImplantArm
        Its Pareto curve and chosen plan taken over both sets of plans (:func:`with_subset`).
    """
    plans = tuple(p for p in steered.plans if not any(c.steered for c in p.channels))
    return with_subset(straight, dataclasses.replace(steered, plans=plans))


def _pareto(plans: Sequence[ImplantPlan]) -> list[ImplantPlan]:
    """Keep the plans no plan with fewer (or as many) needles beats: one per needle count, D90 rising with it.

    A budget means "at most n needles": a plan with more needles and no higher D90 (and no aims newly met) than
    one with fewer is dominated and left out.
    """
    best: dict[int, ImplantPlan] = {}
    for p in plans:
        old = best.get(p.n_needles)
        if old is None or (p.aims_met, p.target.d90_eqd2_gy) > (old.aims_met, old.target.d90_eqd2_gy):
            best[p.n_needles] = p
    out: list[ImplantPlan] = []
    for n in sorted(best):
        p = best[n]
        if not out or p.target.d90_eqd2_gy > out[-1].target.d90_eqd2_gy + 1e-9 or (
                p.aims_met and not any(q.aims_met for q in out)):
            out.append(p)
    return out


def recompute_target(plan: ImplantPlan, grid: Grid, target_mask: np.ndarray, kernel: Tg43Kernel,
                     air_kerma_strength_u: float, aims: Aims | None = None) -> StructureMetrics:
    """Recompute a plan's HR-CTV metrics independently with :func:`dose_on_grid` on another (finer) ``grid``.

    Parameters
    ----------
    plan : ImplantPlan
        Its dwells (positions mm, LPS; times s per fraction) give the dose.
    grid : Grid
        The grid to compute on (voxel centres mm, LPS).
    target_mask : (nk, nj, ni) bool
        The target on ``grid``.
    kernel : Tg43Kernel
        TG-43 dose kernel of the plan's source.
    air_kerma_strength_u : float, U
        Source strength S_K.
    aims : Aims, optional
        EMBRACE II by default (the prescription and α/β of the metrics).

    Returns
    -------
    StructureMetrics
        Physical per fraction and EQD2 totals.
    """
    aims = aims or Aims()
    dose = dose_on_grid(grid, plan.dwells, kernel, air_kerma_strength_u)[np.asarray(target_mask, bool)]
    return structure_metrics("HR-CTV", dose.astype(float), voxel_volume_cc(grid), aims.prescription_gy,
                             aims.alpha_beta_target_gy, aims.fractionation)
