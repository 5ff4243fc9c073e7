"""Implant planning: the needle set and the dwell times that cover the HR-CTV, chosen together.

Candidates (:func:`needle_candidates`): every template hole × (straight, and every stylet design × tension
schedule of the shape bank × roll) whose path passes through the HR-CTV and keeps ``clearance_margin_mm``
from every organ at risk. Paths are screened on Euclidean distance maps of the planning grid (target grown by
the dwell margin; organs at risk), and the kept ones are confirmed with the organs' distance fields (bounds on the
clearance) and, for a path they cannot prove farther than the margin plus :data:`CONFIRM_BAND_MM` from every organ,
with the FCL clearance of :func:`reachplan.planner.geometry.collision.check_path`. Intracavitary channels
(tandem, ring, ovoids) are passed in as :class:`Channel` objects of kind ``"intracavitary"``; they are always
available and not counted as needles. Dwell positions are every ``dwell_step_mm`` along the part of each channel
inside the HR-CTV grown by ``dwell_margin_mm``.

Choice of needles and dwell times (:func:`plan_implant`), for each needle budget K = 1, 2, ... (K = 0 too when
an intracavitary channel is given), meaning "at most K needles":

**The model** (:class:`_Model`), linear in the dwell times ``t``: target points ``A t + u >= P`` (``u``
underdose, ``P`` the per-fraction dose that brings D90 to its aim, plus ``coverage_margin``; GTV points at the
GTV D98 aim); for each organ a **mean-tail-dose row**: the mean dose over its hottest 2 cm³ within ``κ`` × its
D2cm³ limit, written linearly as ``ζ + Σ w_i s_i / 2 cm³ <= κ L``, ``s_i >= (A t)_i - ζ``, ``s, ζ >= 0``
(Rockafellar & Uryasev, J Risk 2(3):21, 2000; as mean-tail-dose in radiotherapy planning, Romeijn et al.,
Oper Res 54(2):201, 2006). The mean over the hottest 2 cm³ is at least D2cm³, so with ``κ`` = 1 the row implies
D2cm³ <= L; ``κ`` is then calibrated to the exact D2cm³ on the organ's 20 cm³ nearest the loaded dwells
(:func:`_calibrate`), which puts D2cm³ on the limit instead of below it. Organ points: the organ's voxels on a
lattice of ``*_oar_pitch_mm``, each weighted by the volume it stands for, nearest to the dwells until they hold
``oar_sample_cc``. Neighbouring dwells on a channel within ``neighbour_ratio`` (as IPSA's dwell-time deviation
constraint / HIPO's dwell-time gradient restriction, Mosleh-Shirazi et al., J Contemp Brachytherapy 11(3),
2019): a channel is loaded on all its dwells or on none. No dwell over ``max_dwell_share`` of the total.
Objective: mean underdose (in units of the prescription) + ``time_weight`` × mean target dose (shorter plans) +
``invasiveness_weight`` × each used needle's normalised hole distance and tissue length ("least invasive").

1. **Needle selection: a mixed-integer programme solved by a deterministic heuristic with a bound.** The model:
   each channel's dwells in ``segments_per_channel`` blocks of equal time, sampled target points; binary ``y_n``
   per needle with each block's time ``<= M y_n`` (``M``: the time at which the block alone brings every target
   point to ``P``, or fills an organ's row), one needle per template hole, ``Σ y_n <= K``. Its LP relaxation
   (HiGHS dual simplex through ``scipy.optimize.milp``) bounds every selection of K needles from below. Starts:
   the relaxation rounded (its largest ``y`` first) with and without the previous budget's needles, that
   selection itself (so the objective never rises with K); then
   a local search (:meth:`_Model.improved`): add a needle or swap one for another of the ``swap_pool`` needles
   with the largest relaxed ``y``, the best move while it lowers the objective, each move an LP on the chosen
   needles' columns alone. No wall-clock limit anywhere: the same input gives the same selection on a quiet or
   a loaded machine. (Before, HiGHS's branch and bound ran for 1 s per budget and seldom left the root node:
   its selections depended on the load and were worse than this search's.) The bound reported per budget is the
   LP relaxation's and the relative gap to the selection kept (:class:`BudgetResult`; plan.json ``selection``):
   the big-M relaxation is weak, so gaps of 0.4-0.95 on the clinical case say that the selection is not proven
   optimal, not that it is that far from it. The LP with every candidate loaded, its organ rows calibrated once,
   bounds every budget (``selection.all_candidates_objective``); every budget's model has those rows.
2. **Dwell times on the chosen channels: a linear programme** over every dwell (no blocks), its organ rows
   calibrated until the D2cm³ they give is within 1 % of the limit. Dwells under ``min_dwell_time_s`` are dropped;
   a needle left with fewer than ``min_dwells`` loaded dwells is not part of the implant: it is dropped and the
   rest re-solved. The plan is checked on every organ voxel near the implant and all times scaled down when a
   D2cm³ still exceeds its limit.

Each new selection's plan is a point of the arm's Pareto curve of needle count against HR-CTV D90 with the organ
limits held; a plan no better than one with fewer needles is dominated and left out, so the curve rises and has
one point per count. The plan chosen is the one with the fewest needles that meets every aim (HR-CTV D90 and D98,
GTV D98 when a GTV is given, organ D2cm³), else the one with the highest D90. The budgets stop
``extra_after_aims`` after the first that meets the aims, after two budgets without a new selection, or when the
selection reaches the all-candidates bound. The final metrics of the target are computed on sub-voxels of at
most :data:`SUBVOXEL_MM`.

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
from scipy import optimize as sopt
from scipy import sparse
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
from reachplan.planner.dose.dwells import DwellSet, dose_on_grid, dwell_directions, grid_points_mm
from reachplan.planner.dose.optimize import Aims, PlanningStructures, Structure
from reachplan.planner.dose.tg43 import Tg43Kernel
from reachplan.planner.geometry.collision import Organ, check_path
from reachplan.planner.geometry.distance_field import distance_transform
from reachplan.planner.steering.schedule import TensionSchedule
from reachplan.planner.steering.steered import ShapeBank, place

NEEDLE_KINDS = ("straight", "steered")
#: a candidate's clearance is confirmed with FCL when an organ's distance field cannot prove it beyond the
#: clearance margin plus this (mm); beyond, the candidate is clear and its clearance is the field's estimate
CONFIRM_BAND_MM = 1.0


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
    swap_pool, swap_passes : the selection's local search at each needle budget: swaps with the needles of the
        largest relaxed ``y`` (this many), for at most this many passes (0: the rounded LP relaxation alone).
    selection_target_points, final_target_points : target points of the selection model and of the dwell-time
        LP on the chosen needles.
    selection_oar_pitch_mm, final_oar_pitch_mm : lattice pitch of the organs' representative points in each.
    oar_sample_cc : organ volume nearest to the dwells that the representative points cover.
    segments_per_channel : dwell blocks per channel in the selection model.
    invasiveness_weight : weight of the needles' invasiveness in the selection objective (a tie-break).
    time_weight : weight of the mean target dose (shorter plans) in both objectives.
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
    swap_pool: int = 8
    swap_passes: int = 3
    segments_per_channel: int = 2
    selection_target_points: int = 200
    final_target_points: int = 800
    selection_oar_pitch_mm: float = 3.0
    final_oar_pitch_mm: float = 3.0
    oar_sample_cc: float = 4.0
    min_dwell_time_s: float = 0.1
    oar_eval_radius_mm: float = 40.0
    invasiveness_weight: float = 1e-3  # tie-breaks in the objective
    time_weight: float = 1e-3

    def __post_init__(self) -> None:
        if not (self.dwell_step_mm > 0 and self.dwell_margin_mm >= 0 and self.tip_offset_mm >= 0
                and self.clearance_margin_mm >= 0):
            raise ValueError("dwell step must be > 0 mm; margins and tip offset >= 0 mm")
        if self.neighbour_ratio < 1 or not 0 < self.max_dwell_share <= 1:
            raise ValueError("neighbour_ratio must be >= 1 and max_dwell_share in (0, 1]")
        if min(self.min_dwells, self.max_needles, self.rolls, self.segments_per_channel,
               self.selection_target_points, self.final_target_points) < 1 or self.steered_per_hole < 0 \
                or self.extra_after_aims < 0:
            raise ValueError("implant settings: counts must be >= 1 (steered_per_hole, extra_after_aims >= 0)")
        if not (self.selection_oar_pitch_mm > 0 and self.final_oar_pitch_mm > 0 and self.oar_sample_cc >= 2.0):
            raise ValueError("implant settings: organ pitches must be > 0 mm and oar_sample_cc >= 2 cm³")


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
    clearance_mm : smallest surface distance to an organ at risk (FCL within the margin plus
        :data:`CONFIRM_BAND_MM`; beyond, the organs' distance-field estimate, within its error bound).
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
    values = distance_transform(crop, spacing)  # infinite without a seed
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

    band_mm = settings.clearance_margin_mm + CONFIRM_BAND_MM

    def confirm(path: np.ndarray) -> float | None:
        # an organ's distance field bounds the clearance: a path it proves too close fails FCL too; one it proves
        # farther than the band from every organ (and not inside one) is clear, its clearance the fields' estimate
        bounds = [None if o.field is None else o.field.path_clearance(path, needle_radius_mm) for o in organs]
        if any(b is not None and b[2] < settings.clearance_margin_mm for b in bounds):
            return None
        if all(b is not None and b[1] > band_mm for b in bounds):
            if any(o.contains(path[0]) for o in organs):
                return None
            return min((b[0] for b in bounds if b is not None), default=float("inf"))
        checks = check_path(path, needle_radius_mm, tuple(organs)) if organs else ()  # containment cached per organ
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
    scaled down so that every organ D2cm³ meets its limit. ``mip_gap`` is the relative gap between the selection of the
    budget that gave this plan and that budget's LP relaxation (None when there is none); ``mip_status`` says
    which budget and how the selection was made.
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
    """One arm (e.g. straight only, straight + steered): its candidates, Pareto curve and chosen plan.

    ``budgets``: the needle selection at each budget tried; ``selection``: how the selection was made and the
    bound of every candidate loaded (plan.json ``selection``); ``plans``: the implant of each Pareto point.
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

    def to_json(self) -> dict[str, object]:
        """Return the arm for plan.json (EQD2 totals in Gy; dwell positions mm LPS; times s per fraction)."""
        doc: dict[str, object] = {
            "candidates": self.n_candidates, "seconds": round(self.seconds, 3), "reason": self.reason,
            "pareto": [{"n_needles": p.n_needles, "hrctv_d90_eqd2_gy": round(p.hrctv_d90_eqd2_gy, 3),
                        "aims_met": p.aims_met} for p in self.pareto],
        }
        pl = self.plan
        if pl is None:
            return {**doc, "needles": [], "aims_met": False, "selection": self.selection}
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
            "selection": {**self.selection, "chosen": pl.mip_status},
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
    # each organ's voxels within ``eval_radius_mm`` of any candidate dwell (every loading's organ dose is read there)
    oar_near: tuple[np.ndarray, ...] = ()
    lattices: dict[tuple[int, float], tuple[np.ndarray, np.ndarray]] = field(default_factory=dict, repr=False)

    def near_organ(self, o: int, pos: np.ndarray, radius_mm: float, vox_cc: float, times_2cc: int = 4) -> np.ndarray:
        """:func:`_near_organ` of organ ``o`` for dwells ``pos`` (a subset of the candidates' dwells).

        Read from ``oar_near`` when that provably holds the answer (every voxel of the organ outside it is farther
        than ``eval_radius_mm`` from every candidate dwell), else from all the organ's voxels.
        """
        if self.oar_near and radius_mm <= self.eval_radius_mm:
            near = self.oar_near[o]
            n_min = min(len(self.oar_pts[o]), times_2cc * math.ceil(2.0 / vox_cc))
            if len(near) >= n_min and len(pos):
                dist = cKDTree(pos).query(near)[0]
                if n_min == 0 or np.partition(dist, n_min - 1)[n_min - 1] <= self.eval_radius_mm:
                    return _near_organ(near, pos, radius_mm, vox_cc, times_2cc, dist, n_min)
        return _near_organ(self.oar_pts[o], pos, radius_mm, vox_cc, times_2cc)

    def lattice(self, o: int, pitch_mm: float, vox_cc: float) -> tuple[np.ndarray, np.ndarray]:
        """Organ ``o``'s voxels binned on a lattice of ``pitch_mm``: one point per bin and its volume (cm³)."""
        key = (o, float(pitch_mm))
        if key not in self.lattices:
            pts = self.oar_pts[o]
            _, first, counts = np.unique(np.floor(pts / pitch_mm).astype(np.int64), axis=0, return_index=True,
                                         return_counts=True)
            self.lattices[key] = (pts[first], counts * vox_cc)
        return self.lattices[key]


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
    return prob.kernel.compiled_dose(points, pos, dirs, times) * prob.gy_per_s


