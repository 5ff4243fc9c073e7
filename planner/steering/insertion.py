"""Insertion models: the path a steered needle cuts while it is pushed in under a tension schedule.

The seam every insertion model plugs into, and the parts the built-in models share. All in the template frame (entry
at the origin, ``+z`` the insertion direction, roll 0 bends toward template ``+x``), millimetres:

* :class:`InsertionModel` (the Protocol; entry-point group ``reachplan.insertion_models``), :class:`NamedInsertion`
  (the built-ins' base), :class:`ModelInfo`, :class:`InsertionPath` and :class:`FailedInsertion`;
* the free-space section curvatures of a design against tension (:func:`curvature_table`) and tip following at a
  given curvature factor (:func:`tip_following_paths`);
* the medium: Winkler modulus after Vesic (1961), ``k = 0.65 E_s/(1-ν²) (E_s D⁴/EI)^(1/12)``
  (:func:`winkler_modulus_pa`), with the phantom's SimuGel modulus E_s = 0.19 MPa (reference: ``oncoreach.md``,
  Tissue and phantom).

The built-in models, from cheapest to richest:

``kinematic`` (:mod:`reachplan.planner.steering.kinematic`)
    Tip following. The tip advances along its tangent, which turns toward the bending direction (set by the
    roll) at the free-space curvature of the stylet's distal (joint) section under the current tension,
    from a rod model, times the design's curvature factor at the tissue's modulus
    (:func:`reachplan.planner.steering.factors.curvature_factor`, fitted per design to the in-tissue Cosserat
    insertion). Cheap and vectorised over many schedules at once.
``tissue_rod`` (:mod:`reachplan.planner.steering.tissue_rod`)
    Reference. The two-tube Cosserat rod (geometrically exact) pushed in steps into an elastic foundation tied
    to the track its tip cut, one modulus along the path or one per organ crossed.

The curvature factor ties the two (:mod:`reachplan.planner.steering.factors`: the packaged table and the fit of the
kinematic model to the rod); it imports both, and neither imports it.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Hashable, Sequence
from dataclasses import dataclass
from functools import lru_cache
from typing import Any, ClassVar, Protocol, cast, runtime_checkable

import numpy as np

from reachplan.planner.errors import PlanInputError
from reachplan.planner.steering.schedule import TensionSchedule
from reachplan.rod_model.beam import PLANAR_BEAM
from reachplan.rod_model.design import RodDesign
from reachplan.rod_model.protocol import RodModel

#: SimuGel #3 Young's modulus (Pa), the phantom's tissue (reference: oncoreach.md, section 4).
SIMUGEL_MODULUS_PA = 0.19e6
#: Poisson's ratio of a water-rich gel, ASSUMED nearly incompressible.
TISSUE_POISSON = 0.49

#: One model setting: (name with its unit, value).
Setting = tuple[str, float | int | str | bool]


@dataclass(frozen=True)
class ModelInfo:
    """The model that produced a number: insertion model and rod model by name, with their settings.

    Parameters
    ----------
    insertion : str
        Insertion model name (``kinematic``, ``tissue_rod``), or ``straight`` for a straight needle.
    rod_model : str
        Rod model that gave the curvatures (``planar_beam``, ``two_tube_cosserat``); "" for a straight needle.
    settings : tuple of (name, value)
        The insertion model's settings, and the rod model's prefixed ``rod_model.`` (units in the names).
    """

    insertion: str
    rod_model: str = ""
    settings: tuple[Setting, ...] = ()

    @property
    def label(self) -> str:
        """``insertion+rod_model`` (e.g. ``kinematic+planar_beam``), or the insertion name alone.

        The JSON ``model`` string.
        """
        return f"{self.insertion}+{self.rod_model}" if self.rod_model else self.insertion

    def to_json(self) -> dict[str, Any]:
        """Return the info as JSON-ready values.

        Returns
        -------
        dict of str to object
            ``{"insertion", "rod_model", "settings": {name: value}}``.
        """
        return {"insertion": self.insertion, "rod_model": self.rod_model, "settings": dict(self.settings)}

    @staticmethod
    def of(insertion: str, model: object, rod_model: RodModel | None = None) -> ModelInfo:
        """Return the info of an insertion model ``model`` (a dataclass) named ``insertion`` on ``rod_model``.

        The settings are ``model``'s scalar fields, then the rod model's prefixed ``rod_model.``.

        Parameters
        ----------
        insertion : str
            The insertion model's name.
        model : object
            The insertion model (a dataclass).
        rod_model : RodModel or None
            The rod model it bends with; None for a model without one.

        Returns
        -------
        ModelInfo
            Names and settings.
        """
        settings = _scalar_fields(model)
        if rod_model is None:
            return ModelInfo(insertion, "", settings)
        rod = tuple((f"rod_model.{k}", v) for k, v in _scalar_fields(rod_model))
        return ModelInfo(insertion, str(rod_model.name), settings + rod)


def _scalar_fields(obj: object) -> tuple[Setting, ...]:
    """Return the (name, value) pairs of a dataclass instance's scalar fields; () for anything else."""
    if not dataclasses.is_dataclass(obj):
        return ()
    pairs = [(f.name, getattr(obj, f.name)) for f in dataclasses.fields(obj)]
    scale = dict(pairs).get("curvature_scale")  # a site calibration, when one is in use: design=ratio
    calibrated = (("curvature_scale", ",".join(f"{k}={v:g}" for k, v in scale)),) if scale else ()
    return tuple((k, v) for k, v in pairs if isinstance(v, (bool, int, float, str))) + calibrated


