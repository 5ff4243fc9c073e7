"""Implant planning on planted cases with a known answer: needle candidates for a volume, the needle set and
dwell times chosen together, straight against steered."""

from __future__ import annotations

import itertools
from dataclasses import dataclass, replace

import numpy as np
import pytest
import trimesh

from reachplan.imaging.types import Grid
from reachplan.planner.case.config import PlanConfig, PlanModels
from reachplan.planner.delivery import implant_needles
from reachplan.planner.dose.aims import Aims
from reachplan.planner.dose.structures import PlanningStructures, Structure
from reachplan.planner.dose.tg43 import Tg43Kernel
from reachplan.planner.geometry.collision import Organ, check_path, make_organ
from reachplan.planner.implant.arms import ImplantArm, recompute_target, with_straight_plans, with_subset
from reachplan.planner.implant.candidates import Channel, needle_candidates
from reachplan.planner.implant.plan import plan_arms, plan_implant
from reachplan.planner.implant.settings import ImplantSettings
from reachplan.planner.lookup import get_source
from reachplan.planner.steering.steered import shape_bank

SK = 40700.0
RADIUS = 0.915
#: organ limits loose enough that only geometry decides (the planted cases test reach, not dose to organs)
LOOSE = Aims(oar_d2cc_eqd2_gy=(("bowel", 400.0), ("rectum", 400.0)))


@dataclass(frozen=True, eq=False)
class Case:
    planning: PlanningStructures
    organs: tuple[Organ, ...]
    ids: list[str]
    xy: np.ndarray
    dist: np.ndarray


def _grid(h: float, lo: tuple[float, float, float], hi: tuple[float, float, float]) -> tuple[Grid, np.ndarray]:
    n = [round((b - a) / h) for a, b in zip(lo, hi, strict=True)]
    aff = np.diag([h, h, h, 1.0])
    aff[:3, 3] = [a + h / 2 for a in lo]
    grid = Grid((n[2], n[1], n[0]), aff)
    k, j, i = np.meshgrid(np.arange(n[2]), np.arange(n[1]), np.arange(n[0]), indexing="ij")
    return grid, grid.to_patient(np.stack([i.ravel(), j.ravel(), k.ravel()], 1)).reshape(n[2], n[1], n[0], 3)


def _box(lo: tuple[float, float, float], hi: tuple[float, float, float]) -> trimesh.Trimesh:
    lo_a, hi_a = np.array(lo), np.array(hi)
    return trimesh.creation.box(extents=hi_a - lo_a, transform=trimesh.transformations.translation_matrix(
        (lo_a + hi_a) / 2))


def _in_box(p: np.ndarray, lo: tuple[float, float, float], hi: tuple[float, float, float]) -> np.ndarray:
    return np.all((p >= np.array(lo)) & (p <= np.array(hi)), axis=-1)


def _case(target: tuple[tuple[float, float, float], float], oars: dict[str, tuple[tuple[float, float, float],
                                                                                 tuple[float, float, float]]]) -> Case:
    """A spherical target (centre, radius, mm), box organs; the template at z = 0 inserting along +z with
    holes every 5 mm, x in [-10, 30], y in [-10, 10]."""
    lo, hi = (-24.0, -24.0, 0.0), (40.0, 24.0, 110.0)
    centre, radius = np.array(target[0]), target[1]
    grid, p = _grid(2.0, lo, hi)
    masks = tuple(Structure(name, _in_box(p, *box)) for name, box in oars.items())
    planning = PlanningStructures(grid, Structure("HR-CTV", np.linalg.norm(p - centre, axis=-1) <= radius), masks)
    organs = tuple(make_organ(name, _box(*box)) for name, box in oars.items())
    xs, ys = np.arange(-10.0, 31.0, 5.0), np.arange(-10.0, 11.0, 5.0)
    xy = np.array([(x, y) for x in xs for y in ys])
    ids = [f"x{x:+.0f}y{y:+.0f}" for x, y in xy]
    return Case(planning, organs, ids, xy, np.hypot(xy[:, 0], xy[:, 1]))


