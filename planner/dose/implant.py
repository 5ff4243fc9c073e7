"""Implant planning: the needle set and the dwell times that cover the HR-CTV, chosen together.

Candidates (:func:`needle_candidates`): every template hole × (straight, and every stylet design × tension
schedule of the shape bank × roll) whose path passes through the HR-CTV and keeps ``clearance_margin_mm``
from every organ at risk. Paths are screened on Euclidean distance maps of the planning grid (target grown by
the dwell margin; organs at risk), and the kept ones are confirmed with the FCL clearance of
:func:`reachplan.planner.geometry.collision.check_path`. Intracavitary channels (tandem, ring, ovoids) are
passed in as :class:`Channel` objects of kind ``"intracavitary"``; they are always available and not counted
as needles. Dwell positions are every ``dwell_step_mm`` along the part of each channel inside the HR-CTV grown
by ``dwell_margin_mm``.

Choice of needles and dwell times (:func:`plan_implant`), for each needle budget K = 1, 2, ... (K = 0 too when
an intracavitary channel is given):

1. **Needle selection: a greedy heuristic with a bound**, on a restricted model: each channel's dwells grouped in
   at most ``segments_per_channel`` consecutive blocks of equal dwell time ``τ_s`` (a piecewise-constant,
   modulation-restricted loading); target points ``A τ + u >= P`` (``u`` underdose, ``P`` the per-fraction
   dose that brings D90 to its aim, plus ``coverage_margin``); organ points ``A τ <= L`` (per point, which implies
   D2cm³ <= L); neighbouring blocks within ``neighbour_ratio``; no block's dwell over ``max_dwell_share`` of the
   total. Objective: mean underdose (in units of the prescription) + a small weight on the mean target dose
   (shorter plans) + ``invasiveness_weight`` × each used needle's normalised hole distance and tissue length (the
   "least invasive" tie-break). Budget K's set is budget K-1's plus the needle whose exact block loading (an LP)
   lowers the objective most, among the ``greedy_candidates`` needles that could fill most of the current
   underdose within their organ caps; one needle per template hole. **Bound:** the mixed-integer model of the
   same selection (binary ``y_n`` per needle, ``τ_s <= M_s y_n``, ``Σ y_n <= K``, HiGHS through
   ``scipy.optimize.milp``) has an LP relaxation whose optimum bounds every K-needle selection from below; it is
   solved for the chosen budget and the relative gap reported (``ImplantPlan.mip_gap``; with
   ``mip_time_limit_s`` > 0 HiGHS's branch and bound also runs and its dual bound tightens it). The big-M
   relaxation is weak: the gap is an honest but loose bound, typically 0.5-0.95 of an objective that is itself
   small when the aims are met.
2. **Dwell times on the chosen needles: a linear programme** over every dwell (no blocks) with the same
   target and organ rows, neighbouring dwells on a channel within ``neighbour_ratio`` (as IPSA's dwell-time
   deviation constraint / HIPO's dwell-time gradient restriction, Mosleh-Shirazi et al., J Contemp Brachytherapy
   11(3), 2019) and no dwell above ``max_dwell_share`` of the total; the hottest 2 cm³ of each organ are then
   released from the point constraints and the LP solved again (D2cm³ is not linear). Dwells under
   ``min_dwell_time_s`` are dropped; the plan is checked on every organ voxel near the implant and all times are
   scaled down when a D2cm³ still exceeds its limit. A needle left with (almost) no time is not part of the
   implant: it is dropped and the rest re-solved.

The needle count against HR-CTV D90 with the organ limits held is the arm's Pareto curve; the plan chosen is
the one with the fewest needles that meets every aim (HR-CTV D90 and D98, GTV D98 when a GTV is given, organ
D2cm³), else the one with the highest D90. The curve stops ``extra_after_aims`` budgets after the first that
meets the aims, when no needle can be added, or after three budgets without a D90 gain of 0.1 Gy. The final
metrics of the target are computed on 3 × 3 × 3 sub-voxels (:data:`SUPERSAMPLE`).

Aims (EQD2, α/β 10 tumour / 3 organs, 45 Gy / 25 fractions external beam + 4 fractions): EMBRACE II
(Pötter et al., Clin Transl Radiat Oncol 9:48, 2018) and the ESGO/ESTRO achievability table (90 % of
patients: HR-CTV D90 > 85, D98 > 75, GTV D98 > 90 Gy), as :class:`reachplan.planner.dose.optimize.Aims`.
"""

from __future__ import annotations

import dataclasses
import itertools
import math
import time
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from scipy import ndimage, sparse
from scipy import optimize as sopt
from scipy.spatial import cKDTree

from reachplan._arrays import arc_length_mm
from reachplan.imaging.types import Grid
from reachplan.planner.dose.coverage import (
    Dvh,
    StructureMetrics,
    cumulative_dvh,
    dose_to_volume,
    structure_metrics,
    voxel_volume_cc,
)
from reachplan.planner.dose.optimize import Aims, PlanningStructures, Structure
from reachplan.planner.dose.tg43 import (
    DwellSet,
    Tg43Kernel,
    dose_on_grid,
    dwell_directions,
    grid_points_mm,
)
from reachplan.planner.geometry.collision import Organ, check_path
from reachplan.planner.steering.schedule import TensionSchedule
from reachplan.planner.steering.steered import ShapeBank, place

NEEDLE_KINDS = ("straight", "steered")


@dataclass(frozen=True)
class ImplantSettings:
    """Settings of implant planning (lengths mm, times s).

    Parameters
    ----------
    dwell_step_mm : distance between dwell positions along a channel.
    dwell_margin_mm : dwells lie on the part of a channel inside the HR-CTV grown by this margin.
    tip_offset_mm : distance from the needle tip to its deepest dwell (the tip lies this far beyond the last
        dwell position).
    clearance_margin_mm : smallest surface distance from a needle to any organ at risk.
    min_dwells : a needle needs at least this many dwell positions to be a candidate.
    neighbour_ratio : neighbouring dwell times on a channel differ by at most this factor (>= 1).
    max_dwell_share : no single dwell carries more than this share of the plan's total time.
    steered_per_hole : steered candidates kept per hole and design (the most dwells, spread apart).
    rolls : roll angles screened per hole (evenly over 360°).
    max_needles : largest needle budget on the Pareto curve.
    extra_after_aims : Pareto points computed beyond the first budget that meets every aim.
    coverage_margin : the LP aims target points at (1 + this) × the D90 prescription.
    mip_time_limit_s, mip_rel_gap : HiGHS limits of the optional branch and bound run for the bound (0: the LP
        relaxation only).
    selection_target_points, selection_oar_points : points of the restricted selection model (target; per
        organ, those nearest to the candidate dwells).
    final_target_points, final_oar_points : the same for the dwell-time LP on the chosen needles.
    segments_per_channel : dwell blocks per channel in the selection model.
    invasiveness_weight : weight of the needles' invasiveness in the selection objective (a tie-break).
    time_weight : weight of the mean target dose (shorter plans) in both objectives.
    greedy_candidates : needles whose exact loading is tried at each greedy step.
    bound : compute the LP-relaxation bound (and gap) of the chosen budget.
    min_dwell_time_s : dwell times below this are set to zero (afterloaders do not deliver shorter dwells).
    oar_eval_radius_mm : organ voxels within this distance of a loaded dwell are evaluated for D2cm³.
    """

    dwell_step_mm: float = 2.5
    dwell_margin_mm: float = 2.5
    tip_offset_mm: float = 1.0
    clearance_margin_mm: float = 2.0
    min_dwells: int = 3
    neighbour_ratio: float = 2.0
    max_dwell_share: float = 0.15
    steered_per_hole: int = 2
    rolls: int = 8
    max_needles: int = 16
    extra_after_aims: int = 1
    coverage_margin: float = 0.03
    mip_time_limit_s: float = 0.0
    mip_rel_gap: float = 0.02
    selection_target_points: int = 300
    selection_oar_points: int = 100
    final_target_points: int = 2000
    final_oar_points: int = 600
    segments_per_channel: int = 2
    invasiveness_weight: float = 1e-3
    time_weight: float = 1e-3
    min_dwell_time_s: float = 0.1
    greedy_candidates: int = 6
    bound: bool = True
    oar_eval_radius_mm: float = 40.0

    def __post_init__(self) -> None:
        if not (self.dwell_step_mm > 0 and self.dwell_margin_mm >= 0 and self.tip_offset_mm >= 0
                and self.clearance_margin_mm >= 0):
            raise ValueError("dwell step must be > 0 mm; margins and tip offset >= 0 mm")
        if self.neighbour_ratio < 1 or not 0 < self.max_dwell_share <= 1:
            raise ValueError("neighbour_ratio must be >= 1 and max_dwell_share in (0, 1]")
        if min(self.min_dwells, self.max_needles, self.rolls, self.segments_per_channel,
               self.selection_target_points, self.selection_oar_points, self.final_target_points,
               self.final_oar_points) < 1 or self.steered_per_hole < 0 or self.extra_after_aims < 0:
            raise ValueError("implant settings: counts must be >= 1 (steered_per_hole, extra_after_aims >= 0)")


