"""The dose of a plan after insertion, against its protocol: its times on the needles found, and a re-optimised plan.

Both are computed exactly as ``reachplan dose`` computes any plan's (the TG-43 secondary check of
:mod:`reachplan.planner.run.dose_check`, the aims of :mod:`reachplan.planner.run.dose_aims`), on RT Plans and
Structure Sets: the plan's own export with each found needle's dwells moved onto it
(:mod:`reachplan.planner.verify.delivered`), and the re-optimised plan's export read back from the files written
(:mod:`reachplan.planner.verify.replan`), so that what is reported is what a TPS would compute from those files.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from reachplan.imaging.types import StructureSet, Volume
from reachplan.planner.errors import PlanInputError


def _aims_of(plan: Any, structures: StructureSet, aims: Any, label: str) -> tuple[Any, Any]:
    """Return a plan's dose check and its aims table, as ``reachplan dose --protocol`` computes them."""
    from reachplan.planner.run.dose_aims import plan_dose_aims
    from reachplan.planner.run.dose_check import DoseCheckConfig, check_plan_dose

    check = check_plan_dose(plan, structures, DoseCheckConfig(points=True), label)
    return check, plan_dose_aims(plan, structures, check.grid, check.dose_gy, check.checks, aims)[0]


def _verdict(table: Any) -> str:
    """Return 'every planning aim met' or the aims not met, and whether the hard limits hold."""
    met = "every planning aim met" if table.aims_met else f"aims not met: {', '.join(table.not_met) or 'none assessed'}"
    return f"{met}, {'hard limits kept' if table.limits_met else 'a hard limit broken'}"


def after_insertion(plan_json: Path, doc: Mapping[str, Any], found: Mapping[str, np.ndarray],
                    planned: Mapping[str, np.ndarray], post: StructureSet | None = None, volume: Volume | None = None,
                    folder: Path | None = None, final: Path | None = None) -> dict[str, Any]:
    """Return the plan's dose on the needles as found, and (with ``post`` and ``folder``) the re-optimised plan's.

    Parameters
    ----------
    plan_json : Path
        The plan the needles were inserted from.
    doc : mapping
        Its document.
    found : mapping of str to (m, 3) float, mm, LPS
        Hole id to found centre line, template plane to tip.
    planned : mapping of str to (k, 3) float, mm, LPS
        Hole id to planned centre line.
    post : StructureSet or None
        The post-insertion image's structures (target, organs, applicators): the re-plan is made on them.
    volume : Volume or None
        The post-insertion image (the planning grid; the series the re-plan's export references).
    folder : Path or None
        Where the re-optimised plan's RT Plan, Structure Set and Dose are written (None: no re-plan).
    final : Path or None
        Where ``folder`` will be once moved into place (the paths reported); default ``folder``.

    Returns
    -------
    dict
        ``planned`` and ``as_inserted`` aims tables with a ``summary``, and ``replanned`` (the re-plan's aims
        table, files and summary, or the reason there is none); just a ``summary`` when the plan's export is not
        found.
    """
    from reachplan.imaging.rtplan import read_rtplan
    from reachplan.imaging.rtstruct import read_rtstruct
    from reachplan.planner.dose.protocol import load_protocol
    from reachplan.planner.run.dose_aims import DVH_METHOD
    from reachplan.planner.verify.delivered import as_inserted
    from reachplan.planner.verify.implant import plan_export

    rp, rs = plan_export(plan_json, doc, "RP_"), plan_export(plan_json, doc, "RS_")
    if rp is None or rs is None:
        return {"summary": "as inserted: the plan's exported RT Plan and Structure Set were not found; no dose "
                           "computed"}
    aims = load_protocol((doc.get("protocol") or {}).get("name"))
    plan, structures = read_rtplan(rp), read_rtstruct(rs)
    moved, moved_structures, kept = as_inserted(plan, structures, planned, found)
    check, before = _aims_of(plan, structures, aims, "planned")
    after = _aims_of(moved, moved_structures, aims, "as_inserted")[1]
    rows = {r.label: r for r in before.results}
    changes = "; ".join(f"{r.label} {rows[r.label].value_eqd2_gy:.1f} -> {r.value_eqd2_gy:.1f}"
                        for r in after.results if r.label in rows and r.value_eqd2_gy is not None
                        and rows[r.label].value_eqd2_gy is not None)
    summary = (f"as inserted, the plan's times on the needles found ({aims.name}, Gy EQD2): {_verdict(after)}. "
               f"{changes}" + (f" (as planned: {', '.join(kept)})" if kept else ""))
    out: dict[str, Any] = {"rtplan": str(rp), "channels_as_planned": list(kept), "dvh_method": DVH_METHOD,
                           "planned": before.to_json(), "as_inserted": after.to_json(), "summary": summary}
    if post is not None and folder is not None:
        out["replanned"] = replanned(doc, found, post, volume, aims, check.choice.name, check.strength.treatment_u,
                                     folder, final)
    return out