#: The model of a straight needle (an exact line, no model settings).
STRAIGHT = ModelInfo("straight")


@dataclass(frozen=True, eq=False)
class InsertionPath:
    """A predicted needle centreline after insertion.

    Parameters
    ----------
    positions_mm : (n, 3) float, mm, template frame; row 0 at the template (origin), last row the tip.
    depth_mm : float
        Inserted arc length.
    model : ModelInfo
        Insertion model and rod model that produced it (label e.g. ``kinematic+planar_beam``).
    """

    positions_mm: np.ndarray
    depth_mm: float
    model: ModelInfo


@dataclass(frozen=True)
class FailedInsertion:
    """An insertion the model could not predict, with the reason.

    It is falsy, so ``if path:`` tells a path from a failure.

    Parameters
    ----------
    model : ModelInfo
        The model that failed.
    reason : str
        Why, in words.
    """

    model: ModelInfo
    reason: str

    def __bool__(self) -> bool:
        return False


@runtime_checkable
class InsertionModel(Protocol):
    """What the planner needs of an insertion model (entry-point group ``reachplan.insertion_models``).

    For type checking; the registry holds a plugin to the same shape structurally
    (:func:`reachplan.plugins.checks.check_insertion_model`).
    """

    @property
    def name(self) -> str:
        """The name the model registers under (``InsertionPath.model.insertion``)."""
        ...

    def insert(self, design: RodDesign, schedules: Sequence[TensionSchedule],
               depth_mm: float) -> list[InsertionPath | FailedInsertion]:
        """Insert ``design`` to ``depth_mm`` once per schedule.

        Parameters
        ----------
        design : RodDesign
            The stylet in its needle.
        schedules : sequence of TensionSchedule
            Tendon tension (N) and roll (degrees) against inserted depth (mm).
        depth_mm : float, mm
            Inserted arc length.

        Returns
        -------
        list of InsertionPath or FailedInsertion
            One path (template frame, mm) or failure per schedule, in order.
        """
        ...


class NamedInsertion:
    """Base of the built-in insertion models: the registered name (class constant ``label``) and :attr:`info`."""

    label: ClassVar[str] = ""
    rod_model: RodModel  # a field of every subclass

    @property
    def name(self) -> str:
        """The name the model registers under (``InsertionPath.model.insertion``)."""
        return self.label

    @property
    def info(self) -> ModelInfo:
        """The model that produced a path: this model, its rod model and their settings."""
        return ModelInfo.of(self.label, self, self.rod_model)

    def scale_for(self, design: RodDesign) -> float:
        """Return the site's curvature calibration of ``design`` (``curvature_scale`` by design name; 1 without).

        Parameters
        ----------
        design : RodDesign
            The stylet.

        Returns
        -------
        float
            The ratio of the site's in-tissue curvature to the model's (dimensionless).
        """
        return dict(getattr(self, "curvature_scale", ())).get(design.name, 1.0)