@pytest.fixture(scope="module")
def kernel() -> Tg43Kernel:
    return Tg43Kernel(get_source("gammamed_plus_hdr"))


@pytest.fixture(scope="module")
def bank() -> object:
    config = PlanConfig()
    design = config.rod_designs[0]
    # the implant logic on a fixed bank: curvature factor 1, not the planner's fitted one (with it, 1.27 in the
    # gel, some candidates graze the lobe: a dwell gap, or every dwell in the margin shell; see issue 15 report)
    screening = replace(PlanModels.for_config(config).screening, tissue_factor=1.0)
    return shape_bank(design, config.family, min(config.max_depth_mm, design.length_mm), screening)


#: the planted cases test reach: nominal planning (no displaced-needle scenarios, no V200 limit; a 9 mm sphere
#: cannot keep D90 with its one needle 2 mm off); robust planning is tested in test_robust.py
SETTINGS = ImplantSettings(max_needles=4, max_dwell_share=0.25, shift_mm=0.0, v200_max_pct=None)


def _arms(case: Case, bank: object, kernel: Tg43Kernel, settings: ImplantSettings = SETTINGS,
          aims: Aims = LOOSE) -> tuple[tuple[Channel, ...], ImplantArm, ImplantArm]:
    cands = needle_candidates(case.ids, case.xy, case.dist, np.eye(4), case.planning, case.organs, RADIUS,
                              settings, [bank])  # type: ignore[list-item]
    straight = plan_implant("straight", [c for c in cands if not c.steered], case.planning, kernel, SK, aims,
                            settings)
    steered = with_subset(plan_implant("steered", cands, case.planning, kernel, SK, aims, settings), straight)
    return cands, straight, steered


@pytest.fixture(scope="module")
def open_case(bank: object, kernel: Tg43Kernel) -> tuple[Case, tuple[Channel, ...], ImplantArm, ImplantArm]:
    """A sphere in the open, an organ well away: straight needles reach it as well as steered ones."""
    case = _case(((5.0, 0.0, 60.0), 9.0), {"Rectum": ((-20.0, 16.0, 20.0), (30.0, 24.0, 100.0))})
    return (case, *_arms(case, bank, kernel))


@pytest.fixture(scope="module")
def lobe_case(bank: object, kernel: Tg43Kernel) -> tuple[Case, tuple[Channel, ...], ImplantArm, ImplantArm]:
    """A deep lateral lobe with an organ standing in front of it: every straight path to the lobe crosses the
    organ (or passes within the 2 mm margin); a needle from a medial hole can bend out to it."""
    case = _case(((17.0, 0.0, 100.0), 7.0), {"Bowel": ((11.0, -14.0, 10.0), (26.0, 14.0, 60.0))})
    return (case, *_arms(case, bank, kernel))


def test_candidates_pass_through_the_target_and_clear_organs(lobe_case: tuple) -> None:
    case, cands, _, _ = lobe_case
    assert cands, "no candidate at all"
    inside = case.planning.target.mask
    grid = case.planning.grid
    for c in cands:
        assert len(c.dwell_positions_mm) >= SETTINGS.min_dwells
        gaps = np.linalg.norm(np.diff(c.dwell_positions_mm, axis=0), axis=1)
        assert np.allclose(gaps, SETTINGS.dwell_step_mm, atol=0.05)  # 2.5 mm apart along the path
        ijk = np.rint(grid.to_index(c.dwell_positions_mm)).astype(int)
        assert inside[ijk[:, 2], ijk[:, 1], ijk[:, 0]].any()
        checks = check_path(c.path_mm, RADIUS, case.organs)
        assert not any(x.collides for x in checks)
        assert min(x.clearance_mm for x in checks) >= SETTINGS.clearance_margin_mm
    # the straight needles that would reach the lobe cross the organ: none is a candidate
    assert not [c for c in cands if c.kind == "straight"]


