"""The delivered plan: the implant (or one needle per target) with its dwell times, assembled for the exporters.

Both implant arms (straight only, straight + steered) are planned for a case's scene
(:func:`reachplan.planner.implant.case.plan_implants`); the delivered plan is the straight + steered arm's chosen
implant, with the reference points, the prescription and the planned dose the exporters write.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from datetime import datetime
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from reachplan.imaging.types import Grid, StructureSet, Volume
from reachplan.planner.case.config import DEFAULT_AIR_KERMA_U
from reachplan.planner.case.result import PlanResult, choose_needles
from reachplan.planner.case.scene import Scene
from reachplan.planner.dose.aims import Aims
from reachplan.planner.dose.evaluation import AimsTable, emit, evaluate_aims, site_warning
from reachplan.planner.dose.structures import gtv_structure, planning_structures
from reachplan.planner.errors import PlanInputError
from reachplan.planner.implant.case import ImplantComparison, plan_implants
from reachplan.planner.implant.problem import PointLimit, point_limits
from reachplan.planner.lookup import get_source, load_template
from reachplan.planner.steering.schedule import TensionSchedule
from reachplan.plugins.sources import SourceData

if TYPE_CHECKING:
    from reachplan.planner.dose.coverage import Dvh
    from reachplan.planner.dose.dwells import DwellSet
    from reachplan.planner.dose.structures import PlanningStructures
    from reachplan.planner.dose.tg43 import Tg43Kernel
    from reachplan.planner.implant.arms import ImplantArm, ImplantPlan
    from reachplan.planner.implant.dwells import OptimisationResult
    from reachplan.planner.implant.settings import ImplantSettings
    from reachplan.plugins.exporters import ExportPlan, NeedleExport
    from reachplan.plugins.exporters.base import PlannedDose, ReferencePoint, SourceSpec


#: What a delivered channel is for when it is an applicator channel (tandem, ring, ovoid), and the delivered plan's
#: kind when every target got its own top-ranked needle (see :class:`Delivery`).
INTRACAVITARY = "intracavitary"
PER_TARGET = "one needle per target"

#: The implant arm exported as the delivered plan: straight + steered (never worse than straight only).
EXPORT_ARM = "steered"
#: A structure holding less than this share of its own (contoured) volume on the dose grid is reported as cropped.
CROPPED_SHARE = 0.97


@dataclass(frozen=True, eq=False)
class WholeDvhs:
    """Cumulative DVHs of whole structures, every exported plan's on one grid (what :func:`whole_dvhs` returns).

    Parameters
    ----------
    grid : Grid
        The dose grid (the planning grid's box around the target and every organ at risk), mm, LPS.
    by_plan : dict of str to tuple of (str, Dvh)
        Per exported plan (``delivered`` and each implant arm by name), the DVH (Gy per fraction, cm³) of the
        target and each organ at risk over every voxel of its mask.
    volume_cc : dict of str to float, cm³
        Each structure's volume on the grid (what its DVH starts at).
    own_cc : dict of str to float, cm³
        Each structure's own volume (its closed mesh), where known.
    """

    grid: Grid
    by_plan: dict[str, tuple[tuple[str, Dvh], ...]]
    volume_cc: dict[str, float]
    own_cc: dict[str, float] = field(default_factory=dict)

    @property
    def cropped(self) -> dict[str, tuple[float, float]]:
        """Structures the grid holds less than :data:`CROPPED_SHARE` of: name -> (on the grid, own volume), cm³."""
        return {n: (v, self.own_cc[n]) for n, v in self.volume_cc.items()
                if n in self.own_cc and v < CROPPED_SHARE * self.own_cc[n]}


@dataclass(frozen=True, eq=False)
class Delivery:
    """The delivered plan: loaded channels with their dwell times, ready for the exporters.

    What :func:`plan_delivery` returns.

    Parameters
    ----------
    optimisation : OptimisationResult
        The delivered plan's dwell times and dose-volume metrics.
    export : ExportPlan
        Only the channels that carry dwell time (a needle the optimum leaves empty is not part of the implant and
        gets no instructions).
    planning : PlanningStructures
        The planning grid and masks the dose was optimised on.
    source : SourceData
        The TG-43 data set the dwell times were optimised with.
    roles : tuple of str
        Per exported channel, what it is for: the target a per-target needle was chosen for, the target volume for
        an implant needle, ``intracavitary`` for an applicator channel.
    kind : str
        Which plan is delivered: ``implant, straight + steered``, ``implant, straight`` or ``one needle per
        target``.
    implant : ImplantComparison or None
        The two implant arms (:func:`~reachplan.planner.implant.case.plan_implants`) when asked for.
    implant_exports : dict of str to ExportPlan
        By arm name, the export of each arm's chosen implant: its channels, reference points and planned dose.
    aims : Aims
        The protocol the plan was made for and is reported against.
    aims_tables : dict of str to AimsTable
        Each plan's dose against every aim: ``straight`` and ``steered`` (the implant arms' chosen plans) and
        ``delivered`` (the exported plan; the same table as its arm's).
    warnings : tuple of str
        ``"Category: message"`` of the protocol's named warnings: the dose target is not the protocol's site's
        (which aims were used), an organ smaller than 2 cm³.
    whole_dvhs : WholeDvhs or None
        Whole-structure DVHs of the delivered plan and each implant arm on the planned dose's grid (None without a
        planned dose).
    """

    optimisation: OptimisationResult
    export: ExportPlan
    planning: PlanningStructures
    source: SourceData
    roles: tuple[str, ...]
    kind: str = PER_TARGET
    implant: ImplantComparison | None = None
    implant_exports: dict[str, ExportPlan] = field(default_factory=dict)
    aims: Aims = field(default_factory=Aims)
    aims_tables: dict[str, AimsTable] = field(default_factory=dict)
    warnings: tuple[str, ...] = ()
    whole_dvhs: WholeDvhs | None = None

    @property
    def n_needles(self) -> int:
        """Template needles delivered (intracavitary channels not counted)."""
        return sum(r != INTRACAVITARY for r in self.roles)

    def to_json(self) -> dict[str, object]:
        """Return plan.json's ``delivery``: the plan's kind, its channels, prescription, points and optimisation.

        Returns
        -------
        dict
            JSON-ready values (mm LPS, Gy); the writer adds the exported ``files``. ``optimisation.aim_met`` is
            the protocol's verdict (``aims``, every planning aim with its headroom), ``optimiser_aim_met`` the
            optimiser's own.
        """
        opt = self.optimisation
        ex = self.export
        table = self.aims_tables.get("delivered")
        return {
            "plan": self.kind,
            "needles": [n.hole_id for n in ex.needles],
            "roles": list(self.roles),
            "prescription": {"target": ex.target_name, "dose_per_fraction_gy": ex.prescription_dose_gy,
                             "fractions": ex.fractions_planned},
            "reference_points": [{"name": p.name, "position_mm": [round(float(x), 2) for x in p.position_mm],
                                  "planned_dose_per_fraction_gy": round(p.planned_dose_gy(ex.needles), 4),
                                  "specification_point": p.name == ex.specification_point}
                                 for p in ex.reference_points],
            "optimisation": {"success": opt.success, "reason": opt.reason,
                             "aim_met": opt.aim_met if table is None else table.aims_met,
                             "optimiser_aim_met": opt.aim_met,
                             "hrctv_d90_gy": round(float(opt.target.d90_gy), 3) if opt.success else None},
            "aims": None if table is None else table.to_json(),
        }

    def implant_json(self) -> dict[str, object] | None:
        """Return plan.json's ``implant`` with each arm's aims (None without implant arms).

        Returns
        -------
        dict or None
            :meth:`ImplantComparison.to_json` with ``<arm>.aims`` (:meth:`AimsTable.to_json`), ``<arm>.aims_met``
            the table's verdict (every planning aim met with the protocol's headroom; the selection's own in
            ``selection_aims_met``), and each organ's D2cm³ None where it is not applicable (under 2 cm³).
        """
        if self.implant is None:
            return None
        doc = self.implant.to_json()
        for name, table in self.aims_tables.items():
            arm = doc.get(name)
            if not isinstance(arm, dict):
                continue
            arm["aims"] = table.to_json()
            arm["selection_aims_met"], arm["aims_met"] = arm.get("aims_met"), table.aims_met
            d2cc = arm.get("oar_d2cc_eqd2_gy")
            if isinstance(d2cc, dict):
                for r in table.results:
                    if r.metric == "D2cm³" and r.value_eqd2_gy is None and r.structure in d2cc:
                        d2cc[r.structure] = None
        return doc


@dataclass(frozen=True, eq=False)
class Exporting:
    """What every exported plan of one case shares; :meth:`plan` makes the export of one set of dwell times.

    Parameters
    ----------
    planning : PlanningStructures
        The planning masks (the prescription point lies in the target; the planned dose covers the target and
        organs).
    structures : StructureSet
        The case's structures (carried into the export; the reference points' landmarks).
    kernel : Tg43Kernel
        The source's TG-43 kernel.
    air_kerma_u : float, U
        Source strength.
    aims : Aims
        The protocol (fractions, prescription per fraction).
    target_roi : str
        The prescription target's ROI name.
    named_points : tuple of (str, (float, float, float))
        Further reference points, name and position (mm, LPS).
    source : SourceSpec
        The treatment source as exported.
    setup_type : str
        DICOM Application Setup Type.
    volume : Volume or None
        The image series the export references.
    input_paths : tuple of Path
        The input files (never written).
    now : datetime
        The plan's date and time.
    planned_dose : bool
        Compute the planned dose for the RT Dose.
    """

    planning: PlanningStructures
    structures: StructureSet
    kernel: Tg43Kernel
    air_kerma_u: float
    aims: Aims
    target_roi: str
    named_points: tuple[tuple[str, Sequence[float]], ...]
    source: SourceSpec
    setup_type: str
    volume: Volume | None
    input_paths: tuple[Path, ...]
    now: datetime
    planned_dose: bool = True

    def plan(self, name: str, needles: Sequence[NeedleExport], dwells: DwellSet, n_channels: int) -> ExportPlan:
        """Return the export of ``dwells`` on ``needles``: its reference points, specification point and dose.

        Parameters
        ----------
        name : str
            The RT Plan Label (cut to 16 characters).
        needles : sequence of NeedleExport
            The channels, in order: exported channel ``ch`` (from 1) holds the dwells with ``dwells.channels == ch``.
        dwells : DwellSet
            Positions (mm, LPS), directions and times (s) of every dwell.
        n_channels : int
            The number of channels.

        Returns
        -------
        ExportPlan
            What the exporters write.
        """
        from reachplan.plugins.exporters import ExportPlan

        act = dwells.select(dwells.times_s > 0)
        aims, fractions = self.aims, self.aims.fractionation.n_fractions
        rx = _rx_point(self.planning, act, self.kernel, self.air_kerma_u, aims.prescription_gy, self.target_roi,
                       self.named_points)
        pts = _reference_points(self.structures, [*rx, *self.named_points], dwells, n_channels, self.kernel,
                                self.air_kerma_u)
        dose = (_planned_dose(self.planning, act, self.kernel, self.air_kerma_u, fractions)
                if self.planned_dose else None)
        return ExportPlan(name[:16], tuple(needles), self.source, structure_set=self.structures, volume=self.volume,
                          input_paths=self.input_paths, fractions_planned=fractions,
                          prescription_dose_gy=aims.prescription_gy, target_name=self.target_roi[:64],
                          reference_points=tuple(pts), application_setup_type=self.setup_type, dose=dose,
                          plan_datetime=self.now, specification_point=rx[0][0] if rx else "")


def plan_delivery(
    result: PlanResult,
    structures: StructureSet,
    grid: Grid | None,
    source_name: str = "gammamed_plus_hdr",
    air_kerma_u: float = DEFAULT_AIR_KERMA_U,
    target_roi: str = "HR-CTV",
    label: str = "reachplan",
    volume: Volume | None = None,
    input_paths: Sequence[Path] = (),
    named_points: Sequence[tuple[str, Sequence[float]]] = (),
    planned_dose: bool = True,
    scene: Scene | None = None,
    implant_settings: ImplantSettings | None = None,
    aims: Aims | None = None,
) -> Delivery:
    """Plan the dwell times on the target and assemble the export plan (RT Plan + Structure Set + Dose + device).

    With ``scene`` both implant arms are planned (:func:`plan_implants`) and exported, and the straight + steered
    arm's chosen implant (never worse than straight only) is the delivered plan, the RT Plan a TPS imports; without
    (or when neither arm has a plan) every target gets its top-ranked feasible needle. Dose by TG-43 against ``aims``
    (every plan's aims table, :func:`_aims_tables`). The export carries the prescription (per-fraction dose whose D90
    meets the planning aim, specified at a target point that receives it), the reference points (that one, Point A,
    ICRU points, ``named_points``: :mod:`reachplan.planner.geometry.reference_points`) with each dwell's dose rate
    there, the application setup type and the planned dose near the target and organs (unless ``planned_dose`` False).

    Parameters
    ----------
    result : PlanResult
        The ranked plan.
    structures : StructureSet
        The case's structures (target volume, organs at risk, reference-point landmarks).
    grid : Grid or None
        The planning grid; None: the structures' own (:func:`planning_structures`).
    source_name : str
        The TG-43 data set, by name.
    air_kerma_u : float, U
        Source strength (cGy cm² h⁻¹).
    target_roi : str
        The target volume's ROI name.
    label : str
        RT Plan label of the delivered plan (cut to 16 characters).
    volume : Volume or None
        The image series the exports reference.
    input_paths : sequence of Path
        The input files, for the exports' provenance.
    named_points : sequence of (str, (float, float, float))
        Further reference points, name and position (mm, LPS).
    planned_dose : bool
        Compute the planned dose for the RT Dose export.
    scene : Scene or None
        With it the implant arms are planned and delivered; None: one needle per target.
    implant_settings : ImplantSettings or None
        Settings of the implant planning; None: the defaults.
    aims : Aims or None
        The protocol's aims (``load_protocol``); None: EMBRACE II.

    Returns
    -------
    Delivery
        The delivered plan, its exports and (with ``scene``) both implant arms.

    Raises
    ------
    PlanInputError
        No feasible needle, no target structure to optimise on, or a bad named point.
    """
    from reachplan.planner.dose.tg43 import Tg43Kernel
    from reachplan.plugins.exporters import SourceSpec

    planning = planning_structures(structures, grid, target_roi, result.config.oar_names,
                                   None if scene is None else scene.applicators)
    source, aims = get_source(source_name), Aims() if aims is None else aims
    kernel = Tg43Kernel(source)
    implant, opt, exports, roles, kind = _delivered(result, scene, planning, source, kernel, air_kerma_u, aims,
                                                    implant_settings, structures, named_points)
    now = datetime.now().replace(microsecond=0)  # the source's reference at midnight, as Eclipse writes it
    exporting = Exporting(planning, structures, kernel, air_kerma_u, aims, target_roi, tuple(named_points),
                          SourceSpec.from_source_data(source, air_kerma_u, now.replace(hour=0, minute=0, second=0)),
                          load_template(result.config.template).application_setup_type, volume,
                          tuple(input_paths), now, planned_dose)
    export = exporting.plan(label, exports, opt.dwells, len(exports))
    implant_exports = _arm_exports(implant, exporting.plan, opt.dwells, export)
    points = list(export.reference_points)
    tables = _aims_tables(aims, planning, implant, opt, kind, points, kernel, air_kerma_u)
    own = {} if scene is None else {n: abs(float(m.volume)) / 1000.0 for n, m in scene.meshes.items()}
    return Delivery(opt, export, planning, source, roles, kind, implant, implant_exports, aims, tables,
                    _protocol_warnings(aims, target_roi, tables),
                    whole_dvhs(planning, {"delivered": export, **implant_exports}, aims.fractionation.n_fractions,
                               own))


def whole_dvhs(planning: PlanningStructures, exports: dict[str, ExportPlan], fractions: int,
               own_cc: dict[str, float] | None = None) -> WholeDvhs | None:
    """Return the whole-structure DVHs of each export's planned dose, all on its one grid (None without a dose).

    Every export's planned dose lies on the same grid, the planning grid's box around the target and every organ
    at risk (:func:`_dose_region`), so each structure's DVH covers every voxel of its planning mask and the plans
    give it the same volume; the implant's own DVHs cover only the voxels near its dwells, where D2cm³ is decided.

    Parameters
    ----------
    planning : PlanningStructures
        The planning masks (the target and the organs at risk, bone and applicators excluded).
    exports : dict of str to ExportPlan
        The plans by name; those without a planned dose on the dose region are skipped.
    fractions : int
        Fractions the planned dose covers (the DVHs are per fraction).
    own_cc : dict of str to float or None, cm³
        Each structure's own volume (its mesh), to tell a structure the grid crops.

    Returns
    -------
    WholeDvhs or None
        None when no export has a planned dose on the dose region.
    """
    from reachplan.planner.dose.coverage import cumulative_dvh, voxel_volume_cc

    lo, hi = _region_box(planning)
    box = tuple(slice(int(a), int(b)) for a, b in zip(lo, hi, strict=True))
    vox = voxel_volume_cc(planning.grid)
    structures = (planning.target, *planning.oars)
    by_plan: dict[str, tuple[tuple[str, Dvh], ...]] = {}
    grid = None
    for name, ex in exports.items():
        if ex.dose is None or ex.dose.grid.shape != tuple(int(b - a) for a, b in zip(lo, hi, strict=True)):
            continue
        grid, per_fraction = ex.dose.grid, np.asarray(ex.dose.dose_gy, dtype=float) / max(fractions, 1)
        by_plan[name] = tuple((s.name, cumulative_dvh(per_fraction[s.mask[box]], vox)) for s in structures
                              if s.mask.any())
    if grid is None:
        return None
    volumes = {s.name: float(s.mask.sum()) * vox for s in structures}
    own = {n: v for n, v in (own_cc or {}).items() if n in volumes}
    return WholeDvhs(grid, by_plan, volumes, own)


def _protocol_warnings(aims: Aims, target_roi: str, tables: dict[str, AimsTable]) -> tuple[str, ...]:
    """Return the protocol's warnings (site, organs under 2 cm³) once each, having issued them as named warnings."""
    notes = [w for w in (site_warning(aims, target_roi),) if w]
    notes += [w for t in tables.values() for w in t.warnings]
    emit(notes)
    return tuple(dict.fromkeys(notes))


