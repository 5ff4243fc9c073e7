"""Robustness of shortlisted candidates to the errors of a handheld insertion.

Needles deviate even when straight (transverse tip deflections of 3.6 ± 2.1 to 7.9 ± 3.0 mm, Karius et
al., Strahlenther. Onkol. 2025; reference ``oncoreach.md``), and a steered needle is pulled and rolled by
hand. Each candidate is re-evaluated under the perturbations of :class:`Perturbations` (tension scaled,
roll offset, entry direction tilted about the hole) with the fast kinematic insertion model and the same
collision check; the worst reach error and the smallest clearance over them are reported.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from reachplan._arrays import arc_length_mm
from reachplan.planner.geometry.collision import Organ
from reachplan.planner.steering.candidates import Candidate, Target, score_path, worst_case
from reachplan.planner.steering.insertion import ModelInfo
from reachplan.planner.steering.kinematic import KINEMATIC, KinematicInsertion
from reachplan.planner.steering.schedule import TensionSchedule
from reachplan.rod_model.design import RodDesign


@dataclass(frozen=True)
class Perturbations:
    """Errors to test: tension × (1 ± ``tension_fraction``), roll ± ``roll_deg`` and an entry tilt of ``tilt_deg``.

    The entry direction is tilted about the two axes of the template plane (both signs).

    Parameters
    ----------
    tension_fraction : float
        Relative tension error, in [0, 1).
    roll_deg : float, degrees
        Roll error of the bending plane (>= 0).
    tilt_deg : float, degrees
        Tilt of the entry direction about the hole, in [0, 30).

    Raises
    ------
    ValueError
        A value outside its range.
    """

    tension_fraction: float = 0.10
    roll_deg: float = 10.0
    tilt_deg: float = 2.0

    def __post_init__(self) -> None:
        if not (0 <= self.tension_fraction < 1 and self.roll_deg >= 0 and 0 <= self.tilt_deg < 30):
            raise ValueError("perturbations: tension fraction in [0, 1), roll >= 0, tilt in [0, 30) degrees")


def _tilt(path_mm: np.ndarray, axis: np.ndarray, angle_deg: float) -> np.ndarray:
    """Rotate a path about its first point (the hole) by ``angle_deg`` about unit ``axis`` (LPS)."""
    a = np.radians(angle_deg)
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    rot = np.eye(3) + np.sin(a) * k + (1 - np.cos(a)) * k @ k
    return (path_mm - path_mm[0]) @ rot.T + path_mm[0]


@dataclass(frozen=True)
class Robustness:
    """Worst case over the perturbations: reach error (mm), clearance (mm), and the perturbation it came from.

    Parameters
    ----------
    worst_reach_mm : float, mm
        Largest reach error over the nominal path and the perturbed ones.
    worst_clearance_mm : float, mm
        Smallest clearance over them (0 when one collides).
    worst_case : str
        The perturbation that set the worst case (``"nominal"`` when none is worse), with the organ hit if any.
    model : ModelInfo
        The fast insertion model the perturbed paths came from.
    """

    worst_reach_mm: float
    worst_clearance_mm: float
    worst_case: str
    model: ModelInfo


def assess(candidate: Candidate, target: Target, organs: Sequence[Organ], patient_from_template: np.ndarray,
           needle_radius_mm: float, perturbations: Perturbations = Perturbations(),
           model: KinematicInsertion = KINEMATIC, reach_tolerance_mm: float = 2.0) -> Robustness:
    """Re-evaluate one candidate under every perturbation (see the module docstring).

    Parameters
    ----------
    candidate : Candidate
        A scored candidate; tension and roll are perturbed only for a steered one with its schedule and design.
    target : Target
        The candidate's target.
    organs : sequence of Organ
        Organs at risk and bone (meshes in LPS mm) the perturbed paths are checked against.
    patient_from_template : (4, 4) float
        Template pose: template frame (mm) to patient LPS (mm); its x and y axes are the tilt axes.
    needle_radius_mm : float, mm
        Needle radius for the collision check.
    perturbations : Perturbations
        The errors to apply.
    model : KinematicInsertion
        Fast insertion model that re-inserts the perturbed schedules (template frame).
    reach_tolerance_mm : float, mm
        Reach tolerance of the plan.

    Returns
    -------
    Robustness
        Worst reach error and smallest clearance over the perturbations, and the perturbation responsible.
    """
    variants = perturbed_paths(candidate.path_mm, candidate.insertion_depth_mm, patient_from_template, perturbations,
                               model, candidate.design if candidate.steered else None, candidate.schedule)
    worst_reach, worst_clear, worst = worst_case(candidate, (
        (label, score_path(target, candidate.hole_id, candidate.hole_distance_mm, path, organs, needle_radius_mm,
                           reach_tolerance_mm, candidate.model, steered=candidate.steered,
                           depth_mm=candidate.insertion_depth_mm)) for label, path in variants))
    return Robustness(worst_reach, worst_clear, worst, model.info)


def perturbed_paths(path_mm: np.ndarray, depth_mm: float, patient_from_template: np.ndarray,
                    perturbations: Perturbations = Perturbations(), model: KinematicInsertion = KINEMATIC,
                    design: RodDesign | None = None, schedule: TensionSchedule | None = None,
                    ) -> list[tuple[str, np.ndarray]]:
    """Return where a needle goes under each perturbation: its path with the error applied, labelled.

    For a steered needle (``design`` and ``schedule`` given) the tension scaled by ``1 ± tension_fraction`` (at most
    the stylet's limit) and the roll offset by ``± roll_deg``: the perturbed minus the nominal insertion of the fast
    ``model`` added to ``path_mm`` (so the reference model's path keeps its shape); for every needle the entry
    direction tilted by ``± tilt_deg`` about the template's x and y axes, about the hole.

    Parameters
    ----------
    path_mm : (n, 3) float, mm, LPS
        The needle's centreline, hole (first point) to tip.
    depth_mm : float, mm
        Inserted arc length.
    patient_from_template : (4, 4) float
        Template frame (mm) to patient LPS (mm); its x and y axes are the tilt axes.
    perturbations : Perturbations
        The errors to apply.
    model : KinematicInsertion
        Fast insertion model of the tension and roll errors (template frame).
    design : RodDesign or None
        The stylet (None: a straight needle, tilts only).
    schedule : TensionSchedule or None
        The needle's tension schedule (None: tilts only).

    Returns
    -------
    list of (str, (n, 3) float)
        The perturbation's label and the perturbed path (mm, LPS, hole to tip): 4 tension and roll errors for a
        steered needle, then 4 tilts.
    """
    m = np.asarray(patient_from_template, float)
    path_mm = np.asarray(path_mm, float)
    variants: list[tuple[str, np.ndarray]] = []
    if design is not None and schedule is not None:
        sch = schedule
        trials = [(f"tension x{1 + f:.2f}", TensionSchedule(
            sch.depth_mm, np.minimum(sch.tension_n * (1 + f), design.max_tension_n), sch.roll_deg))
            for f in (-perturbations.tension_fraction, perturbations.tension_fraction)]
        trials += [(f"roll {d:+.0f} deg", TensionSchedule(sch.depth_mm, sch.tension_n, sch.roll_deg + d))
                   for d in (-perturbations.roll_deg, perturbations.roll_deg)]
        shapes = model.insert_array(design, [sch] + [t for _, t in trials], depth_mm)  # template frame
        s_model = np.linspace(0.0, depth_mm, shapes.shape[1])
        s_path = arc_length_mm(path_mm)
        s_path *= depth_mm / max(s_path[-1], 1e-12)
        for (label, _), shape in zip(trials, shapes[1:], strict=True):
            # the perturbation's effect (perturbed minus nominal, fast model) added to the path
            delta = np.column_stack([np.interp(s_path, s_model, (shape - shapes[0])[:, j]) for j in range(3)])
            variants.append((label, path_mm + delta @ m[:3, :3].T))
    for axis_name, axis in (("x", m[:3, 0]), ("y", m[:3, 1])):
        for sign in (-1.0, 1.0):
            variants.append((f"entry tilt {sign * perturbations.tilt_deg:+.0f} deg about template {axis_name}",
                             _tilt(path_mm, axis, sign * perturbations.tilt_deg)))
    return variants


def with_robustness(c: Candidate, r: Robustness) -> Candidate:
    """Return the candidate carrying its robustness numbers.

    Parameters
    ----------
    c : Candidate
        The candidate that was assessed.
    r : Robustness
        Its assessment by :func:`assess`.

    Returns
    -------
    Candidate
        A copy of ``c`` with ``worst_reach_mm``, ``worst_clearance_mm`` and ``worst_case`` set.
    """
    return dataclasses.replace(c, worst_reach_mm=r.worst_reach_mm, worst_clearance_mm=r.worst_clearance_mm,
                               worst_case=r.worst_case)