def test_straight_cover_as_well_as_steered_in_the_open(open_case: tuple) -> None:
    _, cands, straight, steered = open_case
    assert {c.kind for c in cands} == {"straight", "steered"}
    assert straight.plan is not None and steered.plan is not None
    assert straight.plan.aims_met and steered.plan.aims_met
    assert straight.plan.n_needles == steered.plan.n_needles


def test_only_steered_needles_reach_the_lobe(lobe_case: tuple) -> None:
    _, _, straight, steered = lobe_case
    assert steered.plan is not None and steered.plan.aims_met
    assert all(c.steered for c in steered.plan.channels)
    assert straight.plan is None or not straight.plan.aims_met \
        or steered.plan.n_needles < straight.plan.n_needles


@pytest.mark.parametrize("which", ["open_case", "lobe_case"])
def test_chosen_implants_follow_the_dwell_rules(which: str, request: pytest.FixtureRequest) -> None:
    _, _, *arms = request.getfixturevalue(which)
    for arm in arms:
        if arm.plan is None:
            continue
        plan = arm.plan
        # empty-needle rule: every channel of the implant carries time, on at least three dwells
        assert plan.channels and min(plan.loaded_dwells) >= 3
        assert plan.max_dwell_share <= SETTINGS.max_dwell_share + 1e-9
        # no loaded dwell under the afterloader's minimum (the neighbour ratio is tested on its own below)
        assert np.all(plan.dwells.times_s >= SETTINGS.min_dwell_time_s - 1e-9)
        # the exporters get exactly the loaded needles, each with time
        needles = implant_needles(plan)
        assert [n.hole_id for n in needles] == [c.name for c in plan.channels]
        assert all(float(np.sum(n.dwell_times_s)) > 0 for n in needles)
        assert arm.pareto and any(q.n_needles == plan.n_needles for q in arm.pareto)


def test_modulation_limit_binds(open_case: tuple, bank: object, kernel: Tg43Kernel) -> None:
    """A tight neighbour ratio is respected and changes the loading against a loose one."""
    case, cands, _, _ = open_case
    straight = [c for c in cands if not c.steered]
    spread = {}
    for ratio in (1.2, 1e6):
        s = replace(SETTINGS, neighbour_ratio=ratio, max_dwell_share=1.0, min_dwell_time_s=0.0,
                    smoothness_weight=0.0)
        arm = plan_implant("straight", straight, case.planning, kernel, SK, LOOSE, s)
        assert arm.plan is not None
        worst = 1.0
        for ch in range(1, len(arm.plan.channels) + 1):
            t = arm.plan.dwells.times_s[arm.plan.dwells.channels == ch]
            worst = max(worst, float(np.max(np.maximum(t[1:] / t[:-1], t[:-1] / t[1:]))) if len(t) > 1 else 1.0)
        spread[ratio] = worst
    assert spread[1.2] <= 1.2 * (1 + 1e-6)
    assert spread[1e6] > 1.2


def test_dwell_share_limit(open_case: tuple, kernel: Tg43Kernel) -> None:
    case, cands, _, _ = open_case
    for share in (0.12, 0.3):
        s = replace(SETTINGS, max_needles=3, max_dwell_share=share)
        arm = plan_implant("straight", [c for c in cands if not c.steered], case.planning, kernel, SK, LOOSE, s)
        assert arm.plan is not None
        assert arm.plan.max_dwell_share <= share + 1e-9


def _finer(grid: Grid, mask: np.ndarray, n: int) -> tuple[Grid, np.ndarray]:
    """The grid cropped to the structure's box and split n times along each axis, and the same structure on it
    (each voxel's n³ sub-voxels)."""
    idx = np.argwhere(mask)
    lo, hi = idx.min(axis=0), idx.max(axis=0) + 1
    crop = mask[lo[0]:hi[0], lo[1]:hi[1], lo[2]:hi[2]]
    aff = np.array(grid.patient_from_index, dtype=float)
    aff[:3, 3] = grid.to_patient(np.array([lo[::-1]], dtype=float))[0] - aff[:3, :3].sum(axis=1) * (0.5 - 0.5 / n)
    aff[:3, :3] = aff[:3, :3] / n
    fine = Grid(tuple(int(s) * n for s in crop.shape), aff)  # type: ignore[arg-type]
    return fine, crop.repeat(n, 0).repeat(n, 1).repeat(n, 2)


