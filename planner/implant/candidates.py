"""Candidate channels for a volume: needles through the HR-CTV that keep clear of the organs, and applicator channels.

Candidates (:func:`needle_candidates`): every template hole × (straight, and every stylet design × tension
schedule of the shape bank × roll) whose path passes through the HR-CTV and keeps ``clearance_margin_mm``
from every organ at risk. Paths are screened on Euclidean distance maps of the planning grid (target grown by
the dwell margin; organs at risk), and the kept ones are confirmed with the organs' distance fields (bounds on the
clearance) and, for a path they cannot prove farther than the margin plus :data:`CONFIRM_BAND_MM` from every organ,
with the FCL clearance of :func:`reachplan.planner.geometry.collision.check_path`. Intracavitary channels
(tandem, ring, ovoids, cylinder) are passed in as :class:`Channel` objects of kind ``"intracavitary"``; they are
always available and not counted as needles. Dwell positions are every ``dwell_step_mm`` along the part of each
needle inside the HR-CTV grown by ``dwell_margin_mm``; in an applicator channel they follow its path by arc length
from the afterloader's source-tip offset (``applicator_tip_offset_mm`` back from the channel's end), those in that
region kept.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import ClassVar

import numpy as np

from reachplan._arrays import arc_length_mm
from reachplan.imaging.types import Grid
from reachplan.planner.dose.dwells import dwell_directions
from reachplan.planner.dose.structures import PlanningStructures
from reachplan.planner.geometry.collision import Organ, check_path
from reachplan.planner.geometry.distance_field import distance_transform
from reachplan.planner.implant.settings import ImplantSettings
from reachplan.planner.steering.candidates import TissueBand
from reachplan.planner.steering.insertion import STRAIGHT
from reachplan.planner.steering.schedule import TensionSchedule
from reachplan.planner.steering.steered import ShapeBank, place
from reachplan.plugins.applicators import Applicator

NEEDLE_KINDS = ("straight", "steered")
#: a candidate's clearance is confirmed with FCL when an organ's distance field cannot prove it beyond the
#: clearance margin plus this (mm); beyond, the candidate is clear and its clearance is the field's estimate
CONFIRM_BAND_MM = 1.0


@dataclass(frozen=True, eq=False)
class Channel:
    """A candidate source channel: a needle (straight or steered) or an intracavitary channel.

    Parameters
    ----------
    name : str
        Hole id (needles) or applicator channel name.
    kind : str
        ``"straight"``, ``"steered"`` or ``"intracavitary"``.
    path_mm : (k, 3) float, mm, LPS
        From the template (base) to the tip.
    dwell_positions_mm : (d, 3) float, mm, LPS
        Deepest first.
    hole_distance_mm : float, mm
        Distance of the hole from the template centre (0 for intracavitary channels).
    tissue_length_mm : float, mm
        Needle length beyond the template plane.
    clearance_mm : float, mm
        Smallest surface distance to an organ at risk (FCL within the margin plus :data:`CONFIRM_BAND_MM`; beyond,
        the organs' distance-field estimate, within its error bound).
    design : str
        Stylet preset ("" for a straight needle).
    schedule : TensionSchedule or None
        Tension and roll along the insertion (None for a straight needle).
    scenario_paths_mm : tuple of (k, 3) float, mm, LPS
        Where the needle may really go: paths of the planner's own uncertainty model (for a steered needle the
        robustness room's worst-case paths), base to tip; empty when not computed. Robust planning adds its own
        sideways shifts of ``path_mm`` to these.
    model : str
        The model that predicted ``path_mm``, as its label (``ModelInfo.label``): the screening model's for a steered
        candidate, the reference model's once re-solved (:mod:`reachplan.planner.implant.needles`), ``"straight"`` for
        a straight needle; "" for an intracavitary channel.
    check : NeedleCheck or None
        The needle's check as an exported needle (reference re-solve, robustness, tension); None when not checked.
    tissue_band : TissueBand or None
        A steered implant needle's path over the plan's range of tissue moduli and its worst case
        (:mod:`reachplan.planner.implant.tissue`); None when not computed.
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
    scenario_paths_mm: tuple[np.ndarray, ...] = field(default=(), repr=False)
    model: str = ""
    check: NeedleCheck | None = None
    tissue_band: TissueBand | None = None

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
        """(d, 3) float, unit vectors, LPS: the source axis at each dwell, toward the tip."""
        return dwell_directions(self.path_mm[::-1], self.dwell_positions_mm)  # it takes the path tip first


@dataclass(frozen=True)
class NeedleCheck:
    """An implant needle checked like a ranked one: its model, tension against the limit, worst case, dwell shift.

    Parameters
    ----------
    peak_tension_n : float, N
        Largest tendon tension of the schedule (0 for a straight needle).
    tension_limit_n : float or None, N
        The stylet's design limit (None for a straight needle).
    tension_reserve : float
        The fraction of the limit the plan keeps in reserve (``PlanConfig.tension_reserve``; 0 for a straight needle).
    reach_error_mm : float, mm
        Distance from the checked path's tip to the planned tip (the screening path's; 0 for a straight needle).
    worst_reach_mm : float, mm
        Largest tip error from the planned tip over the robustness check's perturbations (and the nominal path).
    worst_clearance_mm : float, mm
        Smallest clearance to an organ at risk over them (0 when one collides; inf without organs).
    worst_case : str
        The perturbation that set the worst case (``"nominal"`` when none is worse).
    robustness_model : str
        The fast model of the perturbed paths (``ModelInfo.label``).
    dwell_shift_mm : float, mm
        Largest distance between a dwell on the screening path and the same dwell (same distance from the tip) on
        the re-solved path (0 for a straight needle).
    """

    peak_tension_n: float
    tension_limit_n: float | None
    tension_reserve: float
    reach_error_mm: float
    worst_reach_mm: float
    worst_clearance_mm: float
    worst_case: str
    robustness_model: str
    dwell_shift_mm: float = 0.0

    #: the JSON fields of a channel that was not checked (an intracavitary channel, a plan not checked)
    NOT_CHECKED: ClassVar[dict[str, object]] = dict.fromkeys(
        ("peak_tension_n", "tension_limit_n", "tension_reserve", "tension_reserve_n", "reach_error_mm",
         "worst_reach_mm", "worst_clearance_mm", "worst_case", "robustness_model", "dwell_shift_mm"))

    def to_json(self) -> dict[str, object]:
        """Return the check for plan.json's ``implant.<arm>.needles[*]``.

        Returns
        -------
        dict
            ``peak_tension_n``, ``tension_limit_n`` (N; None without a stylet), ``tension_reserve`` (the fraction
            kept), ``tension_reserve_n`` (limit less peak, N), ``reach_error_mm``, ``worst_reach_mm``,
            ``worst_clearance_mm`` (None when not finite), ``worst_case``, ``robustness_model``, ``dwell_shift_mm``.
        """
        def r(v: float | None) -> float | None:
            return None if v is None or not np.isfinite(v) else round(float(v), 3)

        limit = self.tension_limit_n
        return {"peak_tension_n": r(self.peak_tension_n), "tension_limit_n": r(limit),
                "tension_reserve": round(self.tension_reserve, 4),
                "tension_reserve_n": None if limit is None else r(limit - self.peak_tension_n),
                "reach_error_mm": r(self.reach_error_mm), "worst_reach_mm": r(self.worst_reach_mm),
                "worst_clearance_mm": r(self.worst_clearance_mm), "worst_case": self.worst_case,
                "robustness_model": self.robustness_model, "dwell_shift_mm": r(self.dwell_shift_mm)}


# --- candidates ---------------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class _Field:
    """A distance map (mm) on a crop of the planning grid; points outside the crop read ``outside``.

    ``values`` holds the crop framed by one voxel of ``outside`` on every side, ``offset`` the frame's first voxel:
    a point's voxel clipped to the framed array reads the crop inside it and ``outside`` beyond it.
    """

    index_from_patient: np.ndarray
    offset: np.ndarray  # (3,) int, (k, j, i) of the framed array's first voxel on the full grid
    values: np.ndarray  # (nk + 2, nj + 2, ni + 2) float, the crop framed by ``outside``
    outside: float

    def index(self, points_mm: np.ndarray) -> np.ndarray:
        """Return the voxel of each point on the full planning grid (the same for every field of one grid).

        Parameters
        ----------
        points_mm : (..., 3) float, mm, LPS
            Points in the patient frame.

        Returns
        -------
        (..., 3) int32, voxel index (k, j, i)
            The nearest voxel centre, on the full grid (not the crop); may lie outside it.
        """
        p = np.asarray(points_mm, dtype=np.float32)
        a = self.index_from_patient.astype(np.float32)
        return np.rint(p @ a[:3, :3].T + a[:3, 3]).astype(np.int32)[..., ::-1]

    def at(self, points_mm: np.ndarray, kji: np.ndarray | None = None) -> np.ndarray:
        """Return the distance map's value at each point (its nearest voxel centre).

        Parameters
        ----------
        points_mm : (..., 3) float, mm, LPS
            The points (not read when ``kji`` is given).
        kji : (..., 3) int, voxel index (k, j, i), optional
            The points' voxels on the full grid (:meth:`index`), when already known.

        Returns
        -------
        (...,) float, mm
            Distance to the mask (0 inside); ``outside`` for a point beyond the crop.
        """
        kji = (self.index(points_mm) if kji is None else kji) - self.offset
        _, nj, ni = self.values.shape
        k, j, i = np.moveaxis(np.clip(kji, 0, np.array(self.values.shape) - 1), -1, 0)  # beyond: the frame
        out: np.ndarray = self.values.ravel().take((k * nj + j) * ni + i)
        return out


def _distance_field(grid: Grid, mask: np.ndarray, pad_mm: float, box_mask: np.ndarray | None = None) -> _Field:
    """Return the distance (mm) from each voxel centre to the nearest voxel of ``mask`` (0 inside).

    On the crop holding ``box_mask`` (default ``mask``) padded by ``pad_mm``.
    """
    spacing = grid.spacing_mm[::-1]  # (k, j, i)
    box = mask if box_mask is None else box_mask
    idx = np.argwhere(box)
    if len(idx) == 0:
        return _Field(grid.index_from_patient, np.zeros(3, int), np.full((1, 1, 1), np.inf), np.inf)  # all frame
    pad = np.ceil(pad_mm / spacing).astype(int) + 1
    lo = np.maximum(idx.min(axis=0) - pad, 0)
    hi = np.minimum(idx.max(axis=0) + pad + 1, np.array(grid.shape))
    crop = mask[lo[0]:hi[0], lo[1]:hi[1], lo[2]:hi[2]]
    values = distance_transform(crop, spacing)  # infinite without a seed
    framed = np.pad(np.asarray(values, dtype=float), 1, constant_values=np.inf)
    return _Field(grid.index_from_patient, lo - 1, framed, np.inf)


def confirmed_clearance(path_mm: np.ndarray, organs: Sequence[Organ], needle_radius_mm: float, margin_mm: float,
                        band_mm: float) -> float | None:
    """Return a candidate path's clearance from the organs, or None when it comes closer than ``margin_mm``.

    An organ's distance field bounds the clearance: a path it proves too close fails FCL too; one it proves farther
    than ``band_mm`` from every organ (and not starting inside one) is clear, its clearance the fields' estimate.
    Otherwise FCL decides (:func:`reachplan.planner.geometry.collision.check_path`).

    Parameters
    ----------
    path_mm : (k, 3) float
        The needle's centreline, mm, LPS, base to tip.
    organs : sequence of Organ
        The organs to keep off (meshes, with distance fields where built).
    needle_radius_mm : float
        The needle's outer radius, mm.
    margin_mm : float
        The clearance a candidate must keep, mm.
    band_mm : float
        Beyond this clearance (mm) the distance fields' estimate is taken without FCL.

    Returns
    -------
    float or None
        The smallest surface distance to an organ, mm (inf without organs); None for a path too close or colliding.
    """
    bounds = [None if o.field is None else o.field.path_clearance(path_mm, needle_radius_mm) for o in organs]
    if any(b is not None and b[2] < margin_mm for b in bounds):
        return None
    if all(b is not None and b[1] > band_mm for b in bounds):
        if any(o.contains(path_mm[0]) for o in organs):
            return None
        return min((b[0] for b in bounds if b is not None), default=float("inf"))
    checks = check_path(path_mm, needle_radius_mm, tuple(organs)) if organs else ()  # containment cached per organ
    clearance = min((c.clearance_mm for c in checks), default=float("inf"))
    if any(c.collides for c in checks) or clearance < margin_mm:
        return None
    return clearance


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


def needle_candidates(hole_ids: Sequence[str], hole_xy_mm: np.ndarray, hole_distance_mm: np.ndarray,
                      patient_from_template: np.ndarray, planning: PlanningStructures, organs: Sequence[Organ],
                      needle_radius_mm: float, settings: ImplantSettings | None = None,
                      banks: Sequence[ShapeBank] = (), max_depth_mm: float = 200.0,
                      straight: bool = True) -> tuple[Channel, ...]:
    """Candidate needles through the HR-CTV that keep the clearance margin to every organ at risk.

    Parameters
    ----------
    hole_ids : sequence of str
        The template's needle holes (H of them).
    hole_xy_mm : (H, 2) float, mm, template frame
        Each hole's position on the template.
    hole_distance_mm : (H,) float, mm
        Each hole's distance from the template centre.
    patient_from_template : (4, 4) float, homogeneous, template frame mm -> LPS mm
        The template's pose (its z axis is the insertion direction).
    planning : PlanningStructures
        The target and organ masks (the organ masks give the screening distance map).
    organs : sequence of Organ
        Organ meshes (LPS mm) for the exact (FCL) clearance of the kept candidates.
    needle_radius_mm : float, mm
    settings : ImplantSettings, optional
        Dwell step and margin, clearance margin, minimum dwells, rolls and steered candidates per hole.
    banks : sequence of ShapeBank
        Steered shape banks (one per stylet design; none: straight needles only).
    max_depth_mm : float, mm
        Deepest straight needle screened.
    straight : bool
        Include straight needles.

    Returns
    -------
    tuple of Channel
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
        return confirmed_clearance(path, organs, needle_radius_mm, settings.clearance_margin_mm, band_mm)

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
                           tip, clearance, model=STRAIGHT.label))
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
    cos = np.array([math.cos(math.radians(r)) for r in rolls])
    sin = np.array([math.sin(math.radians(r)) for r in rolls])
    rot_t = np.zeros((len(rolls), 1, 3, 3))  # each roll's rotation about the template axis, transposed
    rot_t[:, 0, 0, 0], rot_t[:, 0, 0, 1], rot_t[:, 0, 1, 0], rot_t[:, 0, 1, 1] = cos, sin, -sin, cos
    rot_t[:, 0, 2, 2] = 1.0
    by_hole = {c.name: c for c in straight_channels}
    out: list[Channel] = []
    for h, hole in enumerate(hole_ids):
        found = []  # (approximate dwell count, peak tension, shape index, roll, centroid)
        # every roll at once: (rolls, S', n, 3), each roll's slice the product its own loop computed
        local = coarse[None] @ rot_t + np.array([xy[h, 0], xy[h, 1], 0.0])
        pts = local @ m[:3, :3].T + m[:3, 3]  # LPS
        kji = region.index(pts)
        inside = region.at(pts, kji) <= in_region
        n_in = inside.sum(axis=2)
        ro, rows = np.nonzero(n_in / per_dwell >= settings.min_dwells)
        if len(rows):
            last = inside.shape[2] - 1 - np.argmax(inside[ro, rows, ::-1], axis=1)
            tip_idx = np.minimum(last + math.ceil(settings.tip_offset_mm / (bank.step_mm * every)),
                                 inside.shape[2] - 1)
            clear = np.minimum.accumulate(oar.at(pts[ro, rows], kji[ro, rows]), axis=1)[np.arange(len(rows)),
                                                                                        tip_idx]
            centroids = (inside[ro, rows][..., None] * pts[ro, rows]).sum(axis=1) / n_in[ro, rows][:, None]
            for r in np.flatnonzero(clear >= oar_min):
                k = int(bent[rows[r]])
                found.append((float(n_in[ro[r], rows[r]]), bank.schedules[k].peak_tension_n, k, float(rolls[ro[r]]),
                              centroids[r]))
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
                               clearance, bank.design.name, sched, model=bank.model.label))
            kept.append(centroid)
            n_kept += 1
    return out


def applicator_dwell_arclengths(length_mm: float, settings: ImplantSettings) -> np.ndarray:
    """Return the dwell positions an afterloader can reach in an applicator channel, as arc lengths, deepest first.

    The deepest lies ``settings.applicator_tip_offset_mm`` back from the channel's end; the others follow every
    ``settings.dwell_step_mm`` toward the base.

    Parameters
    ----------
    length_mm : float, mm
        The channel's length along its path (base to end).
    settings : ImplantSettings
        The tip offset and the dwell step.

    Returns
    -------
    (d,) float, mm
        Arc lengths from the channel's base, decreasing, all within [0, ``length_mm``]; empty when the channel is
        shorter than the tip offset.
    """
    first = float(length_mm) - settings.applicator_tip_offset_mm
    if not first >= 0.0:
        return np.zeros(0)
    return first - settings.dwell_step_mm * np.arange(int(first // settings.dwell_step_mm + 1e-9) + 1)


def intracavitary_channel(name: str, path_mm: np.ndarray, planning: PlanningStructures,
                          settings: ImplantSettings | None = None) -> Channel | None:
    """Return an applicator channel with the dwells along its path that lie in the target grown by the dwell margin.

    The dwell positions follow the channel's path (curved as drawn) by arc length from the source-tip offset
    (:func:`applicator_dwell_arclengths`); those inside the HR-CTV grown by ``settings.dwell_margin_mm`` are kept.

    Parameters
    ----------
    name : str
        The channel's name (e.g. ``"Tandem"``).
    path_mm : (k, 3) float, mm, LPS
        Tandem, ring, ovoid or cylinder channel, base to end (:attr:`Applicator.channels`).
    planning : PlanningStructures
        The target mask gives the dwell region.
    settings : ImplantSettings, optional
        Dwell step, dwell margin, applicator tip offset and minimum dwells.

    Returns
    -------
    Channel or None
        Of kind ``"intracavitary"``, dwells deepest first; None when it has fewer than ``settings.min_dwells`` dwells
        in the region.
    """
    settings = settings or ImplantSettings()
    p = np.asarray(path_mm, dtype=float)
    pts = _dwells_in_region(p, applicator_dwell_arclengths(float(arc_length_mm(p)[-1]), settings), planning, settings)
    return None if pts is None else Channel(name, "intracavitary", p, pts)


def _dwells_in_region(path_mm: np.ndarray, s_dw: np.ndarray, planning: PlanningStructures,
                      settings: ImplantSettings) -> np.ndarray | None:
    """Return the points of ``path_mm`` at arc lengths ``s_dw`` that lie in the target grown by the dwell margin.

    None when fewer than ``settings.min_dwells`` do.
    """
    pts = _points_at(path_mm, s_dw)
    region = _distance_field(planning.grid, planning.target.mask, settings.dwell_margin_mm + 5.0)
    pts = pts[region.at(pts) <= settings.dwell_margin_mm + 1e-6] if len(pts) else pts
    return None if len(pts) < settings.min_dwells else pts


def placed_needle(name: str, kind: str, path_mm: np.ndarray, planning: PlanningStructures,
                  settings: ImplantSettings | None = None, hole_distance_mm: float = 0.0,
                  design: str = "") -> Channel | None:
    """Return a needle that lies where it lies (found in an image) as a channel, its dwells those it can take.

    The afterloader reaches positions every ``settings.dwell_step_mm`` back from ``settings.tip_offset_mm`` short of
    the tip (the deepest dwell of a planned needle lies there too, :func:`needle_candidates`); those in the HR-CTV
    grown by ``settings.dwell_margin_mm`` are kept.

    Parameters
    ----------
    name : str
        The hole id.
    kind : str
        ``"straight"`` or ``"steered"``.
    path_mm : (k, 3) float, mm, LPS
        Its centre line, from the template plane to the tip.
    planning : PlanningStructures
        The target mask gives the dwell region.
    settings : ImplantSettings, optional
        Dwell step, dwell margin, tip offset and minimum dwells.
    hole_distance_mm : float, mm
        The hole's distance from the template centre.
    design : str
        Its stylet preset ("" for a straight needle).

    Returns
    -------
    Channel or None
        Dwells deepest first; None when fewer than ``settings.min_dwells`` of them lie in the region.
    """
    settings = settings or ImplantSettings()
    p = np.asarray(path_mm, dtype=float)
    length = float(arc_length_mm(p)[-1])
    first = length - settings.tip_offset_mm
    s_dw = first - settings.dwell_step_mm * np.arange(int(max(first, 0.0) // settings.dwell_step_mm) + 1)
    pts = _dwells_in_region(p, s_dw[s_dw >= 0.0], planning, settings)
    return None if pts is None else Channel(name, kind, p, pts, hole_distance_mm, length, design=design)


def applicator_channels(applicators: Sequence[Applicator], planning: PlanningStructures,
                        settings: ImplantSettings | None = None) -> tuple[Channel, ...]:
    """Return the intracavitary channels of the loadable applicators (a tandem's), with dwells in the target.

    Parameters
    ----------
    applicators : sequence of Applicator
        The case's applicators (:attr:`Scene.applicators`); their channels are (n, 3) centrelines, mm, LPS, base to
        end, curved as drawn (a tandem's is the centre line of its ROI:
        :mod:`reachplan.plugins.applicators.centreline`).
    planning : PlanningStructures
        The target whose grown region holds the dwells.
    settings : ImplantSettings or None
        Dwell step and margin; channels with fewer than ``settings.min_dwells`` dwells there are left out.

    Returns
    -------
    tuple of Channel
        One per loaded applicator channel, named after the applicator (``name k`` when it has several).
    """
    out = []
    for a in applicators:
        if not a.loadable:
            continue
        for k, path in enumerate(a.channels, start=1):
            name = a.name if len(a.channels) == 1 else f"{a.name} {k}"
            channel = intracavitary_channel(name, path, planning, settings)
            if channel is not None:
                out.append(channel)
    return tuple(out)
