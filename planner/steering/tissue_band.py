"""The tissue band: where a steered needle goes when the tissue is softer or stiffer than planned.

The planner predicts a steered needle's path in tissue of a given Young's modulus: the phantom gel's 0.19 MPa
(SimuGel #3, reference ``oncoreach.md``, section 4) unless the plan names another (``--tissue-modulus``) or one per
organ (``--organ-modulus``). The patient's tissue is not known that well, so each steered needle the plan shows is
re-inserted with its planned schedule in tissue whose every modulus is scaled over :class:`ModulusBand` (default
÷ 3 to × 3), and its worst reach error and smallest clearance over that band are reported.

Default range: the reference material gives no Young's modulus for uterus, cervix or parametrium (searched:
``gyn_anatomy.md`` and ``oncoreach.md`` give only the gel's), so the band is the plan's modulus × / ÷ 3, ASSUMED,
and every band says so (:data:`DEFAULT_SOURCE`); a cited range is given with ``--modulus-band FACTOR``.

Model: the in-tissue Cosserat rod (:mod:`~reachplan.planner.steering.tissue_rod`), which holds at every modulus (the
kinematic model's curvature factor is fitted only from 0.1 MPa, above the default band's soft end of 0.063 MPa). The
band's paths are the needle's own path plus the change the rod predicts (rod at the scaled moduli minus rod at the
planned ones, both on :data:`BAND_MODEL`'s coarse 4 mm insertion steps). Against the planner's reference rod (2 mm
steps with Richardson extrapolation; ``reachplan bench band``, ``docs/tissue_band.csv``): the stiff edge's tip change
within 0.06 mm, the soft edge's within 0.19 mm except for needles pulled from the template with deep tips (0.5 mm at
150 mm, pessimistic), at a third of the reference's CPU per solve (0.19 s against 0.53 s); three solves a needle,
memoised.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from reachplan._arrays import arc_length_mm
from reachplan.planner.errors import PlanInputError
from reachplan.planner.geometry.collision import Organ
from reachplan.planner.steering.candidates import Candidate, Target, TissueBand, score_path, worst_case
from reachplan.planner.steering.insertion import SIMUGEL_MODULUS_PA
from reachplan.planner.steering.schedule import TensionSchedule
from reachplan.planner.steering.steered import insert_memo
from reachplan.planner.steering.tissue_rod import TissueRodInsertion
from reachplan.rod_model.cosserat import TwoTubeCosserat
from reachplan.rod_model.design import RodDesign

#: Where the default modulus range comes from.
DEFAULT_SOURCE = ("ASSUMED: the plan's tissue modulus (the phantom gel's 0.19 MPa, SimuGel #3, oncoreach.md) "
                  "x/÷ 3; the reference material gives no Young's modulus for uterus, cervix or parametrium")

#: The band's rod model: 4 mm insertion steps, 1 RK4 step per mm, no extrapolation (the coarse half of the
#: reference's Richardson pair; see the module docstring). 2 mm RK4 steps failed the rod's own step-doubling check
#: in the gel ÷ 3 (ramp from 40 mm, tip at 120 mm: the tip moved 0.0502 mm against a 0.05 mm limit).
BAND_MODEL = TissueRodInsertion(rod_model=TwoTubeCosserat(steps_per_mm=1.0), step_mm=4.0)


@dataclass(frozen=True)
class ModulusBand:
    """The range of tissue moduli a steered needle is re-inserted over: the plan's moduli ÷ / × ``factor``.

    Parameters
    ----------
    factor : float
        The band spans the plan's moduli divided and multiplied by this (>= 1; 1: no band).
    steps : int
        Paths on each side of the nominal one, at the factors ``factor ** (j / steps)``, ``j = ±1 … ±steps``.
    source : str
        Where the range comes from (a citation, or ASSUMED with the reason); reported with every band.

    Raises
    ------
    ValueError
        A factor below 1 or not finite, fewer than one step, or an empty source.
    """

    factor: float = 3.0
    steps: int = 1
    source: str = DEFAULT_SOURCE

    def __post_init__(self) -> None:
        if not (np.isfinite(self.factor) and self.factor >= 1.0):
            raise ValueError(f"the modulus band's factor must be a number >= 1 (1: no band), got {self.factor}")
        if self.steps < 1 or not self.source:
            raise ValueError("the modulus band needs at least one step a side and a source")

    @property
    def enabled(self) -> bool:
        """True when the band has a width (``factor > 1``)."""
        return self.factor > 1.0

    @property
    def scales(self) -> tuple[float, ...]:
        """The factors on the plan's moduli, increasing, 1 (the nominal path) in the middle: ``2 * steps + 1``."""
        j = np.arange(-self.steps, self.steps + 1)
        return tuple(float(v) for v in self.factor ** (j / self.steps))


def uniform_profile(modulus_pa: float = SIMUGEL_MODULUS_PA) -> tuple[np.ndarray, np.ndarray]:
    """Return a modulus profile of one modulus along the whole insertion.

    Parameters
    ----------
    modulus_pa : float, Pa
        The tissue's Young's modulus.

    Returns
    -------
    depth_mm : (1,) float, mm
        ``[0]``.
    modulus_pa : (1,) float, Pa
        ``[modulus_pa]``.
    """
    return np.array([0.0]), np.array([float(modulus_pa)])


def _solved(solved: np.ndarray | str) -> np.ndarray:
    """Return a memoised rod solve; raise the typed error for its failure."""
    if isinstance(solved, str):
        raise PlanInputError(f"tissue band: {solved}")
    return solved


