"""The kinematic model's curvature factor: fitted per stylet design to the in-tissue rod, packaged as a table.

The kinematic (tip-following) insertion model turns its path at the joint section's free-space curvature times a
factor that depends on the design and the tissue's modulus. The factor is fitted to the in-tissue Cosserat insertion
(:mod:`reachplan.planner.steering.tissue_rod`) by least squares on the tip (:func:`fit_curvature_factor`), for every
preset at a few moduli (``reachplan bench factors``), and packaged (``curvature_factors.json``, keyed by
:func:`design_key`); :func:`curvature_factor` reads the table, and fits a design the table does not hold.

This module sits above both insertion models' modules (:mod:`reachplan.planner.steering.insertion`, the tip-following
kernel, and :mod:`reachplan.planner.steering.tissue_rod`); neither imports it. The kinematic model
(:mod:`reachplan.planner.steering.kinematic`) takes its default factor from here.
"""

from __future__ import annotations

import dataclasses
import hashlib
from collections.abc import Sequence
from dataclasses import dataclass, replace
from functools import cached_property, lru_cache
from typing import Any

import numpy as np

from reachplan.planner.errors import PlanInputError
from reachplan.planner.steering.insertion import tip_following_paths
from reachplan.planner.steering.schedule import TensionSchedule
from reachplan.planner.steering.tissue_rod import PLANNER_REFERENCE
from reachplan.rod_model.design import RodDesign, preset

#: Lower end of the tip-following range, Pa: below it the tissue does not hold the shaft on the track its tip
#: cut (the tube's Winkler length (4 EI / k)^(1/4) exceeds ~35 mm) and one curvature factor cannot describe the
#: in-tissue rod (its fit error rises from 1.4 mm RMS at 0.1 MPa to 3.8 mm at 10 kPa; ``reachplan bench models``).
TIP_FOLLOWING_MIN_PA = 1e5
#: Package data: each stylet design's curvature factor against the tissue modulus, fitted to the in-tissue rod
#: (``reachplan bench factors --install``; :func:`fit_curvature_factor`).
FACTOR_TABLE = "curvature_factors.json"
#: The design whose factor is used when none is named (the planner's default design).
REFERENCE_DESIGN = "15ga-30j-tip"


