"""Steered candidates: a bank of insertion shapes per design, matched to targets hole by hole.

For schedules of constant roll the path bends in one plane, so a shape computed at roll 0 serves every
roll: rolling the wrist by φ rotates the path about the insertion axis. For a hole and a target the best
roll is then the target's azimuth about the hole's axis, and what remains is planar: the distance from the
target's (lateral offset, depth) to each shape of the bank, minimised over the insertion depth.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from reachplan._arrays import arc_length_mm
from reachplan.planner.errors import PlanInputError
from reachplan.planner.steering.insertion import InsertionPath, ModelInfo
from reachplan.planner.steering.kinematic import KINEMATIC, KinematicInsertion
from reachplan.planner.steering.schedule import TensionSchedule
from reachplan.planner.steering.tissue_rod import TissueRodInsertion, forget_runs
from reachplan.rod_model.design import RodDesign


@dataclass(frozen=True)
class ScheduleFamily:
    """Ramp schedules ``TensionSchedule.ramp(onset, ramp, fraction × max tension)``, every combination.

    Defaults: 11 onsets (0-100 mm) × 2 ramps × 5 plateaus = 110 schedules per design (the roll is solved
    exactly for each hole and target, so it is not gridded).

    Parameters
    ----------
    onsets_mm : tuple of float, mm
        Depths beyond the template plane where the ramp starts.
    ramps_mm : tuple of float, mm
        Depths over which the tension rises.
    plateau_fractions : tuple of float
        Plateau tensions as fractions of the design's maximum tension, in (0, 1].

    Raises
    ------
    ValueError
        An empty tuple, or a fraction outside (0, 1].
    """

    onsets_mm: tuple[float, ...] = tuple(float(v) for v in range(0, 101, 10))
    ramps_mm: tuple[float, ...] = (5.0, 20.0)
    plateau_fractions: tuple[float, ...] = (0.2, 0.4, 0.6, 0.8, 1.0)

    def __post_init__(self) -> None:
        if not (self.onsets_mm and self.ramps_mm and self.plateau_fractions):
            raise ValueError("a schedule family needs at least one onset, ramp and plateau")
        if any(f <= 0 or f > 1 for f in self.plateau_fractions):
            raise ValueError("plateau fractions must be in (0, 1] of the design's maximum tension")

    def schedules(self, design: RodDesign, roll_deg: float = 0.0, reserve: float = 0.0) -> tuple[TensionSchedule, ...]:
        """Return every onset × ramp × plateau (fraction of the usable tension) ramp at ``roll_deg``.

        Parameters
        ----------
        design : RodDesign
            The stylet design; the usable tension ``(1 - reserve) × max_tension_n`` scales the plateaus.
        roll_deg : float, degrees
            Roll of every schedule, template frame.
        reserve : float
            Fraction of the design's tension limit kept in reserve, in [0, 1) (:func:`usable_tension_n`).

        Returns
        -------
        tuple of TensionSchedule
            ``len(onsets_mm) * len(ramps_mm) * len(plateau_fractions)`` schedules, onset slowest, plateau fastest.
        """
        usable = usable_tension_n(design, reserve)
        return tuple(TensionSchedule.ramp(o, r, f * usable, roll_deg)
                     for o in self.onsets_mm for r in self.ramps_mm for f in self.plateau_fractions)


def usable_tension_n(design: RodDesign, reserve: float = 0.0) -> float:
    """Return the largest tension a plan may use: the design's limit less a reserve.

    The reserve leaves room for the hand's tension error (the robustness check's ± 10 %,
    :class:`~reachplan.planner.steering.robustness.Perturbations`) without passing the stylet's limit.

    Parameters
    ----------
    design : RodDesign
        The stylet design (``max_tension_n``, N).
    reserve : float
        Fraction of ``max_tension_n`` kept in reserve, in [0, 1).

    Returns
    -------
    float, N
        ``(1 - reserve) × max_tension_n``.

    Raises
    ------
    ValueError
        ``reserve`` outside [0, 1).
    """
    if not 0.0 <= reserve < 1.0:
        raise ValueError(f"the tension reserve must be a fraction in [0, 1) of the stylet's limit, got {reserve}")
    return (1.0 - reserve) * design.max_tension_n


@dataclass(frozen=True, eq=False)
class ShapeBank:
    """Insertion shapes of one design at roll 0, in the template frame.

    Parameters
    ----------
    design : RodDesign
        The stylet design (all shapes are of it).
    schedules : tuple of TensionSchedule
        The S schedules, at roll 0.
    shapes_mm : (S, n, 3) float, mm, template frame
        Row ``i`` of shape ``k`` is the tip after ``i * step_mm`` of insertion from the hole at the origin along
        +z (tip-following models: the path to a shallower depth is a prefix of the deeper one).
    step_mm : float, mm
        Insertion depth between rows.
    model : ModelInfo
        The insertion model that computed the shapes.
    """

    design: RodDesign
    schedules: tuple[TensionSchedule, ...]
    shapes_mm: np.ndarray
    step_mm: float
    model: ModelInfo


@lru_cache(maxsize=32)
def shape_bank(design: RodDesign, family: ScheduleFamily = ScheduleFamily(), depth_mm: float = 200.0,
               model: KinematicInsertion = KINEMATIC, reserve: float = 0.0) -> ShapeBank:
    """Compute (and cache) the shapes of ``family`` for ``design`` up to ``depth_mm``, a tension reserve kept.

    Parameters
    ----------
    design : RodDesign
        The stylet design.
    family : ScheduleFamily
        The schedules to insert.
    depth_mm : float, mm
        Deepest insertion (capped at the design's length).
    model : KinematicInsertion
        The fast insertion model.
    reserve : float
        Fraction of the design's tension limit no schedule uses (:meth:`ScheduleFamily.schedules`).

    Returns
    -------
    ShapeBank
        The shapes at roll 0, template frame.
    """
    schedules = family.schedules(design, reserve=reserve)
    depth = min(depth_mm, design.length_mm)
    shapes = model.insert_array(design, schedules, depth)
    return ShapeBank(design, schedules, shapes, depth / (shapes.shape[1] - 1), model.info)


@dataclass(frozen=True)
class Match:
    """Best schedules of a bank for one hole and target (template frame quantities).

    Parameters
    ----------
    order : (K,) int
        Indices into the bank's schedules, best first.
    depth_mm : (K,) float, mm
        Insertion depth of each where its path passes closest to the target.
    reach_mm : (K,) float, mm
        Distance from that point of the path to the target.
    roll_deg : float, degrees
        The roll that aims the bend at the target (template frame, 0 = template +x).
    """

    order: np.ndarray
    depth_mm: np.ndarray
    reach_mm: np.ndarray
    roll_deg: float


def _planar(rel_mm: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(lateral offset ρ, depth ζ, roll φ in degrees) of target offsets ``rel_mm`` (H, 3) from holes."""
    rho = np.hypot(rel_mm[:, 0], rel_mm[:, 1])
    return rho, rel_mm[:, 2], np.degrees(np.arctan2(rel_mm[:, 1], rel_mm[:, 0]))


def match_targets(bank: ShapeBank, rel_mm: np.ndarray, keep: int = 8) -> list[Match]:
    """For each hole, the ``keep`` schedules whose tips pass closest to the target.

    The distance of the target to each shape is minimised over the insertion depth, projecting onto the
    shape's segments (so it does not depend on the sampling step).

    Parameters
    ----------
    bank : ShapeBank
        The shapes of one design.
    rel_mm : (H, 3) float, mm, template frame
        Target minus hole entry, one row per hole.
    keep : int
        Number of schedules kept per hole.

    Returns
    -------
    list of Match
        One per hole, in the rows' order.
    """
    rho, zeta, roll = _planar(np.asarray(rel_mm, float))
    xz = bank.shapes_mm[:, :, [0, 2]]  # (S, n, 2)
    a, b = xz[:, :-1], xz[:, 1:]  # segments (S, n-1, 2)
    ab = b - a
    len2 = np.maximum(np.sum(ab * ab, axis=-1), 1e-18)
    out: list[Match] = []
    for h in range(len(rho)):
        p = np.array([rho[h], zeta[h]])
        t = np.clip(np.sum((p - a) * ab, axis=-1) / len2, 0.0, 1.0)  # (S, n-1)
        d = np.linalg.norm(a + t[..., None] * ab - p, axis=-1)
        seg = np.argmin(d, axis=1)
        best = d[np.arange(len(d)), seg]
        order = np.lexsort((np.arange(len(best)), np.round(best, 6)))[:keep]
        depth = (seg[order] + t[order, seg[order]]) * bank.step_mm
        out.append(Match(order, depth, best[order], float(roll[h])))
    return out


def place(shape_mm: np.ndarray, step_mm: float, depth_mm: float, roll_deg: float, entry_xy_mm: np.ndarray,
          patient_from_template: np.ndarray, sample_mm: float = 5.0) -> np.ndarray:
    """Cut a bank shape at ``depth_mm``, roll it by ``roll_deg`` and put it at a hole, in the patient.

    Parameters
    ----------
    shape_mm : (n, 3) float, mm, template frame
        One shape of a :class:`ShapeBank` (hole at the origin, roll 0).
    step_mm : float, mm
        Insertion depth between the shape's rows.
    depth_mm : float, mm
        Insertion depth to cut at.
    roll_deg : float, degrees
        Roll about the hole's axis (template frame).
    entry_xy_mm : (2,) float, mm, template frame
        The hole's position in the template plane.
    patient_from_template : (4, 4) float
        Template frame (mm) to patient LPS (mm).
    sample_mm : float, mm
        Approximate spacing of the returned points.

    Returns
    -------
    (m, 3) float, mm, LPS
        Points about ``sample_mm`` apart from the hole to the tip (the tip exact).
    """
    n_full = int(np.floor(depth_mm / step_mm + 1e-9))
    prefix = shape_mm[: n_full + 1]
    frac = depth_mm / step_mm - n_full
    if frac > 1e-9 and n_full + 1 < len(shape_mm):
        prefix = np.vstack([prefix, shape_mm[n_full] + frac * (shape_mm[n_full + 1] - shape_mm[n_full])])
    every = max(1, round(sample_mm / step_mm))
    idx = np.unique(np.r_[np.arange(0, len(prefix), every), len(prefix) - 1])
    pts = prefix[idx]
    c, s = np.cos(np.radians(roll_deg)), np.sin(np.radians(roll_deg))
    rot = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    local = pts @ rot.T + np.array([entry_xy_mm[0], entry_xy_mm[1], 0.0])
    m = np.asarray(patient_from_template, float)
    return local @ m[:3, :3].T + m[:3, 3]


def _key(values: np.ndarray) -> tuple[float, ...]:
    """Values rounded to 1e-6, as a hashable key."""
    return tuple(round(float(v), 6) for v in np.asarray(values).ravel())


@lru_cache(maxsize=256)
def _insert(model: TissueRodInsertion, design: RodDesign, schedule: tuple[tuple[float, ...], ...], depth_mm: float,
            profile: tuple[tuple[float, ...], ...] | None, sample_mm: float) -> np.ndarray | str:
    """One insertion by ``model`` resampled every ~``sample_mm`` of arc length (read-only), or why it failed.

    Cached: mirror-image candidates (the same schedule at roll 0 from holes symmetric about the target's plane)
    and the candidates of targets planned twice cost one solve.
    """
    prof = None if profile is None else (np.array(profile[0]), np.array(profile[1]))
    positions = model.insert_one(design, TensionSchedule(*map(np.array, schedule)), depth_mm, prof)
    if not isinstance(positions, np.ndarray):
        return f"{model.name} failed {positions.reason}"
    if not np.all(np.isfinite(positions)):
        return f"{model.name} failed: the predicted shape is not finite"
    arc = arc_length_mm(positions)
    even = np.linspace(0.0, arc[-1], max(2, round(depth_mm / sample_mm)) + 1)
    out = np.column_stack([np.interp(even, arc, positions[:, i]) for i in range(3)])
    out.setflags(write=False)
    return out


def forget_insertions() -> None:
    """Empty the memos of in-tissue insertions (:func:`insert_memo` and the rod's runs): a benchmark's cold start."""
    _insert.cache_clear()
    forget_runs()


def insert_memo(model: TissueRodInsertion, design: RodDesign, schedule: TensionSchedule, depth_mm: float,
                modulus_profile: tuple[np.ndarray, np.ndarray] | None = None,
                sample_mm: float = 1.0) -> np.ndarray | str:
    """Insert one schedule with a rod insertion model, memoised on its values rounded to 1e-6 (mm, N, deg, Pa).

    Mirror-image candidates agree to rounding, not to the last bit, and so share a solve.

    Parameters
    ----------
    model : TissueRodInsertion
        The in-tissue rod model.
    design : RodDesign
        The stylet design.
    schedule : TensionSchedule
        Tension (N) and roll (deg) against depth (mm).
    depth_mm : float, mm
        Insertion depth.
    modulus_profile : tuple of ((p,) float, (p,) float) or None
        ``(depth_mm, modulus_pa)`` along the insertion (:meth:`TissueRodInsertion.insert_one`); None: the model's.
    sample_mm : float, mm
        Arc-length spacing of the returned path.

    Returns
    -------
    (m + 1, 3) float ndarray or str
        The centreline (mm, template frame, read-only), ``m = max(2, round(depth_mm / sample_mm))`` equal arc-length
        steps, hole first; or why the model failed.
    """
    key = tuple(_key(a) for a in (schedule.depth_mm, schedule.tension_n, schedule.roll_deg))
    profile = None if modulus_profile is None else tuple(_key(a) for a in modulus_profile)
    return _insert(model, design, key, round(float(depth_mm), 6), profile, float(sample_mm))


def refine_with(model: TissueRodInsertion, design: RodDesign, schedule: TensionSchedule, depth_mm: float,
                rel_mm: np.ndarray, fast: KinematicInsertion = KINEMATIC, iterations: int = 3,
                modulus_profile: tuple[np.ndarray, np.ndarray] | None = None, sample_mm: float = 1.0,
                tolerance_mm: float = 0.25, max_tension_n: float | None = None,
                ) -> tuple[TensionSchedule, InsertionPath]:
    """Re-solve a screened candidate with a richer insertion model and correct its aim.

    Space mapping: the richer model's tip departs from the fast model's by δ; the fast model is re-aimed at
    ``target − δ`` (new plateau tension by a 1-D search over the same ramp, the roll kept), and the richer
    model re-solves, at most ``iterations`` times, until its tip is within ``tolerance_mm`` of the target (or the
    plateau changes by less than 0.01 N: e.g. at the stylet's limit). The in-tissue rod and the kinematic model
    differ by a few millimetres, by more at higher tension: one iteration left 1.2 mm of miss on the clinical
    case's Target_param_L, the loop 0.17 mm. The closest of the solves is returned; repeated solves of one
    schedule are memoised.

    Parameters
    ----------
    model : TissueRodInsertion
        The richer insertion model.
    design : RodDesign
        The stylet design.
    schedule : TensionSchedule
        The screened candidate's schedule (roll 0).
    depth_mm : float, mm
        Insertion depth.
    rel_mm : (3,) float, mm, template frame
        Target minus hole entry.
    fast : KinematicInsertion
        The fast model that is re-aimed.
    iterations : int
        Most corrections.
    modulus_profile : tuple of ((p,) float, (p,) float) or None
        ``(depth_mm, modulus_pa)``: the tissue modulus (Pa) along the insertion, piecewise constant from each
        depth (mm) on (per organ), passed to :meth:`TissueRodInsertion.insert_one`; None: the model's own modulus.
    sample_mm : float, mm
        Arc-length spacing of the returned path.
    tolerance_mm : float, mm
        Stop once the richer model's tip is this close to the target.
    max_tension_n : float or None, N
        Highest plateau the re-aim may use (the design's limit less the plan's reserve, :func:`usable_tension_n`);
        None: the design's limit.

    Returns
    -------
    schedule : TensionSchedule
        The schedule whose path ends closest to the target (roll 0).
    path : InsertionPath
        The richer model's centreline, mm, template frame (hole at the origin, roll 0; the caller rolls and
        places it), resampled every ``depth_mm / round(depth_mm / sample_mm)`` mm of arc length (tip exact).

    Raises
    ------
    PlanInputError
        The richer model fails (its reason), or its shape is not finite.
    """
    from scipy.optimize import minimize_scalar

    target = np.array([np.hypot(rel_mm[0], rel_mm[1]), 0.0, rel_mm[2]])
    aim = target.copy()
    top = design.max_tension_n if max_tension_n is None else min(max_tension_n, design.max_tension_n)
    sch = schedule
    label = model.info

    def solve(s: TensionSchedule) -> InsertionPath:
        positions = insert_memo(model, design, s, depth_mm, modulus_profile, sample_mm)
        if isinstance(positions, str):
            raise PlanInputError(positions)
        return InsertionPath(positions, depth_mm, label)

    res = solve(sch)
    best_sch, best_res = sch, res
    for _ in range(iterations):
        if np.linalg.norm(res.positions_mm[-1] - target) <= tolerance_mm:
            break
        aim = aim + (target - res.positions_mm[-1])  # correct the aim by the richer model's miss
        d, r = sch.depth_mm, sch.roll_deg
        unit = sch.tension_n / max(sch.peak_tension_n, 1e-12)  # the schedule's shape, plateau 1 N

        def miss(t: float, d: np.ndarray = d, r: np.ndarray = r, unit: np.ndarray = unit,
                 aim: np.ndarray = aim) -> float:
            tip = fast.insert_array(design, [TensionSchedule(d, unit * t, r)], depth_mm)[0, -1]
            return float(np.linalg.norm(tip - aim))

        plateau = minimize_scalar(miss, bounds=(0.0, top), method="bounded",
                                  options={"xatol": 1e-3})
        if abs(float(plateau.x) - sch.peak_tension_n) < 0.01:  # N: no change worth a solve (e.g. at the limit)
            break
        sch = TensionSchedule(d, unit * float(plateau.x), r)
        res = solve(sch)
        if np.linalg.norm(res.positions_mm[-1] - target) < np.linalg.norm(best_res.positions_mm[-1] - target):
            best_sch, best_res = sch, res
    return best_sch, best_res


def reach_radius_mm(bank: ShapeBank, depths_mm: np.ndarray) -> np.ndarray:
    """Return the largest lateral offset (mm) a hole reaches at each depth (mm along its axis).

    Over the bank's schedules and all rolls: the reachable workspace at that depth is a disk of this radius about
    the hole's axis (organs not considered).

    Parameters
    ----------
    bank : ShapeBank
        The shapes of one design.
    depths_mm : (k,) float, mm
        Depths along the hole's axis (template z).

    Returns
    -------
    (k,) float, mm
        The radius at each depth (0 where no shape gets that deep).
    """
    xz = bank.shapes_mm[:, :, [0, 2]]
    out = np.zeros(len(depths_mm))
    for i, z in enumerate(np.asarray(depths_mm, float)):
        below, above = xz[:, :-1], xz[:, 1:]
        cross = (below[..., 1] <= z) & (above[..., 1] > z)
        t = (z - below[..., 1]) / np.maximum(above[..., 1] - below[..., 1], 1e-12)
        x = below[..., 0] + t * (above[..., 0] - below[..., 0])
        out[i] = float(np.max(np.where(cross, x, 0.0)))
    return out