def _aims_tables(aims: Aims, planning: PlanningStructures, implant: ImplantComparison | None,
                 opt: OptimisationResult, kind: str, points: Sequence[ReferencePoint], kernel: Tg43Kernel,
                 air_kerma_u: float) -> dict[str, AimsTable]:
    """Each implant arm's chosen plan and the delivered plan against every aim (points: the delivered plan's)."""
    from reachplan.planner.dose.coverage import voxel_volume_cc
    from reachplan.planner.dose.dwells import dose_at_points

    vox = voxel_volume_cc(planning.grid)
    volumes = {o.name: float(o.mask.sum()) * vox for o in planning.oars}
    where = np.array([p.position_mm for p in points]).reshape(-1, 3)

    def at_points(dwells: DwellSet) -> list[tuple[str, float]]:
        if not len(where) or not len(dwells):
            return []
        doses = dose_at_points(where, dwells, kernel, air_kerma_u)
        return [(p.name, float(d)) for p, d in zip(points, doses, strict=True)]

    tables: dict[str, AimsTable] = {}
    for arm in implant.arms if implant is not None else ():
        if arm.plan is not None:
            pl = arm.plan
            tables[arm.name] = evaluate_aims(aims, pl.target, pl.oars, organ_volumes_cc=volumes, gtv=pl.gtv,
                                             points=at_points(pl.dwells))
    delivered = EXPORT_ARM if kind == "implant, straight + steered" else kind.removeprefix("implant, ")
    if delivered in tables:
        tables["delivered"] = tables[delivered]
    elif opt.success:
        tables["delivered"] = evaluate_aims(aims, opt.target, opt.oars, organ_volumes_cc=volumes,
                                            points=at_points(opt.dwells.select(opt.dwells.times_s > 0)))
    return tables


