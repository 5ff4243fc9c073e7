"""Whether a brachy RT Plan can be used: the one check ``dose``, ``plan --rtplan`` and ``inspect`` share.

The plan's own problems (:func:`reachplan.imaging.brachy_plan.plan_problems`: no channels, a channel whose dwells
are unknown, no source, no strength) and, for the source, whether registered TG-43 data fit it
(:func:`reachplan.plugins.sources.identify.identify_source`, as ``dose`` chooses its data). ``dose`` and
``plan --rtplan`` stop with a :class:`~reachplan.planner.errors.PlanInputError`; ``inspect`` lists each problem as
an :class:`~reachplan.imaging.errors.UnusablePlanWarning`.
"""

from __future__ import annotations

from collections.abc import Collection

from reachplan.imaging.brachy_plan import BrachySource, PlanProblem, RtPlan, plan_problems
from reachplan.planner.errors import PlanInputError
from reachplan.planner.lookup import all_sources
from reachplan.plugins.errors import SourceMatchError
from reachplan.plugins.sources.identify import PlanSource, identify_source


def plan_source(plan: RtPlan, src: BrachySource) -> PlanSource:
    """Return what the plan says of its source, for :func:`~reachplan.plugins.sources.identify.identify_source`.

    Parameters
    ----------
    plan : RtPlan
        The brachy plan: its treatment type and treatment machine are read.
    src : BrachySource
        The source its channels refer to.

    Returns
    -------
    PlanSource
        Isotope, half-life, model, manufacturer, active length, treatment type and machine.
    """
    return PlanSource(isotope_name=src.isotope_name, half_life_days=src.half_life_days, model_id=src.model_id,
                      manufacturer=src.manufacturer, active_length_mm=src.active_length_mm,
                      treatment_type=plan.treatment_type, machine_name=plan.machine_name)


def usable_problems(plan: RtPlan, source: str | None = None) -> tuple[PlanProblem, ...]:
    """List what makes a brachy plan unusable for ``plan`` and ``dose``.

    Parameters
    ----------
    plan : RtPlan
        The plan as read.
    source : str or None
        The TG-43 data set the user named (``--source``); None: one must be identified from the plan, and a
        source no registered data set fits (an isotope without data, e.g. Cs-137) is a problem.

    Returns
    -------
    tuple of PlanProblem
        The plan's own problems, then the source's; empty for a usable plan.
    """
    found = list(plan_problems(plan))
    if source is None and plan.sources and not any(p.kind == "source" for p in found):
        numbers = [c.source_number for c in plan.channels if c.source_number is not None]
        src = next((s for s in plan.sources if s.number in numbers), plan.sources[0])
        try:
            identify_source(all_sources(), plan_source(plan, src))
        except SourceMatchError as exc:
            found.append(PlanProblem("source", str(exc)))
    return tuple(found)


def require_usable(plan: RtPlan, label: str, *, source: str | None = None,
                   kinds: Collection[str] = ("geometry", "source")) -> None:
    """Stop with a typed error when the plan has a problem of one of ``kinds`` (:func:`usable_problems`).

    Parameters
    ----------
    plan : RtPlan
        The plan as read.
    label : str
        How the command names the plan (its option and file).
    source : str or None
        The TG-43 data set named with ``--source``, if any.
    kinds : collection of str
        The kinds of problem that matter to the caller: ``plan --rtplan`` places the template on the channels
        (``"geometry"``), ``dose`` needs the source too.

    Raises
    ------
    PlanInputError
        Every problem found, on one line.
    """
    problems = [p for p in usable_problems(plan, source) if p.kind in kinds]
    if problems:
        raise PlanInputError(f"{label}: " + "; ".join(p.message for p in problems))
