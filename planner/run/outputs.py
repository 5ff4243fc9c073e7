"""The files of a planned case: figures, the exports (DICOM RT, device instructions), report.html and plan.json.

Every write is atomic (:mod:`reachplan.imaging.files`); the caller stages the folder so that nothing appears in
the output folder unless the whole case succeeds.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path

from reachplan.imaging.files import atomic_write_bytes, atomic_write_json, json_safe
from reachplan.planner.lookup import exporter
from reachplan.planner.report import figures
from reachplan.planner.report.build import report_html
from reachplan.planner.report.terminal import top_candidates
from reachplan.planner.report.workspace import workspace_figure
from reachplan.planner.run.case import CaseResult, rod_model_errors
from reachplan.plugins.exporters import ExportOptions
from reachplan.plugins.exporters.base import ExportPlan

#: the exporters of the delivered plan, and of each implant arm's chosen implant (``export/implant_<arm>/``: RT Plan,
#: Structure Set and Dose of the arm, and its device instructions)
PLAN_EXPORTERS: tuple[str, ...] = ("dicom_rt", "device_json", "device_csv", "device_html")
ARM_EXPORTERS: tuple[str, ...] = PLAN_EXPORTERS


@dataclass(frozen=True)
class CaseFiles:
    """What :func:`write_outputs` wrote, as the user will find it (paths inside the final folder).

    Parameters
    ----------
    doc : dict
        plan.json's content.
    report : Path
        report.html.
    plan : Path
        plan.json.
    exports : tuple of Path
        Every exported file (DICOM RT Plan, Structure Set, Dose, device instructions).
    """

    doc: dict[str, object]
    report: Path
    plan: Path
    exports: tuple[Path, ...]

    @property
    def device_instructions(self) -> tuple[Path, ...]:
        """The device-instruction JSON files and printable pages, delivered plan first.

        Returns
        -------
        tuple of Path
            Paths inside the final folder.
        """
        return tuple(f for f in self.exports if "device" in f.name and f.suffix in (".json", ".html"))


def _export(plan: ExportPlan, names: tuple[str, ...], folder: Path, out: Path, final: Path,
            style: str = "eclipse") -> list[Path]:
    """Run the exporters ``names`` on ``plan`` into ``folder``; return the written files as paths inside ``final``."""
    files: list[Path] = []
    for name in names:
        written = exporter(name).export(plan, folder, ExportOptions(overwrite=True, rtplan_style=style))
        files += [final / Path(f.path).relative_to(out) for f in written.files]
    return files


def write_outputs(case: CaseResult, out: Path, final: Path | None = None, *, extra: Mapping[str, object] | None = None,
                  complete: Callable[[dict[str, object]], None] | None = None, quiet: bool = True) -> CaseFiles:
    """Write a planned case's files into ``out``.

    Parameters
    ----------
    case : CaseResult
        What :func:`~reachplan.planner.run.case.run_case` computed.
    out : Path
        The (staging) folder written into.
    final : Path or None
        Where ``out`` will be once moved into place (default ``out``): every path written inside a file or
        returned is there.
    extra : Mapping of str to object or None
        Keys put first in plan.json (e.g. the case's description).
    complete : callable or None
        Called with plan.json's content just before it is written, to add what the caller knows.
    quiet : bool
        No progress bars.

    Returns
    -------
    CaseFiles
        plan.json's content and the paths written.
    """
    final = out if final is None else Path(final)
    doc: dict[str, object] = {**dict(extra or {}), **case.to_json()}
    overview_png = figures.overview(case.scene, top_candidates(case.result), case.inputs.volume)
    workspace_png = workspace_figure(case.scene, case.config.plan)
    atomic_write_bytes(out / "overview.png", overview_png)
    atomic_write_bytes(out / "workspace.png", workspace_png)
    files: list[Path] = []
    delivery = case.delivery
    if delivery is not None:
        files += _export(delivery.export, PLAN_EXPORTERS, out / "export", out, final, case.config.rtplan_style)
        for arm_name, arm_export in delivery.implant_exports.items():
            files += _export(arm_export, ARM_EXPORTERS, out / "export" / f"implant_{arm_name}", out, final)
        section = doc["delivery"]
        assert isinstance(section, dict)
        section["files"] = [str(f) for f in files]
    t = time.perf_counter()
    html = report_html(case.scene, case.result, volume=case.inputs.volume, delivery=delivery,
                       comparison=case.comparison, comparison_note=case.comparison_note, case=case.inputs.label,
                       timings=case.timings, source_name=case.config.source, quiet=quiet, overview_png=overview_png,
                       workspace_png=workspace_png, model_errors=rod_model_errors())
    atomic_write_bytes(out / "report.html", html.encode("utf-8"))
    doc["report"] = str(final / "report.html")
    doc["timings"] = {**case.timings, "report_s": time.perf_counter() - t}
    if complete is not None:
        complete(doc)
    atomic_write_json(out / "plan.json", json_safe(doc))
    return CaseFiles(doc, final / "report.html", final / "plan.json", tuple(files))
