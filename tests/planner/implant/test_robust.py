"""Robust loading and clinical loading on a planted case, checked against an independent dose computation.

The implant's dose, and the dose with any one needle shifted 2 mm sideways (the test's own shifts), are recomputed
with the numpy TG-43 path on the grid (``dose_on_grid(method="numpy")``, not the compiled kernel the planner uses)
and the structures' voxels: the planning aims with the headroom hold nominally, the hard limits and D90 >= 85 Gy in
every scenario; V200 within its limit; no loaded dwell under the minimum; a smoother loading than without the
gradient term.
"""

from __future__ import annotations

import argparse
from dataclasses import dataclass, replace

import numpy as np
import pytest

from reachplan.imaging.types import Grid
from reachplan.planner.dose.aims import Aims
from reachplan.planner.dose.coverage import dose_to_fraction, dose_to_volume, voxel_volume_cc
from reachplan.planner.dose.dwells import DwellSet, dose_on_grid
from reachplan.planner.dose.structures import PlanningStructures, Structure
from reachplan.planner.dose.tg43 import Tg43Kernel
from reachplan.planner.implant.arms import ImplantArm, ImplantPlan
from reachplan.planner.implant.candidates import Channel, needle_candidates
from reachplan.planner.implant.plan import plan_implant
from reachplan.planner.implant.robust import channel_scenarios
from reachplan.planner.implant.settings import ImplantSettings
from reachplan.planner.lookup import get_source

SK = 40700.0
#: EMBRACE II: rectum D2cm³ aim 65 Gy less 1 Gy headroom nominally, hard limit 75 Gy with a needle off
TIGHT = Aims()
#: a 15 mm sphere with needles 5 mm apart reaches V200 <= 35 % and D90 >= 90 Gy with few needles only at some cost
#: in coverage; the V200 limit here is 45 % (the demo's test holds the default 35 %)
SETTINGS = ImplantSettings(max_needles=4, max_dwell_share=0.25, extra_after_aims=0, v200_max_pct=45.0)


@dataclass(frozen=True, eq=False)
class Case:
    planning: PlanningStructures
    cands: tuple[Channel, ...]


@pytest.fixture(scope="module")
def kernel() -> Tg43Kernel:
    return Tg43Kernel(get_source("gammamed_plus_hdr"))


@pytest.fixture(scope="module")
def case() -> Case:
    """A 15 mm sphere 60 mm deep, the rectum 5 mm behind it (+y); straight needles along +z, holes every 5 mm."""
    h, lo, n = 2.0, np.array([-30.0, -30.0, 0.0]), (30, 30, 50)
    aff = np.diag([h, h, h, 1.0])
    aff[:3, 3] = lo + h / 2
    grid = Grid((n[2], n[1], n[0]), aff)
    k, j, i = np.meshgrid(np.arange(n[2]), np.arange(n[1]), np.arange(n[0]), indexing="ij")
    p = grid.to_patient(np.stack([i.ravel(), j.ravel(), k.ravel()], 1)).reshape(n[2], n[1], n[0], 3)
    target = Structure("HR-CTV", np.linalg.norm(p - np.array([0.0, 0.0, 60.0]), axis=-1) <= 15.0)
    rectum = Structure("Rectum", np.all((p >= [-25.0, 20.0, 30.0]) & (p <= [25.0, 28.0, 90.0]), axis=-1))
    planning = PlanningStructures(grid, target, (rectum,))
    xy = np.array([(x, y) for x in np.arange(-10.0, 11.0, 5.0) for y in np.arange(-10.0, 11.0, 5.0)])
    ids = [f"x{x:+.0f}y{y:+.0f}" for x, y in xy]
    cands = needle_candidates(ids, xy, np.hypot(xy[:, 0], xy[:, 1]), np.eye(4), planning, (), 0.915, SETTINGS)
    return Case(planning, cands)


@pytest.fixture(scope="module")
def robust(case: Case, kernel: Tg43Kernel) -> ImplantArm:
    return plan_implant("straight", case.cands, case.planning, kernel, SK, TIGHT, SETTINGS)