@pytest.mark.parametrize("which", ["open_case", "lobe_case"])
def test_final_dose_on_a_finer_grid_agrees(which: str, request: pytest.FixtureRequest, kernel: Tg43Kernel) -> None:
    """The chosen implant's dose recomputed independently (``dose_on_grid``) on a grid six times finer
    (0.33 mm; the optimiser's is 2 mm, its final metrics on 3 × 3 × 3 sub-voxels) gives the same D90 within 1 %."""
    case, _, *arms = request.getfixturevalue(which)
    for arm in arms:
        if arm.plan is None:
            continue
        fine = recompute_target(arm.plan, *_finer(case.planning.grid, case.planning.target.mask, 6), kernel, SK,
                                LOOSE)
        assert fine.d90_gy == pytest.approx(arm.plan.target.d90_gy, rel=0.01)
        assert fine.d90_eqd2_gy == pytest.approx(arm.plan.target.d90_eqd2_gy, rel=0.01)


def test_organ_limit_holds(open_case: tuple, kernel: Tg43Kernel) -> None:
    """A strict rectum limit is met on every rectum voxel (recomputed independently)."""
    from reachplan.planner.dose.coverage import dose_to_volume, voxel_volume_cc
    from reachplan.planner.dose.dwells import dose_on_grid

    case, cands, _, _ = open_case
    aims = Aims(oar_d2cc_eqd2_gy=(("rectum", 62.0),))
    arm = plan_implant("straight", [c for c in cands if not c.steered], case.planning, kernel, SK, aims, SETTINGS)
    assert arm.plan is not None
    grid = case.planning.grid
    dose = dose_on_grid(grid, arm.plan.dwells, kernel, SK)[case.planning.oars[0].mask]
    d2 = dose_to_volume(dose.astype(float), voxel_volume_cc(grid), 2.0)
    assert aims.fractionation.total_eqd2(d2, aims.alpha_beta_oar_gy) <= 62.0 * (1 + 1e-4)


def test_tandem_is_a_channel_not_a_needle(open_case: tuple, kernel: Tg43Kernel) -> None:
    """A tandem through the target's centre is used by both arms and never counted as a needle; with it the
    implant needs no more needles than without."""
    from reachplan.planner.implant.candidates import intracavitary_channel

    case, cands, straight, _ = open_case
    tandem = intracavitary_channel("Tandem", np.array([[5.0, 0.0, 0.0], [5.0, 0.0, 75.0]]), case.planning, SETTINGS)
    assert tandem is not None and not tandem.is_needle
    assert np.all(np.linalg.norm(tandem.dwell_positions_mm - [5.0, 0.0, 60.0], axis=1) <= 9.0 + 2.5 + 1.0)
    arm = plan_implant("straight", [*[c for c in cands if not c.steered], tandem], case.planning, kernel, SK, LOOSE,
                       SETTINGS)
    assert arm.plan is not None and arm.plan.aims_met
    assert arm.plan.n_needles == sum(c.is_needle for c in arm.plan.channels)
    assert any(not c.is_needle for c in arm.plan.channels)
    assert straight.plan is not None and arm.plan.n_needles <= straight.plan.n_needles
    assert arm.plan.needle_time_share < 1.0
    (zero,) = [b for b in arm.budgets if b.budget == 0]  # the tandem alone: the one selection, solved, not searched
    assert zero.status == "the only selection of no needle" and zero.mip_gap == 0.0 and zero.n_needles == 0
    assert zero.plan is not None and not any(c.is_needle for c in zero.plan.channels)


