"""Insertion models: the path a steered needle cuts while it is pushed in under a tension schedule.

Two built-in models behind one Protocol, both in the template frame (entry at the origin, ``+z`` the insertion
direction, roll 0 bends toward template ``+x``), millimetres:

``kinematic``
    Tip following. The tip advances along its tangent, which turns toward the bending direction (set by the
    roll) at the free-space curvature of the stylet's distal (joint) section under the current tension,
    from a rod model, times the design's curvature factor at the tissue's modulus (:func:`curvature_factor`,
    fitted per design to the in-tissue Cosserat insertion of :mod:`reachplan.planner.steering.tissue_rod`).
    Cheap and vectorised over many schedules at once.
``tissue_rod`` (:mod:`reachplan.planner.steering.tissue_rod`)
    Reference. The two-tube Cosserat rod (geometrically exact) pushed in steps into an elastic foundation tied
    to the track its tip cut, one modulus along the path or one per organ crossed.

The medium: Winkler modulus after Vesic (1961), ``k = 0.65 E_s/(1-ν²) (E_s D⁴/EI)^(1/12)`` (:func:`winkler_modulus_pa`),
with the phantom's SimuGel modulus E_s = 0.19 MPa (reference: ``oncoreach.md``, Tissue and phantom).
"""

from __future__ import annotations

import dataclasses
import hashlib
from collections.abc import Hashable, Sequence
from dataclasses import dataclass
from functools import cached_property, lru_cache
from typing import Any, ClassVar, Protocol, cast, runtime_checkable

import numpy as np

from reachplan.planner.errors import PlanInputError
from reachplan.planner.steering.schedule import TensionSchedule
from reachplan.rod_model.beam import PLANAR_BEAM
from reachplan.rod_model.design import RodDesign, preset
from reachplan.rod_model.protocol import RodModel

#: SimuGel #3 Young's modulus (Pa), the phantom's tissue (reference: oncoreach.md, section 4).
SIMUGEL_MODULUS_PA = 0.19e6
#: Poisson's ratio of a water-rich gel, ASSUMED nearly incompressible.
TISSUE_POISSON = 0.49


#: Lower end of the tip-following range, Pa: below it the tissue does not hold the shaft on the track its tip
#: cut (the tube's Winkler length (4 EI / k)^(1/4) exceeds ~35 mm) and one curvature factor cannot describe the
#: in-tissue rod (its fit error rises from 1.4 mm RMS at 0.1 MPa to 3.8 mm at 10 kPa; ``reachplan bench models``).
TIP_FOLLOWING_MIN_PA = 1e5
#: Package data: each stylet design's curvature factor against the tissue modulus, fitted to the in-tissue rod
#: (``reachplan bench factors --install``; :func:`reachplan.planner.steering.tissue_rod.fit_curvature_factor`).
FACTOR_TABLE = "curvature_factors.json"
#: The design whose factor is used when none is named (the planner's default design).
REFERENCE_DESIGN = "15ga-30j-tip"


def design_key(design: RodDesign) -> str:
    """Return a fingerprint of a design's mechanics, its name left out (16 hex digits of a SHA-256).

    Of the design's ``repr``: frozen dataclasses of numbers and tuples, so the same design gives the same key in
    every process; a calibrated preset keeps its name but not its key.
    """
    return hashlib.sha256(repr(dataclasses.replace(design, name="")).encode()).hexdigest()[:16]