@dataclass(frozen=True, eq=False)
class CurvatureTable:
    """Free-space section curvatures of a design against tendon tension, from one rod model.

    Exact at the tabulated tensions, linear between.

    Parameters
    ----------
    rod_model : str
        Name of the rod model the table came from.
    tensions_n : (t,) float, N
        The tabulated tensions, increasing from 0.
    section_bounds_mm : (k + 1,) float, mm
        Arc-length boundaries of the design's sections, from the base.
    section_curvature_per_mm : (t, k) float, 1/mm
        Each section's curvature at each tension.
    joint_section : int
        Index of the distal (joint) section.
    """

    rod_model: str  # name of the rod model the table came from
    tensions_n: np.ndarray
    section_bounds_mm: np.ndarray
    section_curvature_per_mm: np.ndarray
    joint_section: int

    def joint(self, tension_n: np.ndarray) -> np.ndarray:
        """Joint-section curvature at the given tensions.

        Parameters
        ----------
        tension_n : array, N
            Tendon tensions (any shape).

        Returns
        -------
        array, 1/mm
            The joint section's curvature, the shape of ``tension_n``.
        """
        return np.interp(tension_n, self.tensions_n, self.section_curvature_per_mm[:, self.joint_section])

    def sections(self, tension_n: float) -> np.ndarray:
        """Every section's curvature at one tension.

        Parameters
        ----------
        tension_n : float, N
            The tendon tension.

        Returns
        -------
        (k,) float, 1/mm
            Curvature per section, base to tip.
        """
        return np.array([np.interp(tension_n, self.tensions_n, c) for c in self.section_curvature_per_mm.T])


def curvature_table(design: RodDesign, rod_model: RodModel = PLANAR_BEAM, n: int = 21) -> CurvatureTable:
    """Tabulate the free-space section curvatures of ``design`` from 0 to its maximum tension at ``n`` tensions.

    Cached per (design, rod model, n): the rod model must be hashable (a frozen dataclass, as the built-in
    ones are).

    Parameters
    ----------
    design : RodDesign
        The stylet in its needle.
    rod_model : RodModel
        The rod model solving the free-space shapes (batched).
    n : int
        Number of tensions, evenly spaced.

    Returns
    -------
    CurvatureTable
        The section curvatures (1/mm) at the ``n`` tensions (N).

    Raises
    ------
    PlanInputError
        When the rod model does not converge at some tabulated tension (the table would be wrong).
    """
    return _curvature_table(design, cast(Hashable, rod_model), n)


@lru_cache(maxsize=64)
def _curvature_table(design: RodDesign, key: Hashable, n: int) -> CurvatureTable:
    rod_model = cast(RodModel, key)
    tensions = np.linspace(0.0, design.max_tension_n, n)
    batch = rod_model.solve_batch(design, tensions)
    if not np.all(batch.converged):
        bad = tensions[~np.asarray(batch.converged)]
        raise PlanInputError(f"rod model {rod_model.name} did not converge for {design.name} at {bad} N")
    return CurvatureTable(rod_model.name, tensions, np.asarray(batch.section_bounds_mm, float),
                          np.asarray(batch.section_curvature_per_m, float) * 1e-3, int(batch.joint_section))


def _rotate(v: np.ndarray, axis: np.ndarray, angle: np.ndarray) -> np.ndarray:
    """Rodrigues rotation of rows ``v`` about unit rows ``axis`` by ``angle`` (rad); all (S, 3) / (S,)."""
    c, s = np.cos(angle)[:, None], np.sin(angle)[:, None]
    return v * c + np.cross(axis, v) * s + axis * np.einsum("ij,ij->i", axis, v)[:, None] * (1 - c)



