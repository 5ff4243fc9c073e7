"""The straight-versus-steered dose comparison the report shows.

Each arm's per-target best needles, optimised the same way: a dose computation, run with the delivery (the report
only draws it).
"""

from __future__ import annotations

from reachplan.imaging.types import Grid, StructureSet
from reachplan.planner.case.config import DEFAULT_AIR_KERMA_U
from reachplan.planner.case.result import PlanResult, choose_needles
from reachplan.planner.delivery import Delivery, planning_structures
from reachplan.planner.dose.aims import Aims
from reachplan.planner.dose.structures import PlanningStructures
from reachplan.planner.implant.compare import Comparison, compare_arms
from reachplan.planner.implant.dwells import OptimizerSettings
from reachplan.planner.report.options import COMPARISON_SETTINGS, ReportOptions
from reachplan.planner.report.progress import MovingBar
from reachplan.plugins.sources import SourceData


def compare_chosen(result: PlanResult, structures: StructureSet, grid: Grid | None,
                   source: SourceData, target_roi: str = "HR-CTV",
                   air_kerma_u: float = DEFAULT_AIR_KERMA_U,
                   settings: OptimizerSettings = COMPARISON_SETTINGS,
                   planning: PlanningStructures | None = None, aims: Aims | None = None) -> Comparison | None:
    """Compare straight and steered dose with the per-target best needle of each kind.

    Each arm gets the per-target best needle of its kind (:func:`~reachplan.planner.case.result.choose_needles`),
    optimised the same way (:func:`~reachplan.planner.implant.compare.compare_arms`). An arm with no feasible needle
    is left out.

    Parameters
    ----------
    result : PlanResult
        The ranked plan.
    structures : StructureSet
        The case's structures.
    grid : Grid or None
        Planning grid; None: the structures' own (see :func:`reachplan.planner.delivery.planning_structures`).
    source : SourceData
        The TG-43 data set (the delivery's, :attr:`~reachplan.planner.delivery.Delivery.source`).
    target_roi : str
        The target volume's ROI name.
    air_kerma_u : float, U
        Source strength (cGy cm² h⁻¹).
    settings : OptimizerSettings
        LP settings of both arms.
    planning : PlanningStructures or None
        The delivery's structures, when already built (else
        :func:`reachplan.planner.delivery.planning_structures` builds them).
    aims : Aims or None
        The protocol's aims (the delivery's); None: EMBRACE II.

    Returns
    -------
    Comparison or None
        Both arms' coverage; None when both are empty.
    """
    from reachplan.planner.dose.tg43 import Tg43Kernel

    arms = [(name, [c.path_mm for c in choose_needles(result, steered=steered)])
            for name, steered in (("straight", False), ("steered", True))]
    arms = [a for a in arms if a[1]]
    if not arms:
        return None
    if planning is None:
        planning = planning_structures(structures, grid, target_roi, result.config.oar_names)
    kernel = Tg43Kernel(source)
    return compare_arms(arms, planning, kernel, air_kerma_u, aims=aims, settings=settings)


def straight_vs_steered(result: PlanResult, structures: StructureSet, delivery: Delivery | None,
                        grid: Grid | None = None, target_roi: str = "HR-CTV", options: ReportOptions | None = None,
                        quiet: bool = True) -> tuple[Comparison | None, str]:
    """Run the straight-versus-steered dose comparison the report shows (:func:`compare_chosen`).

    A dose computation, run with the delivery (the report only draws).

    Parameters
    ----------
    result : PlanResult
        The ranked plan whose chosen needles are compared.
    structures : StructureSet
        The case's structures (HR-CTV and organs at risk).
    delivery : Delivery or None
        The delivered plan; None: ranked only.
    grid : Grid or None
        Planning grid (None: the structures').
    target_roi : str
        The target volume's ROI name.
    options : ReportOptions or None
        Whether and how to compare (None: the defaults).
    quiet : bool
        No progress bar.

    Returns
    -------
    comparison : Comparison or None
        The comparison, or None.
    note : str
        The sentence the report prints instead: no delivery (ranked only), comparison turned off, implant arms
        compared instead, or no feasible needle; "" with a comparison.
    """
    options = options or ReportOptions()
    if delivery is None:
        return None, "No dose: the plan was ranked only (--no-export)."
    if not options.comparison:
        return None, ""
    if delivery.implant is not None:  # the implant arms are the comparison (whole target volume, chosen sets)
        return None, ("Straight versus steered is compared as whole implants, each arm's needle set and dwell "
                      "times chosen together: see the section 'Implant'.")
    bar = MovingBar(total=1, desc="straight vs steered dose", disable=quiet, leave=False)  # one step of seconds
    comparison = compare_chosen(result, structures, grid, delivery.source, target_roi,
                                delivery.export.source.air_kerma_rate_u, options.comparison_settings,
                                planning=delivery.planning, aims=delivery.aims)
    bar.update()
    bar.close()
    return comparison, "" if comparison is not None else "No feasible needle of either kind: nothing to compare."