def _shifted(plan: ImplantPlan, needle: int, offset: np.ndarray) -> DwellSet:
    """The plan's dwells with one needle's (1-based channel) moved by ``offset`` (mm), times kept."""
    pos = plan.dwells.positions_mm.copy()
    pos[plan.dwells.channels == needle] += offset
    return DwellSet(pos, plan.dwells.directions, plan.dwells.times_s, plan.dwells.channels)


def _metrics(planning: PlanningStructures, dwells: DwellSet, kernel: Tg43Kernel,
             aims: Aims) -> tuple[float, float, float, float]:
    """Independent HR-CTV D90, D98, V200 (%) and rectum D2cm³ (EQD2 Gy) on the grid's voxels (numpy TG-43)."""
    dose = dose_on_grid(planning.grid, dwells, kernel, SK, method="numpy").astype(float)
    t = dose[planning.target.mask]
    fr = aims.fractionation
    d2 = dose_to_volume(dose[planning.oars[0].mask], voxel_volume_cc(planning.grid), 2.0)
    return (fr.total_eqd2(dose_to_fraction(t, 0.9), aims.alpha_beta_target_gy),
            fr.total_eqd2(dose_to_fraction(t, 0.98), aims.alpha_beta_target_gy),
            100.0 * float(np.mean(t >= 2.0 * aims.prescription_gy)), fr.total_eqd2(d2, aims.alpha_beta_oar_gy))


#: independent (voxel-centre, 2 mm) against the planner's sub-voxel metrics: D90 within this, Gy EQD2
TOL_GY = 1.5


def test_the_robust_plan_keeps_every_aim_and_every_hard_limit_with_any_needle_off(
        case: Case, robust: ImplantArm, kernel: Tg43Kernel) -> None:
    plan = robust.plan
    assert plan is not None and plan.aims_met, (robust.reason, robust.pareto)
    d90, d98, v200, rectum = _metrics(case.planning, plan.dwells, kernel, TIGHT)
    assert d90 >= TIGHT.target_d90_eqd2_gy - TOL_GY and d98 >= TIGHT.target_d98_eqd2_gy - TOL_GY
    assert rectum <= 64.0 + 0.3  # the planning aim less the headroom (the planner's D2cm³ is exact on these voxels)
    assert v200 <= SETTINGS.v200_max_pct + 2.0  # type: ignore[operator]
    assert plan.v200_pct <= SETTINGS.v200_max_pct  # type: ignore[operator]
    loaded = plan.dwells.times_s
    assert np.all(loaded >= SETTINGS.min_dwell_time_s - 1e-9)
    # every needle shifted 2 mm sideways in 4 directions (the needles run along +z): the hard limit and D90 >= 85
    worst_rectum, worst_d90 = 0.0, np.inf
    for ch in range(1, len(plan.channels) + 1):
        for offset in ([2.0, 0, 0], [-2.0, 0, 0], [0, 2.0, 0], [0, -2.0, 0]):
            s_d90, _, _, s_rectum = _metrics(case.planning, _shifted(plan, ch, np.array(offset)), kernel, TIGHT)
            worst_rectum, worst_d90 = max(worst_rectum, s_rectum), min(worst_d90, s_d90)
    assert worst_rectum <= 75.0
    assert worst_d90 >= TIGHT.target_d90_limit_eqd2_gy - TOL_GY
    rob = plan.robustness
    assert rob["scenarios"] == 4 * plan.n_needles and rob["hard_limits_met"]
    assert rob["worst_oar_d2cc_eqd2_gy"]["Rectum"]["value"] == pytest.approx(worst_rectum, abs=0.3)  # type: ignore[index]
    assert rob["worst_hrctv_d90_eqd2_gy"] == pytest.approx(worst_d90, abs=TOL_GY)


