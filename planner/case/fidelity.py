"""Per-candidate model fidelity: each steered candidate gets the cheapest insertion model its margins allow.

"Model no more than a scene needs". A steered candidate's numbers (reach error, clearance) come from the insertion
model that solved it; the model's error *in tissue* (its tip against the planner's reference rod, measured per
stylet design, tissue modulus and depth by ``reachplan bench fidelity``, package data
:data:`ERROR_TABLE`) must stay inside what the candidate's margins allow:

tolerance
    ``min(clearance_mm - safety_margin_mm, reach_tolerance_mm)``. The path of a model with tip error ``e`` lies
    within about ``e`` of the reference's everywhere (in tissue the needle follows the track its tip cut, so the
    path at arc length ``s`` departs from the reference's by the tip's departure when the tip was at ``s``, which
    grows with depth: the tip error at the candidate's depth bounds it), so a model within the clearance less the
    safety margin cannot turn a clear needle into one that touches; and a model whose error exceeds the reach
    tolerance cannot tell whether the needle reaches its target at all.
rungs (:data:`RUNGS`, cheapest first)
    ``kinematic`` (the screening model: its numbers are kept, no solve), the in-tissue rod at 4 mm insertion
    steps, the same at 4 mm extrapolated with 8 mm ones, at 2 mm steps, and the reference (2 mm extrapolated with
    4 mm, :data:`~reachplan.planner.steering.tissue_rod.PLANNER_REFERENCE`). The cheapest rung whose measured
    largest tip error (at the candidate's design, the modulus of the tissue holding its target, interpolated in
    its depth) is within the tolerance is chosen.
the decision boundary
    A candidate whose score could, within its model's error, beat the best candidate solved exactly (a straight
    needle, or one re-solved with the reference) is re-solved with the reference: that keeps the top-ranked
    candidate per target the one the reference policy would rank first.

``--models reference`` re-solves every feasible steered candidate with the reference model instead.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, replace
from functools import cache
from importlib import resources

import numpy as np

from reachplan.planner.steering.factors import design_key
from reachplan.planner.steering.tissue_rod import PLANNER_REFERENCE, TissueRodInsertion
from reachplan.rod_model.design import RodDesign

#: Package data written by ``reachplan bench fidelity --install``: each rung's measured in-tissue tip error.
ERROR_TABLE = "model_errors_tissue.json"
#: The model-choice policies of ``--models``.
POLICIES: tuple[str, ...] = ("scene", "reference")


@dataclass(frozen=True)
class Rung:
    """One insertion model of the fidelity ladder.

    Parameters
    ----------
    name : str
        Its name in the error table and in ``model_reason`` (``kinematic``, ``tissue_rod@4mm``, ...).
    words : str
        The model in words.
    step_mm : float or None, mm
        Insertion step of the in-tissue rod that re-solves a candidate at this rung; None for the screening model
        (its numbers are kept, no re-solve).
    richardson : bool
        The rod's path is extrapolated with one at twice the step.
    """

    name: str
    words: str
    step_mm: float | None = None
    richardson: bool = False

    def model(self, reference: TissueRodInsertion = PLANNER_REFERENCE) -> TissueRodInsertion | None:
        """Return the in-tissue rod of this rung: ``reference`` at this rung's steps; None for the screening model.

        The reference rung is ``reference`` itself.

        Parameters
        ----------
        reference : TissueRodInsertion
            The plan's reference model (its rod, tissue and slip settings are kept).

        Returns
        -------
        TissueRodInsertion or None
            The model that re-solves a candidate at this rung.
        """
        if self.step_mm is None:
            return None
        if self.name == "reference" or (self.step_mm == reference.step_mm and self.richardson == reference.richardson):
            return reference  # the plan's reference, whatever its settings
        return replace(reference, step_mm=self.step_mm, richardson=self.richardson)


#: The ladder, cheapest first: the screening model's numbers cost nothing, and an in-tissue rod insertion costs about
#: its number of steps (4 mm, 4 + 8 mm, 2 mm, 2 + 4 mm: 1 : 1.4 : 1.9 : 2.9 measured for 15ga-30j-tip in the gel,
#: ``reachplan bench fidelity``, ``ms_per_insertion`` in the table); the last is the planner's reference
#: (:data:`~reachplan.planner.steering.tissue_rod.PLANNER_REFERENCE`: 2 mm steps extrapolated with 4 mm ones).
RUNGS: tuple[Rung, ...] = (
    Rung("kinematic", "the screening model (tip following at the design's curvature factor)"),
    Rung("tissue_rod@4mm", "the in-tissue rod at 4 mm insertion steps", 4.0),
    Rung("tissue_rod@4+8mm", "the in-tissue rod at 4 mm steps extrapolated with 8 mm ones", 4.0, True),
    Rung("tissue_rod@2mm", "the in-tissue rod at 2 mm insertion steps", 2.0),
    Rung("reference", "the reference: the in-tissue rod at 2 mm steps extrapolated with 4 mm ones",
         PLANNER_REFERENCE.step_mm, PLANNER_REFERENCE.richardson),
)
RUNG_BY_NAME: dict[str, Rung] = {r.name: r for r in RUNGS}
REFERENCE_RUNG = RUNG_BY_NAME["reference"]
#: ASSUMED safety margin, mm: the clearance a candidate keeps beyond its model's error (the needle's own radius is
#: already in the clearance). One millimetre, about the planning CT's slice-to-slice contour uncertainty.
SAFETY_MARGIN_MM = 1.0


@dataclass(frozen=True)
class ErrorRow:
    """One rung's measured in-tissue tip error for one design and modulus (a row of :data:`ERROR_TABLE`).

    Parameters
    ----------
    design : str
        The design's preset name when measured.
    key : str
        :func:`~reachplan.planner.steering.factors.design_key` of the design.
    modulus_pa : float, Pa
        Tissue Young's modulus.
    rung : str
        :attr:`Rung.name`.
    depths_mm : tuple of float, mm
        Insertion depths the tips were compared at, increasing.
    max_mm : tuple of float, mm
        Largest tip distance from the reference over the schedules, at each depth (inf where an insertion failed).
    rms_mm : tuple of float, mm
        Root mean square of the same.
    ms_per_insertion : float, ms
        Median CPU time of one insertion to the deepest depth (the first rows measured: wall time); the screening
        model's per path.
    """

    design: str
    key: str
    modulus_pa: float
    rung: str
    depths_mm: tuple[float, ...]
    max_mm: tuple[float, ...]
    rms_mm: tuple[float, ...]
    ms_per_insertion: float

    def error_at(self, depth_mm: float) -> float:
        """Return the largest tip error (mm) at ``depth_mm``: linear in depth between rows, extrapolated beyond.

        Parameters
        ----------
        depth_mm : float, mm
            The candidate's insertion depth.

        Returns
        -------
        float, mm
            The interpolated largest error (inf at and beyond a depth where an insertion failed).
        """
        d = np.asarray(self.depths_mm, dtype=float)
        e = np.asarray(self.max_mm, dtype=float)
        bad = np.flatnonzero(~np.isfinite(e))
        if len(bad):  # an insertion failed there: trusted only short of the row before it
            if bad[0] == 0 or depth_mm > d[bad[0] - 1]:
                return float("inf")
            d, e = d[: bad[0]], e[: bad[0]]
        if depth_mm <= d[-1] or len(d) < 2:
            return float(np.interp(depth_mm, d, e))
        slope = max(0.0, (e[-1] - e[-2]) / (d[-1] - d[-2]))
        return float(e[-1] + slope * (depth_mm - d[-1]))

    def to_json(self) -> dict[str, object]:
        """Return the row as plain JSON data.

        Returns
        -------
        dict of str to object
            Its fields (mm, Pa, ms).
        """
        return {"design": self.design, "key": self.key, "modulus_pa": self.modulus_pa, "rung": self.rung,
                "depths_mm": list(self.depths_mm), "max_mm": list(self.max_mm), "rms_mm": list(self.rms_mm),
                "ms_per_insertion": self.ms_per_insertion}


@cache
def error_table() -> tuple[ErrorRow, ...]:
    """Read the packaged in-tissue error table (empty when the package has none).

    Returns
    -------
    tuple of ErrorRow
        Every measured row.
    """
    try:
        text = resources.files("reachplan.planner.case").joinpath(ERROR_TABLE).read_text(encoding="utf-8")
    except FileNotFoundError:
        return ()
    return tuple(ErrorRow(str(r["design"]), str(r["key"]), float(r["modulus_pa"]), str(r["rung"]),
                          tuple(map(float, r["depths_mm"])), tuple(float(x) for x in r["max_mm"]),
                          tuple(float(x) for x in r["rms_mm"]), float(r["ms_per_insertion"]))
                 for r in json.loads(text)["rows"])


def rung_error_mm(rung: str, design: RodDesign, modulus_pa: float, depth_mm: float,
                  rows: tuple[ErrorRow, ...] | None = None) -> tuple[float, float]:
    """Return the measured largest in-tissue tip error of ``rung`` (mm) and its time per insertion (ms).

    For a design, tissue modulus and depth. Between tabulated moduli the larger of the two neighbours' errors
    (conservative) and times; outside them the nearest. The reference's own error is 0 by definition.

    Parameters
    ----------
    rung : str
        :attr:`Rung.name`.
    design : RodDesign
        The stylet (found in the table by :func:`design_key`).
    modulus_pa : float, Pa
        The tissue's Young's modulus at the target.
    depth_mm : float, mm
        The candidate's insertion depth.
    rows : tuple of ErrorRow or None
        The table; None: :func:`error_table`.

    Returns
    -------
    error_mm : float, mm
        The error; inf when the table holds no row for this design and rung (the rung cannot be trusted), 0 for
        the reference.
    ms : float, ms
        Its measured time per insertion (inf when not tabulated).
    """
    rows = error_table() if rows is None else rows
    key = design_key(design)
    mine = sorted((r for r in rows if r.key == key and r.rung == rung), key=lambda r: r.modulus_pa)
    if not mine:
        return (0.0 if rung == REFERENCE_RUNG.name else float("inf")), float("inf")
    moduli = np.array([r.modulus_pa for r in mine])
    hi = int(np.searchsorted(moduli, modulus_pa * (1 - 1e-9)))
    near = [mine[min(hi, len(mine) - 1)]]
    if 0 < hi < len(mine) and not np.isclose(moduli[hi], modulus_pa, rtol=1e-6):
        near.append(mine[hi - 1])
    return max(r.error_at(depth_mm) for r in near), max(r.ms_per_insertion for r in near)


@dataclass(frozen=True)
class ModelChoice:
    """The model a candidate's numbers come from, and why.

    Parameters
    ----------
    rung : Rung
        The chosen rung.
    tolerance_mm : float, mm
        The tip error the candidate's margins allow (may be negative: no model is accurate enough, reference).
    reason : str
        In words: the tolerance, what set it, the rung's measured error.
    """

    rung: Rung
    tolerance_mm: float
    reason: str


def candidate_tolerance_mm(clearance_mm: float, reach_tolerance_mm: float,
                           safety_margin_mm: float = SAFETY_MARGIN_MM) -> tuple[float, str]:
    """Return the tip error a candidate's margins allow, and what set it.

    Parameters
    ----------
    clearance_mm : float, mm
        The candidate's clearance to the nearest organ (from the screening model); inf with no organ at all, NaN
        when it was not checked (nothing is accurate enough then).
    reach_tolerance_mm : float, mm
        The plan's reach tolerance.
    safety_margin_mm : float, mm
        Clearance kept beyond the model's error.

    Returns
    -------
    tolerance_mm : float, mm
        ``min(clearance_mm - safety_margin_mm, reach_tolerance_mm)``.
    why : str
        ``"clearance"`` or ``"reach tolerance"``.
    """
    by_clear = -safety_margin_mm if np.isnan(clearance_mm) else clearance_mm - safety_margin_mm  # inf: no organ
    if by_clear < reach_tolerance_mm:
        return float(by_clear), "clearance"
    return float(reach_tolerance_mm), "reach tolerance"


def choose_rung(clearance_mm: float, design: RodDesign, modulus_pa: float, depth_mm: float,
                reach_tolerance_mm: float, safety_margin_mm: float = SAFETY_MARGIN_MM,
                rows: tuple[ErrorRow, ...] | None = None) -> ModelChoice:
    """Return the cheapest rung (the first of :data:`RUNGS`) whose measured in-tissue error is within the tolerance.

    Parameters
    ----------
    clearance_mm : float, mm
        The candidate's clearance (screening model).
    design : RodDesign
        Its stylet.
    modulus_pa : float, Pa
        The tissue's modulus at its target.
    depth_mm : float, mm
        Its insertion depth.
    reach_tolerance_mm : float, mm
        The plan's reach tolerance.
    safety_margin_mm : float, mm
        Clearance kept beyond the model's error.
    rows : tuple of ErrorRow or None
        The error table; None: the packaged one.

    Returns
    -------
    ModelChoice
        The rung (the reference when none qualifies), the tolerance and the reason.
    """
    tol, why = candidate_tolerance_mm(clearance_mm, reach_tolerance_mm, safety_margin_mm)
    at = f"{design.name} at {modulus_pa / 1e6:.3g} MPa, {depth_mm:.0f} mm deep"
    source = (f"clearance {clearance_mm:.2f} mm less the {safety_margin_mm:g} mm margin" if why == "clearance"
              else f"the {reach_tolerance_mm:g} mm reach tolerance")
    measured = {r.name: rung_error_mm(r.name, design, modulus_pa, depth_mm, rows) for r in RUNGS[:-1]}
    fits = [r for r in RUNGS[:-1] if measured[r.name][0] <= tol]
    if fits:  # the ladder is in cost order
        rung = fits[0]
        return ModelChoice(rung, tol, f"{rung.name}: {source} allows {tol:.2f} mm; {rung.words} is within "
                                      f"{measured[rung.name][0]:.2f} mm in tissue ({at})")
    kin = measured[RUNGS[0].name][0]
    return ModelChoice(REFERENCE_RUNG, tol, f"reference: {source} allows {tol:.2f} mm; no cheaper model is within "
                                            f"it (kinematic {kin:.2f} mm in tissue, {at})")