def test_cohort_summary_of_paired_arms() -> None:
    """Needles saved and D90 gained: the mean of the paired differences, inside its bootstrap interval, which
    narrows as the cohort grows (differences drawn around known means)."""
    from reachplan.planner.errors import StudyError
    from reachplan.planner.study.implant import summarise_implants

    rng = np.random.default_rng(3)

    def cohort(n: int) -> list[dict[str, object]]:
        out: list[dict[str, object]] = []
        for _ in range(n):
            k = int(rng.integers(4, 9))
            d90 = float(rng.normal(88.0, 2.0))
            out.append({"straight": {"n_needles": k, "hrctv_d90_eqd2_gy": d90, "aims_met": d90 >= 85},
                        "steered": {"n_needles": k - int(rng.integers(1, 4)), "hrctv_d90_eqd2_gy": d90 + 1.5,
                                    "aims_met": True}})
        return out

    small, large = summarise_implants(cohort(10)), summarise_implants(cohort(200))
    for s in (small, large):
        assert s.needles_saved.ci95 is not None and s.needles_saved.mean is not None
        assert s.needles_saved.ci95[0] <= s.needles_saved.mean <= s.needles_saved.ci95[1]
        assert s.d90_gain_gy.mean == pytest.approx(1.5)
    lo, hi = large.needles_saved.ci95 or (0.0, 0.0)
    assert lo < 2.0 < hi  # true mean: 2 needles saved
    assert small.needles_saved.ci95 is not None and hi - lo < small.needles_saved.ci95[1] - small.needles_saved.ci95[0]
    assert large.aims_met_steered == 200
    with pytest.raises(StudyError):
        summarise_implants([{"straight": {"n_needles": 3}, "steered": {}}])


def _no_worse(arm: ImplantArm, subset: ImplantArm) -> None:
    """At every needle count of ``subset``'s curve, ``arm`` has a point with no more needles and no lower D90."""
    for q in subset.pareto:
        assert any(p.n_needles <= q.n_needles and p.hrctv_d90_eqd2_gy >= q.hrctv_d90_eqd2_gy - 1e-9
                   for p in arm.pareto), (q, arm.pareto)


def _with_lobe(case: Case, centre: tuple[float, float, float], radius: float) -> Case:
    """The case with a spherical lobe (centre, radius, mm) added to its target."""
    grid = case.planning.grid
    k, j, i = np.nonzero(np.ones(grid.shape, dtype=bool))
    p = grid.to_patient(np.column_stack([i, j, k])).reshape(*grid.shape, 3)
    lobe = np.linalg.norm(p - np.array(centre), axis=-1) <= radius
    planning = PlanningStructures(grid, Structure("HR-CTV", case.planning.target.mask | lobe), case.planning.oars)
    return Case(planning, case.organs, case.ids, case.xy, case.dist)


def test_pareto_is_monotone_with_its_gap_reported(open_case: tuple, bank: object, kernel: Tg43Kernel) -> None:
    """Two lobes 30 mm apart, the rectum near both (EMBRACE II limits): one needle is not enough; "at most n
    needles" gives D90 rising with n, no needle count twice; each budget's selection MIP reports the bound it
    proved, and its objective never rises with the budget."""
    case = _with_lobe(_case(((-5.0, 0.0, 60.0), 8.0), {"Rectum": ((-20.0, 11.0, 20.0), (30.0, 24.0, 100.0))}),
                      (25.0, 0.0, 60.0), 8.0)
    settings = replace(SETTINGS, extra_after_aims=2)
    cands = needle_candidates(case.ids, case.xy, case.dist, np.eye(4), case.planning, case.organs, RADIUS,
                              settings)
    arm = plan_implant("straight", cands, case.planning, kernel, SK, Aims(), settings)
    counts = [p.n_needles for p in arm.pareto]
    d90 = [p.hrctv_d90_eqd2_gy for p in arm.pareto]
    assert len(counts) >= 2 and counts[0] >= 1, arm.pareto  # one needle is not enough here
    assert counts == sorted(set(counts))
    assert all(b > a for a, b in itertools.pairwise(d90))
    assert arm.budgets and [b.budget for b in arm.budgets] == sorted({b.budget for b in arm.budgets})
    for prev, b in itertools.pairwise(arm.budgets):
        assert b.objective <= prev.objective * (1 + 1e-6) + 1e-12  # a budget's selection is the next one's too
    for b in arm.budgets:
        assert b.n_needles <= b.budget
        assert b.dual_bound is not None and b.dual_bound <= b.objective * (1 + 1e-6) + 1e-9
        assert b.mip_gap is not None and 0.0 <= b.mip_gap <= 1.0
    doc = arm.to_json()
    sel = doc["selection"]
    assert isinstance(sel, dict) and len(sel["budgets"]) == len(arm.budgets)  # type: ignore[arg-type]
    assert all("mip_gap" in b for b in sel["budgets"])  # type: ignore[union-attr]


