"""Settings of implant planning: candidates, the selection model, the dwell-time model and the optimiser's name."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class ImplantSettings:
    """Settings of implant planning (lengths mm, times s).

    Parameters
    ----------
    dwell_step_mm : float, mm
        Distance between dwell positions along a channel.
    dwell_margin_mm : float, mm
        Dwells lie on the part of a channel inside the HR-CTV grown by this margin.
    tip_offset_mm : float, mm
        Distance from the needle tip to its deepest dwell (the tip lies this far beyond the last dwell
        position).
    applicator_tip_offset_mm : float, mm
        The afterloader's source-tip offset in an applicator channel (tandem, ring, ovoid, cylinder): the deepest
        dwell position lies this far back along the channel (arc length) from the channel's end, and the others
        every ``dwell_step_mm`` behind it. Default 3.5 mm: the distance from the channel end (DICOM relative
        position 0, PS3.3 C.8.8.15.9) of the first dwell position in the genuine Eclipse/BrachyVision exports for
        the built-in source, GammaMed Plus HDR and PDR (``reference/tps_examples``: ovoids and the PDR tandem at
        3.5 mm, the HDR tandem at 7.5 mm; ``reference/rtplan_conventions.md`` section 7). It is more than half the
        source's active length (3.5 mm, AAPM/ESTRO consensus data, Perez-Calatayud et al. 2012), as it must be: the
        source centre cannot reach the channel's end. The channel's end is taken where the drawn applicator ends,
        so the applicator's wall at its tip is part of this offset.
    clearance_margin_mm : float, mm
        Smallest surface distance from a needle to any organ at risk.
    min_dwells : int
        A needle needs at least this many dwell positions to be a candidate.
    neighbour_ratio : float or None
        Neighbouring dwell times on a channel differ by at most this factor (>= 1; None, the default: no such rule,
        the smoothness term shapes the loading instead).
    smoothness_weight : float
        Weight of the dwell-time gradient term (the sum of the time differences of neighbouring dwells, as a dose at
        the target, in units of the prescription) in both objectives (0: none).
    max_dwell_share : float
        No single dwell carries more than this share of the plan's total time.
    steered_per_hole : int
        Steered candidates kept per hole and design (the most dwells, spread apart).
    rolls : int
        Roll angles screened per hole (evenly over 360°).
    max_needles : int
        Largest needle budget on the Pareto curve.
    extra_after_aims : int
        Pareto points computed beyond the first budget that meets every aim.
    coverage_margin : float
        The LP aims target points at (1 + this) × the D90 prescription.
    exhaustive_max_selections : int
        At a needle budget K, when there are at most this many selections of at most K needles (one per hole), each
        one's dwell LP is solved and the best kept: the selection is then proven optimal on the selection model
        (0: never enumerate). 200 covers one and two needles among 19 straight candidates, one among 98 steered.
    swap_pool, swap_passes : int
        The selection's local search at each needle budget: swaps with the needles of the largest relaxed ``y``
        (this many), for at most this many passes (0: the rounded LP relaxation alone).
    selection_target_points, final_target_points : int
        Target points of the selection model and of the dwell-time LP on the chosen needles.
    selection_oar_pitch_mm, final_oar_pitch_mm : float, mm
        Lattice pitch of the organs' representative points in each.
    oar_sample_cc : float, cm³
        Organ volume nearest to the dwells that the representative points cover.
    segments_per_channel : int
        Dwell blocks per channel in the selection model.
    invasiveness_weight : float
        Weight of the needles' invasiveness in the selection objective (a tie-break).
    time_weight : float
        Weight of the mean target dose (shorter plans) in both objectives.
    min_dwell_time_s : float, s
        No loaded dwell is shorter than this: a dwell is 0 or at least this long (afterloaders do not deliver
        shorter dwells; the optimiser decides which short dwells go to 0 and which up to this).
    v200_max_pct : float, %
        Largest share of the HR-CTV that may receive twice the prescription (V200); None: no limit.
    shift_mm : float, mm
        Robust planning: every needle is also planned displaced this far sideways (perpendicular to its axis), in
        ``shift_directions`` directions, one needle at a time; 0: nominal planning only.
    shift_directions : int
        Directions of the sideways shifts (evenly around the axis).
    robust_rounds : int
        Rounds of constraint generation: solve, check every scenario, add the violated ones' rows, solve again.
    needles : int or None
        The needle count to pick from each arm's Pareto curve (``--needles``); None: the fewest needles that meet
        every aim.
    oar_eval_radius_mm : float, mm
        Organ voxels within this distance of a loaded dwell are evaluated for D2cm³.
    optimiser : str
        Name of the dwell optimiser (entry-point group ``reachplan.optimisers``) that selects the needles and loads
        the chosen ones (:mod:`reachplan.planner.implant.optimiser`); ``"lp"``: the built-in linear
        programmes (:mod:`reachplan.planner.implant.selection`).

    Raises
    ------
    ValueError
        A setting out of its range.
    """

    dwell_step_mm: float = 2.5
    dwell_margin_mm: float = 2.5
    tip_offset_mm: float = 1.0
    applicator_tip_offset_mm: float = 3.5
    clearance_margin_mm: float = 2.0
    min_dwells: int = 3
    neighbour_ratio: float | None = None
    smoothness_weight: float = 0.05
    max_dwell_share: float = 0.15
    steered_per_hole: int = 2
    rolls: int = 8
    max_needles: int = 16
    extra_after_aims: int = 1
    coverage_margin: float = 0.03
    exhaustive_max_selections: int = 200
    swap_pool: int = 6
    swap_passes: int = 2
    segments_per_channel: int = 2
    selection_target_points: int = 200
    final_target_points: int = 800
    selection_oar_pitch_mm: float = 3.0
    final_oar_pitch_mm: float = 3.0
    oar_sample_cc: float = 4.0
    min_dwell_time_s: float = 0.5
    v200_max_pct: float | None = 35.0
    shift_mm: float = 2.0
    shift_directions: int = 4
    robust_rounds: int = 4
    needles: int | None = None
    oar_eval_radius_mm: float = 40.0
    invasiveness_weight: float = 1e-3  # tie-breaks in the objective
    time_weight: float = 1e-3
    optimiser: str = "lp"

    def __post_init__(self) -> None:
        if not (self.dwell_step_mm > 0 and self.dwell_margin_mm >= 0 and self.tip_offset_mm >= 0
                and self.applicator_tip_offset_mm >= 0 and self.clearance_margin_mm >= 0):
            raise ValueError("dwell step must be > 0 mm; margins and tip offsets >= 0 mm")
        if (self.neighbour_ratio is not None and self.neighbour_ratio < 1) or not 0 < self.max_dwell_share <= 1:
            raise ValueError("neighbour_ratio must be >= 1 and max_dwell_share in (0, 1]")
        if min(self.min_dwells, self.max_needles, self.rolls, self.segments_per_channel,
               self.selection_target_points, self.final_target_points) < 1 or self.steered_per_hole < 0 \
                or self.extra_after_aims < 0:
            raise ValueError("implant settings: counts must be >= 1 (steered_per_hole, extra_after_aims >= 0)")
        if self.exhaustive_max_selections < 0:
            raise ValueError("implant settings: exhaustive_max_selections must be >= 0 (0: never enumerate)")
        if not (self.selection_oar_pitch_mm > 0 and self.final_oar_pitch_mm > 0 and self.oar_sample_cc >= 2.0):
            raise ValueError("implant settings: organ pitches must be > 0 mm and oar_sample_cc >= 2 cm³")
        if self.smoothness_weight < 0 or self.min_dwell_time_s < 0 or self.shift_mm < 0 or self.robust_rounds < 1 \
                or self.shift_directions < 1 or (self.v200_max_pct is not None and not 0 < self.v200_max_pct <= 100):
            raise ValueError("implant settings: smoothness weight, minimum dwell time and shift must be >= 0, "
                             "robust rounds and shift directions >= 1, V200 limit in (0, 100] %")
        if self.needles is not None and self.needles < 0:
            raise ValueError("implant settings: the needle count to pick must be >= 0")
        if not self.optimiser.strip():
            raise ValueError("implant settings: the optimiser needs a name")
