"""Robust loading: the hard limits held when one needle is displaced, by constraint generation on the linear model.

**Scenarios** (:func:`channel_scenarios`): each needle of an implant displaced on its own, the other channels where
planned. Every needle is shifted ``shift_mm`` sideways in ``shift_directions`` directions perpendicular to its axis
(at each dwell perpendicular to the needle's local direction, so no dwell moves less than ``shift_mm`` off the
planned path); a steered needle also runs along each of its :attr:`Channel.scenario_paths_mm` (the robustness
room's worst-case paths), its dwells at the same arc length from the template. The dwells keep their times: the
dose of a scenario is the nominal dose less the needle's planned contribution plus its displaced one, linear in the
times.

**The robust problem** is scenario-based minimax in the sense of Fredriksson, Forsgren & Hårdemark (Med Phys
38(3):1672, 2011): the nominal plan keeps every organ's planning aim less the headroom
(``Aims.oar_gy(name, "planning")``) and every scenario its hard limit (``Aims.oar_gy(name, "limit")``). With finitely
many scenarios the robust counterpart
of the LP is the LP with one set of organ rows per scenario (Ben-Tal & Nemirovski, Math Program 88:411, 2000;
Bertsimas & Sim, Oper Res 52(1):35, 2004, for the price of robustness); for HDR brachytherapy under catheter and
applicator displacement, Balvert, den Hertog & Hoffmann (INFORMS J Comput 31(1):100, 2019) and the cervix study
of applicator shifts in Appl Sci 11(6):2592 (2021). The rows are added lazily (constraint generation, the
cutting-set method of Mutapcic & Boyd, Optim Methods Softw 24(3):381, 2009): solve, evaluate every scenario exactly
(its D2cm³ on the organ's voxels), add the rows of the scenarios over a hard limit, solve again. Few scenarios ever
bind (those of the needles near an organ), so the LP stays small. Each row set's calibration ``κ`` is updated with
the others (:func:`reachplan.planner.implant.problem._calibrate`).

HR-CTV D90 in every scenario (hard limit ``target_d90_limit_eqd2_gy``) is evaluated the same way and reported;
when a scenario falls below it, the nominal coverage aim is raised by the shortfall and the rounds run again.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from reachplan._arrays import arc_length_mm
from reachplan.planner.dose.aims import Aims
from reachplan.planner.dose.coverage import dose_to_fraction, dose_to_volume
from reachplan.planner.dose.dwells import dwell_directions
from reachplan.planner.implant.candidates import Channel
from reachplan.planner.implant.optimiser import WARM_START, DwellOptimiser, DwellProblem, OrganRows
from reachplan.planner.implant.problem import (
    PointLimit,
    _calibrate,
    _modulation,
    _organ_samples,
    _Problem,
    _rates,
    _stride,
    point_rows,
)
from reachplan.planner.implant.settings import ImplantSettings

#: target voxels (an even stride through them) on which each scenario's HR-CTV D90 is evaluated
SCENARIO_TARGET_POINTS = 6000
#: the V200 rows' first calibration (the mean over the hottest third is some three times the dose where it begins)
V200_KAPPA_START = 3.0
#: HR-CTV points of the V200 rows (an even stride through the final model's target points)
V200_POINTS = 250
#: the rounds stop when no row set's calibration moves by more than this (relative)
KAPPA_TOLERANCE = 0.03
#: the V200 rows hold this much (percentage points of the HR-CTV) below the limit
V200_MARGIN_PCT = 1.0


@dataclass(frozen=True, eq=False)
class Scenario:
    """One needle displaced: where its dwells go (the other channels stay where planned).

    Parameters
    ----------
    channel : int
        The displaced channel (index into the arm's channels).
    label : str
        How it is displaced (e.g. ``"2 mm 90°"``, ``"path 1"``).
    positions_mm : (d, 3) float, mm, LPS
        The channel's dwells displaced (all its candidate dwells, in the channel's order).
    directions : (d, 3) float, unit vectors, LPS
        The source axis at each displaced dwell.
    """

    channel: int
    label: str
    positions_mm: np.ndarray
    directions: np.ndarray


def _perpendicular_basis(axis: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Return two unit vectors perpendicular to ``axis`` and to each other (the first without a y component)."""
    a = axis / np.linalg.norm(axis)
    ref = np.array([0.0, 1.0, 0.0]) if abs(a[1]) < 0.9 else np.array([1.0, 0.0, 0.0])
    e1 = np.cross(ref, a)
    e1 /= np.linalg.norm(e1)
    return e1, np.cross(a, e1)