def test_steered_arm_never_worse_and_ties_in_the_open(open_case: tuple) -> None:
    """The straight + steered arm holds every straight candidate (its MIP starts from the straight selection):
    in the open both arms need the same count and the steered arm's D90 is no lower."""
    _, _, straight, steered = open_case
    _no_worse(steered, straight)
    assert straight.plan is not None and steered.plan is not None
    assert steered.plan.n_needles == straight.plan.n_needles
    assert steered.plan.target.d90_eqd2_gy >= straight.plan.target.d90_eqd2_gy - 1e-9


def test_fair_arms_the_straight_arm_takes_the_steered_searchs_straight_plans(open_case: tuple) -> None:
    """A straight arm whose own search found nothing (planted: no plans) takes in every plan of the steered arm
    that holds no steered needle, and none that holds one: steering then saves no needle where straight ones do."""
    _, _, straight, steered = open_case
    blind = replace(straight, plans=(), plan=None, pareto=())
    fair = with_straight_plans(blind, steered)
    straight_only = [p for p in steered.plans if not any(c.steered for c in p.channels)]
    assert straight_only and len(fair.plans) == len(straight_only)
    assert not any(c.steered for p in fair.plans for c in p.channels)
    assert fair.plan is not None and steered.plan is not None
    if not any(c.steered for c in steered.plan.channels):  # the steered arm chose straight needles: a tie
        assert fair.plan.n_needles == steered.plan.n_needles
    assert with_straight_plans(straight, steered).plan.n_needles <= straight.plan.n_needles  # never worse


def test_steered_arm_strictly_wins_with_a_hidden_lobe(bank: object, kernel: Tg43Kernel) -> None:
    """A target in the open with a deep lateral lobe behind an organ: straight needles cover the open part only,
    steered ones reach the lobe too, so the steered arm strictly wins (meets the aims where the straight arm does
    not, or with fewer needles, or a D90 higher by over 1 Gy)."""
    case = _with_lobe(_case(((0.0, 0.0, 70.0), 8.0), {"Bowel": ((11.0, -14.0, 10.0), (26.0, 14.0, 60.0))}),
                      (17.0, 0.0, 100.0), 7.0)
    settings = replace(SETTINGS, max_needles=3)
    _, straight, steered = _arms(case, bank, kernel, settings, Aims())  # the bowel limit holds
    assert straight.plan is not None and steered.plan is not None
    _no_worse(steered, straight)
    s, t = steered.plan, straight.plan
    assert (s.aims_met and not t.aims_met) or (s.aims_met and s.n_needles < t.n_needles) \
        or s.target.d90_eqd2_gy > t.target.d90_eqd2_gy + 1.0, (steered.pareto, straight.pareto)
    assert any(c.steered for c in s.channels)


