"""Learning the tissue: the in-tissue curvature fitted to steered needles found after insertion.

The planner's insertion models bend a steered needle by an in-tissue curvature that no real insertion has checked:
the kinematic model's curvature factor (:mod:`reachplan.planner.steering.factors`) and the in-tissue rod are
fitted to, or set by, the phantom's gel (0.19 MPa). A steered needle found in the post-insertion image (its
centre line from the template's hole to its tip) is exactly the evidence that would check them: this module
fits, per needle, the ratio by which its path departs from its hole's axis more (or less) than the plan's path of
the same schedule did, and pools the needles of one design into a site's ratio with its uncertainty. The site's
curvature factor is the plan's times that ratio; ``plan --calibration`` applies it to every insertion model
(:class:`~reachplan.planner.steering.kinematic.KinematicInsertion`,
:class:`~reachplan.planner.steering.tissue_rod.TissueRodInsertion`: ``curvature_scale``).

Per needle (:func:`fit_needle`)
    Least squares on the found centre line in the template frame of its hole (hole at the origin, the hole's axis
    +z): its lateral position at each found point's depth against the planned path's lateral position at the same
    depth times the ratio, turned by a roll offset (the bending plane as the hand set it), plus an entry tilt (a
    lateral offset growing linearly with depth). The roll and the tilt are nuisances the planner's own
    perturbation model draws (:class:`~reachplan.planner.steering.robustness.Perturbations`); a tension error is
    not separable from the ratio (both scale the curvature) and is averaged out over needles. For the kinematic
    model the lateral departure is linear in the curvature factor to second order in the path's angle (a
    15 % change of factor is recovered within 1 % on a 100 mm insertion that turns 17 degrees).
Pooled (:func:`pool`)
    The mean of the needles' ratios, with a Student-t 95 % interval over the needles (their spread includes each
    needle's tension error, roll and reconstruction error); one needle gives no interval.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from reachplan.planner.errors import PlanInputError

#: Fewest found points (about 1 mm apart) a needle's fit uses.
MIN_POINTS = 10
#: The curvature ratios a site calibration may hold (and a fit may reach): beyond them the needles fitted, not the
#: tissue, are wrong.
RATIO_RANGE: tuple[float, float] = (0.2, 5.0)
#: A needle whose planned path departs less than this from its hole's axis (mm) carries no information on the
#: factor.
MIN_DEFLECTION_MM = 2.0
#: A needle whose fit leaves more than this (mm, rms of the lateral residual) is not used: the fits of needles
#: tracked right leave 0.03-0.2 mm on the synthetic post-insertion images; a track that took another needle's past a
#: crossing left 1.6 mm.
MAX_FIT_RMS_MM = 1.0


@dataclass(frozen=True)
class FoundSteered:
    """One steered needle as the plan meant it and as the image shows it.

    Parameters
    ----------
    source : str
        Where it was found (a reconstruction's folder or case name).
    hole_id : str
        Its template hole.
    design : str
        The stylet preset.
    planned_factor : float
        The curvature factor of the planner's kinematic model for the design at the plan's tissue modulus, without
        a site calibration (the site's factor is this times the ratio).
    planned_mm : (k, 3) float, mm, template frame of its hole
        The plan's centre line, hole (origin) to tip, the hole's axis +z.
    found_mm : (n, 3) float, mm, template frame of its hole
        The found centre line, in the same frame.
    plan_scale : float
        The site calibration the plan itself applied to the design (``curvature_scale``; 1: none): the fitted
        factor is the plan's factor times it times the fitted ratio.
    """

    source: str
    hole_id: str
    design: str
    planned_factor: float
    planned_mm: np.ndarray
    found_mm: np.ndarray
    plan_scale: float = 1.0


@dataclass(frozen=True)
class NeedleFit:
    """One needle's fitted curvature factor.

    Parameters
    ----------
    source, hole_id, design : str
        As in :class:`FoundSteered`.
    planned_factor : float
        The factor the plan's kinematic model used.
    factor : float
        The fitted factor.
    roll_offset_deg : float, deg
        Fitted offset of the bending plane from the plan's.
    tilt_deg : float, deg
        Fitted entry tilt.
    rms_mm : float, mm
        Root mean square lateral residual of the fit.
    points : int
        Found points used.
    """

    source: str
    hole_id: str
    design: str
    planned_factor: float
    factor: float
    roll_offset_deg: float
    tilt_deg: float
    rms_mm: float
    points: int

    @property
    def ratio(self) -> float:
        """Fitted over planned factor."""
        return self.factor / self.planned_factor

    def to_json(self) -> dict[str, object]:
        """Return the fit as plain JSON data.

        Returns
        -------
        dict of str to object
            Its fields and ``ratio`` (deg, mm).
        """
        return {"source": self.source, "hole_id": self.hole_id, "design": self.design,
                "planned_factor": round(self.planned_factor, 5), "factor": round(self.factor, 5),
                "ratio": round(self.ratio, 5), "roll_offset_deg": round(self.roll_offset_deg, 3),
                "tilt_deg": round(self.tilt_deg, 4), "rms_mm": round(self.rms_mm, 4), "points": self.points}


def _lateral_at(path_mm: np.ndarray, z_mm: np.ndarray) -> np.ndarray:
    """Lateral (x, y) of a template-frame path at depths ``z_mm`` (mm), linear between its samples."""
    z = path_mm[:, 2]
    keep = np.r_[True, np.diff(z) > 1e-9]  # depth increases along a needle that does not turn back
    return np.column_stack([np.interp(z_mm, z[keep], path_mm[keep, i]) for i in (0, 1)])


def fit_needle(needle: FoundSteered) -> NeedleFit:
    """Fit the ratio, a roll offset and an entry tilt that make the planned path's departure the found one's.

    Parameters
    ----------
    needle : FoundSteered
        The needle as planned and found.

    Returns
    -------
    NeedleFit
        The fitted factor (the plan's times the ratio) and nuisances.

    Raises
    ------
    PlanInputError
        Too few found points along the planned depths, a planned path too straight to tell the curvature
        (:data:`MIN_DEFLECTION_MM`), or a found needle the fit cannot follow (:data:`MAX_FIT_RMS_MM`).
    """
    from scipy.optimize import least_squares

    found = np.asarray(needle.found_mm, dtype=float).reshape(-1, 3)
    planned = np.asarray(needle.planned_mm, dtype=float).reshape(-1, 3)
    z = found[:, 2]
    use = (z > 1.0) & (z <= planned[-1, 2])
    if int(use.sum()) < MIN_POINTS or len(planned) < 2:
        raise PlanInputError(f"needle {needle.hole_id} ({needle.source}): {int(use.sum())} found points along its "
                             f"planned depths; a fit needs at least {MIN_POINTS}")
    z, xy = z[use], found[use, :2]
    lateral = _lateral_at(planned, z)
    if float(np.max(np.linalg.norm(lateral, axis=1))) < MIN_DEFLECTION_MM:
        raise PlanInputError(f"needle {needle.hole_id} ({needle.source}): its planned path departs less than "
                             f"{MIN_DEFLECTION_MM:g} mm from its hole's axis; it tells nothing of the curvature")

    def residual(p: np.ndarray) -> np.ndarray:
        c, s = math.cos(math.radians(p[1])), math.sin(math.radians(p[1]))
        return (xy - p[0] * lateral @ np.array([[c, s], [-s, c]]) - np.outer(z, p[2:4])).ravel()

    fit = least_squares(residual, np.array([1.0, 0.0, 0.0, 0.0]), bounds=([RATIO_RANGE[0], -45.0, -0.1, -0.1],
                                                                          [RATIO_RANGE[1], 45.0, 0.1, 0.1]),
                        x_scale=np.array([0.1, 5.0, 0.01, 0.01]))
    r = fit.fun.reshape(-1, 2)
    rms = float(np.sqrt(np.mean((r**2).sum(axis=1))))
    if rms > MAX_FIT_RMS_MM:
        raise PlanInputError(f"needle {needle.hole_id} ({needle.source}): the fitted path follows the found one only "
                             f"within {rms:.1f} mm rms (more than {MAX_FIT_RMS_MM:g}): a track taken from another "
                             "needle, or a needle bent by what the model does not know; not used")
    return NeedleFit(needle.source, needle.hole_id, needle.design, needle.planned_factor,
                     needle.planned_factor * needle.plan_scale * float(fit.x[0]), float(fit.x[1]),
                     math.degrees(math.atan(float(np.hypot(*fit.x[2:4])))), rms, len(z))


@dataclass(frozen=True)
class FactorEstimate:
    """A site's curvature factor for one design, pooled over its needles.

    Parameters
    ----------
    design : str
        The stylet preset.
    planned_factor : float
        The plan's factor (the needles' mean, when their moduli differ).
    ratio : float
        Mean of the needles' fitted over planned factors.
    ci95 : tuple of float
        Student-t 95 % interval of the mean ratio over the needles; NaN with one needle.
    fits : tuple of NeedleFit
        The needles.
    """

    design: str
    planned_factor: float
    ratio: float
    ci95: tuple[float, float]
    fits: tuple[NeedleFit, ...]

    @property
    def factor(self) -> float:
        """The site's factor: the plan's times the pooled ratio."""
        return self.planned_factor * self.ratio

    def to_json(self) -> dict[str, object]:
        """Return the estimate as plain JSON data.

        Returns
        -------
        dict of str to object
            ``design``, ``planned_factor``, ``factor``, ``ratio``, ``ci95_ratio`` (null bounds with one needle),
            ``needles``, ``method`` and each needle's fit.
        """
        ci = [None if not np.isfinite(v) else round(v, 5) for v in self.ci95]
        return {"design": self.design, "planned_factor": round(self.planned_factor, 5),
                "factor": round(self.factor, 5), "ratio": round(self.ratio, 5), "ci95_ratio": ci,
                "needles": len(self.fits), "method": POOL_METHOD, "fits": [f.to_json() for f in self.fits]}


#: How :func:`pool` combines needles, in words (written with every estimate).
POOL_METHOD = ("per needle: least squares of the found centre line's departure from its hole's axis against the "
               "planned path's times a ratio (with a roll offset and an entry tilt); pooled: mean of the needles' "
               "ratios, Student-t 95 % interval over needles")


def pool(fits: Sequence[NeedleFit]) -> list[FactorEstimate]:
    """Pool needle fits per design (:data:`POOL_METHOD`).

    Parameters
    ----------
    fits : sequence of NeedleFit
        Needles of any designs.

    Returns
    -------
    list of FactorEstimate
        One per design, in name order.
    """
    from scipy import stats

    out = []
    for design in sorted({f.design for f in fits}):
        mine = tuple(f for f in fits if f.design == design)
        ratios = np.array([f.ratio for f in mine])
        mean = float(ratios.mean())
        if len(mine) > 1:
            half = float(stats.t.ppf(0.975, len(mine) - 1) * ratios.std(ddof=1) / math.sqrt(len(mine)))
            ci = (mean - half, mean + half)
        else:
            ci = (float("nan"), float("nan"))
        out.append(FactorEstimate(design, float(np.mean([f.planned_factor for f in mine])), mean, ci, mine))
    return out


#: The ``format`` of a site calibration file (``reachplan calibrate``; ``plan --calibration``).
SITE_FORMAT = "reachplan-site-calibration/1"


def site_document(fits: Sequence[NeedleFit], previous: dict[str, object] | None = None) -> dict[str, object]:
    """Return a site calibration file's content: ``fits`` pooled with those ``previous`` holds, per design.

    A needle fitted again (same ``source`` and ``hole_id``) replaces its earlier fit.

    Parameters
    ----------
    fits : sequence of NeedleFit
        New needle fits.
    previous : dict or None
        An earlier file's content (:func:`site_fits` reads its fits).

    Returns
    -------
    dict of str to object
        ``format`` (:data:`SITE_FORMAT`), ``method``, ``designs`` (each :meth:`FactorEstimate.to_json`).
    """
    kept = {(f.source, f.hole_id): f for f in (site_fits(previous) if previous else [])}
    kept.update({(f.source, f.hole_id): f for f in fits})
    return {"format": SITE_FORMAT, "method": POOL_METHOD,
            "designs": [e.to_json() for e in pool(list(kept.values()))]}


def _number(value: object, what: str) -> float:
    """``value`` as a finite float, or the typed error naming ``what``."""
    try:
        x = float(value)  # type: ignore[arg-type]
    except (TypeError, ValueError):
        x = float("nan")
    if not math.isfinite(x):
        raise PlanInputError(f"site calibration: {what} must be a finite number, got {value!r}")
    return x


def site_fits(doc: dict[str, object]) -> list[NeedleFit]:
    """Return the needle fits a site calibration file holds.

    Parameters
    ----------
    doc : dict
        The file's content.

    Returns
    -------
    list of NeedleFit
        Every design's needles.

    Raises
    ------
    PlanInputError
        Not a site calibration file (its ``format``), or a design or needle without its numbers.
    """
    if not isinstance(doc, dict) or doc.get("format") != SITE_FORMAT:
        raise PlanInputError(f"not a site calibration file: its 'format' must be {SITE_FORMAT!r} (written by "
                             "'reachplan calibrate')")
    designs = doc.get("designs")
    if not isinstance(designs, list):
        raise PlanInputError("site calibration: 'designs' must be a list")
    out = []
    for d in designs:
        for f in (d.get("fits") if isinstance(d, dict) else None) or []:
            if not isinstance(f, dict):
                raise PlanInputError("site calibration: each fit must be an object")
            out.append(NeedleFit(str(f.get("source", "")), str(f.get("hole_id", "")), str(d.get("design", "")),
                                 _number(f.get("planned_factor"), "planned_factor"),
                                 _number(f.get("factor"), "factor"), _number(f.get("roll_offset_deg", 0.0), "roll"),
                                 _number(f.get("tilt_deg", 0.0), "tilt"), _number(f.get("rms_mm", 0.0), "rms_mm"),
                                 int(_number(f.get("points", 0), "points"))))
    return out


def site_scales(doc: dict[str, object]) -> tuple[tuple[str, float], ...]:
    """Return each design's calibration ratio from a site calibration file (``PlanConfig.curvature_scale``).

    Parameters
    ----------
    doc : dict
        The file's content.

    Returns
    -------
    tuple of (str, float)
        Design name and its pooled ratio (:func:`pool` of the file's fits), in name order.

    Raises
    ------
    PlanInputError
        As :func:`site_fits`; or a file with no fitted needle.
    """
    estimates = pool(site_fits(doc))
    if not estimates:
        raise PlanInputError("site calibration: the file holds no fitted needle")
    return tuple((e.design, round(e.ratio, 5)) for e in estimates)