def _arm_exports(implant: ImplantComparison | None,
                 export_of: Callable[[str, Sequence[NeedleExport], DwellSet, int], ExportPlan],
                 delivered: DwellSet, export: ExportPlan) -> dict[str, ExportPlan]:
    """Return each implant arm's chosen implant as an export of its own (RT Plan + Structure Set + Dose, device).

    ``export_of(name, needles, dwells, n_channels)`` builds one from the arm's own dwells: its reference points and
    planned dose; the delivered arm's (``delivered`` dwells) are those of the delivery's ``export``.
    """
    out = {}
    for a in implant.arms if implant is not None else ():
        if a.plan is None or not a.plan.channels:
            continue
        name, needles = f"implant_{a.name}", implant_needles(a.plan)
        out[a.name] = (dataclasses.replace(export, label=name[:16], needles=tuple(needles))
                       if a.plan.dwells is delivered else export_of(name, needles, a.plan.dwells, len(a.plan.channels)))
    return out


def case_point_limits(structures: StructureSet, aims: Aims,
                      named_points: Sequence[tuple[str, Sequence[float]]] = ()) -> tuple[PointLimit, ...]:
    """Return the protocol's dose points with an aim that this case's reference points stand for.

    Parameters
    ----------
    structures : StructureSet
        The case's ROIs (mm, LPS): the landmarks of the placed points
        (:mod:`reachplan.planner.geometry.reference_points`).
    aims : Aims
        The protocol.
    named_points : sequence of (str, (float, float, float))
        Further reference points, name and position (mm, LPS); malformed ones are left to the export's check.

    Returns
    -------
    tuple of PointLimit
        Per fraction, the planning value (aim less headroom) and hard limit of each matched point.
    """
    from reachplan.planner.geometry.reference_points import place_reference_points

    placed, _ = place_reference_points(structures)
    named = [(n, np.asarray(p, dtype=float)) for n, p in named_points
             if np.asarray(p, dtype=float).shape == (3,) and np.all(np.isfinite(np.asarray(p, dtype=float)))]
    return point_limits(aims, [*((p.name, p.position_mm) for p in placed), *named])