def test_arms_at_once_are_deterministic_and_never_worse(open_case: tuple, kernel: Tg43Kernel) -> None:
    """Both arms planned at once (two threads) give exactly what they give one after the other and what
    ``plan_implant`` gives (no wall-clock limit decides a selection); the steered arm merged with the straight
    one is never worse than it, and its selection at each budget never worse on the selection model; the steered
    arm's budgets stop past the straight arm's first plan that meets every aim."""
    case, cands, straight, _ = open_case
    arms = [("straight", [c for c in cands if not c.steered]), ("steered", list(cands))]
    at_once = plan_arms(arms, case.planning, kernel, SK, LOOSE, SETTINGS)
    serial = plan_arms(arms, case.planning, kernel, SK, LOOSE, SETTINGS, workers=1)
    for a, b in zip(at_once, serial, strict=True):
        assert [(x.budget, x.objective, [c.name for c in x.selected]) for x in a.budgets] == \
            [(x.budget, x.objective, [c.name for c in x.selected]) for x in b.budgets]
        assert a.pareto == b.pareto
    assert at_once[0].pareto == straight.pareto
    assert at_once[0].plan is not None and straight.plan is not None
    assert [c.name for c in at_once[0].plan.channels] == [c.name for c in straight.plan.channels]
    _no_worse(with_subset(at_once[1], at_once[0]), at_once[0])
    # the straight arm's selection at each budget starts the steered arm's search there: never worse on the model
    theirs = {b.budget: b.objective for b in at_once[0].budgets}
    both = [(b.objective, theirs[b.budget]) for b in at_once[1].budgets if b.budget in theirs]
    assert both and all(o <= t + 1e-6 * abs(t) for o, t in both), both
    # the steered arm takes in the straight arm's implants, and its budgets stop where the straight arm's first plan
    # meeting every aim would stop its own
    met = [b.budget for b in at_once[0].budgets if b.plan is not None and b.plan.aims_met]
    assert met, at_once[0].pareto
    _no_worse(at_once[1], at_once[0])
    assert max(b.budget for b in at_once[1].budgets) <= max(met[0] + SETTINGS.extra_after_aims, SETTINGS.needles or 0)



def test_a_later_arms_budgets_stop_past_the_first_arms_first_plan_meeting_every_aim() -> None:
    """An arm that takes in another arm's implants stops its budgets past that arm's first plan meeting every aim (as
    past its own, ``extra_after_aims`` later); the other arm's budgets are read once it is past them, from another
    thread too."""
    import threading
    from types import SimpleNamespace

    from reachplan.planner.implant.optimiser import DwellSolution
    from reachplan.planner.implant.plan import _budgets, _Published

    class FirstK:  # selects the first K needles at budget K, each loaded
        name = "first-k"

        def optimise(self, problem: object, *, budget: int | None = None, limit_factor: object = None,
                     start: object = ()) -> DwellSolution:
            k = int(budget or 0)
            return DwellSolution(np.arange(4) < k, "planted", 1.0 / (1 + k), None, tuple(range(k)))

    def plan(d90: float) -> SimpleNamespace:
        return SimpleNamespace(aims_met=False, target=SimpleNamespace(d90_eqd2_gy=d90))

    channels = [SimpleNamespace(name=f"N{i}", is_needle=True) for i in range(4)]

    def budgets(extra: int, their_met: object) -> list[int]:
        final = lambda chosen, status, gap: plan(80.0 + 5 * len(chosen))  # noqa: E731 - never meets the aims
        final.prob = SimpleNamespace(channels=channels, channel_of=np.arange(4))  # type: ignore[attr-defined]
        final.settings = replace(SETTINGS, max_needles=4, extra_after_aims=extra, needles=None)  # type: ignore[attr-defined]
        done, _ = _budgets(None, [0, 1, 2, 3], FirstK(), np.ones(1), 0.0, final, [], their_met=their_met)  # type: ignore[arg-type]
        return [b.budget for b in done]

    assert budgets(0, None) == [1, 2, 3, 4]  # on its own: no plan meets the aims, every budget
    first = _Published()
    threading.Timer(0.2, lambda: (first.planned(1, False), first.planned(2, True), first.close())).start()
    assert budgets(0, first.met_before) == [1, 2]  # waits for the other arm; met at 2: nothing past it
    assert budgets(1, first.met_before) == [1, 2, 3]
    assert first.met_before(2) is None and first.met_before(3) == 2
