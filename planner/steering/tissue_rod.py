"""In-tissue insertion with the geometrically exact rod.

The two-tube Cosserat model pushed in steps through an elastic foundation tied to the track its tip cut.

Model (template frame: entry at the origin, ``+z`` the insertion direction, roll 0 bends toward ``+x``; mm)
    At each insertion step the inserted length ``d`` of the stylet-in-needle (its distal ``d`` mm: the joint
    section first) is solved as a Cosserat rod clamped at the template (:meth:`TwoTubeCosserat.solve` with
    ``inserted_mm``), tendon tension and roll from the schedule at that depth, held by a Winkler foundation:
    a force per length ``−k δ`` toward the tissue's rest position at the same arc length, ``δ`` the lateral
    offset (:class:`reachplan.rod_model.design.Foundation`). The tissue ahead of the tip is cut along the path
    the tip takes: its tangent, turning at the rate it turned in the last step (a second-order extrapolation;
    cutting straight chords was first order and, in stiff tissue, made the joints look resisted). The needle
    slides along its own track (the virtual-spring models of Glozman & Shoham, IEEE T-RO 23(3), 2007, and
    Misra, Reed et al., IJRR 29(13), 2010). Nonlinear: the holding force per length saturates at
    ``k · slip_mm``; where the needle moves further from its track, the track is moved with it (the tissue
    gives way: plastic slip, kept for the later steps). The modulus may vary along the track (per organ);
    ``k`` follows Vesic's formula (:func:`reachplan.planner.steering.insertion.winkler_modulus_pa`).
Solver
    Each step is a boundary-value problem of the two-tube rod. In stiff tissue single shooting breaks down
    (the foundation's solutions grow as ``exp(∫β ds)``, ``β = (k / 4 EI)^(1/4)``): the rod model switches to
    multiple shooting (:mod:`reachplan.rod_model.multiple_shooting`). Deep in stiff tissue only the distal
    ``window_winkler`` Winkler lengths of the shaft (plus the joint section) are re-solved, clamped where the
    previous step left the needle: a disturbance decays as ``exp(−s/λ)`` along a held shaft (at 3 MPa, 1.5 and 3
    Winkler lengths give the same tip to 0.01 mm).
Tip force
    An axial cutting force ``cut_force_n`` against the tip's previous tangent (a dead load updated each step;
    cutting plus friction forces of the order of 1 N, Okamura, Simone & O'Leary, IEEE TBME 51(10), 2004).
    ASSUMED default 0: no value is published for the phantom's gel, and with it the zero-modulus limit is the
    free-space shape. A symmetric tip has no lateral cutting force.

The trend with modulus (``reachplan bench models``, ``rod_models_tissue.csv``; ``docs/mechanics.md``)
    The tip deflection at a fixed depth is *not* monotonic in the modulus. The checks (slip threshold 0.25 mm /
    1 mm / none, re-solve window on or off, insertion steps 4 / 2 / 1 mm) move the peak by less than 0.25 mm: the
    branches are mechanical.

    1. *Holding* (rises with the modulus). At zero modulus the needle has the free-space shape of its inserted
       length (test); a steered needle turns only as far as the tissue holds its shaft on the curved track its
       tip cut. The shaft (stylet tube in needle, EI = 7.6 mN·m²) is held once its Winkler length
       ``(4 EI / k)^(1/4)`` is short against the depth: 102 mm at 1 kPa, 55 mm at 10 kPa, 29 mm at 0.1 MPa.
       15ga-20j-tip pulled at 10 N from the template, tip at 120 mm: 4.98 mm at 0, 5.8 mm at 1 kPa, 11.4 mm at
       10 kPa, 26.3 mm at 0.1 MPa, 29.6 mm at 0.19 MPa. Bevel-tip needles show the same (curvature rises with
       tissue stiffness, Misra et al. 2010).
    2. *Decoupling* (falls to tip following). While the shaft's Winkler length is comparable with the joint
       section, the held shaft's bending reaches the tip through the soft joints and the tip turns faster than
       the joints' free-space curvature; the peak lies where that length is about 0.6 joint-section lengths
       (0.1 MPa for 30 joints, 49.5 mm; about 1 MPa for 15 joints, 24.7 mm; test), and beyond it the deflection
       falls to pure tip following at the free-space curvature (Webster et al., IJRR 25(5-6), 2006), reached by
       about 1 MPa for 30 joints (pulled to 10 N at the template, tip at 120 mm: 30.25 / 27.94 / 27.89 mm at
       0.1 / 1 / 10 MPa, tip following 27.97 mm; test).
    3. *Resisting* (falls with the modulus). A tendon pulled while the joints are embedded bends them only
       within about their own Winkler length of the tip, which shrinks as ``k^(-1/4)``; with the tendon pulled
       before the joints enter, nothing resists them (the tip cuts its own curved track: at 30 mm the tip is
       the free-space one at every modulus, test). 15ga-30j-tip, 5 mm ramp at 40 mm to 10 N, tip at 140 mm:
       26.0 mm at 0.1 MPa, 25.0 at 0.19 MPa, 21.9 at 1 MPa, 20.2 at 10 MPa.

    What the planner needs is the kinematic model's curvature factor over the tip-following range (>= 0.1 MPa),
    fitted per design (:mod:`reachplan.planner.steering.factors`, which imports this module):
    15ga-30j-tip is past its peak there and its factor falls monotonically, from 1.33 at 0.1 MPa (1.28 in the gel)
    toward 1 in rigid tissue; a shorter or stiffer joint section peaks in stiffer tissue, so its factor rises
    through the gel (15ga-15j-tip: below 1 there).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from functools import lru_cache
from typing import ClassVar

import numpy as np

from reachplan._arrays import arc_length_mm
from reachplan.planner.errors import PlanInputError
from reachplan.planner.steering.insertion import (
    SIMUGEL_MODULUS_PA,
    TISSUE_POISSON,
    FailedInsertion,
    InsertionPath,
    NamedInsertion,
    winkler_modulus_pa,
)
from reachplan.planner.steering.schedule import TensionSchedule
from reachplan.rod_model.cosserat import TwoTubeCosserat
from reachplan.rod_model.design import Foundation, Loads, RodDesign
from reachplan.rod_model.result import RodPath


@dataclass(frozen=True)
class TissueRodInsertion(NamedInsertion):
    """Quasi-static insertion of the Cosserat rod in an elastic, slipping medium (see the module docstring).

    Parameters
    ----------
    tissue_modulus_pa : float, Pa, >= 0
        Young's modulus of the medium (default SimuGel #3, 0.19 MPa); 0 gives free space.
    rod_model : TwoTubeCosserat
        The rod model solving each step (its ``inserted_mm`` and foundation support); 2 RK4 steps per mm by
        default: the default 0.5 fails its own step-doubling check in tissue of 0.19 MPa and stiffer.
    step_mm : float
        Insertion step, mm (every step end is a node of the track). At 0.19 MPa, 15ga-20j-tip pulled from the
        template, tip at 60 mm: 4 / 2 / 1 mm steps give 7.32 / 7.30 / 7.28 mm.
    node_mm : float
        Spacing of the foundation's nodes along the track, mm.
    slip_mm : float
        Lateral offset from the track beyond which the tissue gives way, mm (ASSUMED 1 mm).
    cut_force_n : float
        Axial cutting force at the tip, N (ASSUMED 0).
    poisson : float
        Poisson's ratio of the medium.
    arc_cut : bool
        Cut new tissue along the tip's turning path (default) instead of a straight chord along its tangent.
    window_winkler : float
        Re-solve only the joint section plus this many of the shaft's Winkler lengths behind it (the softest
        tissue inside sets the length), clamped where the last step left the needle; 0: always the whole
        inserted length.
    richardson : bool
        :meth:`insert_one` returns ``2 P(step) − P(2 step)`` (Richardson extrapolation in the insertion step,
        whose error is first order: 4 → 2 mm moves the tip 1.6-1.7 times as much as 2 → 1 mm), both paths taken
        at the same fractions of their arc length, every ``node_mm``. 15ga-30j-tip in the gel, 20 mm ramps from
        0 / 40 mm to 5 / 10 N, tip at 150 mm: 2 mm steps are 0.18-0.41 mm from the extrapolation of 1 and 2 mm
        steps, 1 mm steps 0.09-0.21 mm, this (2 and 4 mm, 1.5 times the cost of 2 mm) 0.03-0.08 mm.
    curvature_scale : tuple of (str, float)
        A site's calibration (:mod:`reachplan.planner.steering.calibration`): per design name, the ratio of the
        curvature its needles showed to the kinematic model's. The rod's path departs from the hole's axis (the
        template frame's x and y) by that ratio times its own: the same change as the kinematic model's to first
        order in the angle (an empirical correction, not a change of the rod's mechanics).
    """

    label: ClassVar[str] = "tissue_rod"
    tissue_modulus_pa: float = SIMUGEL_MODULUS_PA
    rod_model: TwoTubeCosserat = field(default_factory=lambda: TwoTubeCosserat(steps_per_mm=2.0))
    step_mm: float = 2.0
    node_mm: float = 1.0
    slip_mm: float = 1.0
    cut_force_n: float = 0.0
    poisson: float = TISSUE_POISSON
    arc_cut: bool = True
    window_winkler: float = 6.0
    richardson: bool = False
    curvature_scale: tuple[tuple[str, float], ...] = ()

    def __post_init__(self) -> None:
        if not (self.tissue_modulus_pa >= 0 and self.step_mm > 0 and self.node_mm > 0 and self.slip_mm > 0
                and self.cut_force_n >= 0):
            raise PlanInputError("tissue_rod: modulus and cut force must be >= 0, steps and slip > 0")

    def insert(self, design: RodDesign, schedules: Sequence[TensionSchedule],
               depth_mm: float) -> list[InsertionPath | FailedInsertion]:
        """Insert ``design`` to ``depth_mm`` once per schedule (positions mm, template frame).

        A step whose rod solve fails gives a :class:`FailedInsertion` with the depth and the reason.

        Parameters
        ----------
        design : RodDesign
            The stylet in its needle.
        schedules : sequence of TensionSchedule
            Tension (N) and roll (degrees) against depth (mm), one insertion each.
        depth_mm : float, mm
            Insertion depth, in ``(0, design.length_mm]``.

        Returns
        -------
        list of InsertionPath or FailedInsertion
            One per schedule, in order (:meth:`insert_one`).
        """
        out: list[InsertionPath | FailedInsertion] = []
        for sch in schedules:
            r = self.insert_one(design, sch, depth_mm)
            out.append(r if isinstance(r, FailedInsertion) else InsertionPath(r, depth_mm, self.info))
        return out

    def _stiffness(self, design: RodDesign, modulus_pa: np.ndarray) -> np.ndarray:
        """N/mm per mm of needle at each node (0 where the modulus is 0)."""
        k = np.zeros(len(modulus_pa))
        for e in np.unique(modulus_pa):
            if e > 0:
                k[modulus_pa == e] = winkler_modulus_pa(design, float(e), self.poisson) * 1e-6
        return k

    def insert_one(self, design: RodDesign, schedule: TensionSchedule, depth_mm: float,
                   modulus_profile: tuple[np.ndarray, np.ndarray] | None = None) -> np.ndarray | FailedInsertion:
        """Return the centreline of the needle inserted to ``depth_mm``, or the failure.

        Parameters
        ----------
        design : RodDesign
            The needle.
        schedule : TensionSchedule
            Tendon tension and roll against depth.
        depth_mm : float
            Insertion depth, mm, in ``(0, design.length_mm]``.
        modulus_profile : tuple of ((p,) float ndarray, (p,) float ndarray), optional
            ``(depth_mm, modulus_pa)``: the medium's modulus along the track, piecewise constant from each depth
            on (per organ); None = ``tissue_modulus_pa`` everywhere.

        Returns
        -------
        (n, 3) float ndarray or FailedInsertion
            The inserted centreline, mm, template frame (row 0 at the template, last row the tip): at the rod
            model's integration points, or with ``richardson`` every ``node_mm`` of arc length.
        """
        scale = self.scale_for(design)
        path = _run(self, design, schedule, depth_mm, modulus_profile)
        if isinstance(path, FailedInsertion) or not (self.richardson or scale != 1.0):
            return path
        if self.richardson:
            coarse = _run(replace(self, step_mm=2 * self.step_mm), design, schedule, depth_mm, modulus_profile)
            if isinstance(coarse, FailedInsertion):
                return coarse
            frac = np.linspace(0.0, 1.0, max(2, round(depth_mm / self.node_mm)) + 1)
            fine_at, coarse_at = (np.column_stack([np.interp(frac, a / a[-1], p[:, i]) for i in range(3)])
                                  for p, a in ((path, arc_length_mm(path)), (coarse, arc_length_mm(coarse))))
            path = 2.0 * fine_at - coarse_at
        return path * np.array([scale, scale, 1.0])

    def _moduli_at(self, nodes: np.ndarray, modulus_profile: tuple[np.ndarray, np.ndarray] | None) -> np.ndarray:
        """Return the medium's modulus (Pa) at ``nodes`` (mm of inserted arc): the profile's or the default."""
        if modulus_profile is None:
            return np.full(len(nodes), float(self.tissue_modulus_pa))
        at, values = (np.asarray(a, dtype=float) for a in modulus_profile)
        if at.shape != values.shape or at.ndim != 1 or len(at) == 0 or np.any(np.diff(at) <= 0):
            raise PlanInputError("modulus_profile must be two 1-D arrays (depth_mm increasing, modulus_pa)")
        return values[np.clip(np.searchsorted(at, nodes, side="right") - 1, 0, len(at) - 1)]

    def insert_steps(self, design: RodDesign, schedule: TensionSchedule, depth_mm: float,
                     modulus_profile: tuple[np.ndarray, np.ndarray] | None = None
                     ) -> tuple[np.ndarray | FailedInsertion, list[tuple[float, np.ndarray]]]:
        """Insert as :meth:`insert_one`, also returning the tip after every insertion step.

        Parameters
        ----------
        design : RodDesign
            The stylet in its needle.
        schedule : TensionSchedule
            Tendon tension (N) and roll (degrees) against inserted depth (mm).
        depth_mm : float, mm
            Insertion depth, in ``(0, design.length_mm]``.
        modulus_profile : tuple of ((p,) float ndarray, (p,) float ndarray), optional
            ``(depth_mm, modulus_pa)`` as in :meth:`insert_one`; None = ``tissue_modulus_pa`` everywhere.

        Returns
        -------
        path : (n, 3) float ndarray or FailedInsertion
            As :meth:`insert_one` (mm, template frame).
        steps : list of (float, (3,) float ndarray)
            ``[(depth_mm, tip_mm), ...]``: the tip (mm, template frame) after each step, up to the failure if any.

        Raises
        ------
        PlanInputError
            A depth out of range, a schedule above the design's maximum tension, or a malformed ``modulus_profile``.
        """
        steps: list[tuple[float, np.ndarray]] = []
        if not (np.isfinite(depth_mm) and 0 < depth_mm <= design.length_mm):
            raise PlanInputError(f"insertion depth must be in (0, {design.length_mm:.0f}] mm, got {depth_mm}")
        if schedule.peak_tension_n > design.max_tension_n + 1e-9:
            raise PlanInputError(f"the schedule exceeds {design.name}'s maximum tension {design.max_tension_n} N")
        n_steps = max(1, int(np.ceil(depth_mm / self.step_mm - 1e-9)))
        ends = np.linspace(0.0, depth_mm, n_steps + 1)[1:]
        nodes = np.union1d(np.linspace(0.0, depth_mm, max(2, round(depth_mm / self.node_mm)) + 1), ends)
        stiffness = self._stiffness(design, self._moduli_at(nodes, modulus_profile))
        tube_ei = next(s.ei1 + s.ei2 for s in design.sections() if s.kind == "tube") * 1e6  # N mm²
        distal_mm = design.length_mm - next(s.start_m for s in design.sections() if s.kind == "joints") * 1e3
        track = np.zeros((len(nodes), 3))
        tip = np.zeros(3)
        tangent = np.array([0.0, 0.0, 1.0])
        turn = np.zeros(3)  # rate of turning of the tip's tangent per mm of insertion (last step), 1/mm
        cut_to = 0.0
        shape: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None  # (s, positions, frames) of the last step
        warm: np.ndarray | None = None
        for depth in ends:
            new = (nodes > cut_to + 1e-9) & (nodes <= depth + 1e-9)
            ahead = nodes[new] - cut_to
            # new tissue is cut along the path the tip follows: its tangent, turning as it did in the last step
            track[new] = tip + np.outer(ahead, tangent) + 0.5 * np.outer(ahead**2, turn)
            cut_to = depth
            inside = nodes <= depth + 1e-9
            held = stiffness[inside] > 0
            window = depth
            if self.window_winkler > 0 and np.any(held):
                k_min = float(np.min(stiffness[inside][held]))
                window = min(depth, distal_mm + self.window_winkler * (4 * tube_ei / k_min) ** 0.25)
            base = depth - window
            if shape is None or base <= 1e-9:
                base, origin, rot = 0.0, np.zeros(3), np.eye(3)
            else:
                origin, rot = _pose_at(*shape, base)
            s_in = nodes[inside & (nodes >= base - 1e-9)]
            if s_in[-1] < depth - 1e-9:
                s_in = np.r_[s_in, depth]
            if s_in[0] > base + 1e-9:
                s_in = np.r_[base, s_in]
            k_in = np.interp(s_in, nodes, stiffness)
            tr_in = np.column_stack([np.interp(s_in, nodes, track[:, i]) for i in range(3)])
            found = Foundation(s_in - base, k_in, (tr_in - origin) @ rot, np.full(len(s_in), self.slip_mm))
            tension, roll = schedule.at(np.array([depth]))
            loads = Loads((float(tension[0]),) + (0.0,) * (design.n_tendons - 1), roll_deg=float(roll[0]),
                          tip_force_n=tuple(-self.cut_force_n * (rot.T @ tangent)), foundation=found)
            result = self.rod_model.solve(design, loads, warm, inserted_mm=float(window))
            if not isinstance(result, RodPath):
                return FailedInsertion(self.info, f"at depth {depth:.1f} mm: {getattr(result, 'reason', '')}"), steps
            warm = result.base_unknowns
            s_new = result.s_mm + base
            pos_new = result.positions_mm @ rot.T + origin
            frames_new = np.einsum("ij,njk->nik", rot, result.frames)
            if shape is not None and base > 0:  # the proximal part, held on its track, is kept
                keep = shape[0] < base - 1e-9
                s_new = np.r_[shape[0][keep], s_new]
                pos_new = np.vstack([shape[1][keep], pos_new])
                frames_new = np.concatenate([shape[2][keep], frames_new])
            shape = (s_new, pos_new, frames_new)
            # the tissue gives way where the needle left its track by more than the slip offset
            pos = np.column_stack([np.interp(nodes[inside], s_new, pos_new[:, i]) for i in range(3)])
            _give_way(track, inside, pos, self.slip_mm)
            h = depth - (steps[-1][0] if steps else 0.0)
            new_tangent = frames_new[-1][:, 2]
            turn = new_tangent - tangent
            turn = (turn - np.dot(turn, new_tangent) * new_tangent) / h if self.arc_cut else np.zeros(3)
            tip, tangent = pos_new[-1], new_tangent
            steps.append((float(depth), tip.copy()))
        assert shape is not None
        return shape[1], steps


def _run(model: TissueRodInsertion, design: RodDesign, schedule: TensionSchedule, depth_mm: float,
         modulus_profile: tuple[np.ndarray, np.ndarray] | None) -> np.ndarray | FailedInsertion:
    """One insertion at ``model``'s step (no extrapolation), memoised on its exact inputs (read-only result).

    The runs at one step size are shared by every model made of them: a rung at 4 mm steps, the 4 mm half of the
    reference (2 mm extrapolated with 4 mm) and of the rung at 4 mm extrapolated with 8 mm, and the tissue band's
    nominal shape all solve the same insertion when given the same schedule and tissue.
    """
    key = tuple(tuple(np.asarray(a, dtype=float).ravel().tolist())
                for a in (schedule.depth_mm, schedule.tension_n, schedule.roll_deg))
    if modulus_profile is None:  # the same tissue as a one-piece profile of the model's modulus
        modulus_profile = (np.zeros(1), np.full(1, float(model.tissue_modulus_pa)))
    profile = tuple(tuple(np.asarray(a, dtype=float).ravel().tolist()) for a in modulus_profile)
    return _run_memo(replace(model, richardson=False, curvature_scale=()), design, key, float(depth_mm), profile)


@lru_cache(maxsize=512)
def _run_memo(model: TissueRodInsertion, design: RodDesign, schedule: tuple[tuple[float, ...], ...],
              depth_mm: float, profile: tuple[tuple[float, ...], ...]) -> np.ndarray | FailedInsertion:
    """:func:`_run`'s cached solve (hashable inputs)."""
    prof = (np.array(profile[0]), np.array(profile[1]))
    path, _ = model.insert_steps(design, TensionSchedule(*map(np.array, schedule)), depth_mm, prof)
    if isinstance(path, np.ndarray):
        path.setflags(write=False)
    return path


def forget_runs() -> None:
    """Empty the memo of insertion runs (:func:`_run`)."""
    _run_memo.cache_clear()


def _give_way(track: np.ndarray, inside: np.ndarray, pos: np.ndarray, slip_mm: float) -> None:
    """Move the track (in place) where the needle left it by more than ``slip_mm``: to ``slip_mm`` from the needle.

    ``track`` (n, 3) mm; ``inside`` (n,) bool, the nodes in the tissue; ``pos`` the needle at those nodes, mm.
    """
    off = pos - track[inside]
    dist = np.linalg.norm(off, axis=1)
    far = dist > slip_mm
    if np.any(far):
        idx = np.nonzero(inside)[0][far]
        track[idx] += off[far] * (1.0 - slip_mm / dist[far])[:, None]


def _pose_at(s_mm: np.ndarray, positions_mm: np.ndarray, frames: np.ndarray,
             at_mm: float) -> tuple[np.ndarray, np.ndarray]:
    """Position (3,) mm and orthonormal frame (3, 3) of a solved centreline at arc length ``at_mm``.

    Linear between samples; the frame is re-orthonormalised (nearest rotation, by SVD).
    """
    i = int(np.clip(np.searchsorted(s_mm, at_mm) - 1, 0, len(s_mm) - 2))
    w = (at_mm - s_mm[i]) / (s_mm[i + 1] - s_mm[i])
    p = (1 - w) * positions_mm[i] + w * positions_mm[i + 1]
    u, _, vt = np.linalg.svd((1 - w) * frames[i] + w * frames[i + 1])
    return p, u @ vt


TISSUE_ROD = TissueRodInsertion()
#: The planner's reference re-solve (:func:`reachplan.planner.case.search.refine_shortlist`): 2 mm insertion steps
#: extrapolated with 4 mm ones (``richardson``), 1 RK4 step per mm. 15ga-30j-tip, 5 mm ramp from the template to
#: 10 N, tip at 120 mm in the gel: 29.70 / 29.80 / 29.85 mm at 4 / 2 / 1 mm steps (extrapolated 29.90, from 1 and
#: 2 mm 29.91); 2 RK4 steps per mm change it by 0.001 mm.
PLANNER_REFERENCE = TissueRodInsertion(rod_model=TwoTubeCosserat(steps_per_mm=1.0), richardson=True)