#: largest sub-voxel size (mm) at which the final metrics of the target (and GTV) are computed
SUBVOXEL_MM = 0.7


def _supersampled(grid: Grid, mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Points (mm, LPS) and weights at which a structure's final metrics are computed.

    Each voxel split along each axis into ``ceil(spacing / SUBVOXEL_MM)`` sub-voxels (:data:`SUBVOXEL_MM`). The dose
    falls steeply across a target's edge, where D90 and D98 are decided: voxel centres alone are 1-3 % off on a 2 mm
    grid; the tests check the result against a grid six times finer than 2 mm.
    """
    n_axis = [max(1, math.ceil(float(h) / SUBVOXEL_MM - 1e-9)) for h in grid.spacing_mm]  # (i, j, k)
    k, j, i = np.nonzero(mask)
    ijk = np.column_stack([i, j, k]).astype(float)
    ax = [(np.arange(n) + 0.5) / n - 0.5 for n in n_axis]
    off = np.array([[a, b, c] for a in ax[0] for b in ax[1] for c in ax[2]])
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


def _tail_mean(rates: np.ndarray, weight_cc: np.ndarray, volume_cc: float) -> np.ndarray:
    """Mean of each column over its hottest ``volume_cc`` (rows weighted by the volume each stands for).

    ``rates``: (p, k); returns (k,). A column whose rows hold less than ``volume_cc`` is averaged over
    ``volume_cc`` all the same (the mean-tail-dose row's value with its threshold at 0).
    """
    if rates.size == 0:
        return np.zeros(rates.shape[1] if rates.ndim == 2 else 0)
    order = np.argsort(-rates, axis=0, kind="stable")
    r = np.take_along_axis(rates, order, axis=0)
    w = weight_cc[order]
    before = np.cumsum(w, axis=0) - w
    part = np.clip(volume_cc - before, 0.0, w)
    out: np.ndarray = (part * r).sum(axis=0) / volume_cc
    return out


def _organ_sample(lattice: tuple[np.ndarray, np.ndarray], near_mm: np.ndarray,
                  volume_cc: float) -> tuple[np.ndarray, np.ndarray]:
    """Return an organ's representative points for its D2cm³ row, and the volume (cm³) each stands for.

    ``lattice``: the organ's voxel centres binned on a lattice, one point ((n, 3) mm LPS) per bin and the volume
    (cm³) of its voxels (:meth:`_Problem.lattice`); of those, the ones nearest to the dwells ``near_mm``
    ((d, 3) mm) until they hold ``volume_cc``.
    """
    reps, w = lattice
    if len(reps) == 0 or len(near_mm) == 0:
        return np.zeros((0, 3)), np.zeros(0)
    order = np.argsort(cKDTree(near_mm).query(reps)[0], kind="stable")
    n = min(len(order), int(np.searchsorted(np.cumsum(w[order]), volume_cc)) + 1)
    keep = np.sort(order[:n])
    return reps[keep], w[keep]


@dataclass(frozen=True, eq=False)
class _OrganRows:
    """One organ's D2cm³ row: rates (Gy s⁻¹, (p, D)) of its representative points, their volumes (cm³), limit."""

    rates: np.ndarray
    weight_cc: np.ndarray
    limit_gy: float


class _Model:
    """The linear model of a loading (module docstring, "the model"), as an LP or, with needle binaries, a MIP.

    Variables ``[t (units), y (needles), u (target points), T, ζ (organs), s (organ points)]``. A unit is a run
    of consecutive dwells of one channel with a common time (a block in the selection model, one dwell in the
    final one); ``t`` is its time per dwell (s).

    Parameters
    ----------
    units : dwell columns (of ``a_t`` and the organ rates) of each unit, consecutive along each channel.
    unit_ch : (U,) channel of each unit.
    a_t : (m, D) Gy s⁻¹ per fraction at the target (and GTV) points; ``p``: (m,) the dose each should reach.
    organs : the D2cm³ rows.
    needles : channels with a binary (none: an LP over every unit).
    hole_of : template hole of each needle in ``needles`` (a hole takes one needle).
    cost : (len(needles),) invasiveness of each.
    """

    def __init__(self, units: Sequence[np.ndarray], unit_ch: np.ndarray, a_t: np.ndarray, p: np.ndarray,
                 organs: Sequence[_OrganRows], needles: Sequence[int], hole_of: Sequence[str], cost: np.ndarray,
                 settings: ImplantSettings, p_t: float) -> None:
        n_u, n_y, m = len(units), len(needles), len(a_t)
        sizes = np.array([len(u) for u in units], dtype=float)
        member = sparse.csr_matrix((np.ones(int(sizes.sum())), (np.concatenate(units),
                                                                np.repeat(np.arange(n_u), sizes.astype(int)))),
                                   shape=(a_t.shape[1], n_u))
        at = np.asarray((member.T @ a_t.T).T)
        ao = [np.asarray((member.T @ o.rates.T).T) for o in organs]
        n_p = sum(len(o.weight_cc) for o in organs)
        n_o = len(organs)
        i_y, i_u, i_T, i_z, i_s = n_u, n_u + n_y, n_u + n_y + m, n_u + n_y + m + 1, n_u + n_y + m + 1 + n_o
        n = i_s + n_p
        c = np.zeros(n)
        c[:n_u] = settings.time_weight * sizes * at.mean(axis=0) / (p_t * max(sizes.sum(), 1.0))
        c[i_y:i_u] = settings.invasiveness_weight * cost
        c[i_u:i_T] = 1.0 / (m * p_t)
        blocks: list[sparse.spmatrix] = []
        lb: list[np.ndarray] = []
        ub: list[np.ndarray] = []

        def add(rows: sparse.spmatrix, lo: float | np.ndarray, hi: float | np.ndarray) -> None:
            blocks.append(sparse.csr_matrix(rows))
            lb.append(np.broadcast_to(lo, rows.shape[0]).astype(float))
            ub.append(np.broadcast_to(hi, rows.shape[0]).astype(float))

        def cols(parts: Sequence[tuple[int, sparse.spmatrix]], n_rows: int) -> sparse.spmatrix:
            """Return a row block holding each ``(first column, matrix)`` part, zeros elsewhere."""
            mats = []
            at_col = 0
            for start, mat in parts:
                if start > at_col:
                    mats.append(sparse.csr_matrix((n_rows, start - at_col)))
                mats.append(sparse.csr_matrix(mat))
                at_col = start + mat.shape[1]
            if at_col < n:
                mats.append(sparse.csr_matrix((n_rows, n - at_col)))
            return sparse.hstack(mats, format="csr")

        add(cols([(0, at), (i_u, sparse.identity(m))], m), p, np.inf)  # target: A t + u >= p
        # the total time T = Σ sizes·t, and no dwell over the share: t - share·T <= 0
        add(cols([(0, sizes[None, :]), (i_T, -np.ones((1, 1)))], 1), 0.0, 0.0)
        share = settings.max_dwell_share * (1 - 1e-3)
        add(cols([(0, sparse.identity(n_u)), (i_T, -share * np.ones((n_u, 1)))], n_u), -np.inf, 0.0)
        groups = [np.flatnonzero(unit_ch == ch) for ch in np.unique(unit_ch)]
        for rowset in _neighbour_rows(groups, n_u, settings.neighbour_ratio):
            add(cols([(0, rowset)], rowset.shape[0]), -np.inf, 0.0)
        # each organ's mean dose over its hottest 2 cm³ within its limit (a mean-tail-dose row; it implies D2cm³
        # <= limit): ζ + Σ w_i s_i / 2 cm³ <= limit, s_i >= (A t)_i - ζ, s >= 0, ζ >= 0
        start = 0
        limit_rows = []
        for k, (o, a) in enumerate(zip(organs, ao, strict=True)):
            q = len(o.weight_cc)
            add(cols([(0, a), (i_z + k, -np.ones((q, 1))), (i_s + start, -sparse.identity(q))], q), -np.inf, 0.0)
            limit_rows.append(sum(len(x) for x in lb))
            add(cols([(i_z + k, np.ones((1, 1))), (i_s + start, o.weight_cc[None, :] / 2.0)], 1), -np.inf,
                o.limit_gy)
            start += q
        # big-M: a unit's time is at most what brings every target point to its dose alone (more only adds
        # time; scaling the whole loading down keeps every row) and at most what alone fills an organ's limit
        big_m = p.max() / np.maximum(at.min(axis=0), 1e-30)
        for o, a in zip(organs, ao, strict=True):
            big_m = np.minimum(big_m, o.limit_gy / np.maximum(_tail_mean(a, o.weight_cc, 2.0), 1e-30))
        self.big_m = big_m
        if n_y:
            y_of = {ch: i for i, ch in enumerate(needles)}
            r_i, c_i, v = [], [], []
            r = 0
            for u_i, ch in enumerate(unit_ch):
                if int(ch) in y_of:
                    r_i += [r, r]
                    c_i += [u_i, i_y + y_of[int(ch)]]
                    v += [1.0, -float(big_m[u_i])]
                    r += 1
            add(sparse.csr_matrix((v, (r_i, c_i)), shape=(r, n)), -np.inf, 0.0)
            holes = sorted(set(hole_of))
            h_of = {h: i for i, h in enumerate(holes)}
            per_hole = sparse.csr_matrix((np.ones(n_y), ([h_of[h] for h in hole_of], np.arange(n_y))),
                                         shape=(len(holes), n_y))
            add(cols([(i_y, per_hole)], len(holes)), -np.inf, 1.0)
            add(cols([(i_y, np.ones((1, n_y)))], 1), -np.inf, np.inf)  # the budget row (last)
        self.a = sparse.vstack(blocks, format="csr")
        self.a_csc = self.a.tocsc()
        y_index = {ch: i for i, ch in enumerate(needles)}
        self.unit_y = np.array([y_index.get(int(ch), -1) for ch in unit_ch], dtype=int)  # -1: not a needle
        self.lb, self.ub = np.concatenate(lb), np.concatenate(ub)
        self.limit_rows = np.array(limit_rows, dtype=int)
        self.limits = np.array([o.limit_gy for o in organs])
        self.c, self.n, self.n_u, self.n_y, self.i_y, self.i_u = c, n, n_u, n_y, i_y, i_u
        self.member, self.at, self.ao, self.organs, self.p = member, at, ao, organs, p
        self.needles, self.hole_of = list(needles), list(hole_of)
        self.settings = settings

    def solve(self, budget: int | None = None, kappa: np.ndarray | None = None,
              only: Sequence[int] | None = None) -> sopt.OptimizeResult:
        """Solve the LP (the needle binaries relaxed to [0, 1]) with at most ``budget`` needles (None: no budget).

        ``kappa`` (per organ): each organ's mean-tail-dose row may reach ``kappa`` × its limit (the calibration of
        that row to D2cm³, see :func:`_calibrate`). ``only``: the needles (indices into ``needles``) used (``y`` = 1),
        the others held empty: the LP is then solved on their columns alone (and the intracavitary channels'), and
        ``x`` returned in the full model's columns.
        """
        ub = self.ub.copy()
        if kappa is not None and len(self.limit_rows):
            ub[self.limit_rows] = self.limits * kappa
        if self.n_y and budget is not None:
            ub[-1] = float(budget)
        lo = np.zeros(self.n)
        hi = np.full(self.n, np.inf)
        hi[self.i_y:self.i_u] = 1.0
        cols = np.arange(self.n)
        if only is not None:
            on = np.zeros(self.n_y, dtype=bool)
            on[np.asarray(only, dtype=int)] = True
            lo[self.i_y:self.i_u] = on
            keep = np.ones(self.n, dtype=bool)
            keep[:self.n_u] = self.unit_y < 0
            keep[:self.n_u][self.unit_y >= 0] = on[self.unit_y[self.unit_y >= 0]]
            keep[self.i_y:self.i_u] = on
            cols = np.flatnonzero(keep)
        a = self.a if only is None else self.a_csc[:, cols]
        res = sopt.milp(self.c[cols], constraints=[sopt.LinearConstraint(a, self.lb, ub)],
                        bounds=sopt.Bounds(lo[cols], hi[cols]), options={"disp": False})
        if only is not None and res.x is not None:
            x = np.zeros(self.n)
            x[cols] = res.x
            res.x = x
        return res

    def rounded(self, budget: int, kappa: np.ndarray, relaxed: sopt.OptimizeResult,
                keep: Sequence[int] = ()) -> sopt.OptimizeResult | None:
        """Return a feasible selection of at most ``budget`` needles by rounding the LP relaxation ``relaxed``.

        The needles ``keep`` (an incumbent's), then those with the largest relaxed ``y``, one per hole; their best
        loading (an LP). None when that fails.
        """
        picked = list(dict.fromkeys(int(i) for i in keep))[:budget]
        holes = {self.hole_of[i] for i in picked}
        if relaxed.x is not None:
            y = relaxed.x[self.i_y:self.i_u]
            for i in np.argsort(-y, kind="stable"):
                if len(picked) >= budget or y[i] <= 1e-6:
                    break
                if self.hole_of[int(i)] not in holes:
                    picked.append(int(i))
                    holes.add(self.hole_of[int(i)])
        res = self.solve(budget, kappa=kappa, only=picked)
        return res if res.x is not None else None

    def improved(self, budget: int, kappa: np.ndarray, relaxed: sopt.OptimizeResult,
                 start: sopt.OptimizeResult) -> tuple[sopt.OptimizeResult, int]:
        """Improve the selection ``start`` by swaps (a deterministic local search); return it and the LPs solved.

        Moves: add a needle (when under ``budget``) or swap one for another, each drawn from the ``swap_pool``
        needles with the largest relaxed ``y`` (``relaxed``, the LP relaxation at this budget); the best move is
        taken while it lowers the objective, for at most ``swap_passes`` passes. Every move is a feasible selection,
        so the objective never rises; the LP relaxation still bounds the optimum from below.
        """
        best = start
        n_lp = 0
        if relaxed.x is None or self.settings.swap_passes == 0:
            return best, n_lp
        y = relaxed.x[self.i_y:self.i_u]
        pool = [int(i) for i in np.argsort(-y, kind="stable")[:self.settings.swap_pool] if y[i] > 1e-6]
        tried: set[frozenset[int]] = set()
        for _ in range(self.settings.swap_passes):
            sel = [int(i) for i in np.flatnonzero(best.x[self.i_y:self.i_u] > 0.5)]
            tried.add(frozenset(sel))
            moves = []
            for j in pool:
                if j in sel:
                    continue
                outs: list[int | None] = [None] if len(sel) < budget else []
                for out in [*outs, *sel]:
                    rest = [i for i in sel if i != out]
                    if self.hole_of[j] not in {self.hole_of[i] for i in rest}:
                        moves.append([*rest, j])
            step = best
            for move in moves:
                if frozenset(move) in tried:
                    continue
                tried.add(frozenset(move))
                res = self.solve(budget, kappa=kappa, only=move)
                n_lp += 1
                if res.x is not None and float(res.fun) < float(step.fun) - 1e-9 * max(1.0, abs(float(step.fun))):
                    step = res
            if step is best:
                break
            best = step
        return best, n_lp

    def dwell_times(self, x: np.ndarray) -> np.ndarray:
        """(D,) dwell times (s) of a solution ``x``."""
        out: np.ndarray = self.member @ np.maximum(x[:self.n_u], 0.0)
        return out

    def tail_means(self, x: np.ndarray) -> np.ndarray:
        """Each organ's mean dose (Gy) over its hottest 2 cm³ of representative points, for solution ``x``."""
        t = np.maximum(x[:self.n_u], 0.0)
        return np.array([float(_tail_mean((a @ t)[:, None], o.weight_cc, 2.0)[0])
                         for a, o in zip(self.ao, self.organs, strict=True)])


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
    for o, limit in enumerate(prob.oar_limits):
        d = _dose(prob.near_organ(o, pos, prob.eval_radius_mm, vox_cc), pos, dirs, t, prob)
        dose_oar.append(d)
        if limit is not None and len(d):
            d2 = dose_to_volume(d, vox_cc, 2.0)
            if d2 > limit:
                scale = min(scale, limit / d2 * (1 - 1e-9))
    t = t * scale
    sub_cc = vox_cc * len(prob.target_pts) / max(len(prob.target_fine[0]), 1)  # target and GTV on sub-voxels
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


@dataclass(frozen=True)
class BudgetResult:
    """The needle selection at one budget ("at most ``budget`` needles").

    ``objective``: the selection model's value at the selection kept; ``dual_bound``: the LP relaxation's (a
    lower bound of every selection of ``budget`` needles), ``mip_gap``: the relative gap between the two (None when
    the relaxation failed); ``n_needles``: the
    needles selected; ``new``: False when the selection equals a smaller budget's (no new Pareto point).
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
        """Return the record for plan.json ``selection.budgets``."""
        return {"budget": self.budget, "n_needles": self.n_needles, "objective": round(self.objective, 6),
                "dual_bound": None if self.dual_bound is None else round(self.dual_bound, 6),
                "mip_gap": None if self.mip_gap is None else round(self.mip_gap, 5), "status": self.status,
                "seconds": round(self.seconds, 3), "new_selection": self.new}


def _organ_rows(prob: _Problem, pos: np.ndarray, dirs: np.ndarray, pitch_mm: float, volume_cc: float,
                vox_cc: float) -> list[_OrganRows]:
    """Return the D2cm³ rows of every organ with a limit, for the dwells ``pos``/``dirs`` (module docstring)."""
    out = []
    for o, limit in enumerate(prob.oar_limits):
        if limit is None:
            continue
        reps, w = _organ_sample(prob.lattice(o, pitch_mm, vox_cc), pos, volume_cc)
        out.append(_OrganRows(_rates(reps, pos, dirs, prob), w, float(limit)))
    return out


def _d2cc(prob: _Problem, pos: np.ndarray, dirs: np.ndarray, t: np.ndarray, vox_cc: float) -> np.ndarray:
    """Return the D2cm³ (Gy per fraction) of every organ with a limit, on its 20 cm³ nearest the loaded dwells."""
    on = t > 0
    out = []
    for o, (pts, limit) in enumerate(zip(prob.oar_pts, prob.oar_limits, strict=True)):
        if limit is None:
            continue
        if not on.any() or len(pts) == 0:
            out.append(0.0)
            continue
        near = prob.near_organ(o, pos[on], 0.0, vox_cc, 10)  # the nearest 20 cm³ hold the hottest 2 cm³
        out.append(dose_to_volume(_dose(near, pos[on], dirs[on], t[on], prob), vox_cc, 2.0))
    return np.array(out)


def _near_organ(pts: np.ndarray, pos: np.ndarray, radius_mm: float, vox_cc: float, times_2cc: int = 4,
                dist: np.ndarray | None = None, n_min: int | None = None) -> np.ndarray:
    """Return an organ's voxels within ``radius_mm`` of a dwell, and at least its nearest ``times_2cc`` × 2 cm³.

    ``dist``: each voxel's distance to the dwells when known; ``n_min``: the voxel count of ``times_2cc`` × 2 cm³
    (of the whole organ when ``pts`` is a part of it).
    """
    if dist is None:
        dist = cKDTree(pos).query(pts)[0] if len(pos) else np.zeros(len(pts))
    if n_min is None:
        n_min = min(len(pts), times_2cc * math.ceil(2.0 / vox_cc))
    keep = dist <= radius_mm
    keep[np.argsort(dist, kind="stable")[:n_min]] = True
    out: np.ndarray = pts[keep]
    return out


def _calibrate(kappa: np.ndarray, d2: np.ndarray, tails: np.ndarray, limits: np.ndarray) -> np.ndarray:
    """Calibrate each organ's mean-tail-dose row to its D2cm³.

    An organ whose row binds (or whose exact D2cm³ is over its limit) gets ``kappa × limit / D2cm³``: the mean
    over the hottest 2 cm³ exceeds D2cm³ by a factor that changes little between nearby loadings, so the next
    solution's D2cm³ lands on the limit (within 1 % in two rounds on the clinical case).
    """
    out = kappa.copy()
    binds = (tails >= 0.98 * limits * kappa) | (d2 > limits * (1 + 1e-3))
    ok = binds & (d2 > 0)
    out[ok] = np.clip(kappa[ok] * limits[ok] / d2[ok] * (1 - 2e-3), 0.25, 4.0)
    return out


def plan_implant(name: str, channels: Sequence[Channel], planning: PlanningStructures, kernel: Tg43Kernel,
                 air_kerma_strength_u: float, aims: Aims | None = None, settings: ImplantSettings | None = None, *,
                 gtv: Structure | None = None) -> ImplantArm:
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
    needles = [i for i, c in enumerate(channels) if c.is_needle]
    if not channels:
        return ImplantArm(name, 0, (), None, time.perf_counter() - t0, "no candidate channel")
    grid = planning.grid
    vox_cc = voxel_volume_cc(grid)
    positions = np.concatenate([c.dwell_positions_mm for c in channels])
    directions = np.concatenate([c.dwell_directions for c in channels])
    channel_of = np.repeat(np.arange(len(channels)), [len(c.dwell_positions_mm) for c in channels])
    prob = _Problem(
        channels, positions, directions, channel_of,
        grid_points_mm(grid, np.flatnonzero(planning.target.mask.ravel())),
        None if gtv is None else grid_points_mm(grid, np.flatnonzero(gtv.mask.ravel())),
        tuple(grid_points_mm(grid, np.flatnonzero(o.mask.ravel())) for o in planning.oars),
        tuple(aims.oar_limit_gy(o.name) for o in planning.oars), air_kerma_strength_u / 360000.0, kernel,
        tuple(o.name for o in planning.oars), settings.oar_eval_radius_mm, _supersampled(grid, planning.target.mask),
        None if gtv is None else _supersampled(grid, gtv.mask))
    tree = cKDTree(positions)  # every voxel of an organ outside oar_near is farther than the radius from any dwell
    prob = dataclasses.replace(prob, oar_near=tuple(
        pts[np.isfinite(tree.query(pts, distance_upper_bound=settings.oar_eval_radius_mm * (1 + 1e-6) + 1e-6)[0])]
        for pts in prob.oar_pts))
    p_t = aims.prescription_gy * (1.0 + settings.coverage_margin)
    p_g = aims.fractionation.per_fraction_for(aims.gtv_d98_eqd2_gy, aims.alpha_beta_target_gy) * (
        1.0 + settings.coverage_margin)

    def target_rows(n_pts: int) -> tuple[np.ndarray, np.ndarray]:
        pts = [prob.target_pts[_stride(len(prob.target_pts), n_pts)]]
        p = [np.full(len(pts[0]), p_t)]
        if prob.gtv_pts is not None and len(prob.gtv_pts):
            pts.append(prob.gtv_pts[_stride(len(prob.gtv_pts), max(1, n_pts // 4))])
            p.append(np.full(len(pts[1]), p_g))
        return np.concatenate(pts), np.concatenate(p)

    sel_pts, sel_p = target_rows(settings.selection_target_points)
    fin_pts, fin_p = target_rows(settings.final_target_points)
    cost = np.zeros(len(needles))
    if needles:
        dmax = max(max(channels[i].hole_distance_mm for i in needles), 1e-9)
        lmax = max(max(channels[i].tissue_length_mm for i in needles), 1e-9)
        cost = np.array([0.5 * channels[i].hole_distance_mm / dmax + 0.5 * channels[i].tissue_length_mm / lmax
                         for i in needles])
    units, unit_ch = [], []
    for c in range(len(channels)):
        for part in np.array_split(np.flatnonzero(channel_of == c), min(settings.segments_per_channel,
                                                                        int(np.sum(channel_of == c)))):
            units.append(part)
            unit_ch.append(c)
    organs = _organ_rows(prob, positions, directions, settings.selection_oar_pitch_mm, settings.oar_sample_cc,
                         vox_cc)
    limits = np.array([o.limit_gy for o in organs])
    model = _Model(units, np.array(unit_ch), _rates(sel_pts, positions, directions, prob), sel_p, organs, needles,
                   [channels[i].name for i in needles], cost, settings, p_t)
    kappa = np.ones(len(organs))
    # the arm's bound: every candidate loaded, no budget (an LP); its solution calibrates the organ rows
    free = model.solve(None, kappa=kappa)
    if free.x is not None:
        kappa = _calibrate(kappa, _d2cc(prob, positions, directions, model.dwell_times(free.x), vox_cc),
                           model.tail_means(free.x), limits)
        free = model.solve(None, kappa=kappa)
    bound = float(free.fun) if free.x is not None else float("nan")

    def select(k: int, keep: Sequence[int]) -> tuple[np.ndarray | None, float, float | None, str]:
        """Select at most ``k`` needles: return (solution, objective, lower bound (LP relaxation), how it ended).

        Starts: the LP relaxation rounded with the last budget's needles kept (so the objective never rises with
        ``k``: every budget's model has the same organ rows); then swaps.
        """
        relaxed = model.solve(k, kappa=kappa)  # its optimum bounds every selection of k needles from below
        starts = [model.rounded(k, kappa, relaxed, keep), model.rounded(k, kappa, relaxed, ())]
        if keep:  # the last budget's selection itself (a needle added to it costs its invasiveness)
            last = model.solve(k, kappa=kappa, only=keep)
            starts.append(last if last.x is not None else None)
        inc = min((r for r in starts if r is not None), key=lambda r: float(r.fun), default=None)
        lower = float(relaxed.fun) if relaxed.x is not None else None
        if inc is None:
            return None, float("inf"), lower, "no feasible selection (the rounded LP relaxation failed)"
        best, n_lp = model.improved(k, kappa, relaxed, inc)
        status = (f"rounded LP relaxation improved by {n_lp} swap LPs" if best is not inc else
                  f"rounded LP relaxation, no better swap in {n_lp} LPs")
        return best.x, float(best.fun), lower, status

    intracavitary = [c for c in range(len(channels)) if not channels[c].is_needle]
    budgets: list[BudgetResult] = []
    plans: list[ImplantPlan] = []
    seen: dict[tuple[int, ...], ImplantPlan | None] = {}
    keep: list[int] = []  # the last budget's needles (indices into ``needles``): a start for the next
    met_at: int | None = None
    stall = 0
    for k in range(0 if intracavitary else 1, min(settings.max_needles, len(needles)) + 1):
        t_k = time.perf_counter()
        x, value, lower, status = select(k, keep)
        if x is None:
            budgets.append(BudgetResult(k, 0, value, None, None, status, time.perf_counter() - t_k, False))
            continue
        times = model.dwell_times(x)
        ch_time = np.bincount(channel_of, weights=times, minlength=len(channels))
        keep = [i for i in range(len(needles)) if x[model.i_y + i] > 0.5 and ch_time[needles[i]] > 0]
        picked = tuple(sorted([needles[i] for i in keep] + intracavitary))
        gap = None if lower is None else max(0.0, (value - lower) / max(abs(value), 1e-12))
        new = bool(picked) and picked not in seen
        if new:
            seen[picked] = _final(
                prob, np.array(picked, dtype=int), fin_pts, fin_p, aims, settings, vox_cc, kappa.copy(),
                f"budget {k}: selection objective {value:.6g}, {status}", gap)
        budgets.append(BudgetResult(k, len(keep), value, lower, gap, status, time.perf_counter() - t_k, new,
                                    tuple(channels[c] for c in picked), seen.get(picked) if new else None))
        if new:
            stall = 0
            plan = seen[picked]
            if plan is not None:
                plans.append(plan)
                if plan.aims_met and met_at is None:
                    met_at = k
        else:
            stall += 1
        if met_at is not None and k >= met_at + settings.extra_after_aims:
            break
        if stall >= 2 or value <= bound + 1e-9 * max(1.0, abs(bound)):
            break  # nothing new twice, or the selection reaches the bound of every candidate loaded
    record: dict[str, object] = {
        "model": "needle selection: LP relaxation (HiGHS through scipy.optimize.milp) on sampled target points and "
                 "organ mean-tail-dose rows, dwells in blocks, rounded and improved by swaps; dwell times: LP on every "
                 "dwell of the selection",
        "all_candidates_objective": None if not np.isfinite(bound) else round(bound, 6),
        "budgets": [b.to_json() for b in budgets]}
    return _arm(name, len(needles), plans, time.perf_counter() - t0, tuple(budgets), record)


def _arm(name: str, n_candidates: int, plans: Sequence[ImplantPlan], seconds: float,
         budgets: tuple[BudgetResult, ...], record: dict[str, object]) -> ImplantArm:
    """Return an arm from its plans: the Pareto curve and the plan chosen from it (:func:`plan_implant`)."""
    pareto_plans = _pareto(plans)
    pareto = tuple(ParetoPoint(p.n_needles, p.target.d90_eqd2_gy, p.aims_met) for p in pareto_plans)
    if not pareto_plans:
        return ImplantArm(name, n_candidates, (), None, seconds, "no needle budget gave a plan (every LP failed)",
                          budgets, record)
    meeting = [p for p in pareto_plans if p.aims_met]
    chosen = (min(meeting, key=lambda p: (p.n_needles, -p.target.d90_eqd2_gy)) if meeting
              else max(pareto_plans, key=lambda p: (p.target.d90_eqd2_gy, -p.n_needles)))
    reason = "" if meeting else "no needle budget meets every aim; the plan with the highest D90 is kept"
    return ImplantArm(name, n_candidates, pareto, chosen, seconds, reason, budgets, record, tuple(pareto_plans))


def with_subset(arm: ImplantArm, subset: ImplantArm) -> ImplantArm:
    """Return ``arm`` with the implants of ``subset`` (an arm planned on a subset of its candidates) added.

    Every implant of the subset arm is one of this arm's too, so the result is never worse than ``subset``: its
    Pareto curve and chosen plan are taken over both arms' plans (two arms planned independently, e.g. at once).
    """
    return _arm(arm.name, arm.n_candidates, [*arm.plans, *subset.plans], arm.seconds, arm.budgets, arm.selection)


def plan_arms(arms: Sequence[tuple[str, Sequence[Channel]]], planning: PlanningStructures, kernel: Tg43Kernel,
              air_kerma_strength_u: float, aims: Aims | None = None, settings: ImplantSettings | None = None, *,
              gtv: Structure | None = None, workers: int = 2) -> tuple[ImplantArm, ...]:
    """Plan several arms (:func:`plan_implant`, each on its own), in up to ``workers`` threads.

    HiGHS and the compiled dose kernels release the GIL, so two arms run on two cores. Threads only when the
    compiled kernels' threading layer allows calls from several threads at once (``omp`` or ``tbb``; numba's
    ``workqueue`` does not); else one after the other, with the same result (the arms do not share state).
    """
    def one(arm: tuple[str, Sequence[Channel]]) -> ImplantArm:
        return plan_implant(arm[0], arm[1], planning, kernel, air_kerma_strength_u, aims, settings, gtv=gtv)

    if workers < 2 or len(arms) < 2 or not _threads_safe(kernel):
        return tuple(one(a) for a in arms)
    from concurrent.futures import ThreadPoolExecutor

    with ThreadPoolExecutor(min(workers, len(arms))) as pool:
        return tuple(pool.map(one, arms))


def _threads_safe(kernel: Tg43Kernel) -> bool:
    """Return True when numba's threading layer runs parallel kernels called from several threads at once."""
    import numba

    kernel.compiled_dose(np.zeros((1, 3)), np.ones((1, 3)), np.array([[0.0, 0.0, 1.0]]), np.ones(1))  # loads it
    try:
        return str(numba.threading_layer()) in ("omp", "tbb")
    except ValueError:  # no parallel kernel has run
        return False


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


def _final(prob: _Problem, chosen: np.ndarray, fin_pts: np.ndarray, fin_p: np.ndarray, aims: Aims,
           settings: ImplantSettings, vox_cc: float, kappa: np.ndarray, status: str, gap: float | None,
           ) -> ImplantPlan | None:
    """Dwell times on the chosen channels (an LP on every dwell; the empty-needle rule) and the plan's metrics."""
    p_t = aims.prescription_gy * (1.0 + settings.coverage_margin)
    t = np.zeros(0)
    cols = np.zeros(0, dtype=int)
    for _ in range(3):
        cols = np.flatnonzero(np.isin(prob.channel_of, chosen))
        pos, dirs = prob.positions[cols], prob.directions[cols]
        a_t = _rates(fin_pts, pos, dirs, prob)
        organs = _organ_rows(prob, pos, dirs, settings.final_oar_pitch_mm, settings.oar_sample_cc, vox_cc)
        limits = np.array([o.limit_gy for o in organs])
        model = _Model([np.array([j]) for j in range(len(cols))], prob.channel_of[cols], a_t, fin_p, organs, [], [],
                       np.zeros(0), settings, p_t)
        kap = kappa.copy()
        x = None
        for _ in range(4):  # until the organ rows are calibrated to D2cm³ within 1 %
            res = model.solve(kappa=kap)
            if res.x is None:
                break
            x = res.x
            new = _calibrate(kap, _d2cc(prob, pos, dirs, model.dwell_times(x), vox_cc), model.tail_means(x), limits)
            if np.all(np.abs(new / kap - 1) < 0.01):
                break
            kap = new
        if x is None:
            return None
        t = model.dwell_times(x)
        t = np.where(t >= settings.min_dwell_time_s, t, 0.0)
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
