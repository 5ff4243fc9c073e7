"""The chain that ``plan`` and ``demo`` share: structures -> scene -> ranked needles -> delivered plan.

:func:`run_case` computes; :func:`reachplan.planner.run.outputs.write_outputs` writes what it computed. The
command line reads the inputs, calls both and prints.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

from reachplan.imaging.types import StructureSet, Volume
from reachplan.planner.case.config import PlanConfig
from reachplan.planner.case.result import PlanResult
from reachplan.planner.case.scene import Scene, build_scene
from reachplan.planner.case.search import plan
from reachplan.planner.delivery import Delivery, plan_delivery
from reachplan.planner.dose.aims import Aims
from reachplan.planner.dose.evaluation import protocol_json
from reachplan.planner.errors import PlanInputError
from reachplan.planner.geometry.organs import check_unique, has_closed
from reachplan.planner.geometry.template import TemplatePose
from reachplan.planner.handoff import obstacles_line, with_handoff
from reachplan.planner.implant.settings import ImplantSettings
from reachplan.planner.report.comparison import straight_vs_steered
from reachplan.planner.report.progress import spinner
from reachplan.planner.steering.candidates import Target
from reachplan.rod_model.errors import RodModelError
from reachplan.rod_model.select import ErrorRow, error_table

if TYPE_CHECKING:
    from reachplan.planner.implant.compare import Comparison


@dataclass(frozen=True, eq=False)
class CaseInput:
    """What a case is planned on, as read from disk (or made) by the caller.

    Parameters
    ----------
    structures : StructureSet
        The ROIs (organs, targets, applicators), contours in mm, LPS.
    volume : Volume or None
        The CT/MR series (its grid rasterises the contours); None plans on the contours alone.
    paths : tuple of Path
        The files or folders the case was read from (the exports refuse to overwrite them).
    label : str
        The case's name in the report.
    builtin : bool
        A built-in case (``demo``): its analytic structures keep the implant's default dwell margin.
    """

    structures: StructureSet
    volume: Volume | None = None
    paths: tuple[Path, ...] = ()
    label: str = "case"
    builtin: bool = False


@dataclass(frozen=True)
class CaseConfig:
    """What to plan on a case, and how.

    :func:`run_case` takes it with the :class:`CaseInput`.

    Parameters
    ----------
    plan : PlanConfig
        The steering search's settings (template, organs at risk, stylet designs, ranking weights).
    target_names : tuple of str or None
        Target ROI names (their centroids, or their points); None: every ROI named ``Target*``.
    target_points : tuple of Target
        Further targets given as points (mm, LPS).
    pose : TemplatePose or None
        The template pose; None: fitted to the ``Obturator`` ROI.
    allow_no_oars : bool
        Plan even when no organ at risk is found.
    standard_names : tuple of str or None
        The synonym table's standard names (ROIs mapped to none are listed in the notes).
    export : bool
        Optimise the dwell times and assemble the delivered plan (False: rank only).
    implant : bool
        Plan the implant for the whole target volume, straight only and straight + steered.
    source : str
        The TG-43 data set of the dose.
    target_roi : str
        The ROI the dwell times are optimised on.
    named_points : tuple of (str, (float, float, float))
        Dose reference points (name, mm LPS) the delivered plan carries.
    aims : Aims
        The protocol's aims the dose is planned to and reported against (``--protocol``; default EMBRACE II).
    dwell_margin_mm : float or None, mm
        Dwells lie in the target grown by this; None: 0 on a real structure set (the target as drawn), the
        implant's default (:class:`~reachplan.planner.implant.settings.ImplantSettings`) on a built-in case.
    rtplan_style : str
        Layout of the exported RT Plan's prescription: ``"eclipse"`` or ``"vitesse"``
        (:class:`~reachplan.plugins.exporters.base.ExportOptions`).
    implant_settings : ImplantSettings
        The implant planning's settings (e.g. the applicator channels' source-tip offset).
    """

    plan: PlanConfig = field(default_factory=PlanConfig)
    target_names: tuple[str, ...] | None = None
    target_points: tuple[Target, ...] = ()
    pose: TemplatePose | None = None
    allow_no_oars: bool = False
    standard_names: tuple[str, ...] | None = None
    export: bool = True
    implant: bool = True
    source: str = "gammamed_plus_hdr"
    target_roi: str = "HR-CTV"
    named_points: tuple[tuple[str, tuple[float, float, float]], ...] = ()
    aims: Aims = field(default_factory=Aims)
    dwell_margin_mm: float | None = None
    rtplan_style: str = "eclipse"
    implant_settings: ImplantSettings = field(default_factory=ImplantSettings)


@dataclass(frozen=True, eq=False)
class CaseResult:
    """Everything :func:`run_case` computed, for the writers and the terminal.

    Parameters
    ----------
    inputs : CaseInput
        What was planned: structures, volume and paths.
    config : CaseConfig
        How; its ``plan.oar_names`` are the organs at risk the scene found.
    scene : Scene
        Organs, targets, template and pose.
    result : PlanResult
        Every scored candidate and the ranking per target.
    delivery : Delivery or None
        The delivered plan (None: ranked only).
    comparison : Comparison or None
        The straight-versus-steered dose comparison of per-target needles, when it was run.
    comparison_note : str
        What the report says instead of (or about) the comparison.
    timings : dict of str to float
        Wall time of each stage, s (``scene_s``, ``plan_s``, ``delivery_s``, ``handoff_s``).
    """

    inputs: CaseInput
    config: CaseConfig
    scene: Scene
    result: PlanResult
    delivery: Delivery | None
    comparison: Comparison | None
    comparison_note: str
    timings: dict[str, float]

    def to_json(self) -> dict[str, object]:
        """Return plan.json's computed part: the ranking, the template pose, warnings, delivery and implant.

        Returns
        -------
        dict
            JSON-ready values (mm, N, LPS, Gy); the writer adds the files and the report's place. ``applicators``: which
            ROIs were taken as applicators (obstacles or not); with a delivery, ``insert_list`` (the hand-off,
            :class:`~reachplan.plugins.exporters.handoff.InsertList`). With dose:
            ``protocol`` (which aims were used, :func:`~reachplan.planner.dose.evaluation.protocol_json`), the
            protocol's warnings added to ``warnings``, ``delivery.aims`` and ``implant.<arm>.aims``.
        """
        doc: dict[str, object] = self.result.to_json()
        doc["applicators"] = obstacles_line(self.scene)
        if self.delivery is not None and self.delivery.export.handoff is not None:
            doc["insert_list"] = self.delivery.export.handoff.to_json()
        if self.scene.pose is not None:
            doc["template_pose"] = self.scene.pose.to_json()
        warnings = list(self.scene.notes)
        doc["warnings"] = warnings
        doc["blocked_straight"] = [b.to_json() for b in self.result.blocked_straight()]
        if self.delivery is not None:
            doc["protocol"] = protocol_json(self.delivery.aims)
            warnings += self.delivery.warnings
            doc["delivery"] = self.delivery.to_json()
            if self.delivery.implant is not None:
                doc["implant"] = self.delivery.implant_json()
        return doc


def check_case(inputs: CaseInput, config: CaseConfig) -> None:
    """Check what can be checked before any work: the dose target has closed contours.

    Parameters
    ----------
    inputs : CaseInput
        The structures whose dose target is checked.
    config : CaseConfig
        Says whether dose is planned (``export``) and on which ROI (``target_roi``).

    Raises
    ------
    PlanInputError
        The dose target ROI is missing or has no closed contours.
    """
    if config.export:
        check_unique(inputs.structures, [config.target_roi])
        roi = inputs.structures.get(config.target_roi)
        if not has_closed(roi):
            raise PlanInputError(f"the dose target ROI {roi.name!r} has no closed contours; name another with "
                                 "--target-roi or plan with --no-export")


def run_case(inputs: CaseInput, config: CaseConfig, *, quiet: bool = True,
             on_scene: Callable[[Scene], None] | None = None) -> CaseResult:
    """Plan a case: scene, steering search and ranking, then (``config.export``) the delivered plan.

    Parameters
    ----------
    inputs : CaseInput
        The structures (and image) to plan on.
    config : CaseConfig
        What to plan, and how.
    quiet : bool
        No progress bars.
    on_scene : callable or None
        Called with the scene as soon as it is built (the command line prints its notes and pose then).

    Returns
    -------
    CaseResult
        The scene, the ranked candidates, the delivery and the comparison, with the stages' wall times.

    Raises
    ------
    PlanInputError
        Bad input (no target, no organ at risk, a dose target without closed contours, ...).
    """
    check_case(inputs, config)
    timings: dict[str, float] = {}
    t = time.perf_counter()
    grid = inputs.volume.grid if inputs.volume is not None else None
    scene = build_scene(inputs.structures, config.target_names, config.target_points, grid=grid,
                        patient_from_template=config.pose, config=config.plan, quiet=quiet,
                        allow_no_oars=config.allow_no_oars, standard_names=config.standard_names)
    timings["scene_s"] = time.perf_counter() - t
    if on_scene is not None:
        on_scene(scene)
    # the organs given a modulus by the names the scene meshed them under (--organ-modulus may differ in case)
    moduli = tuple((inputs.structures.get(n).normalized_name, e) for n, e in config.plan.tissue_moduli_pa)
    config = dataclasses.replace(config, plan=dataclasses.replace(config.plan, tissue_moduli_pa=moduli,
                                                                  oar_names=tuple(o.name for o in scene.organs)))
    t, cpu = time.perf_counter(), time.process_time()
    result = plan(scene, config.plan, quiet=quiet)
    timings["plan_s"] = time.perf_counter() - t
    timings["plan_cpu_s"] = time.process_time() - cpu  # this process's CPU: a loaded machine's wall time is noise
    if not config.export:
        comparison, note = straight_vs_steered(result, inputs.structures, None)  # no dose: the note says so
        return CaseResult(inputs, config, scene, result, None, comparison, note, timings)
    t = time.perf_counter()
    with spinner("delivery: implant arms, dwell times, dose", quiet):  # ~20 s with no other bar: it must move
        delivery = plan_delivery(result, inputs.structures, grid, source_name=config.source,
                                 target_roi=config.target_roi, volume=inputs.volume, input_paths=inputs.paths,
                                 named_points=config.named_points, scene=scene if config.implant else None,
                                 aims=config.aims, implant_settings=implant_settings(inputs, config))
    comparison, note = straight_vs_steered(result, inputs.structures, delivery, grid, config.target_roi, quiet=quiet)
    timings["delivery_s"] = time.perf_counter() - t
    t = time.perf_counter()
    delivery = with_handoff(delivery, scene, result, config.implant_settings.clearance_margin_mm)
    timings["handoff_s"] = time.perf_counter() - t
    return CaseResult(inputs, config, scene, result, delivery, comparison, note, timings)


def implant_settings(inputs: CaseInput, config: CaseConfig) -> ImplantSettings:
    """Return the implant settings of a case: dwells in the target as drawn on a real structure set.

    Parameters
    ----------
    inputs : CaseInput
        Whether the case is built in (its analytic structures keep the default dwell margin).
    config : CaseConfig
        ``dwell_margin_mm`` when given.

    Returns
    -------
    ImplantSettings
        ``config.implant_settings`` with ``dwell_margin_mm`` = the one given, else 0 on a real structure set, else
        the settings' own.
    """
    margin = config.dwell_margin_mm
    if margin is None:
        margin = config.implant_settings.dwell_margin_mm if inputs.builtin else 0.0
    return dataclasses.replace(config.implant_settings, dwell_margin_mm=margin)


def rod_model_errors() -> tuple[ErrorRow, ...]:
    """Return the measured rod-model error table (the rod-model benchmark's, packaged); () when not available.

    Returns
    -------
    tuple of ErrorRow
        For the report's speed-versus-accuracy section.
    """
    try:
        return error_table()
    except RodModelError:
        return ()