def _delivered(result: PlanResult, scene: Scene | None, planning: PlanningStructures, source: SourceData,
               kernel: Tg43Kernel, air_kerma_u: float, aims: Aims, implant_settings: ImplantSettings | None,
               structures: StructureSet, named_points: Sequence[tuple[str, Sequence[float]]] = (),
               ) -> tuple[ImplantComparison | None, OptimisationResult, tuple[NeedleExport, ...], tuple[str, ...], str]:
    """Return the implant arms (with ``scene``) and the plan to deliver: optimisation, needles, roles and kind.

    The implant arm :func:`_delivered_implant` picks, else one needle per target (:func:`_per_target`). The implant
    also aims at the GTV (GTV_res, :func:`~reachplan.planner.dose.structures.gtv_structure`) when ``structures``
    has one, and holds the protocol's dose points (:func:`case_point_limits`: the ICRU recto-vaginal point) with the
    organs.
    """
    implant = None
    if scene is not None:
        implant = plan_implants(scene, planning, result.config, source, air_kerma_u, implant_settings, aims=aims,
                                gtv=gtv_structure(structures, planning.grid),
                                points=case_point_limits(structures, aims, named_points))
    delivered = _delivered_implant(implant, planning.target.name)
    if delivered is not None:
        arm, opt, exports, roles = delivered
        kind = "implant, straight + steered" if arm.name == EXPORT_ARM else f"implant, {arm.name}"
    else:
        opt, exports, roles = _per_target(result, planning, kernel, air_kerma_u, aims)
        kind = PER_TARGET
    return implant, opt, exports, roles, kind