def design_key(design: RodDesign) -> str:
    """Return a fingerprint of a design's mechanics, its name left out (16 hex digits of a SHA-256).

    Of the design's ``repr``: frozen dataclasses of numbers and tuples, so the same design gives the same key in
    every process; a calibrated preset keeps its name but not its key.

    Parameters
    ----------
    design : RodDesign
        The design.

    Returns
    -------
    str
        16 hex digits.
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
        """Return the curve as plain JSON data (the package table's entry).

        Returns
        -------
        dict of str to object
            ``design``, ``key``, ``moduli_pa`` (Pa), ``factors`` and ``rms_mm`` (mm).
        """
        return {"design": self.design, "key": self.key, "moduli_pa": list(self.moduli_pa),
                "factors": list(self.factors), "rms_mm": list(self.rms_mm)}


@lru_cache(maxsize=1)
def factor_table() -> dict[str, FactorCurve]:
    """Return the packaged curvature factors by :func:`design_key` (empty when the package has no table).

    Returns
    -------
    dict of str to FactorCurve
        :func:`design_key` -> the design's factor against modulus.
    """
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
    insertion (:func:`fit_curvature_factor`: 20 mm ramps from 0-60 mm
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

    Parameters
    ----------
    modulus_pa : float, Pa
        Young's modulus of the tissue, at least :data:`TIP_FOLLOWING_MIN_PA`.
    design : RodDesign or None
        The stylet design; None: :data:`REFERENCE_DESIGN`.

    Returns
    -------
    float
        The factor (dimensionless) on the joint section's free-space curvature.

    Raises
    ------
    PlanInputError
        ``modulus_pa`` below :data:`TIP_FOLLOWING_MIN_PA` or not finite: use the in-tissue rod model there.
    """
    check_tip_following(modulus_pa)
    if design is None:
        design = preset(REFERENCE_DESIGN)
    curve = factor_table().get(design_key(design))
    if curve is not None:
        return curve(float(modulus_pa))
    return _fitted_factor(design, float(modulus_pa))


def check_tip_following(modulus_pa: float) -> None:
    """Check that tissue of ``modulus_pa`` holds the needle on its track (the kinematic model's range).

    Parameters
    ----------
    modulus_pa : float
        Young's modulus of the tissue, Pa.

    Raises
    ------
    PlanInputError
        ``modulus_pa`` below :data:`TIP_FOLLOWING_MIN_PA` or not finite.
    """
    if not (np.isfinite(modulus_pa) and modulus_pa >= TIP_FOLLOWING_MIN_PA):
        raise PlanInputError(f"tissue modulus {modulus_pa:g} Pa is below the tip-following range (>= "
                             f"{TIP_FOLLOWING_MIN_PA:g} Pa): the tissue does not hold the needle on its track; "
                             "give a tissue_factor or use the tissue_rod insertion model")


@lru_cache(maxsize=64)
def _fitted_factor(design: RodDesign, modulus_pa: float) -> float:
    """Fit the factor of a design the packaged table does not hold (memoised)."""
    return fit_curvature_factor(design, modulus_pa).factor


#: The schedules and depths a curvature factor is fitted over (:func:`fit_curvature_factor`): 20 mm ramps from these
#: onsets (mm) to these fractions of the design's maximum tension (the planner's schedule family), tips at these
#: depths (mm; those beyond the design's length dropped).
FACTOR_ONSETS_MM: tuple[float, ...] = (0.0, 20.0, 40.0, 60.0)
FACTOR_FRACTIONS: tuple[float, ...] = (0.6, 1.0)
FACTOR_DEPTHS_MM: tuple[float, ...] = (60.0, 90.0, 120.0, 150.0)


@dataclass(frozen=True)
class FactorFit:
    """The kinematic curvature factor fitted to the in-tissue rod at one modulus.

    Parameters
    ----------
    factor : float
        Least squares over every schedule and depth (dimensionless).
    rms_mm : float, mm
        The kinematic model's tip error with it, root mean square.
    tips : int
        How many rod tips were fitted (a failed insertion step loses its depths).
    """

    factor: float
    rms_mm: float
    tips: int


def factor_schedules(design: RodDesign, onsets_mm: Sequence[float] = FACTOR_ONSETS_MM,
                     fractions: Sequence[float] = FACTOR_FRACTIONS) -> list[TensionSchedule]:
    """Return the ramps a curvature factor is fitted over: 20 mm from each onset (mm) to each fraction of the limit.

    Parameters
    ----------
    design : RodDesign
        Its maximum tension (N) scales the fractions.
    onsets_mm : sequence of float, mm
        Depths where a ramp starts.
    fractions : sequence of float
        Fractions of the maximum tension a ramp ends at.

    Returns
    -------
    list of TensionSchedule
        One per onset and fraction, onsets outer.
    """
    return [TensionSchedule.ramp(float(o), 20.0, f * design.max_tension_n) for o in onsets_mm for f in fractions]


def fit_factor(design: RodDesign, schedules: Sequence[TensionSchedule], depths_mm: np.ndarray,
               tips_mm: np.ndarray) -> FactorFit:
    """Fit the kinematic curvature factor of ``design`` to rod tips (least squares over the finite ones).

    Parameters
    ----------
    design : RodDesign
        The stylet in its needle.
    schedules : sequence of TensionSchedule
        The S schedules the rod was inserted with.
    depths_mm : (D,) float, mm
        Depths the tips were taken at (whole mm: rows of a kinematic path at 1 mm steps).
    tips_mm : (S, D, 3) float, mm, template frame
        The rod's tip for each schedule at each depth, NaN past a failed insertion step.

    Returns
    -------
    FactorFit
        The factor in [0, 3], its RMS tip error (mm) and the number of tips used.

    Raises
    ------
    PlanInputError
        Fewer than two finite tips.
    """
    from scipy.optimize import minimize_scalar

    depths = np.asarray(depths_mm, dtype=float)
    ok = np.all(np.isfinite(tips_mm), axis=-1)
    if ok.sum() < 2:
        raise PlanInputError(f"the in-tissue rod failed for {design.name}: fewer than two tips, no curvature factor")
    rows = np.round(depths).astype(int)  # rows of a kinematic path at 1 mm steps

    def misfit(f: float) -> float:
        kin = tip_following_paths(design, schedules, float(depths[-1]), f)[:, rows]
        return float(np.sum(np.sum((kin - tips_mm) ** 2, axis=-1)[ok]))

    best = minimize_scalar(misfit, bounds=(0.0, 3.0), method="bounded", options={"xatol": 1e-4})
    return FactorFit(float(best.x), float(np.sqrt(misfit(float(best.x)) / ok.sum())), int(ok.sum()))


def fit_curvature_factor(design: RodDesign, modulus_pa: float, onsets_mm: Sequence[float] = FACTOR_ONSETS_MM,
                         fractions: Sequence[float] = FACTOR_FRACTIONS,
                         depths_mm: Sequence[float] = FACTOR_DEPTHS_MM) -> FactorFit:
    """Fit the kinematic model's curvature factor of ``design`` to the in-tissue rod in tissue of ``modulus_pa``.

    The rod is the planner's reference (:data:`PLANNER_REFERENCE`: 1 RK4 step per mm) with 2 mm insertion steps
    and no extrapolation (the tips at every depth come from one insertion; the step moves a 150 mm tip by 0.2-0.4
    mm, a fifth of the fit's residual). The factor minimises the squared tip distance between the kinematic model
    and the rod over :func:`factor_schedules`, tips at each depth (:func:`fit_factor`). About 10 s for the
    default 8 schedules × 4 depths.

    Parameters
    ----------
    design : RodDesign
        The stylet in its needle.
    modulus_pa : float, Pa
        Young's modulus of the tissue.
    onsets_mm : sequence of float, mm
        Ramp onsets of :func:`factor_schedules`.
    fractions : sequence of float
        Ramp ends, as fractions of the maximum tension.
    depths_mm : sequence of float, mm
        Depths the tips are compared at (those beyond the design's length are dropped).

    Returns
    -------
    FactorFit
        The fitted factor.

    Raises
    ------
    PlanInputError
        Fewer than two rod tips (every insertion failed early), or no depth within the design's length.
    """
    depths = np.array([d for d in depths_mm if 0 < d <= design.length_mm], dtype=float)
    if len(depths) == 0:
        raise PlanInputError(f"no fitting depth within {design.name}'s length {design.length_mm:.0f} mm")
    schedules = factor_schedules(design, onsets_mm, fractions)
    rod = replace(PLANNER_REFERENCE, richardson=False, tissue_modulus_pa=float(modulus_pa))
    tips = np.full((len(schedules), len(depths), 3), np.nan)
    for i, sch in enumerate(schedules):
        _, steps = rod.insert_steps(design, sch, float(depths[-1]))
        got = {round(d, 6): tip for d, tip in steps}
        for j, d in enumerate(depths):
            tips[i, j] = got.get(round(float(d), 6), np.full(3, np.nan))
    return fit_factor(design, schedules, depths, tips)