@dataclass(frozen=True, eq=False)
class Channel:
    """A candidate source channel: a needle (straight or steered) or an intracavitary channel.

    Parameters
    ----------
    name : hole id (needles) or applicator channel name.
    kind : ``"straight"``, ``"steered"`` or ``"intracavitary"``.
    path_mm : (k, 3) float, mm, LPS, from the template (base) to the tip.
    dwell_positions_mm : (d, 3) float, mm, LPS, deepest first.
    hole_distance_mm : distance of the hole from the template centre (0 for intracavitary channels).
    tissue_length_mm : needle length beyond the template plane.
    clearance_mm : smallest surface distance to an organ at risk (FCL).
    design : stylet preset ("" for a straight needle).
    schedule : tension and roll along the insertion (None for a straight needle).
    """

    name: str
    kind: str
    path_mm: np.ndarray = field(repr=False)
    dwell_positions_mm: np.ndarray = field(repr=False)
    hole_distance_mm: float = 0.0
    tissue_length_mm: float = 0.0
    clearance_mm: float = float("inf")
    design: str = ""
    schedule: TensionSchedule | None = field(default=None, repr=False)

    @property
    def is_needle(self) -> bool:
        """True for a template needle (not an intracavitary channel)."""
        return self.kind in NEEDLE_KINDS

    @property
    def steered(self) -> bool:
        """True for a steered needle."""
        return self.kind == "steered"

    @property
    def dwell_directions(self) -> np.ndarray:
        """(d, 3) unit vectors toward the tip at each dwell."""
        return dwell_directions(self.path_mm, self.dwell_positions_mm)


# --- candidates ---------------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class _Field:
    """A distance map (mm) on a crop of the planning grid; points outside the crop read ``outside``."""

    index_from_patient: np.ndarray
    offset: np.ndarray  # (3,) int, (k, j, i) of the crop's first voxel
    values: np.ndarray  # (nk, nj, ni) float
    outside: float

    def index(self, points_mm: np.ndarray) -> np.ndarray:
        """(..., 3) int (k, j, i) voxel of each point on the full grid (shared by fields of one grid)."""
        p = np.asarray(points_mm, dtype=np.float32)
        a = self.index_from_patient.astype(np.float32)
        return np.rint(p @ a[:3, :3].T + a[:3, 3]).astype(np.int32)[..., ::-1]

    def at(self, points_mm: np.ndarray, kji: np.ndarray | None = None) -> np.ndarray:
        """Distance (mm) at each point ((..., 3) mm, LPS; or its voxel ``kji`` from :meth:`index`)."""
        kji = (self.index(points_mm) if kji is None else kji) - self.offset
        shape = np.array(self.values.shape)
        ok = np.all((kji >= 0) & (kji < shape), axis=-1)
        kc = np.where(ok[..., None], kji, 0)
        out: np.ndarray = np.where(ok, self.values[kc[..., 0], kc[..., 1], kc[..., 2]], self.outside)
        return out


def _distance_field(grid: Grid, mask: np.ndarray, pad_mm: float, box_mask: np.ndarray | None = None) -> _Field:
    """Return the distance (mm) from each voxel centre to the nearest voxel of ``mask`` (0 inside).

    On the crop holding ``box_mask`` (default ``mask``) padded by ``pad_mm``.
    """
    spacing = grid.spacing_mm[::-1]  # (k, j, i)
    box = mask if box_mask is None else box_mask
    idx = np.argwhere(box)
    if len(idx) == 0:
        return _Field(grid.index_from_patient, np.zeros(3, int), np.full((1, 1, 1), np.inf), np.inf)
    pad = np.ceil(pad_mm / spacing).astype(int) + 1
    lo = np.maximum(idx.min(axis=0) - pad, 0)
    hi = np.minimum(idx.max(axis=0) + pad + 1, np.array(grid.shape))
    crop = mask[lo[0]:hi[0], lo[1]:hi[1], lo[2]:hi[2]]
    values = ndimage.distance_transform_edt(~crop, sampling=spacing) if crop.any() else np.full(crop.shape, np.inf)
    return _Field(grid.index_from_patient, lo, np.asarray(values, dtype=float), np.inf)