def _planned_dose(planning: PlanningStructures, active: DwellSet, kernel: Tg43Kernel, air_kerma_u: float,
                  fractions: int) -> PlannedDose:
    """Return the planned dose of all ``fractions`` (Gy) on the target's and organs' region of the planning grid."""
    from reachplan.planner.dose.dwells import dose_on_grid
    from reachplan.plugins.exporters.base import PlannedDose

    dose_grid = _dose_region(planning)
    values = dose_on_grid(dose_grid, active, kernel, air_kerma_u) if len(active) else np.zeros(dose_grid.shape)
    return PlannedDose(values * fractions, dose_grid)


def _rx_point(planning: PlanningStructures, active: DwellSet, kernel: Tg43Kernel, air_kerma_u: float, dose_gy: float,
              target_roi: str, named_points: Sequence[tuple[str, Sequence[float]]],
              ) -> list[tuple[str, Sequence[float]]]:
    """Return the prescription's specification point ``[(name, position mm LPS)]``, or ``[]`` when there is none.

    A point of the target where the planned dose per fraction is the prescription
    (:func:`~reachplan.planner.dose.rx_point.prescription_point`).
    """
    from reachplan.planner.dose.dwells import grid_points_mm
    from reachplan.planner.dose.rx_point import prescription_point

    name = f"{target_roi} Rx point"[:64]
    if any(n == name for n, _ in named_points):
        return []
    pts = grid_points_mm(planning.grid, np.flatnonzero(planning.target.mask.ravel()))
    where = prescription_point(pts, active, kernel, air_kerma_u, dose_gy)
    return [] if where is None else [(name, tuple(float(x) for x in where))]