@dataclass(frozen=True)
class FactorCurve:
    """One design's kinematic curvature factor against the tissue modulus, fitted to the in-tissue rod.

    Parameters
    ----------
    design : str
        The design's name when it was fitted.
    key : str
        :func:`design_key` of the design fitted.
    moduli_pa : tuple of float, Pa
        Increasing, from :data:`TIP_FOLLOWING_MIN_PA`.
    factors : tuple of float
        The fitted factor at each modulus.
    rms_mm : tuple of float, mm
        The kinematic model's root-mean-square tip error against the rod with that factor.
    """

    design: str
    key: str
    moduli_pa: tuple[float, ...]
    factors: tuple[float, ...]
    rms_mm: tuple[float, ...]

    def __call__(self, modulus_pa: float) -> float:
        """Return the factor at ``modulus_pa`` (Pa, at least the first tabulated modulus).

        A natural cubic spline in log modulus through the fitted factors (held out at 0.5 MPa, the rod's factor and
        the spline's differ by at most 0.002 over the presets; linear interpolation was up to 0.04 low at the
        peaks; ``docs/curvature_factors.csv``). Stiffer than the last modulus, the excess over pure tip following
        (factor 1) decays as the power of the modulus the last two points give, when it does decay there (the
        joints' Winkler length shrinks as a power of the modulus, see :func:`curvature_factor`); otherwise the
        last factor holds.
        """
        e = np.log(np.asarray(self.moduli_pa, dtype=float))
        c = np.asarray(self.factors, dtype=float)
        x = float(np.log(modulus_pa))
        if x <= e[-1] or len(e) < 2:
            return float(self._spline(x)) if len(e) > 2 else float(np.interp(x, e, c))
        a, b = c[-2] - 1.0, c[-1] - 1.0
        if not (a > b > 0.0):
            return float(c[-1])
        p = np.log(a / b) / (e[-1] - e[-2])
        return float(1.0 + b * np.exp(-p * (x - e[-1])))

    @cached_property
    def _spline(self) -> Any:
        from scipy.interpolate import CubicSpline

        return CubicSpline(np.log(np.asarray(self.moduli_pa, dtype=float)), np.asarray(self.factors, dtype=float),
                           bc_type="natural")

    def to_json(self) -> dict[str, object]:
        """Return the curve as plain JSON data (the package table's entry)."""
        return {"design": self.design, "key": self.key, "moduli_pa": list(self.moduli_pa),
                "factors": list(self.factors), "rms_mm": list(self.rms_mm)}


@lru_cache(maxsize=1)
def factor_table() -> dict[str, FactorCurve]:
    """Return the packaged curvature factors by :func:`design_key` (empty when the package has no table)."""
    import json
    from importlib import resources

    try:
        text = resources.files("reachplan.planner.steering").joinpath(FACTOR_TABLE).read_text(encoding="utf-8")
    except FileNotFoundError:
        return {}
    curves = [FactorCurve(str(d["design"]), str(d["key"]), tuple(map(float, d["moduli_pa"])),
                          tuple(map(float, d["factors"])), tuple(map(float, d["rms_mm"])))
              for d in json.loads(text)["designs"]]
    return {c.key: c for c in curves}


def curvature_factor(modulus_pa: float, design: RodDesign | None = None) -> float:
    """Return the kinematic model's curvature factor of ``design`` in tissue of Young's modulus ``modulus_pa`` (Pa).

    The path curvature over the joint section's free-space curvature, fitted per design to the in-tissue Cosserat
    insertion (:func:`reachplan.planner.steering.tissue_rod.fit_curvature_factor`: 20 mm ramps from 0-60 mm
    onsets to 60 / 100 % of the maximum tension, tips at 60-150 mm) at 0.1, 0.19, 0.3, 1, 3 and 10 MPa, and
    interpolated (:class:`FactorCurve`; ``reachplan bench factors``, ``docs/curvature_factors.csv``). It depends
    on the design: in the gel (0.19 MPa) it is 1.28 for 15ga-30j-tip, whose held shaft adds to the joints'
    turn, but below 1 for 15ga-15j-tip and 13ga-20j-tip, whose shorter or stiffer joint sections are not yet
    decoupled from a shaft the gel barely holds (``docs/mechanics.md``). In rigid tissue the joint section bends
    only as it cuts new track, so the path takes the joint section's free-space curvature (tip following,
    factor 1; Webster et al., IJRR 25(5-6), 2006); in softer tissue a tendon pulled while the joints are embedded
    also bends them within about a Winkler length of the tip, ``(4 EI / k)^(1/4)`` (Hetényi, *Beams on Elastic
    Foundation*, 1946), and the held track keeps that extra turn (Glozman & Shoham, IEEE T-RO 23(3), 2007).

    ``design``: default :data:`REFERENCE_DESIGN`. A design not in the packaged table (a calibrated or new one,
    told apart by :func:`design_key`) is fitted here, at this modulus, once per process (about 10 s).

    Raises
    ------
    PlanInputError
        ``modulus_pa`` below :data:`TIP_FOLLOWING_MIN_PA` or not finite: use the in-tissue rod model there.
    """
    _check_tip_following(modulus_pa)
    if design is None:
        design = preset(REFERENCE_DESIGN)
    curve = factor_table().get(design_key(design))
    if curve is not None:
        return curve(float(modulus_pa))
    return _fitted_factor(design, float(modulus_pa))