def band_paths(path_mm: np.ndarray, depth_mm: float, design: RodDesign, schedule: TensionSchedule,
               profile: tuple[np.ndarray, np.ndarray], patient_from_template: np.ndarray,
               band: ModulusBand = ModulusBand(), model: TissueRodInsertion = BAND_MODEL) -> list[np.ndarray]:
    """Return the needle's path at each of the band's scales (module docstring): the path plus the rod's change.

    Parameters
    ----------
    path_mm : (n, 3) float, mm, LPS
        The needle's planned centreline, hole (first point) to tip.
    depth_mm : float, mm
        Inserted arc length.
    design : RodDesign
        The stylet.
    schedule : TensionSchedule
        The planned schedule (constant roll, template frame).
    profile : tuple of ((p,) float, (p,) float)
        ``(depth_mm, modulus_pa)``: the plan's tissue modulus (Pa) along the insertion, piecewise constant from each
        depth (mm) on.
    patient_from_template : (4, 4) float
        Template frame (mm) to patient LPS (mm).
    band : ModulusBand
        The scales.
    model : TissueRodInsertion
        The rod model of the change of shape.

    Returns
    -------
    list of (n, 3) float, mm, LPS
        One path per scale of ``band.scales``, in order (the nominal one is ``path_mm``).

    Raises
    ------
    PlanInputError
        The rod model fails at a scale (its reason), or the schedule's roll is not constant.
    """
    roll = np.asarray(schedule.roll_deg, float)
    if np.ptp(roll) > 1e-9:
        raise PlanInputError("tissue band: the schedule's roll must be constant (a planar steered needle)")
    base = TensionSchedule(schedule.depth_mm, schedule.tension_n, np.zeros(len(roll)))
    at, moduli = (np.asarray(a, float) for a in profile)
    shapes = {s: _solved(insert_memo(model, design, base, depth_mm, (at, moduli * s), sample_mm=model.node_mm))
              for s in band.scales}
    c, s_ = np.cos(np.radians(roll[0])), np.sin(np.radians(roll[0]))
    to_patient = np.asarray(patient_from_template, float)[:3, :3] @ np.array([[c, -s_, 0.0], [s_, c, 0.0],
                                                                                [0.0, 0.0, 1.0]])
    path_mm = np.asarray(path_mm, float)
    frac = arc_length_mm(path_mm)
    frac /= max(frac[-1], 1e-12)
    nominal = shapes[1.0]
    out = []
    for scale in band.scales:
        change = shapes[scale] - nominal  # template frame at roll 0, equal arc-length samples
        along = np.linspace(0.0, 1.0, len(change))
        delta = np.column_stack([np.interp(frac, along, change[:, j]) for j in range(3)])
        out.append(path_mm + delta @ to_patient.T)
    return out


def assess_band(candidate: Candidate, aim: Target, organs: Sequence[Organ], patient_from_template: np.ndarray,
                needle_radius_mm: float, profile: tuple[np.ndarray, np.ndarray], band: ModulusBand = ModulusBand(),
                reach_tolerance_mm: float = 2.0, model: TissueRodInsertion = BAND_MODEL) -> TissueBand:
    """Re-insert a steered candidate over the band of moduli; the paths, each one's reach and clearance, the worst.

    Parameters
    ----------
    candidate : Candidate
        A steered candidate with its design and schedule (its path mm, LPS).
    aim : Target
        The point its reach is measured from (the target; for an implant needle its planned tip).
    organs : sequence of Organ
        Organs at risk and bone (meshes, LPS mm) the band's paths are checked against.
    patient_from_template : (4, 4) float
        Template frame (mm) to patient LPS (mm).
    needle_radius_mm : float, mm
        Needle radius of the collision check.
    profile : tuple of ((p,) float, (p,) float)
        ``(depth_mm, modulus_pa)``: the plan's modulus (Pa) along the candidate's insertion.
    band : ModulusBand
        The scales of the moduli.
    reach_tolerance_mm : float, mm
        The plan's reach tolerance.
    model : TissueRodInsertion
        The rod model of the change of shape.

    Returns
    -------
    TissueBand
        Paths (mm, LPS), reach errors and clearances per scale, the worst case and its modulus.

    Raises
    ------
    PlanInputError
        A straight candidate (no design or schedule), or the rod fails at a scale.
    """
    if candidate.design is None or candidate.schedule is None:
        raise PlanInputError(f"tissue band: {candidate.hole_id} is not a steered needle with a schedule")
    paths = band_paths(candidate.path_mm, candidate.insertion_depth_mm, candidate.design, candidate.schedule,
                       profile, patient_from_template, band, model)
    tip_pa = float(np.asarray(profile[1], float)[-1])  # the profile's last modulus: the tissue at the tip
    scored = []
    for scale, path in zip(band.scales, paths, strict=True):
        c = candidate if scale == 1.0 else score_path(
            aim, candidate.hole_id, candidate.hole_distance_mm, path, organs, needle_radius_mm, reach_tolerance_mm,
            candidate.model, steered=True, depth_mm=candidate.insertion_depth_mm)
        label = f"tissue {'x' if scale > 1 else '÷'}{max(scale, 1 / scale):.3g} ({tip_pa * scale / 1e6:.3g} MPa)"
        scored.append((label, c))
    worst_reach, worst_clear, worst = worst_case(candidate, scored)
    return TissueBand(band.scales, tuple(tip_pa * s for s in band.scales), tuple(paths),
                      tuple(c.reach_error_mm for _, c in scored), tuple(c.clearance_mm for _, c in scored),
                      worst_reach, worst_clear, worst, model.info.label, band.source)