def _reference_points(structures: StructureSet, named_points: Sequence[tuple[str, Sequence[float]]],
                      dwells: DwellSet, n_channels: int, kernel: Tg43Kernel, air_kerma_u: float
                      ) -> list[ReferencePoint]:
    """Return the exported plan's reference points: the placed ones, then ``named_points``, with dose rates.

    Rates in Gy s⁻¹ per dwell, per exported channel in its dwell order (exported channel ``ch`` holds the dwells
    with ``channels == ch``).
    """
    from reachplan.planner.dose.dwells import rate_matrix
    from reachplan.planner.geometry.reference_points import place_reference_points
    from reachplan.plugins.exporters.base import ReferencePoint

    placed, _ = place_reference_points(structures)
    wanted = [(p.name, p.position_mm) for p in placed]
    for name, xyz in named_points:
        pos = np.asarray(xyz, dtype=float)
        if pos.shape != (3,) or not np.all(np.isfinite(pos)):
            raise PlanInputError(f"reference point {name!r}: give three finite coordinates in mm (LPS)")
        wanted.append((name, pos))
    gy_per_s = air_kerma_u / 360000.0  # rate_matrix is cGy h⁻¹ U⁻¹: × S_K / 100 / 3600 gives Gy s⁻¹
    points = []
    for name, pos in wanted:
        rate = rate_matrix(pos[None], dwells.positions_mm, dwells.directions, kernel)[0] * gy_per_s
        # per exported channel, in its dwell order (exported channel ch holds the dwells with channels == ch)
        rates = tuple(rate[dwells.channels == ch] for ch in range(1, n_channels + 1))
        try:
            points.append(ReferencePoint(name, pos, rates))
        except ValueError as exc:
            raise PlanInputError(str(exc)) from None
    return points