def _check_tip_following(modulus_pa: float) -> None:
    if not (np.isfinite(modulus_pa) and modulus_pa >= TIP_FOLLOWING_MIN_PA):
        raise PlanInputError(f"tissue modulus {modulus_pa:g} Pa is below the tip-following range (>= "
                             f"{TIP_FOLLOWING_MIN_PA:g} Pa): the tissue does not hold the needle on its track; "
                             "give a tissue_factor or use the tissue_rod insertion model")


@lru_cache(maxsize=64)
def _fitted_factor(design: RodDesign, modulus_pa: float) -> float:
    """Fit the factor of a design the packaged table does not hold (memoised)."""
    from reachplan.planner.steering.tissue_rod import fit_curvature_factor  # the rod imports this module

    return fit_curvature_factor(design, modulus_pa).factor


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
        """Return ``{"insertion", "rod_model", "settings": {name: value}}``."""
        return {"insertion": self.insertion, "rod_model": self.rod_model, "settings": dict(self.settings)}

    @staticmethod
    def of(insertion: str, model: object, rod_model: RodModel | None = None) -> ModelInfo:
        """Return the info of an insertion model ``model`` (a dataclass) named ``insertion`` on ``rod_model``.

        The settings are ``model``'s scalar fields, then the rod model's prefixed ``rod_model.``.
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
    pairs = ((f.name, getattr(obj, f.name)) for f in dataclasses.fields(obj))
    return tuple((k, v) for k, v in pairs if isinstance(v, (bool, int, float, str)))


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
    """An insertion the model could not predict, with the reason."""

    model: ModelInfo
    reason: str

    def __bool__(self) -> bool:
        return False


@runtime_checkable
class InsertionModel(Protocol):
    """What the planner needs of an insertion model (entry-point group ``reachplan.insertion_models``)."""

    @property
    def name(self) -> str:
        """The name the model registers under (``InsertionPath.model.insertion``)."""
        ...

    def insert(self, design: RodDesign, schedules: Sequence[TensionSchedule],
               depth_mm: float) -> list[InsertionPath | FailedInsertion]:
        """Insert ``design`` to ``depth_mm`` once per schedule: one path or failure per schedule, in order."""
        ...


def check_insertion_model(obj: object) -> None:
    """Raise ``TypeError`` when ``obj`` does not implement :class:`InsertionModel`."""
    if not isinstance(obj, InsertionModel):
        raise TypeError(f"{obj!r} does not implement InsertionModel (.name, .insert(design, schedules, depth_mm))")


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


@dataclass(frozen=True, eq=False)
class CurvatureTable:
    """Free-space section curvatures of a design against tendon tension, from one rod model.

    ``section_curvature_per_mm`` is (n_tensions, k); exact at the tabulated tensions, linear between.
    """

    rod_model: str  # name of the rod model the table came from
    tensions_n: np.ndarray
    section_bounds_mm: np.ndarray
    section_curvature_per_mm: np.ndarray
    joint_section: int

    def joint(self, tension_n: np.ndarray) -> np.ndarray:
        """Joint-section curvature (1/mm) at the given tensions (N)."""
        return np.interp(tension_n, self.tensions_n, self.section_curvature_per_mm[:, self.joint_section])

    def sections(self, tension_n: float) -> np.ndarray:
        """(k,) curvature (1/mm) of every section at one tension."""
        return np.array([np.interp(tension_n, self.tensions_n, c) for c in self.section_curvature_per_mm.T])


def curvature_table(design: RodDesign, rod_model: RodModel = PLANAR_BEAM, n: int = 21) -> CurvatureTable:
    """Tabulate the free-space section curvatures of ``design`` from 0 to its maximum tension at ``n`` tensions.

    Cached per (design, rod model, n): the rod model must be hashable (a frozen dataclass, as the built-in
    ones are).

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