def _arc_of(path: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Return the arc length (mm from ``path[0]``) of the nearest point of the polyline ``path`` to each point."""
    s = arc_length_mm(path)
    seg = np.diff(path, axis=0)
    length = np.maximum(np.linalg.norm(seg, axis=1), 1e-12)
    u = seg / length[:, None]
    rel = points[:, None, :] - path[None, :-1, :]
    t = np.clip(np.einsum("nsk,sk->ns", rel, u), 0.0, length[None, :])
    dist = np.linalg.norm(rel - t[..., None] * u[None], axis=2)
    best = np.argmin(dist, axis=1)
    out: np.ndarray = s[best] + t[np.arange(len(points)), best]
    return out


def channel_scenarios(channel: Channel, index: int, shift_mm: float, n_directions: int) -> list[Scenario]:
    """Return the displacement scenarios of one needle (none for an intracavitary channel).

    Parameters
    ----------
    channel : Channel
        The needle (path and dwells mm, LPS, base to tip; its ``scenario_paths_mm``).
    index : int
        The channel's index in the arm (recorded in each scenario).
    shift_mm : float, mm
        Sideways shift (0: none).
    n_directions : int
        Directions of the sideways shift, evenly around the needle's axis (base to tip).

    Returns
    -------
    list of Scenario
        The sideways shifts, then one per scenario path.
    """
    if not channel.is_needle:
        return []
    pos, dirs = channel.dwell_positions_mm, channel.dwell_directions
    out = []
    if shift_mm > 0:
        e1, e2 = _perpendicular_basis(channel.path_mm[-1] - channel.path_mm[0])
        for k in range(n_directions):
            angle = 2.0 * np.pi * k / n_directions
            v = np.cos(angle) * e1 + np.sin(angle) * e2
            w = v[None, :] - (dirs @ v)[:, None] * dirs  # perpendicular to the needle at each dwell
            w /= np.maximum(np.linalg.norm(w, axis=1), 1e-12)[:, None]
            out.append(Scenario(index, f"{shift_mm:g} mm {np.degrees(angle):.0f}°", pos + shift_mm * w, dirs))
    if channel.scenario_paths_mm:
        s_dw = _arc_of(np.asarray(channel.path_mm, dtype=float), pos)
        for k, path in enumerate(channel.scenario_paths_mm, start=1):
            p = np.asarray(path, dtype=float)
            s_p = arc_length_mm(p)
            s_q = np.clip(s_dw, 0.0, s_p[-1])
            moved = np.column_stack([np.interp(s_q, s_p, p[:, a]) for a in range(3)])
            out.append(Scenario(index, f"path {k}", moved, dwell_directions(p, moved)))
    return out


@dataclass(frozen=True)
class ScenarioResult:
    """One scenario's metrics (per fraction, physical).

    Parameters
    ----------
    hole : str
        The displaced needle's hole (its channel name).
    label : str
        How it is displaced.
    d2cc_gy : (n_organs,) float, Gy per fraction
        Each organ's D2cm³ (organs with an aim, in the order of the problem's organs with an aim).
    d90_gy : float, Gy per fraction
        HR-CTV D90.
    """

    hole: str
    label: str
    d2cc_gy: tuple[float, ...]
    d90_gy: float


class ScenarioCheck:
    """Every scenario of a chosen set of channels, evaluated exactly for any loading of its columns.

    The organs' points: each organ's voxels nearest the chosen dwells (10 cm³, where its hottest 2 cm³ lies in every
    scenario); the target's: an even stride through the HR-CTV voxels. Each scenario's change of the dose rates at
    those points (displaced less planned, for its needle's dwells) is computed once (float32), so a loading's
    scenarios cost one small product each.

    Parameters
    ----------
    prob : _Problem
        The arm's sampled problem.
    cols : (c,) int
        The chosen dwell columns (into ``prob.positions``), grouped by channel.
    scenarios : list of Scenario
        The scenarios of the chosen needles.
    vox_cc : float, cm³
        Voxel volume of the planning grid.
    """

    def __init__(self, prob: _Problem, cols: np.ndarray, scenarios: list[Scenario], vox_cc: float) -> None:
        self.prob, self.cols, self.scenarios, self.vox_cc = prob, cols, scenarios, vox_cc
        pos, dirs = prob.positions[cols], prob.directions[cols]
        self.organs = [o for o, limit in enumerate(prob.oar_limits) if limit is not None]
        organ_pts = [prob.near_organ(o, pos, 0.0, vox_cc, 5) for o in self.organs]
        self.target = prob.target_pts[_stride(len(prob.target_pts), SCENARIO_TARGET_POINTS)]
        self.points = np.concatenate([*organ_pts, self.target]) if organ_pts else self.target
        self.split = np.cumsum([len(p) for p in organ_pts])  # organ k's points: split[k-1]:split[k]
        self.rates = _rates(self.points, pos, dirs, prob).astype(np.float32)  # (P, c)
        ch = prob.channel_of[cols]
        self.local = [np.flatnonzero(ch == s.channel) for s in scenarios]  # the channel's dwells within ``cols``
        first = {int(c): int(np.flatnonzero(prob.channel_of == c)[0]) for c in set(ch.tolist())}
        # the scenario's rows of its channel's dwells that are in ``cols``
        self.rows = [cols[loc] - first[s.channel] for s, loc in zip(scenarios, self.local, strict=True)]
        self.delta = [(_rates(self.points, s.positions_mm[r], s.directions[r], prob) - self.rates[:, loc]
                       ).astype(np.float32) for s, loc, r in zip(scenarios, self.local, self.rows, strict=True)]

    def _metrics(self, dose: np.ndarray) -> tuple[tuple[float, ...], float]:
        """Return each organ's D2cm³ and the HR-CTV D90 (Gy per fraction) of a dose at :attr:`points`."""
        parts = np.split(dose, self.split)
        d2 = tuple(dose_to_volume(p.astype(float), self.vox_cc, 2.0) if len(p) else 0.0 for p in parts[:-1])
        return d2, dose_to_fraction(parts[-1].astype(float), 0.9)

    def evaluate(self, t: np.ndarray) -> list[ScenarioResult]:
        """Return every scenario's organ D2cm³ and HR-CTV D90 for the loading ``t``.

        Parameters
        ----------
        t : (c,) float, s
            Dwell time of each chosen column.

        Returns
        -------
        list of ScenarioResult
            In the order of the scenarios.
        """
        t32 = t.astype(np.float32)
        base = self.rates @ t32
        out = []
        for s, loc, delta in zip(self.scenarios, self.local, self.delta, strict=True):
            d2, d90 = self._metrics(base + delta @ t32[loc])
            out.append(ScenarioResult(self.prob.channels[s.channel].name, s.label, d2, d90))
        return out

    def nominal(self, times_s: np.ndarray) -> tuple[tuple[float, ...], float]:
        """Return the nominal organ D2cm³ and HR-CTV D90 (Gy per fraction) on the scenarios' points.

        The D90's difference to the final metrics' (on sub-voxels) is the bias of their sampling.

        Parameters
        ----------
        times_s : (c,) float, s
            The loading of the chosen columns.

        Returns
        -------
        d2cc : tuple of float, Gy per fraction
            Each organ's (organs with an aim).
        d90 : float, Gy per fraction
        """
        return self._metrics(self.rates @ times_s.astype(np.float32))

    def dose_at_target(self, times_s: np.ndarray) -> np.ndarray:
        """Return the nominal dose at the scenarios' HR-CTV points for the loading ``times_s`` (s, chosen columns).

        Parameters
        ----------
        times_s : (c,) float, s

        Returns
        -------
        (n,) float, Gy per fraction
        """
        start = self.split[-1] if len(self.split) else 0
        out: np.ndarray = (self.rates[start:] @ times_s.astype(np.float32)).astype(float)
        return out

    def displaced_rates(self, k: int, rates: np.ndarray, points: np.ndarray) -> np.ndarray:
        """Return the rates ``rates`` with scenario ``k``'s needle displaced.

        Parameters
        ----------
        k : int
            The scenario.
        rates : (p, c) float, Gy s⁻¹ per fraction
            Nominal rates of the chosen columns at ``points``.
        points : (p, 3) float, mm, LPS
            The points of the rows.

        Returns
        -------
        (p, c) float, Gy s⁻¹ per fraction
        """
        s, loc, rows = self.scenarios[k], self.local[k], self.rows[k]
        out = rates.copy()
        out[:, loc] = _rates(points, s.positions_mm[rows], s.directions[rows], self.prob)
        return out


def worst(results: list[ScenarioResult], hard_gy: np.ndarray) -> tuple[np.ndarray, float]:
    """Return each organ's worst D2cm³ over the scenarios and the lowest HR-CTV D90 (Gy per fraction).

    Parameters
    ----------
    results : list of ScenarioResult
        Every scenario's metrics.
    hard_gy : (n_organs,) float, Gy per fraction
        The organs' hard limits (gives the shape when there is no scenario).

    Returns
    -------
    d2cc : (n_organs,) float, Gy per fraction
    d90 : float, Gy per fraction
        inf when there is no scenario.
    """
    if not results:
        return np.zeros(len(hard_gy)), float("inf")
    return np.max([r.d2cc_gy for r in results], axis=0), min(r.d90_gy for r in results)


def worst_points(check: ScenarioCheck, times_s: np.ndarray) -> list[tuple[float, str]]:
    """Return each dose point's highest dose over the scenarios (Gy per fraction) and the scenario that gives it.

    Parameters
    ----------
    check : ScenarioCheck
        The scenarios of the chosen needles (its problem's ``points``).
    times_s : (c,) float, s
        The loading of the chosen columns.

    Returns
    -------
    list of (float, str)
        One per point; the nominal dose and ``"nominal"`` when there is no scenario.
    """
    prob, cols = check.prob, check.cols
    pos, dirs = prob.positions[cols], prob.directions[cols]
    out = []
    for p in prob.points:
        rates = _rates(p.position_mm[None], pos, dirs, prob)
        best = (float((rates @ times_s)[0]), "nominal")
        for k, sc in enumerate(check.scenarios):
            dose = float((check.displaced_rates(k, rates, p.position_mm[None]) @ times_s)[0])
            if dose > best[0]:
                best = (dose, f"{prob.channels[sc.channel].name} {sc.label}")
        out.append(best)
    return out


def robustness_json(results: list[ScenarioResult], names: tuple[str, ...], aims: Aims,
                    shift_mm: float, n_directions: int,
                    points: Sequence[tuple[PointLimit, float, str]] = ()) -> dict[str, object]:
    """Return plan.json's ``robustness`` of a plan: the scenarios, each organ's worst D2cm³ and the lowest D90.

    Parameters
    ----------
    results : list of ScenarioResult
        Every scenario's metrics (per fraction).
    names : tuple of str
        The organs of ``d2cc_gy``.
    aims : Aims
        The protocol (EQD2 of the metrics, the hard limits).
    shift_mm : float, mm
        The sideways shift of the scenarios.
    n_directions : int
        Its directions.
    points : sequence of (PointLimit, float, str)
        Each dose point with its highest dose over the scenarios (Gy per fraction) and that scenario
        (:func:`worst_points`).

    Returns
    -------
    dict
        ``scenarios`` (count), ``shift_mm``, ``directions``, ``worst_hrctv_d90_eqd2_gy`` with its scenario,
        ``worst_oar_d2cc_eqd2_gy`` (organ → value, scenario, hard limit), ``worst_point_eqd2_gy`` (point → value,
        scenario, hard limit), ``hard_limits_met``.
    """
    fr, ab_t, ab_o = aims.fractionation, aims.alpha_beta_target_gy, aims.alpha_beta_oar_gy
    doc: dict[str, object] = {"scenarios": len(results), "shift_mm": shift_mm, "directions": n_directions}
    if not results:
        return {**doc, "hard_limits_met": True}
    low = min(results, key=lambda r: r.d90_gy)
    organs = {}
    ok = fr.total_eqd2(low.d90_gy, ab_t) >= aims.target_d90_limit_eqd2_gy - 1e-6
    for i, name in enumerate(names):
        w = max(results, key=lambda r: r.d2cc_gy[i])
        value, limit = fr.total_eqd2(w.d2cc_gy[i], ab_o), aims.oar_eqd2_gy(name, "limit")
        ok = ok and (limit is None or value <= limit + 1e-6)
        organs[name] = {"value": round(value, 3), "scenario": f"{w.hole} {w.label}", "hard_limit": limit}
    dose_points = {}
    for p, dose_gy, scenario in points:
        value, limit = fr.total_eqd2(dose_gy, p.alpha_beta_gy), fr.total_eqd2(p.hard_gy, p.alpha_beta_gy)
        ok = ok and value <= limit + 1e-6
        dose_points[p.name] = {"value": round(value, 3), "scenario": scenario, "hard_limit": round(limit, 3)}
    return {**doc, "worst_hrctv_d90_eqd2_gy": round(fr.total_eqd2(low.d90_gy, ab_t), 3),
            "hrctv_d90_hard_limit_eqd2_gy": aims.target_d90_limit_eqd2_gy,
            "worst_hrctv_d90_scenario": f"{low.hole} {low.label}", "worst_oar_d2cc_eqd2_gy": organs,
            "worst_point_eqd2_gy": dose_points, "hard_limits_met": bool(ok)}


def v200_points(n_target: int, n_fin: int) -> np.ndarray:
    """Return the rows of the final model's target points that carry the V200 rows.

    Parameters
    ----------
    n_target : int
        The HR-CTV's voxels.
    n_fin : int
        The final model's HR-CTV points (its first rows, :func:`reachplan.planner.implant.problem._target_rows`).

    Returns
    -------
    (q,) int
        An even stride of :data:`V200_POINTS` through the first ``min(n_target, n_fin)`` rows.
    """
    return _stride(min(n_target, n_fin), V200_POINTS)


def v200_row_pct(settings: ImplantSettings) -> float:
    """Return the V200 rows' share (%): the limit less :data:`V200_MARGIN_PCT`.

    The rows are on a stride of voxel centres, the plan's V200 on sub-voxels.

    Parameters
    ----------
    settings : ImplantSettings
        Its ``v200_max_pct`` (not None).

    Returns
    -------
    float, %
    """
    assert settings.v200_max_pct is not None
    return max(settings.v200_max_pct - V200_MARGIN_PCT, 0.5 * settings.v200_max_pct)


class _RobustModel:
    """The rows of one robust loading: nominal organ rows, V200 rows, the scenarios' rows, and their rounds.

    **V200**: the mean dose over the HR-CTV's hottest (``v200_max_pct`` less :data:`V200_MARGIN_PCT`) % under
    ``κ`` × twice the prescription (the rows of :class:`reachplan.planner.implant.optimiser.OrganRows` over that
    volume; the mean over a share is at least the dose where it begins, so ``κ`` = 1 implies the limit). Near each
    source the dose is high, so that mean is some three times the dose where the share begins: ``κ`` starts at
    :data:`V200_KAPPA_START` (or the last plan's) and is calibrated each round to the exact dose where the share
    begins (on the scenario check's target voxels), as the organs' rows are to D2cm³.
    """

    def __init__(self, prob: _Problem, cols: np.ndarray, fin_pts: np.ndarray, fin_p: np.ndarray, aims: Aims,
                 settings: ImplantSettings, vox_cc: float) -> None:
        self.prob, self.settings = prob, settings
        pos, dirs = prob.positions[cols], prob.directions[cols]
        self.samples = _organ_samples(prob, pos, settings.final_oar_pitch_mm, settings.oar_sample_cc, vox_cc)
        self.rates = [_rates(reps, pos, dirs, prob) for _, reps, _ in self.samples]
        self.nominal = [OrganRows(r, w, float(prob.oar_limits[o]), 2.0, prob.oar_names[o])  # type: ignore[arg-type]
                        for (o, _, w), r in zip(self.samples, self.rates, strict=True)]
        self.hard = np.array([prob.oar_hard[o] for o, _, _ in self.samples], dtype=float)
        a_t = _rates(fin_pts, pos, dirs, prob)
        self.rx = aims.prescription_gy
        self.v200 = []
        if settings.v200_max_pct is not None:
            rows = v200_points(len(prob.target_pts), settings.final_target_points)
            volume = len(prob.target_pts) * vox_cc
            self.v200 = [OrganRows(a_t[rows], np.full(len(rows), volume / len(rows)), 2.0 * self.rx,
                                   volume * v200_row_pct(settings) / 100.0, "HR-CTV V200")]
        channels = sorted({int(c) for c in prob.channel_of[cols]})
        self.check = ScenarioCheck(prob, cols, [s for c in channels for s in channel_scenarios(
            prob.channels[c], c, settings.shift_mm, settings.shift_directions)], vox_cc)
        # each dose point: nominal within its planning value, and within its hard limit in every scenario (one row
        # each: exact, κ = 1, all from the start)
        self.points = point_rows(prob, pos, dirs)
        for p, nominal in zip(prob.points, list(self.points), strict=True):
            self.points += [OrganRows(self.check.displaced_rates(k, nominal.rates, p.position_mm[None]), np.ones(1),
                                      p.hard_gy, 1.0, f"{p.name}, {prob.channels[sc.channel].name} {sc.label}")
                            for k, sc in enumerate(self.check.scenarios)]
        self.active: list[tuple[int, int]] = []  # (scenario, organ) with rows
        self.scen: dict[tuple[int, int], OrganRows] = {}  # their rows, built once
        self.last: DwellProblem | None = None  # the last problem handed out
        self.p_scale, self.d90_limit = 1.0, aims.per_fraction_target_gy(aims.target_d90_limit_eqd2_gy)
        self.fin_p = fin_p
        self.base = DwellProblem(a_t, fin_p, self.rx * (1.0 + settings.coverage_margin), (), prob.channel_of[cols],
                                 _modulation(settings))

    def problem(self, min_time_s: float = 0.0) -> DwellProblem:
        """Return the problem with the rows found so far (nominal organs, scenarios, then V200).

        Parameters
        ----------
        min_time_s : float, s
            The problem's minimum loaded dwell time (0: none).

        Returns
        -------
        DwellProblem
        """
        for k, i in self.active:
            if (k, i) not in self.scen:
                sc = self.check.scenarios[k]
                self.scen[k, i] = OrganRows(self.check.displaced_rates(k, self.rates[i], self.samples[i][1]),
                                            self.samples[i][2], float(self.hard[i]), 2.0,
                                            f"{self.nominal[i].name}, {self.prob.channels[sc.channel].name} {sc.label}")
        scen = [self.scen[key] for key in self.active]
        # the last round's problem: the optimiser may start from its solution (the same rows and more)
        cache = {} if self.last is None else {WARM_START: self.last}
        self.last = dataclasses.replace(self.base, target_dose_gy=self.fin_p * self.p_scale,
                                        organs=(*self.nominal, *scen, *self.v200, *self.points),
                                        min_time_s=min_time_s, cache=cache)
        return self.last

    def factors(self, kap: np.ndarray) -> np.ndarray:
        """Return the limit factors of :meth:`problem`'s rows: ``kap`` (organs, scenarios, V200), then 1 per point row.

        Parameters
        ----------
        kap : (n_rows,) float
            The calibration of the organ, scenario and V200 rows.

        Returns
        -------
        (n_rows + n_point_rows,) float
        """
        return np.concatenate([kap, np.ones(len(self.points))])

    def update(self, times: np.ndarray, problem: DwellProblem, kap: np.ndarray) -> tuple[np.ndarray, bool]:
        """Evaluate a solve; return the next calibration and whether the rounds are done (nothing added or moved).

        Every row set's ``κ`` (nominal organs, scenarios, V200) is recalibrated to its exact value.

        Parameters
        ----------
        times : (c,) float, s
            The solve's dwell times.
        problem : DwellProblem
            The problem solved (:meth:`problem`).
        kap : (n_rows,) float
            The calibration it was solved with.

        Returns
        -------
        kappa : (n_rows',) float
            The next problem's calibration (the added scenarios' rows start at their organ's).
        done : bool
            Nothing was added and no ``κ`` moved by :data:`KAPPA_TOLERANCE` or more.
        """
        results = self.check.evaluate(times)
        v200 = [] if not self.v200 else [dose_to_fraction(self.check.dose_at_target(times),
                                                          v200_row_pct(self.settings) / 100.0)]
        exact = np.concatenate([self.check.nominal(times)[0], [results[k].d2cc_gy[i] for k, i in self.active], v200])
        n_cal = len(kap)  # the point rows after them are exact
        new = _calibrate(kap, exact, problem.tail_means(times)[:n_cal], problem.limits_gy[:n_cal])
        added = [(k, i) for k, r in enumerate(results) for i in range(len(self.hard))
                 if r.d2cc_gy[i] > self.hard[i] * (1 - 2e-3) and (k, i) not in self.active]
        low = min((r.d90_gy for r in results), default=np.inf)  # on voxel centres: the final check is finer
        raise_aim = low < self.d90_limit and self.p_scale < 1.1
        if raise_aim:
            self.p_scale = min(1.1, self.p_scale * self.d90_limit / max(low, 1e-9) * 1.005)
        done = not added and not raise_aim and bool(np.all(np.abs(new / kap - 1) < KAPPA_TOLERANCE))
        n_o = len(self.nominal) + len(self.active)
        self.active += added
        kap_next = np.concatenate([new[:n_o], new[[i for _, i in added]], new[n_o:]])
        return kap_next, done


def robust_times(prob: _Problem, cols: np.ndarray, fin_pts: np.ndarray, fin_p: np.ndarray, aims: Aims,
                 settings: ImplantSettings, vox_cc: float, kappa: np.ndarray,
                 optimiser: DwellOptimiser) -> tuple[np.ndarray, ScenarioCheck, np.ndarray] | None:
    """Return the robust dwell times of the columns ``cols`` (module docstring) and their scenario check.

    Rounds of constraint generation (at most ``robust_rounds``): solve; evaluate the nominal D2cm³, the V200 and every
    scenario exactly; recalibrate every organ row set's ``κ``; add the rows of each scenario and organ over its hard
    limit and the V200 rows (:class:`_RobustModel`); raise the coverage aim when a scenario's D90 is under its hard
    limit. Stops when nothing is added and every ``κ`` moved by less than :data:`KAPPA_TOLERANCE`. A last solve
    applies ``min_dwell_time_s``.

    Parameters
    ----------
    prob : _Problem
        The arm's sampled problem.
    cols : (c,) int
        The dwell columns of the chosen channels (grouped by channel).
    fin_pts : (m, 3) float, mm, LPS
        The final model's target points.
    fin_p : (m,) float, Gy per fraction
        The dose each should reach.
    aims : Aims
        The prescription and the target's hard limit.
    settings : ImplantSettings
        Organ sampling, V200 limit, shifts, rounds, minimum dwell time, modulation.
    vox_cc : float, cm³
        Voxel volume of the planning grid.
    kappa : (n_organs + n_v200,) float
        The calibration of the nominal organ rows and the V200 rows (when limited) to start from (the last plan's).
    optimiser : DwellOptimiser
        Loads the columns (without a budget).

    Returns
    -------
    times : (c,) float, s
        Dwell time of each column.
    check : ScenarioCheck
        The scenarios of the chosen needles.
    kappa : (n_organs + n_v200,) float
        The calibration of the nominal organ rows and the V200 rows reached (the next plan's start).
    None
        When the optimiser finds no loading at all.
    """
    model = _RobustModel(prob, cols, fin_pts, fin_p, aims, settings, vox_cc)
    n_o = len(model.nominal)
    start = np.asarray(kappa, dtype=float)
    kap = np.concatenate([start[:n_o], start[n_o:n_o + len(model.v200)]])
    times = None
    for _ in range(settings.robust_rounds):
        current = model.problem()
        solution = optimiser.optimise(current, limit_factor=model.factors(kap))
        if solution.times_s is None:
            break
        times = solution.times_s
        kap, done = model.update(times, current, kap)
        if done:
            break
    if times is None:
        return None
    short = (times > 1e-9) & (times < settings.min_dwell_time_s * (1 - 1e-9))
    if short.any():  # the LP left dwells under the minimum: solved again with them rounded
        solution = optimiser.optimise(model.problem(settings.min_dwell_time_s), limit_factor=model.factors(kap))
        if solution.times_s is not None:
            times = solution.times_s
    return times, model.check, np.concatenate([kap[:n_o], kap[len(kap) - len(model.v200):]])


def robust_failed(doc: dict[str, object]) -> list[str]:
    """Return the hard limits a plan breaks in some scenario (from its :func:`robustness_json`), each with its value.

    Parameters
    ----------
    doc : dict
        The plan's ``robustness``.

    Returns
    -------
    list of str
        Empty when every hard limit holds in every scenario.
    """
    if doc.get("hard_limits_met", True):
        return []
    out = []
    d90, limit = doc.get("worst_hrctv_d90_eqd2_gy"), doc.get("hrctv_d90_hard_limit_eqd2_gy")
    if isinstance(d90, float) and isinstance(limit, float) and d90 < limit - 1e-6:
        out.append(f"HR-CTV D90 {d90:.1f} < {limit:g} Gy with {doc.get('worst_hrctv_d90_scenario')}")
    organs = doc.get("worst_oar_d2cc_eqd2_gy")
    for name, w in (organs.items() if isinstance(organs, dict) else ()):
        if w["hard_limit"] is not None and w["value"] > w["hard_limit"] + 1e-6:
            out.append(f"{name} D2cm³ {w['value']:.1f} > {w['hard_limit']:g} Gy with {w['scenario']}")
    points = doc.get("worst_point_eqd2_gy")
    for name, w in (points.items() if isinstance(points, dict) else ()):
        if w["value"] > w["hard_limit"] + 1e-6:
            out.append(f"{name} {w['value']:.1f} > {w['hard_limit']:g} Gy with {w['scenario']}")
    return out