def _delivered_implant(
    implant: ImplantComparison | None, target_name: str,
) -> tuple[ImplantArm, OptimisationResult, tuple[NeedleExport, ...], tuple[str, ...]] | None:
    """Return the implant arm to deliver (:data:`EXPORT_ARM`, else the other) as an optimisation result, or None.

    Each channel's role is ``target_name`` for a needle, :data:`INTRACAVITARY` for an applicator channel.
    Channel ``ch`` of the exported plan is the plan's channel ``ch`` (its dwells are ``dwells.channels == ch``).
    """
    from reachplan.planner.implant.dwells import OptimisationResult

    if implant is None:
        return None
    arms = sorted(implant.arms, key=lambda a: a.name != EXPORT_ARM)
    arm = next((a for a in arms if a.plan is not None and a.plan.channels), None)
    if arm is None or arm.plan is None:
        return None
    pl = arm.plan
    gap = "" if pl.mip_gap is None else f"; gap to the LP bound {pl.mip_gap:.2f}"
    n_ic = len(pl.channels) - pl.n_needles
    reason = (f"implant ({arm.name} arm): {pl.n_needles} needle{'s' if pl.n_needles != 1 else ''} and {n_ic} "
              f"intracavitary channel"
              f"{'s' if n_ic != 1 else ''}, chosen with the dwell times (LP relaxation rounded, then a swap "
              f"search{gap})")
    opt = OptimisationResult(pl.dwells, pl.target, pl.oars, True, reason, scaled=pl.scale < 1.0, scale=pl.scale,
                             dvhs=pl.dvhs, aim_met=pl.aims_met)
    roles = tuple(target_name if c.is_needle else INTRACAVITARY for c in pl.channels)
    return arm, opt, implant_needles(pl), roles