def test_needles_k_picks_that_point_of_the_pareto_curve(case: Case, robust: ImplantArm, kernel: Tg43Kernel) -> None:
    """``needles=K`` plans the budgets up to K and keeps the Pareto point with K needles (here more than the fewest
    that meet every aim)."""
    assert robust.plan is not None
    wanted = robust.plan.n_needles + 1
    arm = plan_implant("straight", case.cands, case.planning, kernel, SK, TIGHT, replace(SETTINGS, needles=wanted))
    assert arm.plan is not None and arm.wanted_needles == wanted
    assert max(b.budget for b in arm.budgets) >= wanted  # the budgets ran up to K
    on_curve = [p.n_needles for p in arm.pareto]
    assert arm.plan.n_needles == max(n for n in on_curve if n <= wanted)
    assert arm.plan.n_needles == wanted or "no Pareto point has" in arm.reason
    doc = arm.to_json()
    assert doc["n_needles"] == arm.plan.n_needles and doc["loading"]["wanted_needles"] == wanted  # type: ignore[index]
    balance = doc["time_balance"]
    assert balance["interstitial_share"] == pytest.approx(1.0)  # type: ignore[index]  # needles only
    assert doc["aims_failed"] == list(arm.plan.failed) and doc["robustness"] == arm.plan.robustness


def test_the_gradient_term_smooths_the_loading(case: Case, robust: ImplantArm, kernel: Tg43Kernel) -> None:
    """Summed time steps between neighbouring dwells, against the total time: smaller with the gradient term."""
    def roughness(plan: ImplantPlan) -> float:
        steps = 0.0
        for ch in range(1, len(plan.channels) + 1):
            steps += float(np.abs(np.diff(plan.dwells.times_s[plan.dwells.channels == ch])).sum())
        return steps / plan.total_time_s

    rough = plan_implant("straight", case.cands, case.planning, kernel, SK, TIGHT,
                         replace(SETTINGS, smoothness_weight=0.0, min_dwell_time_s=0.0))
    assert robust.plan is not None and rough.plan is not None
    assert roughness(robust.plan) < 0.5 * roughness(rough.plan)


def test_scenarios_shift_each_dwell_sideways_and_follow_scenario_paths() -> None:
    """A bent needle: each shifted dwell lies 2 mm from its planned place, perpendicular to the needle there; a
    scenario path (the planned one moved 1.5 mm in x) carries the dwells at the same arc length."""
    s = np.linspace(0.0, 60.0, 61)
    path = np.column_stack([0.004 * s ** 2, np.zeros_like(s), s])  # bends in x
    dwells = path[[58, 55, 52, 49, 46]]
    moved = path + np.array([1.5, 0.0, 0.0])
    ch = Channel("A", "steered", path, dwells, scenario_paths_mm=(moved,))
    scen = channel_scenarios(ch, 3, 2.0, 4)
    assert [x.label for x in scen] == ["2 mm 0°", "2 mm 90°", "2 mm 180°", "2 mm 270°", "path 1"]
    assert all(x.channel == 3 for x in scen)
    axis = ch.dwell_directions
    for x in scen[:4]:
        d = x.positions_mm - dwells
        assert np.allclose(np.linalg.norm(d, axis=1), 2.0)
        assert np.allclose(np.einsum("ij,ij->i", d, axis), 0.0, atol=1e-9)
    opposite = scen[0].positions_mm - dwells + scen[2].positions_mm - dwells
    assert np.allclose(opposite, 0.0, atol=1e-9)
    assert np.allclose(scen[4].positions_mm, dwells + np.array([1.5, 0.0, 0.0]), atol=0.05)
    tandem = Channel("Tandem", "intracavitary", path, dwells)
    assert channel_scenarios(tandem, 0, 2.0, 4) == []


def test_needles_argument_is_checked() -> None:
    from reachplan.planner.cli.plan import add_needles_argument

    parser = argparse.ArgumentParser(exit_on_error=False)
    add_needles_argument(parser)
    assert parser.parse_args(["--needles", "6"]).needles == 6
    assert parser.parse_args([]).needles is None
    for bad in ("-1", "two"):
        with pytest.raises(argparse.ArgumentError, match="--needles"):
            parser.parse_args(["--needles", bad])
    with pytest.raises(ValueError, match="needle count"):
        ImplantSettings(needles=-2)


