"""The plan a TPS is handed after insertion: the dwell times optimised again on the needles as found.

After insertion the treatment plan is made on the needles where they lie. The needles found in the post-insertion image
(:mod:`reachplan.planner.verify.find`) become channels whose dwells are the positions an afterloader reaches along each,
from its found tip (:func:`reachplan.planner.implant.candidates.placed_needle`); the loadable applicators of the
post-insertion structure set (a tandem) keep theirs. Which of them to load and their times are chosen exactly as the
planner chooses an implant among its candidates (:func:`reachplan.planner.implant.plan.plan_implant`: the fewest
channels that meet the protocol's aims with the headroom and keep the hard limits with any one needle displaced; a
needle in the patient that the plan does not need is left empty, as it would be in the TPS), on the organs as contoured
on the post-insertion image, and the result is exported as any plan is (:class:`reachplan.planner.delivery.Exporting`):
RT Plan, RT Structure Set with the channels, RT Dose.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from datetime import datetime
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from reachplan.imaging.types import StructureSet, Volume
from reachplan.planner.dose.aims import Aims
from reachplan.planner.errors import PlanInputError

if TYPE_CHECKING:
    from reachplan.planner.dose.structures import PlanningStructures
    from reachplan.planner.implant.arms import ImplantPlan
    from reachplan.planner.implant.candidates import Channel
    from reachplan.planner.implant.settings import ImplantSettings
    from reachplan.plugins.exporters import ExportPlan

#: The re-optimised plan's RT Plan Label.
REPLAN_LABEL = "as_inserted"


@dataclass(frozen=True, eq=False)
class Replan:
    """The dwell times optimised on the needles found.

    Parameters
    ----------
    implant : ImplantPlan or None
        The chosen loading (the channels loaded, their dwells); None when there is none (``reason`` says why).
    channels : tuple of str
        The channels offered to the optimiser: the found needles with dwells in the target, then the applicators'.
    without_dwells : tuple of str
        Found needles with fewer than the minimum dwells in the target region (left out).
    export : ExportPlan or None
        The re-optimised plan as the exporters write it; None without ``implant``.
    reason : str
        Why there is no plan ("" when there is).
    """

    implant: ImplantPlan | None
    channels: tuple[str, ...]
    without_dwells: tuple[str, ...]
    export: ExportPlan | None
    reason: str = ""


def found_channels(found: Mapping[str, np.ndarray], designs: Mapping[str, str], planning: PlanningStructures,
                   settings: ImplantSettings) -> tuple[list[Channel], list[str]]:
    """Return the found needles as channels, and the holes of those with too few dwells in the target region.

    Parameters
    ----------
    found : mapping of str to (m, 3) float, mm, LPS
        Hole id to found centre line, template plane to tip.
    designs : mapping of str to str
        Hole id to its planned stylet preset (a hole not named, or "": a straight needle).
    planning : PlanningStructures
        The target whose grown region holds the dwells.
    settings : ImplantSettings
        Dwell step, margin, tip offset, minimum dwells.

    Returns
    -------
    channels : list of Channel
        One per found needle with dwells, in ``found``'s order.
    without : list of str
        The holes left out.
    """
    from reachplan.planner.implant.candidates import placed_needle

    channels, without = [], []
    for hole, path in found.items():
        design = designs.get(hole, "")
        c = placed_needle(hole, "steered" if design else "straight", path, planning, settings, design=design)
        if c is None:
            without.append(hole)
        else:
            channels.append(c)
    return channels, without


def replan(found: Mapping[str, np.ndarray], designs: Mapping[str, str], structures: StructureSet,
           volume: Volume | None, aims: Aims, source_name: str, air_kerma_u: float, settings: ImplantSettings, *,
           target_roi: str = "HR-CTV", oar_names: Sequence[str] = (), setup_type: str = "SYED_NEBLETT",
           input_paths: Sequence[Path] = (), now: datetime | None = None) -> Replan:
    """Optimise the dwell times on the needles found and the applicators drawn, and assemble the export.

    Parameters
    ----------
    found : mapping of str to (m, 3) float, mm, LPS
        Hole id to found centre line, template plane to tip.
    designs : mapping of str to str
        Hole id to its planned stylet preset ("" or absent: straight).
    structures : StructureSet
        The post-insertion image's structures: the target, the organs at risk, the applicators (contours mm, LPS).
    volume : Volume or None
        The post-insertion image (the planning grid, and the series the export references).
    aims : Aims
        The plan's protocol.
    source_name : str
        The TG-43 data set of the plan's source.
    air_kerma_u : float, U
        Source strength at treatment.
    settings : ImplantSettings
        The implant settings (dwell step and margin, robustness, optimiser).
    target_roi : str
        The target's ROI name.
    oar_names : sequence of str
        The organs at risk (normalised names; those not in ``structures`` are skipped).
    setup_type : str
        DICOM Application Setup Type of the template.
    input_paths : sequence of Path
        Files the re-plan reads (never written).
    now : datetime or None
        The plan's date and time (default: now).

    Returns
    -------
    Replan
        The plan and its export, or the reason there is none.

    Raises
    ------
    PlanInputError
        ``target_roi`` is not in ``structures``.
    """
    from reachplan.planner.delivery import Exporting, case_point_limits, implant_needles
    from reachplan.planner.dose.structures import gtv_structure, planning_structures
    from reachplan.planner.dose.tg43 import Tg43Kernel
    from reachplan.planner.implant.candidates import applicator_channels
    from reachplan.planner.implant.plan import plan_implant
    from reachplan.planner.lookup import applicator_kinds, get_source
    from reachplan.plugins.applicators.build import applicators_from_structures
    from reachplan.plugins.exporters import SourceSpec

    if target_roi not in structures.names:
        raise PlanInputError(f"the post-insertion structure set has no {target_roi} ROI; contour it to re-plan")
    planning = planning_structures(structures, None if volume is None else volume.grid, target_roi, oar_names)
    needles, without = found_channels(found, designs, planning, settings)
    applicators = applicators_from_structures(structures, applicator_kinds())
    channels = [*needles, *applicator_channels(applicators, planning, settings)]
    names = tuple(c.name for c in channels)
    if not channels:
        return Replan(None, names, tuple(without), None, f"no found needle has a dwell in {target_roi}")
    source = get_source(source_name)
    kernel = Tg43Kernel(source)
    arm = plan_implant(REPLAN_LABEL, channels, planning, kernel, air_kerma_u, aims, settings,
                       gtv=gtv_structure(structures, planning.grid), points=case_point_limits(structures, aims))
    implant = arm.plan
    if implant is None or not implant.channels:
        return Replan(None, names, tuple(without), None, arm.reason or "the optimiser found no loading of the needles "
                                                                       "found")
    now = (now or datetime.now()).replace(microsecond=0)
    spec = SourceSpec.from_source_data(source, air_kerma_u, now.replace(hour=0, minute=0, second=0))
    exporting = Exporting(planning, structures, kernel, air_kerma_u, aims, target_roi, (), spec, setup_type, volume,
                          tuple(input_paths), now)
    export = exporting.plan(REPLAN_LABEL, implant_needles(implant), implant.dwells, len(implant.channels))
    return Replan(implant, names, tuple(without), export)