def _dwell_arclengths(inside: np.ndarray, s_mm: np.ndarray, settings: ImplantSettings) -> tuple[float, np.ndarray]:
    """Return the tip depth and the dwell arc lengths (mm, deepest first) of a path in a region.

    The path is sampled at ``s_mm`` with region membership ``inside``; (nan, empty) when it never enters the
    region.
    """
    hit = np.flatnonzero(inside)
    if len(hit) == 0:
        return float("nan"), np.zeros(0)
    last = float(s_mm[hit[-1]])
    tip = min(last + settings.tip_offset_mm, float(s_mm[-1]))
    s = last - settings.dwell_step_mm * np.arange(int(last // settings.dwell_step_mm) + 1)
    ok = np.interp(s, s_mm, inside.astype(float)) > 0.5
    first = float(s_mm[hit[0]])
    s = s[ok & (s >= first - 1e-9)]
    return tip, s


def _points_at(path_mm: np.ndarray, s_query: np.ndarray) -> np.ndarray:
    s = arc_length_mm(path_mm)
    return np.column_stack([np.interp(s_query, s, path_mm[:, a]) for a in range(3)])


def needle_candidates(
    hole_ids: Sequence[str],
    hole_xy_mm: np.ndarray,
    hole_distance_mm: np.ndarray,
    patient_from_template: np.ndarray,
    planning: PlanningStructures,
    organs: Sequence[Organ],
    needle_radius_mm: float,
    settings: ImplantSettings | None = None,
    banks: Sequence[ShapeBank] = (),
    max_depth_mm: float = 200.0,
    straight: bool = True,
) -> tuple[Channel, ...]:
    """Candidate needles through the HR-CTV that keep the clearance margin to every organ at risk.

    Parameters
    ----------
    hole_ids : the template's needle holes.
    hole_xy_mm : (H, 2) float, mm, template frame.
    hole_distance_mm : (H,) float, mm from the template centre.
    patient_from_template : (4, 4) float, template frame to LPS mm.
    planning : the target and organ masks (the organ masks give the screening distance map).
    organs : organ meshes for the exact (FCL) clearance of the kept candidates.
    banks : steered shape banks (one per stylet design; none: straight needles only).
    straight : include straight needles.

    Returns
    -------
    Channels of kind ``"straight"`` and ``"steered"``, each with at least ``settings.min_dwells`` dwells.
    """
    settings = settings or ImplantSettings()
    grid = planning.grid
    m = np.asarray(patient_from_template, dtype=float)
    xy = np.asarray(hole_xy_mm, dtype=float).reshape(-1, 2)
    region = _distance_field(grid, planning.target.mask, settings.dwell_margin_mm + 5.0)
    in_region = settings.dwell_margin_mm + 1e-6
    oar_mask = np.zeros(grid.shape, dtype=bool)
    for o in planning.oars:
        oar_mask |= o.mask
    # the organ map covers everything between the template and the target: the crop holds the target and
    # the holes' entries, padded by the steering reach
    entries = np.column_stack([xy, np.zeros(len(xy))]) @ m[:3, :3].T + m[:3, 3]
    box = planning.target.mask.copy()
    ijk = np.rint(grid.to_index(entries)).astype(int)[:, ::-1]
    ijk = np.clip(ijk, 0, np.array(grid.shape) - 1)
    box[ijk[:, 0], ijk[:, 1], ijk[:, 2]] = True
    oar = _distance_field(grid, oar_mask, 30.0, box)
    # screening threshold: the margin plus the needle radius, less half a voxel diagonal (the map is voxel-
    # centred); the FCL check then holds the exact margin
    slack = 0.5 * float(np.linalg.norm(grid.spacing_mm))
    oar_min = settings.clearance_margin_mm + needle_radius_mm - slack
    out: list[Channel] = []
    s_axis = np.arange(0.0, max_depth_mm + 1e-9, 1.0)
    axis = m[:3, 2] / np.linalg.norm(m[:3, 2])

    def confirm(path: np.ndarray) -> float | None:
        checks = check_path(path, needle_radius_mm, tuple(organs)) if organs else ()
        clearance = min((c.clearance_mm for c in checks), default=float("inf"))
        if any(c.collides for c in checks) or clearance < settings.clearance_margin_mm:
            return None
        return clearance

    for h, hole in enumerate(hole_ids):
        if not straight:
            break
        pts = entries[h] + np.outer(s_axis, axis)
        inside = region.at(pts) <= in_region
        tip, s_dw = _dwell_arclengths(inside, s_axis, settings)
        if len(s_dw) < settings.min_dwells:
            continue
        if np.min(oar.at(pts[s_axis <= tip])) < oar_min:
            continue
        path = entries[h] + np.outer([0.0, tip], axis)
        clearance = confirm(path)
        if clearance is None:
            continue
        out.append(Channel(hole, "straight", path, entries[h] + np.outer(s_dw, axis), float(hole_distance_mm[h]),
                           tip, clearance))
    for bank in banks:
        out += _steered(bank, hole_ids, xy, hole_distance_mm, m, region, in_region, oar, oar_min, settings,
                        confirm, straight_channels=[c for c in out if c.kind == "straight"])
    return tuple(out)


def _steered(bank: ShapeBank, hole_ids: Sequence[str], xy: np.ndarray, hole_distance_mm: np.ndarray,
             m: np.ndarray, region: _Field, in_region: float, oar: _Field, oar_min: float,
             settings: ImplantSettings, confirm: object, straight_channels: list[Channel]) -> list[Channel]:
    """Steered candidates of one design.

    Per hole, the schedules × rolls that pass through the target region and clear the organs on the distance map, up
    to ``steered_per_hole`` of them, spread apart; each confirmed with FCL.
    """
    assert callable(confirm)
    shapes = bank.shapes_mm  # (S, n, 3), template frame, roll 0, hole at the origin
    lateral = np.hypot(shapes[:, -1, 0], shapes[:, -1, 1])
    bent = np.flatnonzero(lateral > 3.0)  # shapes within 3 mm of the axis are straight needles in all but name
    every = max(1, round(2.0 / bank.step_mm))  # screen on points about 2 mm apart
    coarse = shapes[bent][:, ::every]
    s_coarse = np.arange(coarse.shape[1]) * bank.step_mm * every
    per_dwell = settings.dwell_step_mm / (bank.step_mm * every)
    rolls = np.arange(settings.rolls) * 360.0 / settings.rolls
    by_hole = {c.name: c for c in straight_channels}
    out: list[Channel] = []
    for h, hole in enumerate(hole_ids):
        found = []  # (approximate dwell count, peak tension, shape index, roll, centroid)
        for roll in rolls:
            c, s = math.cos(math.radians(roll)), math.sin(math.radians(roll))
            rot = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
            local = coarse @ rot.T + np.array([xy[h, 0], xy[h, 1], 0.0])
            pts = local @ m[:3, :3].T + m[:3, 3]  # (S', n, 3) LPS
            kji = region.index(pts)
            inside = region.at(pts, kji) <= in_region
            n_in = inside.sum(axis=1)
            rows = np.flatnonzero(n_in / per_dwell >= settings.min_dwells)
            if len(rows) == 0:
                continue
            last = inside.shape[1] - 1 - np.argmax(inside[rows, ::-1], axis=1)
            tip_idx = np.minimum(last + math.ceil(settings.tip_offset_mm / (bank.step_mm * every)),
                                 inside.shape[1] - 1)
            clear = np.minimum.accumulate(oar.at(pts[rows], kji[rows]), axis=1)[np.arange(len(rows)), tip_idx]
            ok = clear >= oar_min
            centroids = (inside[rows][..., None] * pts[rows]).sum(axis=1) / n_in[rows][:, None]
            for r in np.flatnonzero(ok):
                k = int(bent[rows[r]])
                found.append((float(n_in[rows[r]]), bank.schedules[k].peak_tension_n, k, float(roll), centroids[r]))
        found.sort(key=lambda f: (-f[0], f[1], f[2], f[3]))
        kept: list[np.ndarray] = []
        if hole in by_hole:
            kept.append(by_hole[hole].dwell_positions_mm.mean(axis=0))
        n_kept = 0
        for _, _, k, roll, centroid in found:
            if n_kept >= settings.steered_per_hole:
                break
            if any(np.linalg.norm(centroid - q) < 4 * settings.dwell_step_mm for q in kept):
                continue
            full = place(shapes[k], bank.step_mm, float(s_coarse[-1]), roll, xy[h], m, sample_mm=bank.step_mm)
            s_full = arc_length_mm(full)
            tip, s_dw = _dwell_arclengths(region.at(full) <= in_region, s_full, settings)
            if len(s_dw) < settings.min_dwells:
                continue
            path = place(shapes[k], bank.step_mm, tip, roll, xy[h], m)
            clearance = confirm(path)
            if clearance is None:
                continue
            base = bank.schedules[k]
            sched = TensionSchedule(base.depth_mm, base.tension_n, np.full(len(base.depth_mm), roll))
            out.append(Channel(hole, "steered", path, _points_at(full, s_dw), float(hole_distance_mm[h]), tip,
                               clearance, bank.design.name, sched))
            kept.append(centroid)
            n_kept += 1
    return out


def intracavitary_channel(name: str, path_mm: np.ndarray, planning: PlanningStructures,
                          settings: ImplantSettings | None = None) -> Channel | None:
    """Return an applicator channel with dwells where it lies in the target grown by the dwell margin.

    ``path_mm``: tandem, ring or ovoid, (k, 3) mm LPS, base to tip. None when it has fewer than ``min_dwells``
    there.
    """
    settings = settings or ImplantSettings()
    p = np.asarray(path_mm, dtype=float)
    s_path = arc_length_mm(p)
    s = np.arange(0.0, s_path[-1] + 1e-9, 0.5)
    pts = _points_at(p, s)
    region = _distance_field(planning.grid, planning.target.mask, settings.dwell_margin_mm + 5.0)
    _, s_dw = _dwell_arclengths(region.at(pts) <= settings.dwell_margin_mm + 1e-6, s, settings)
    if len(s_dw) < settings.min_dwells:
        return None
    return Channel(name, "intracavitary", p, _points_at(p, s_dw))


# --- optimisation -------------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class ImplantPlan:
    """One implant: its loaded channels, dwell times (per fraction) and metrics (EQD2 totals in the metrics).

    ``dwells.channels`` are 1-based indices into ``channels``. ``scale`` < 1 tells that the LP times were
    scaled down so that every organ D2cm³ meets its limit. ``mip_gap`` is the relative gap of the greedy
    selection to the LP-relaxation bound of the selection MIP (None when not computed); ``mip_status`` says
    both numbers.
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
    """One needle budget: needles loaded, HR-CTV D90 (EQD2) with the organ limits held, and the aims."""

    n_needles: int
    hrctv_d90_eqd2_gy: float
    aims_met: bool


@dataclass(frozen=True, eq=False)
class ImplantArm:
    """One arm (e.g. straight only, straight + steered): its candidates, Pareto curve and chosen plan."""

    name: str
    n_candidates: int
    pareto: tuple[ParetoPoint, ...]
    plan: ImplantPlan | None
    seconds: float
    reason: str = ""

    def to_json(self) -> dict[str, object]:
        """Return the arm for plan.json (EQD2 totals in Gy; dwell positions mm LPS; times s per fraction)."""
        doc: dict[str, object] = {
            "candidates": self.n_candidates, "seconds": round(self.seconds, 3), "reason": self.reason,
            "pareto": [{"n_needles": p.n_needles, "hrctv_d90_eqd2_gy": round(p.hrctv_d90_eqd2_gy, 3),
                        "aims_met": p.aims_met} for p in self.pareto],
        }
        pl = self.plan
        if pl is None:
            return {**doc, "needles": [], "aims_met": False}
        needles = []
        for ch, c in enumerate(pl.channels, start=1):
            keep = pl.dwells.channels == ch
            needles.append({
                "hole_id": c.name, "kind": c.kind, "design": c.design,
                "schedule": None if c.schedule is None else [
                    [round(float(d), 3), round(float(t), 3), round(float(r), 3)] for d, t, r in
                    zip(c.schedule.depth_mm, c.schedule.tension_n, c.schedule.roll_deg, strict=True)],
                "hole_distance_mm": round(c.hole_distance_mm, 3), "tissue_length_mm": round(c.tissue_length_mm, 3),
                "clearance_mm": round(c.clearance_mm, 3) if np.isfinite(c.clearance_mm) else None,
                "dwell_positions_mm": np.round(pl.dwells.positions_mm[keep], 3).tolist(),
                "dwell_times_s": np.round(pl.dwells.times_s[keep], 3).tolist(),
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
            "selection": pl.mip_status,
        }


@dataclass(frozen=True, eq=False)
class _Problem:
    channels: tuple[Channel, ...]
    positions: np.ndarray  # (D, 3)
    directions: np.ndarray  # (D, 3)
    channel_of: np.ndarray  # (D,) 0-based
    target_pts: np.ndarray  # all target voxel centres (n, 3)
    gtv_pts: np.ndarray | None
    oar_pts: tuple[np.ndarray, ...]  # all voxels of each organ
    oar_limits: tuple[float | None, ...]
    gy_per_s: float
    kernel: Tg43Kernel
    oar_names: tuple[str, ...]
    eval_radius_mm: float
    target_fine: tuple[np.ndarray, np.ndarray]  # points and weights of the final metrics (_supersampled)
    gtv_fine: tuple[np.ndarray, np.ndarray] | None


def _rates(points: np.ndarray, pos: np.ndarray, dirs: np.ndarray, prob: _Problem) -> np.ndarray:
    """(m, d) Gy per second of dwell (per fraction)."""
    if len(points) == 0 or len(pos) == 0:
        return np.zeros((len(points), len(pos)))
    out = np.empty((len(points), len(pos)))
    step = max(1, (1 << 20) // len(pos))
    for s0 in range(0, len(points), step):
        out[s0:s0 + step] = prob.kernel.compiled_rates(points[s0:s0 + step], pos, dirs)
    return out * prob.gy_per_s


def _dose(points: np.ndarray, pos: np.ndarray, dirs: np.ndarray, times: np.ndarray, prob: _Problem) -> np.ndarray:
    """(m,) dose, Gy per fraction, at ``points`` from dwells with ``times`` (s), by chunks of points."""
    out = np.zeros(len(points))
    if len(pos) == 0:
        return out
    step = max(1, (1 << 20) // len(pos))
    for s0 in range(0, len(points), step):
        out[s0:s0 + step] = prob.kernel.compiled_rates(points[s0:s0 + step], pos, dirs) @ times
    return out * prob.gy_per_s


#: sub-voxels per axis at which the final metrics of the target (and GTV) are computed
SUPERSAMPLE = 3


def _supersampled(grid: Grid, mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Points (mm, LPS) and weights at which a structure's final metrics are computed.

    The n × n × n sub-voxel centres of each voxel, n = :data:`SUPERSAMPLE`. The dose falls steeply across a target's
    edge, where D90 and D98 are decided: voxel centres alone are 1-3 % off on a 2 mm grid; n = 3 is within 0.2 % of
    n = 6 on the planted cases of the tests.
    """
    n = SUPERSAMPLE
    k, j, i = np.nonzero(mask)
    ijk = np.column_stack([i, j, k]).astype(float)
    axis = (np.arange(n) + 0.5) / n - 0.5
    off = np.array([[a, b, c] for a in axis for b in axis for c in axis])
    subs = grid.to_patient((ijk[:, None, :] + off[None]).reshape(-1, 3))
    return subs, np.ones(len(subs), dtype=int)


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


def _stride(n: int, k: int) -> np.ndarray:
    return np.arange(n) if n <= k else np.linspace(0, n - 1, k).round().astype(int)


def _near(points: np.ndarray, dwell_pos: np.ndarray, k: int) -> np.ndarray:
    """Return the indices of the ``k`` points nearest to any dwell."""
    if len(points) == 0 or len(dwell_pos) == 0:
        return np.zeros(0, dtype=int)
    d, _ = cKDTree(dwell_pos).query(points)
    return np.sort(np.argsort(d, kind="stable")[:k])


def _neighbour_rows(groups: Sequence[np.ndarray], n_cols: int, ratio: float) -> list[sparse.csr_matrix]:
    """Rows ``x_a - r x_b <= 0`` and ``x_b - r x_a <= 0`` for consecutive columns a, b of each group."""
    rows, cols, vals = [], [], []
    r = 0
    for g in groups:
        for a, b in itertools.pairwise(g):
            rows += [r, r, r + 1, r + 1]
            cols += [a, b, b, a]
            vals += [1.0, -ratio, 1.0, -ratio]
            r += 2
    if r == 0:
        return []
    return [sparse.csr_matrix((vals, (rows, cols)), shape=(r, n_cols))]


def _share_rows(weights: np.ndarray, n_cols: int, share: float) -> sparse.csr_matrix:
    """Rows ``x_a - share Σ_b w_b x_b <= 0`` for the first ``len(weights)`` columns."""
    n = len(weights)
    dense = np.eye(n) - share * np.outer(np.ones(n), weights)
    return sparse.hstack([sparse.csr_matrix(dense), sparse.csr_matrix((n, n_cols - n))], format="csr")


class _Selection:
    """The restricted needle-selection model (module docstring, step 1), built once per arm.

    Variables ``x = [τ (blocks), y (needles), u (target points)]``; ``solve`` changes only the bounds of ``y``
    and the budget row, so every programme of the arm shares one constraint matrix.
    """

    def __init__(self, prob: _Problem, a_t: np.ndarray, a_g: np.ndarray | None, p_t: float, p_g: float,
                 a_o: Sequence[tuple[np.ndarray, float]], settings: ImplantSettings, cost: np.ndarray) -> None:
        chans = prob.channels
        blocks: list[np.ndarray] = []
        block_ch: list[int] = []
        for c in range(len(chans)):
            idx = np.flatnonzero(prob.channel_of == c)
            for part in np.array_split(idx, min(settings.segments_per_channel, len(idx))):
                blocks.append(part)
                block_ch.append(c)
        n_b = len(blocks)
        sizes = np.array([len(b) for b in blocks], dtype=float)
        member = sparse.csr_matrix((np.ones(int(sizes.sum())), (np.concatenate(blocks),
                                                                np.repeat(np.arange(n_b), sizes.astype(int)))),
                                   shape=(len(prob.channel_of), n_b))
        self.needles = [c for c in range(len(chans)) if chans[c].is_needle]
        y_of = {c: i for i, c in enumerate(self.needles)}
        n_y = len(self.needles)
        tgt = [np.asarray((member.T @ a_t.T).T)]
        rx = [np.full(len(a_t), p_t)]
        if a_g is not None and len(a_g):
            tgt.append(np.asarray((member.T @ a_g.T).T))
            rx.append(np.full(len(a_g), p_g))
        at = np.vstack(tgt)
        p = np.concatenate(rx)
        m = len(at)
        n = n_b + n_y + m
        self.c = np.concatenate([settings.time_weight * at.mean(axis=0) / p_t,
                                 settings.invasiveness_weight * cost[self.needles], np.full(m, 1.0 / (m * p_t))])
        cons = [sparse.hstack([sparse.csr_matrix(at), sparse.csr_matrix((m, n_y)), sparse.identity(m)])]
        lb, ub = [p], [np.full(m, np.inf)]
        cap = np.full(n_b, np.inf)  # a block time no organ point allows beyond (a valid bound)
        for a, limit in a_o:
            if len(a):
                ao = np.asarray((member.T @ a.T).T)
                cons.append(sparse.hstack([sparse.csr_matrix(ao), sparse.csr_matrix((len(ao), n_y + m))]))
                lb.append(np.full(len(ao), -np.inf))
                ub.append(np.full(len(ao), limit))
                cap = np.minimum(cap, limit / np.maximum(ao.max(axis=0), 1e-30))
        # big-M: a block time that alone brings every sampled target point to the prescription, or that an
        # organ point forbids, is not in an optimal loading
        big_m = np.minimum(p.max() / np.maximum(at.min(axis=0), 1e-30), cap)
        rows, cols, vals = [], [], []
        r = 0
        for b, ch in enumerate(block_ch):
            if ch in y_of:
                rows += [r, r]
                cols += [b, n_b + y_of[ch]]
                vals += [1.0, -float(big_m[b])]
                r += 1
        cons.append(sparse.csr_matrix((vals, (rows, cols)), shape=(r, n)))
        lb.append(np.full(r, -np.inf))
        ub.append(np.zeros(r))
        groups = [np.flatnonzero(np.array(block_ch) == ch) for ch in range(len(chans))]
        for rowset in _neighbour_rows(groups, n, settings.neighbour_ratio):
            cons.append(rowset)
            lb.append(np.full(rowset.shape[0], -np.inf))
            ub.append(np.zeros(rowset.shape[0]))
        cons.append(_share_rows(sizes, n, settings.max_dwell_share * (1 - 1e-3)))
        lb.append(np.full(n_b, -np.inf))
        ub.append(np.zeros(n_b))
        budget = np.zeros(n)
        budget[n_b:n_b + n_y] = 1.0
        cons.append(sparse.csr_matrix(budget))
        self.a = sparse.vstack(cons, format="csr")
        self.lb = np.concatenate([*lb, [-np.inf]])
        self.ub = np.concatenate([*ub, [np.inf]])
        self.n_b, self.n_y, self.n = n_b, n_y, n
        self.at, self.p, self.p_t, self.cost, self.cap, self.big_m = at, p, p_t, cost, cap, big_m
        self.ao = [(np.asarray((member.T @ a.T).T), limit) for a, limit in a_o if len(a)]
        self.block_ch = np.array(block_ch)
        self.hole_of = [chans[c].name for c in self.needles]
        self.sizes = sizes
        self.settings = settings
        self.all_ch = [c for c in range(len(chans)) if not chans[c].is_needle]

    def _run(self, budget: float, y_lo: np.ndarray, y_hi: np.ndarray, integral: bool) -> sopt.OptimizeResult:
        ub_rows = self.ub.copy()
        ub_rows[-1] = budget
        lo = np.zeros(self.n)
        hi = np.full(self.n, np.inf)
        lo[self.n_b:self.n_b + self.n_y] = y_lo
        hi[self.n_b:self.n_b + self.n_y] = y_hi
        integrality = np.zeros(self.n)
        options: dict[str, object] = {"disp": False}
        if integral:
            integrality[self.n_b:self.n_b + self.n_y] = 1
            options.update(time_limit=self.settings.mip_time_limit_s, mip_rel_gap=self.settings.mip_rel_gap)
        return sopt.milp(self.c, constraints=sopt.LinearConstraint(self.a, self.lb, ub_rows),
                         integrality=integrality, bounds=sopt.Bounds(lo, hi), options=options)

    def loading(self, chosen: Sequence[int]) -> tuple[float, np.ndarray]:
        """Return the objective of the best block loading on ``chosen``, and its dose at the target points (Gy).

        ``chosen``: indices into ``needles`` (the intracavitary channels are always loaded); (inf, zeros) when
        infeasible.

        A small LP over the chosen channels' blocks only (the rows of the selection model restricted to them).
        """
        chans = {self.needles[i] for i in chosen} | set(self.all_ch)
        cols = np.flatnonzero(np.isin(self.block_ch, list(chans)))
        m = len(self.at)
        if len(cols) == 0:
            return float(np.sum(self.p) / (m * self.p_t)), np.zeros(m)
        at = self.at[:, cols]
        nb = len(cols)
        n = nb + m
        c = np.concatenate([self.settings.time_weight * at.mean(axis=0) / self.p_t, np.full(m, 1.0 / (m * self.p_t))])
        a_ub = [sparse.hstack([sparse.csr_matrix(-at), -sparse.identity(m)])]
        b_ub = [-self.p]
        for ao, limit in self.ao:
            a_ub.append(sparse.hstack([sparse.csr_matrix(ao[:, cols]), sparse.csr_matrix((len(ao), m))]))
            b_ub.append(np.full(len(ao), limit))
        groups = [np.flatnonzero(self.block_ch[cols] == ch) for ch in sorted(chans)]
        for rowset in _neighbour_rows(groups, n, self.settings.neighbour_ratio):
            a_ub.append(rowset)
            b_ub.append(np.zeros(rowset.shape[0]))
        a_ub.append(_share_rows(self.sizes[cols], n, self.settings.max_dwell_share * (1 - 1e-3)))
        b_ub.append(np.zeros(nb))
        res = sopt.linprog(c, A_ub=sparse.vstack(a_ub, format="csr"), b_ub=np.concatenate(b_ub), bounds=(0, None),
                           method="highs")
        if res.status != 0 or res.x is None:
            return float("inf"), np.zeros(m)
        invasive = self.settings.invasiveness_weight * float(sum(self.cost[self.needles[i]] for i in chosen))
        return float(res.fun) + invasive, at @ res.x[:nb]

    def bound(self, k_budget: int) -> float:
        """Return a lower bound on the selection objective with ``k_budget`` needles.

        The LP relaxation of the MIP (``0 <= y <= 1``), tightened by HiGHS's dual bound when ``mip_time_limit_s`` >
        0.
        """
        zeros, ones = np.zeros(self.n_y), np.ones(self.n_y)
        res = self._run(float(k_budget), zeros, ones, integral=False)
        value = float(res.fun) if res.x is not None else float("nan")
        if self.settings.mip_time_limit_s > 0:
            mip = self._run(float(k_budget), zeros, ones, integral=True)
            dual = getattr(mip, "mip_dual_bound", None)
            if dual is not None and np.isfinite(dual):
                value = max(value, float(dual))
        return value

    def step(self, previous: Sequence[int], dose: np.ndarray) -> tuple[list[int], float, np.ndarray]:
        """Greedy step.

        The previous needles plus the one whose exact block loading lowers the objective most, among the
        ``greedy_candidates`` needles that could fill most of the current underdose alone (each within its organ
        caps).
        """
        deficit = np.maximum(self.p - dose, 0.0)
        holes = {self.hole_of[i] for i in previous}  # one needle per template hole
        free = [i for i in range(self.n_y) if i not in set(previous) and self.hole_of[i] not in holes]
        if not free:
            return list(previous), float("inf"), dose
        score = []
        for i in free:
            blocks = np.flatnonzero(self.block_ch == self.needles[i])
            fill = self.at[:, blocks] * np.minimum(self.cap[blocks], self.big_m[blocks])
            score.append(float(np.minimum(fill.sum(axis=1), deficit).sum())
                         - self.settings.invasiveness_weight * self.cost[self.needles[i]])
        order = [free[j] for j in np.argsort(-np.array(score), kind="stable")[: self.settings.greedy_candidates]]
        best: tuple[list[int], float, np.ndarray] = (list(previous), float("inf"), dose)
        for i in order:
            chosen = sorted([*previous, i])
            value, d = self.loading(chosen)
            if value < best[1] - 1e-12:
                best = (chosen, value, d)
        return best


def _dwell_lp(prob: _Problem, cols: np.ndarray, a_t: np.ndarray, a_g: np.ndarray | None, p_t: float, p_g: float,
              a_o: Sequence[tuple[np.ndarray, float]], settings: ImplantSettings, released: Sequence[np.ndarray],
              ) -> np.ndarray | None:
    """Dwell times (s) on the dwells ``cols`` (module docstring, step 2); None when the LP does not solve."""
    at = a_t
    p = np.full(len(at), p_t)
    if a_g is not None and len(a_g):
        at = np.vstack([at, a_g])
        p = np.concatenate([p, np.full(len(a_g), p_g)])
    m, d = at.shape
    n = d + m
    obj = np.concatenate([settings.time_weight * at.mean(axis=0) / p_t, np.full(m, 1.0 / (m * p_t))])
    a_ub = [sparse.hstack([sparse.csr_matrix(-at), -sparse.identity(m)])]
    b_ub = [-p]
    for (a, limit), free in zip(a_o, released, strict=True):
        keep = np.setdiff1d(np.arange(len(a)), free)
        if len(keep):
            a_ub.append(sparse.hstack([sparse.csr_matrix(a[keep]), sparse.csr_matrix((len(keep), m))]))
            b_ub.append(np.full(len(keep), limit))
    groups = [np.flatnonzero(prob.channel_of[cols] == c) for c in np.unique(prob.channel_of[cols])]
    for rowset in _neighbour_rows(groups, n, settings.neighbour_ratio):
        a_ub.append(rowset)
        b_ub.append(np.zeros(rowset.shape[0]))
    a_ub.append(_share_rows(np.ones(d), n, settings.max_dwell_share * (1 - 1e-3)))
    b_ub.append(np.zeros(d))
    res = sopt.linprog(obj, A_ub=sparse.vstack(a_ub, format="csr"), b_ub=np.concatenate(b_ub), bounds=(0, None),
                       method="highs")
    if res.status != 0 or res.x is None:
        return None
    return np.maximum(res.x[:d], 0.0)


def _metrics(prob: _Problem, cols: np.ndarray, times: np.ndarray, aims: Aims, vox_cc: float,
             ) -> tuple[StructureMetrics, float, StructureMetrics | None, tuple[StructureMetrics, ...],
                        tuple[tuple[str, Dvh], ...], float]:
    """Compute target, V200, GTV and organ metrics of a loading on every voxel.

    Organs: voxels within ``oar_eval_radius`` of a loaded dwell. Also returns the factor <= 1 that keeps every
    D2cm³ within its limit.
    """
    loaded = times > 0
    pos, dirs, t = prob.positions[cols][loaded], prob.directions[cols][loaded], times[loaded]
    rx = aims.prescription_gy
    dose_oar = []
    scale = 1.0
    for pts, limit in zip(prob.oar_pts, prob.oar_limits, strict=True):
        # the organ's voxels within the evaluation radius of a loaded dwell, and at least its nearest 4 × 2 cm³
        dist = cKDTree(pos).query(pts)[0] if len(pos) else np.zeros(len(pts))
        n_min = min(len(pts), 4 * math.ceil(2.0 / vox_cc))
        near = pts[(dist <= prob.eval_radius_mm) | (np.argsort(np.argsort(dist, kind="stable")) < n_min)]
        d = _dose(near, pos, dirs, t, prob)
        dose_oar.append(d)
        if limit is not None and len(d):
            d2 = dose_to_volume(d, vox_cc, 2.0)
            if d2 > limit:
                scale = min(scale, limit / d2 * (1 - 1e-9))
    t = t * scale
    sub_cc = vox_cc / SUPERSAMPLE ** 3  # target and GTV on sub-voxels
    dt = np.repeat(_dose(prob.target_fine[0], pos, dirs, t, prob), prob.target_fine[1])
    target = structure_metrics("HR-CTV", dt, sub_cc, rx, aims.alpha_beta_target_gy, aims.fractionation)
    v200 = 100.0 * float(np.count_nonzero(dt >= 2.0 * rx)) / len(dt)
    dvhs = [("HR-CTV", cumulative_dvh(dt, sub_cc))]
    gtv = None
    if prob.gtv_fine is not None and len(prob.gtv_fine[0]):
        dg = np.repeat(_dose(prob.gtv_fine[0], pos, dirs, t, prob), prob.gtv_fine[1])
        gtv = structure_metrics("GTV", dg, sub_cc, rx, aims.alpha_beta_target_gy, aims.fractionation)
        dvhs.append(("GTV", cumulative_dvh(dg, sub_cc)))
    oars = []
    for name, d in zip(prob.oar_names, dose_oar, strict=True):
        d = d * scale if len(d) else np.zeros(1)
        oars.append(structure_metrics(name, d, vox_cc, rx, aims.alpha_beta_oar_gy, aims.fractionation))
        dvhs.append((name, cumulative_dvh(d, vox_cc)))
    return target, v200, gtv, tuple(oars), tuple(dvhs), scale


def _aims_met(target: StructureMetrics, gtv: StructureMetrics | None, oars: Sequence[StructureMetrics],
              aims: Aims) -> bool:
    ok = target.d90_eqd2_gy >= aims.target_d90_eqd2_gy - 1e-6 and target.d98_eqd2_gy >= aims.target_d98_eqd2_gy - 1e-6
    if gtv is not None:
        ok = ok and gtv.d98_eqd2_gy >= aims.gtv_d98_eqd2_gy - 1e-6
    for o in oars:
        limit = next((v for n, v in aims.oar_d2cc_eqd2_gy if n.casefold() in o.name.casefold()), None)
        if limit is not None and o.d2cc_eqd2_gy > limit + 1e-6:
            ok = False
    return bool(ok)


def _better(a: ImplantPlan, b: ImplantPlan) -> bool:
    """Return True when plan ``a`` ranks before ``b`` by the arms' rule.

    A plan meeting every aim beats one that does not; between two that do, fewer needles (then the higher
    HR-CTV D90) wins; between two that do not, the higher D90 (then fewer needles) wins.
    """
    if a.aims_met != b.aims_met:
        return a.aims_met
    if a.aims_met:
        return (a.n_needles, -a.target.d90_eqd2_gy) < (b.n_needles, -b.target.d90_eqd2_gy)
    return (a.target.d90_eqd2_gy, -a.n_needles) > (b.target.d90_eqd2_gy, -b.n_needles)


def dominate(arm: ImplantArm, subset: ImplantArm) -> ImplantArm:
    """Make ``arm`` at least as good as an arm whose candidate channels are a subset of its own.

    The straight + steered arm holds every straight candidate, so every straight implant is also one of its
    implants: a heuristic search over the larger set that ends worse than the smaller arm's answer is replaced
    by that answer (an incumbent, as in branch and bound). At each needle count of the Pareto curve the better
    point is kept (aims met first, then the higher HR-CTV D90).
    """
    best: dict[int, ParetoPoint] = {}
    for pt in (*arm.pareto, *subset.pareto):
        old = best.get(pt.n_needles)
        if old is None or (pt.aims_met, pt.hrctv_d90_eqd2_gy) > (old.aims_met, old.hrctv_d90_eqd2_gy):
            best[pt.n_needles] = pt
    pareto = tuple(best[n] for n in sorted(best))
    plan, reason = arm.plan, arm.reason
    if subset.plan is not None and (plan is None or _better(subset.plan, plan)):
        plan = subset.plan
        reason = (f"the {subset.name} arm's implant (its needles are candidates of this arm too) ranks before this "
                  f"arm's search result and is kept" + (f"; {subset.reason}" if subset.reason else ""))
    return dataclasses.replace(arm, pareto=pareto, plan=plan, reason=reason)


def plan_implant(
    name: str,
    channels: Sequence[Channel],
    planning: PlanningStructures,
    kernel: Tg43Kernel,
    air_kerma_strength_u: float,
    aims: Aims | None = None,
    settings: ImplantSettings | None = None,
    gtv: Structure | None = None,
) -> ImplantArm:
    """Return the Pareto curve of needle count against HR-CTV D90 and the chosen implant of one arm.

    Parameters
    ----------
    name : the arm's name (e.g. ``"straight"``, ``"steered"``).
    channels : candidate needles and intracavitary channels (:func:`needle_candidates`,
        :func:`intracavitary_channel`).
    planning : target and organ masks on the planning grid.
    kernel, air_kerma_strength_u : TG-43 kernel and source strength (U).
    aims : EMBRACE II by default.
    gtv : the GTV mask on the planning grid, when there is one (its D98 is then an aim).

    Returns
    -------
    ImplantArm
        ``plan`` None (with ``reason``) when there is no candidate or no budget gives a plan.
    """
    t0 = time.perf_counter()
    aims = aims or Aims()
    settings = settings or ImplantSettings()
    channels = tuple(c for c in channels if len(c.dwell_positions_mm) >= 1)
    if not any(c.is_needle for c in channels) and not channels:
        return ImplantArm(name, 0, (), None, time.perf_counter() - t0, "no candidate channel")
    grid = planning.grid
    vox_cc = voxel_volume_cc(grid)
    positions = np.concatenate([c.dwell_positions_mm for c in channels])
    directions = np.concatenate([c.dwell_directions for c in channels])
    channel_of = np.repeat(np.arange(len(channels)), [len(c.dwell_positions_mm) for c in channels])
    oar_limits = tuple(aims.oar_limit_gy(o.name) for o in planning.oars)
    prob = _Problem(
        channels, positions, directions, channel_of,
        grid_points_mm(grid, np.flatnonzero(planning.target.mask.ravel())),
        None if gtv is None else grid_points_mm(grid, np.flatnonzero(gtv.mask.ravel())),
        tuple(grid_points_mm(grid, np.flatnonzero(o.mask.ravel())) for o in planning.oars),
        oar_limits, air_kerma_strength_u / 360000.0, kernel, tuple(o.name for o in planning.oars),
        settings.oar_eval_radius_mm, _supersampled(grid, planning.target.mask),
        None if gtv is None else _supersampled(grid, gtv.mask))
    p_t = aims.prescription_gy * (1.0 + settings.coverage_margin)
    p_g = aims.fractionation.per_fraction_for(aims.gtv_d98_eqd2_gy, aims.alpha_beta_target_gy) * (
        1.0 + settings.coverage_margin)
    # the restricted selection model: sampled target points, organ points nearest the candidate dwells
    sel_t = _rates(prob.target_pts[_stride(len(prob.target_pts), settings.selection_target_points)],
                   positions, directions, prob)
    sel_g = None if prob.gtv_pts is None else _rates(
        prob.gtv_pts[_stride(len(prob.gtv_pts), settings.selection_target_points // 4)], positions, directions, prob)
    sel_o = [(_rates(pts[_near(pts, positions, settings.selection_oar_points)], positions, directions, prob), lim)
             for pts, lim in zip(prob.oar_pts, oar_limits, strict=True) if lim is not None]
    fin_t = prob.target_pts[_stride(len(prob.target_pts), settings.final_target_points)]
    fin_g = None if prob.gtv_pts is None else prob.gtv_pts[_stride(len(prob.gtv_pts),
                                                                    settings.final_target_points // 4)]
    needles = [c for c in channels if c.is_needle]
    cost = np.zeros(len(channels))
    if needles:
        dmax = max(max(c.hole_distance_mm for c in needles), 1e-9)
        lmax = max(max(c.tissue_length_mm for c in needles), 1e-9)
        cost = np.array([0.5 * c.hole_distance_mm / dmax + 0.5 * c.tissue_length_mm / lmax for c in channels])
    n_hot = max(1, math.ceil(2.0 / vox_cc - 1e-9) - 1)
    pareto: list[ParetoPoint] = []
    plans: list[ImplantPlan] = []
    met_at: int | None = None
    best_d90 = -np.inf
    stall = 0
    seen: dict[tuple[int, ...], ImplantPlan] = {}
    selection_values: list[float] = []
    selection = _Selection(prob, sel_t, sel_g, p_t, p_g, sel_o, settings, cost)
    previous: list[int] = []
    value, dose = selection.loading([])
    for k in range(0 if selection.all_ch else 1, min(settings.max_needles, len(needles)) + 1):
        if k == 0:  # the intracavitary channels alone
            picked: list[int] = []
        else:
            picked, value, dose = selection.step(previous, dose)
            if len(picked) <= len(previous):
                break
        previous = picked
        status = f"greedy selection objective {value:.4g}"
        chosen = np.array(sorted([selection.needles[i] for i in picked] + selection.all_ch), dtype=int)
        gap = None
        plan = seen.get(tuple(chosen))
        if plan is None:
            plan = _final(prob, chosen, fin_t, fin_g, p_t, p_g, aims, settings, vox_cc, n_hot, gap, status)
            if plan is not None:
                seen[tuple(chosen)] = plan
        if plan is None:
            continue
        plans.append(plan)
        selection_values.append(value)
        pareto.append(ParetoPoint(plan.n_needles, plan.target.d90_eqd2_gy, plan.aims_met))
        if plan.aims_met and met_at is None:
            met_at = k
        if met_at is not None and k >= met_at + settings.extra_after_aims:
            break
        if plan.target.d90_eqd2_gy > best_d90 + 0.1:
            best_d90, stall = plan.target.d90_eqd2_gy, 0
        else:
            stall += 1
            if stall >= 3:
                break
    if not plans:
        return ImplantArm(name, len(needles), (), None, time.perf_counter() - t0,
                          "no needle budget gave a plan (every MIP or LP failed)")
    meeting = [p for p in plans if p.aims_met]
    chosen_plan = (min(meeting, key=lambda p: (p.n_needles, -p.target.d90_eqd2_gy)) if meeting
                   else max(plans, key=lambda p: (p.target.d90_eqd2_gy, -p.n_needles)))
    if settings.bound:  # how far the greedy selection may be from the optimum of the selection model
        k_chosen = sum(c.is_needle for c in chosen_plan.channels)
        lower = selection.bound(k_chosen)
        value = selection_values[plans.index(chosen_plan)]
        gap = (value - lower) / value if value > 0 and np.isfinite(lower) else 0.0
        chosen_plan = dataclasses.replace(chosen_plan, mip_gap=gap, mip_status=(
            f"greedy {value:.4g} against LP-relaxation bound {lower:.4g} (relative gap {gap:.3f})"))
    reason = "" if meeting else "no needle budget meets every aim; the plan with the highest D90 is kept"
    return ImplantArm(name, len(needles), tuple(pareto), chosen_plan, time.perf_counter() - t0, reason)


def _final(prob: _Problem, chosen: np.ndarray, fin_t: np.ndarray, fin_g: np.ndarray | None, p_t: float,
           p_g: float, aims: Aims, settings: ImplantSettings, vox_cc: float, n_hot: int, gap: float | None,
           status: str) -> ImplantPlan | None:
    """Dwell times on the chosen channels (LP, organ release, empty-needle rule) and the plan's metrics."""
    t = np.zeros(0)
    cols = loaded_ch = np.zeros(0, dtype=int)
    for _ in range(3):
        cols = np.flatnonzero(np.isin(prob.channel_of, chosen))
        pos, dirs = prob.positions[cols], prob.directions[cols]
        a_t = _rates(fin_t, pos, dirs, prob)
        a_g = None if fin_g is None else _rates(fin_g, pos, dirs, prob)
        a_o = []
        for pts, lim in zip(prob.oar_pts, prob.oar_limits, strict=True):
            if lim is None:
                continue
            r = _rates(pts[_near(pts, pos, settings.final_oar_points * 3)], pos, dirs, prob)
            hot = np.sort(np.argsort(-r.sum(axis=1), kind="stable")[: settings.final_oar_points])
            a_o.append((r[hot], lim))
        released: list[np.ndarray] = [np.zeros(0, dtype=int) for _ in a_o]
        best: np.ndarray | None = None
        for it in range(2):
            lp = _dwell_lp(prob, cols, a_t, a_g, p_t, p_g, a_o, settings, released)
            if lp is None:
                break
            best = lp
            if it == 0:
                released = [np.argsort(-(a @ lp), kind="stable")[:n_hot] if len(a) else np.zeros(0, int)
                            for a, _ in a_o]
        if best is None:
            return None
        t = np.where(best >= settings.min_dwell_time_s, best, 0.0)
        totals = np.bincount(prob.channel_of[cols], weights=t, minlength=len(prob.channels))
        loaded_ch = np.array([c for c in chosen if totals[c] > 1e-3 * max(t.sum(), 1e-12)], dtype=int)
        if len(loaded_ch) == 0:
            return None
        t = np.where(np.isin(prob.channel_of[cols], loaded_ch), t, 0.0)
        t = _clip_share(t, settings.max_dwell_share)  # the dropped short dwells raised the others' shares
        if len(loaded_ch) == len(chosen):
            break
        chosen = loaded_ch  # a needle the optimum leaves empty is not part of the implant: re-solve without it
    chosen = loaded_ch
    target, v200, gtv, oars, dvhs, scale = _metrics(prob, cols, t, aims, vox_cc)
    keep = t > 0
    new_index = {int(c): i + 1 for i, c in enumerate(chosen)}
    dwells = DwellSet(prob.positions[cols][keep], prob.directions[cols][keep], t[keep] * scale,
                      np.array([new_index[int(c)] for c in prob.channel_of[cols][keep]], dtype=int))
    return ImplantPlan(tuple(prob.channels[int(c)] for c in chosen), dwells, target, v200, oars,
                       _aims_met(target, gtv, oars, aims), gtv, scale, gap, status, dvhs)


def recompute_target(plan: ImplantPlan, grid: Grid, target_mask: np.ndarray, kernel: Tg43Kernel,
                     air_kerma_strength_u: float, aims: Aims | None = None) -> StructureMetrics:
    """Recompute a plan's HR-CTV metrics independently with :func:`dose_on_grid` on another (finer) ``grid``.

    ``target_mask`` ((nk, nj, ni) bool) holds the target; physical per fraction and EQD2 totals.
    """
    aims = aims or Aims()
    dose = dose_on_grid(grid, plan.dwells, kernel, air_kerma_strength_u)[np.asarray(target_mask, bool)]
    return structure_metrics("HR-CTV", dose.astype(float), voxel_volume_cc(grid), aims.prescription_gy,
                             aims.alpha_beta_target_gy, aims.fractionation)