def test_a_dose_point_with_an_aim_is_held_nominally_and_in_every_scenario(
        case: Case, robust: ImplantArm, kernel: Tg43Kernel) -> None:
    """A recto-vaginal point between the sphere and the rectum: the unconstrained plan gives it some dose; with an
    aim below that (and a hard limit above the aim), the plan keeps the point under the aim less the headroom and
    under the hard limit with any needle 2 mm off (the test's own shifts; the dose at the point by
    ``dose_at_points``, not the planner's sampled rows)."""
    from reachplan.planner.dose.aims import PointAim
    from reachplan.planner.dose.dwells import dose_at_points
    from reachplan.planner.implant.problem import point_limits

    where = np.array([0.0, 17.5, 60.0])
    fr, ab = TIGHT.fractionation, TIGHT.alpha_beta_oar_gy

    def eqd2_at(dwells: DwellSet) -> float:
        return fr.total_eqd2(float(dose_at_points(where[None], dwells, kernel, SK)[0]), ab)

    assert robust.plan is not None
    free = eqd2_at(robust.plan.dwells)
    aim, limit = round(free - 6.0, 1), round(free - 2.0, 1)
    aims = replace(TIGHT, points=(PointAim("ICRU recto-vaginal", ("ICRU rectum",), aim, limit),))
    points = point_limits(aims, [("ICRU rectum", where)])
    assert len(points) == 1
    arm = plan_implant("straight", case.cands, case.planning, kernel, SK, aims, SETTINGS, points=points)
    plan = arm.plan
    assert plan is not None, arm.reason
    assert eqd2_at(plan.dwells) <= aim - aims.headroom_eqd2_gy + 0.05
    worst = 0.0
    for ch in range(1, len(plan.channels) + 1):
        for offset in ([2.0, 0, 0], [-2.0, 0, 0], [0, 2.0, 0], [0, -2.0, 0]):
            worst = max(worst, eqd2_at(_shifted(plan, ch, np.array(offset))))
    assert worst <= limit + 0.05
    doc = plan.robustness["worst_point_eqd2_gy"]["ICRU recto-vaginal"]  # type: ignore[index]
    assert doc["value"] == pytest.approx(worst, abs=0.05) and doc["hard_limit"] == pytest.approx(limit, abs=1e-3)
    # a point over its aim is named among the failed aims
    tight = point_limits(replace(aims, points=(PointAim("ICRU recto-vaginal", ("ICRU rectum",), 1.0, 1.0),)),
                         [("ICRU rectum", where)])
    from reachplan.planner.implant.problem import _aims_failed

    failed = _aims_failed(plan.target, plan.gtv, plan.oars, aims, points=[(tight[0], 1.0)])
    assert any(f.startswith("ICRU recto-vaginal") for f in failed)


def test_a_scaled_loadings_metrics_from_the_earlier_doses_are_the_direct_ones(case: Case, kernel: Tg43Kernel) -> None:
    """A loading scaled down (a few dwells held at the minimum time) read from the earlier loading's doses gives the
    metrics computed afresh on every sub-voxel (to the float32 kernel's rounding)."""
    from reachplan.planner.implant.problem import _metrics, _sampled_problem

    prob = _sampled_problem(case.cands[:4], case.planning, kernel, SK, TIGHT, SETTINGS, None)
    cols = np.arange(len(prob.positions))
    t = np.random.default_rng(3).uniform(0.0, 20.0, len(cols)) * (np.arange(len(cols)) % 3 != 0)
    vox = voxel_volume_cc(case.planning.grid)
    first = _metrics(prob, cols, t, TIGHT, vox)
    down = 0.6
    t2 = np.where(t > 0, np.maximum(t * first[5] * down, 5.0), 0.0)  # the shortest held at 5 s
    assert np.any((t > 0) & (t2 == 5.0)) and np.any(t2 > 5.0)
    direct, reread = _metrics(prob, cols, t2, TIGHT, vox), _metrics(prob, cols, t2, TIGHT, vox, base=(first[6], down))
    for a, b in zip([direct[0], *direct[3]], [reread[0], *reread[3]], strict=True):
        assert (a.d90_gy, a.d98_gy, a.d2cc_gy) == pytest.approx((b.d90_gy, b.d98_gy, b.d2cc_gy), rel=1e-7)
    assert direct[1] == pytest.approx(reread[1], abs=0.01) and direct[5] == pytest.approx(reread[5], rel=1e-7)
    assert np.allclose(direct[6].target, reread[6].target, rtol=1e-7, atol=0)