def replanned(doc: Mapping[str, Any], found: Mapping[str, np.ndarray], post: StructureSet, volume: Volume | None,
              aims: Any, source_name: str, air_kerma_u: float, folder: Path, final: Path | None = None,
              ) -> dict[str, Any]:
    """Re-optimise on the needles found (:func:`~reachplan.planner.verify.replan.replan`), export, and check it.

    Parameters
    ----------
    doc : mapping
        The plan's ``plan.json`` document (its needles' designs, organs, template, and whether its case is built in).
    found : mapping of str to (m, 3) float, mm, LPS
        Hole id to found centre line, template plane to tip.
    post : StructureSet
        The post-insertion image's structures.
    volume : Volume or None
        The post-insertion image.
    aims : Aims
        The plan's protocol.
    source_name : str
        The TG-43 data set of the plan's source.
    air_kerma_u : float, U
        Its strength at treatment.
    folder : Path
        Where the RT Plan, Structure Set and Dose are written.
    final : Path or None
        Where ``folder`` will be once moved into place (the paths reported); default ``folder``.

    Returns
    -------
    dict
        ``summary`` (every planning aim met, or the aims not met; or why there is no plan), and with a plan
        ``aims`` (the aims table of the written RT Plan as ``reachplan dose`` computes it), ``aims_met``,
        ``limits_met``, ``loaded``, ``channels``, ``without_dwells``, ``optimiser_failed`` and ``files``.
    """
    from reachplan.imaging.rtplan import read_rtplan
    from reachplan.imaging.rtstruct import read_rtstruct
    from reachplan.planner.implant.settings import ImplantSettings
    from reachplan.planner.lookup import exporter, load_template
    from reachplan.planner.verify.implant import delivered_needles
    from reachplan.planner.verify.replan import replan
    from reachplan.plugins.exporters import ExportOptions

    config = doc.get("config") or {}
    # a built-in case's analytic HR-CTV is planned with the default dwell margin, a drawn one with none (plan's rule)
    settings = ImplantSettings() if doc.get("case_about") else ImplantSettings(dwell_margin_mm=0.0)
    designs = {n.hole_id: n.design for n in delivered_needles(doc)}
    template = load_template(str(config.get("template", "needlefinder_syed_63")))
    try:
        re = replan(found, designs, post, volume, aims, source_name, air_kerma_u, settings,
                    oar_names=tuple(config.get("oar_names") or ()), setup_type=template.application_setup_type)
    except PlanInputError as exc:
        return {"summary": f"not re-optimised: {exc}"}
    left = f"; found needles without a dwell in the target: {', '.join(re.without_dwells)}" if re.without_dwells else ""
    if re.export is None or re.implant is None:
        return {"channels": list(re.channels), "summary": f"not re-optimised: {re.reason}{left}"}
    written = exporter("dicom_rt").export(re.export, folder, ExportOptions(overwrite=True))
    rp, rs = written.path("rtplan"), written.path("rtstruct")
    table = _aims_of(read_rtplan(rp), read_rtstruct(rs), aims, "re-optimised")[1]
    loaded = sorted({c.name for c in re.implant.channels})
    summary = (f"re-optimised on the needles found ({aims.name}, Gy EQD2): {_verdict(table)}; "
               f"{len(loaded)} channels loaded ({', '.join(loaded)}){left}")
    files = [str((final or folder) / Path(f.path).relative_to(folder)) for f in written.files]
    return {"channels": list(re.channels), "loaded": loaded, "without_dwells": list(re.without_dwells),
            "optimiser_failed": list(re.implant.failed), "aims": table.to_json(), "aims_met": table.aims_met,
            "limits_met": table.limits_met, "files": files, "summary": summary}