def tip_following_paths(design: RodDesign, schedules: Sequence[TensionSchedule], depth_mm: float, factor: float,
                        rod_model: RodModel = PLANAR_BEAM, step_mm: float = 1.0) -> np.ndarray:
    """Insert ``design`` to ``depth_mm`` once per schedule by tip following at a given curvature factor.

    The tip advances along its tangent, which turns toward the bending direction (the schedule's roll) at ``factor``
    times the joint section's free-space curvature under the schedule's tension (:func:`curvature_table`); each
    step is an exact circular arc. The kinematic insertion model with its factor chosen
    (:class:`reachplan.planner.steering.kinematic.KinematicInsertion`).

    Parameters
    ----------
    design : RodDesign
        The needle and stylet.
    schedules : sequence of TensionSchedule
        Tension (N) and roll (deg) against depth (mm), S of them.
    depth_mm : float
        Insertion depth, mm, in ``(0, design.length_mm]``.
    factor : float
        Path curvature over the joint section's free-space curvature.
    rod_model : RodModel
        Rod model that gives the curvature table.
    step_mm : float
        Integration step along the insertion, mm.

    Returns
    -------
    (S, n + 1, 3) float ndarray
        The paths, mm, template frame: row ``i`` after ``i * depth_mm / n`` of insertion, ``n = ceil(depth_mm /
        step_mm)``; row 0 at the template, the last row the tip.

    Raises
    ------
    PlanInputError
        A depth outside the design's length, a schedule above the design's maximum tension, or a rod model that does
        not converge for the curvature table.
    """
    _check_depth(design, depth_mm)
    table = curvature_table(design, rod_model)
    n = max(1, int(np.ceil(depth_mm / step_mm)))
    depths = np.linspace(0.0, depth_mm, n + 1)
    h = depth_mm / n
    tension = np.empty((len(schedules), n + 1))
    roll = np.empty_like(tension)
    for i, sch in enumerate(schedules):
        tension[i], roll[i] = sch.at(depths)
    if np.any(tension > design.max_tension_n + 1e-9):
        raise PlanInputError(f"a schedule exceeds {design.name}'s maximum tension {design.max_tension_n} N")
    kappa = factor * table.joint(tension)  # (S, n+1), 1/mm
    phi = np.radians(roll)
    if np.all(np.ptp(phi, axis=1) == 0.0):
        return _planar_paths(kappa, phi[:, 0], h)
    s_count = len(schedules)
    pos = np.zeros((s_count, n + 1, 3))
    t = np.tile([0.0, 0.0, 1.0], (s_count, 1))
    e1 = np.tile([1.0, 0.0, 0.0], (s_count, 1))
    for j in range(n):
        km = 0.5 * (kappa[:, j] + kappa[:, j + 1])
        ph = 0.5 * (phi[:, j] + phi[:, j + 1])
        e2 = np.cross(t, e1)
        b = np.cos(ph)[:, None] * e1 + np.sin(ph)[:, None] * e2
        axis = np.cross(t, b)  # unit: t and b are orthonormal
        half = _rotate(t, axis, 0.5 * km * h)
        chord = h * np.sinc(0.5 * km * h / np.pi)  # = 2 sin(κh/2)/κ, the chord of the arc step
        pos[:, j + 1] = pos[:, j] + chord[:, None] * half  # along the mid-step tangent: exact for an arc
        t_new = _rotate(t, axis, km * h)
        e1 = _rotate(e1, axis, km * h)  # parallel transport of the reference normal
        t = t_new
    return pos

def _planar_paths(kappa: np.ndarray, phi: np.ndarray, h: float) -> np.ndarray:
    """Return tip-following paths of constant roll: (S, n+1, 3) float, mm.

    The tangent angle is the running integral of the curvature, each step an exact circular arc (chord along the
    mid-step tangent).
    """
    km = 0.5 * (kappa[:, 1:] + kappa[:, :-1])  # (S, n)
    theta = np.concatenate([np.zeros((len(km), 1)), np.cumsum(km * h, axis=1)], axis=1)
    mid = theta[:, :-1] + 0.5 * km * h
    chord = h * np.sinc(0.5 * km * h / np.pi)
    lateral = np.concatenate([np.zeros((len(km), 1)), np.cumsum(chord * np.sin(mid), axis=1)], axis=1)
    axial = np.concatenate([np.zeros((len(km), 1)), np.cumsum(chord * np.cos(mid), axis=1)], axis=1)
    return np.stack([lateral * np.cos(phi)[:, None], lateral * np.sin(phi)[:, None], axial], axis=-1)


def winkler_modulus_pa(design: RodDesign, tissue_modulus_pa: float = SIMUGEL_MODULUS_PA,
                       poisson: float = TISSUE_POISSON) -> float:
    """Return the subgrade modulus (N/m per m of needle) of a beam of the needle's diameter in an elastic medium.

    Vesic 1961, using the bending stiffness of the stylet-in-needle tube section.

    Parameters
    ----------
    design : RodDesign
        Its needle's outer diameter and tube section's bending stiffness.
    tissue_modulus_pa : float, Pa
        Young's modulus of the tissue.
    poisson : float
        Poisson's ratio of the tissue, in [0, 0.5).

    Returns
    -------
    float, Pa
        The subgrade modulus (N/m per m of needle).

    Raises
    ------
    PlanInputError
        A modulus that is not positive or a Poisson's ratio out of range.
    """
    if tissue_modulus_pa <= 0 or not (0 <= poisson < 0.5):
        raise PlanInputError("tissue modulus must be > 0 Pa and Poisson's ratio in [0, 0.5)")
    d = design.needle.outer_diameter_mm * 1e-3
    tube = next(s for s in design.sections() if s.kind == "tube")
    ei = tube.ei1 + tube.ei2
    return 0.65 * tissue_modulus_pa / (1 - poisson**2) * (tissue_modulus_pa * d**4 / ei) ** (1 / 12)


def _check_depth(design: RodDesign, depth_mm: float) -> None:
    if not (np.isfinite(depth_mm) and 0 < depth_mm <= design.length_mm):
        raise PlanInputError(f"insertion depth must be in (0, {design.length_mm:.0f}] mm for {design.name}, "
                             f"got {depth_mm}")