@dataclass(frozen=True)
class KinematicInsertion(NamedInsertion):
    """Tip-following insertion (see the module docstring), vectorised over schedules.

    Parameters
    ----------
    tissue_modulus_pa : float
        Young's modulus of the tissue the needle steers in (default the phantom's SimuGel, 0.19 MPa); with the
        design it sets the curvature factor by :func:`curvature_factor` (the per-organ modulus in a plan).
    tissue_factor : float or None
        Path curvature over the joint section's free-space curvature; None (default): ``curvature_factor(
        tissue_modulus_pa, design)``, fitted per design to the in-tissue Cosserat insertion. A number overrides
        it for every design.
    rod_model : RodModel
        Rod model that gives the curvature table (default :data:`~reachplan.rod_model.beam.PLANAR_BEAM`,
        exact to 0.1 % of the two-tube model for free-space curvature; see the rod-model benchmark).
    step_mm : float
        Integration step along the insertion.

    Raises
    ------
    PlanInputError
        A modulus below :data:`TIP_FOLLOWING_MIN_PA` without an explicit ``tissue_factor`` (the tissue does not
        hold the needle on its track there: tip following does not describe it), or a negative factor.
    """

    label: ClassVar[str] = "kinematic"
    tissue_modulus_pa: float = SIMUGEL_MODULUS_PA
    tissue_factor: float | None = None
    rod_model: RodModel = PLANAR_BEAM
    step_mm: float = 1.0

    def __post_init__(self) -> None:
        if self.tissue_factor is None:
            _check_tip_following(self.tissue_modulus_pa)
        elif not (np.isfinite(self.tissue_factor) and self.tissue_factor >= 0):
            raise PlanInputError(f"tissue_factor must be a finite number >= 0, got {self.tissue_factor}")

    def factor_for(self, design: RodDesign) -> float:
        """Return the curvature factor in use for ``design``: ``tissue_factor``, or the design's fitted one.

        The fitted one is :func:`curvature_factor` at ``tissue_modulus_pa``.
        """
        return curvature_factor(self.tissue_modulus_pa, design) if self.tissue_factor is None else self.tissue_factor

    def insert(self, design: RodDesign, schedules: Sequence[TensionSchedule],
               depth_mm: float) -> list[InsertionPath | FailedInsertion]:
        """Insert ``design`` to ``depth_mm`` once per schedule (positions mm, template frame)."""
        paths = self.insert_array(design, schedules, depth_mm)
        return [InsertionPath(p, depth_mm, self.info) for p in paths]

    def insert_array(self, design: RodDesign, schedules: Sequence[TensionSchedule], depth_mm: float) -> np.ndarray:
        """All paths at once: (S, n, 3) float, mm, template frame."""
        _check_depth(design, depth_mm)
        table = curvature_table(design, self.rod_model)
        n = max(1, int(np.ceil(depth_mm / self.step_mm)))
        depths = np.linspace(0.0, depth_mm, n + 1)
        h = depth_mm / n
        tension = np.empty((len(schedules), n + 1))
        roll = np.empty_like(tension)
        for i, sch in enumerate(schedules):
            tension[i], roll[i] = sch.at(depths)
        if np.any(tension > design.max_tension_n + 1e-9):
            raise PlanInputError(f"a schedule exceeds {design.name}'s maximum tension {design.max_tension_n} N")
        kappa = self.factor_for(design) * table.joint(tension)  # (S, n+1), 1/mm
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


KINEMATIC = KinematicInsertion()