def _per_target(
    result: PlanResult, planning: PlanningStructures, kernel: Tg43Kernel, air_kerma_u: float, aims: Aims,
) -> tuple[OptimisationResult, tuple[NeedleExport, ...], tuple[str, ...]]:
    """Every target's top-ranked feasible needle with optimised dwell times; empty needles are left out.

    The dwells are renumbered so that channel ``ch`` of the result is the ``ch``-th exported needle.
    """
    from reachplan.planner.dose.dwells import DwellSet
    from reachplan.planner.implant.dwells import optimise_dwell_times
    from reachplan.plugins.exporters import NeedleExport

    needles = choose_needles(result)
    if not needles:
        raise PlanInputError("no feasible needle to deliver: every target is out of reach or blocked")
    opt = optimise_dwell_times([c.path_mm for c in needles], planning, kernel, air_kerma_u, aims)
    exports: list[NeedleExport] = []
    roles: list[str] = []
    kept: list[DwellSet] = []
    for ch, c in enumerate(needles, start=1):
        keep = (opt.dwells.channels == ch) & (opt.dwells.times_s > 0)
        if not keep.any():  # a needle the optimum leaves empty is not part of the implant: no instructions
            continue
        sub = opt.dwells.select(keep)
        kept.append(DwellSet(sub.positions_mm, sub.directions, sub.times_s, np.full(len(sub), len(kept) + 1)))
        roles.append(c.target)
        exports.append(NeedleExport(c.hole_id, c.path_mm, sub.positions_mm, sub.times_s, c.design_name,
                                    _schedule_rows(c.schedule)))
    if kept:
        opt = dataclasses.replace(opt, dwells=DwellSet.concatenate(kept))
    return opt, tuple(exports), tuple(roles)


def _schedule_rows(schedule: TensionSchedule | None) -> np.ndarray | None:
    """(k, 3) rows (depth mm, tension N, roll deg) of a schedule, or None."""
    return None if schedule is None else np.column_stack([schedule.depth_mm, schedule.tension_n, schedule.roll_deg])


def implant_needles(plan: ImplantPlan) -> tuple[NeedleExport, ...]:
    """Return the loaded channels of an implant as exporter needles, in the plan's order.

    Every one carries time: an empty channel is not in ``plan.channels``.

    Parameters
    ----------
    plan : ImplantPlan
        An arm's chosen implant; channel ``ch`` (from 1) holds the dwells with ``dwells.channels == ch``.

    Returns
    -------
    tuple of NeedleExport
        Path, dwell positions (mm, LPS) and times (s) per channel, applicator channels flagged.
    """
    from reachplan.plugins.exporters import NeedleExport

    out = []
    for ch, c in enumerate(plan.channels, start=1):
        keep = plan.dwells.channels == ch
        out.append(NeedleExport(c.name, c.path_mm, plan.dwells.positions_mm[keep], plan.dwells.times_s[keep],
                                c.design, _schedule_rows(c.schedule), applicator=not c.is_needle))
    return tuple(out)


def _region_box(planning: PlanningStructures, margin: int = 2) -> tuple[np.ndarray, np.ndarray]:
    """Return the (k, j, i) index box [lo, hi) of the planning grid around the target and the organs at risk.

    ``margin``: voxels added on every side.
    """
    mask = planning.target.mask.copy()
    for o in planning.oars:
        mask |= o.mask
    idx = np.argwhere(mask)
    return np.maximum(idx.min(axis=0) - margin, 0), np.minimum(idx.max(axis=0) + margin + 1, planning.grid.shape)


def _dose_region(planning: PlanningStructures, margin: int = 2) -> Grid:
    """Return the part of the planning grid around the target and the organs at risk, as a grid of its own.

    ``margin``: voxels added on every side.
    """
    lo, hi = _region_box(planning, margin)
    affine = planning.grid.patient_from_index.copy()
    affine[:3, 3] = affine[:3, :3] @ np.array([lo[2], lo[1], lo[0]], dtype=float) + affine[:3, 3]
    shape = (int(hi[0] - lo[0]), int(hi[1] - lo[1]), int(hi[2] - lo[2]))
    return Grid(shape, affine)
