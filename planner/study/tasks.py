"""One study task: a case x a stylet design, planned for all the study's targets, as rows.

A task ships only names and paths; the heavy inputs (the case's structure set, organ meshes and collision
objects) are loaded by the process that runs it and kept in a small per-process cache, so a worker that runs
several designs of one case loads it once.
"""

from __future__ import annotations

import dataclasses
import os
import socket
import sys
import threading
import time
from collections import OrderedDict
from collections.abc import Sequence
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import TYPE_CHECKING

from reachplan import ReachplanError
from reachplan.planner.errors import StudyError

if TYPE_CHECKING:
    from reachplan.imaging.types import StructureSet
    from reachplan.planner.case.config import PlanConfig
    from reachplan.planner.case.result import PlanResult
    from reachplan.planner.case.scene import Scene

#: The design name that plans straight needles only (no stylet): the baseline of a study.
STRAIGHT = "straight"


@dataclass(frozen=True)
class Case:
    """A patient (or phantom) case.

    Parameters
    ----------
    case_id : str, a plain folder name
        Names the case in the results.
    rtstruct : Path
        Its RT Structure Set.

    Raises
    ------
    ValueError
        A case id that is empty, holds a path separator or starts with a dot.
    """

    case_id: str
    rtstruct: Path

    def __post_init__(self) -> None:
        if not self.case_id or any(ch in self.case_id for ch in "/\\\0") or self.case_id.startswith("."):
            raise ValueError(f"case id {self.case_id!r} must be a plain folder name")


@dataclass(frozen=True)
class StudyTask:
    """One unit of work: every target of ``case`` planned with stylet ``design`` (``straight``: none).

    Parameters
    ----------
    case : Case
        The case: its id and structure set.
    design : str
        Stylet preset name, or :data:`STRAIGHT` for straight needles only.
    targets : tuple of str or None
        ROI names of the targets; None = every ROI named ``Target*`` in the case.
    dose : bool
        Also choose one needle per target and optimise the dwell times on the HR-CTV (as ``reachplan plan`` does
        before exporting).
    """

    case: Case
    design: str
    targets: tuple[str, ...] | None
    dose: bool = False

    @property
    def key(self) -> str:
        """Unique, file-name-safe key of the task; also the name of its part file (the ledger)."""
        return f"{self.case.case_id}--{self.design}"


@dataclass(frozen=True)
class StudyRow:
    """One result row: a case x design x target.

    ``status`` is ``ok`` or ``failed`` (the task failed; ``reason`` says why, the metrics are None, and
    ``target`` is "" when the task failed before its targets were known). For ``ok`` rows, ``reason`` is ""
    when the target is reached and otherwise the reason of its top-ranked candidate.
    ``steered_*`` describe the best-ranked feasible steered candidate and ``straight_*`` the best feasible
    straight one (None when there is none). Times are the same on every row of a task; CPU time well below wall
    time means the machine was oversubscribed.

    Parameters
    ----------
    task, case, design, target : str
        Task key, case id, stylet design and target ROI name.
    status, reason : str
        ``ok`` or ``failed``, and why (see above).
    reached_steered, reached_straight : bool or None
        A feasible steered (straight) candidate exists.
    n_candidates, n_feasible : int or None
        Candidates of the target, and how many are feasible.
    best_is_steered : bool or None
        The overall top-ranked feasible candidate is steered.
    steered_hole, straight_hole : str or None
        Template hole of the best steered (straight) candidate.
    steered_reach_error_mm, straight_reach_error_mm : float or None, mm
        Reach error.
    steered_clearance_mm, straight_clearance_mm : float or None, mm
        Clearance to the nearest organ at risk.
    steered_peak_tension_n : float or None, N
        Peak tendon tension.
    steered_insertion_depth_mm, straight_insertion_depth_mm : float or None, mm
        Insertion depth beyond the template.
    steered_hole_distance_mm, straight_hole_distance_mm : float or None, mm
        Hole distance from the template centre.
    steered_model : str or None
        Label of the model that produced the steered path.
    task_scene_s : float or None, s
        Time the task spent loading the case (0 when the worker had it cached).
    task_plan_s : float or None, s
        Time planning all the task's targets.
    task_cpu_s : float or None, s
        CPU time of the whole task.
    task_hrctv_d90_gy : float or None, Gy
        HR-CTV D90 after the dwell-time optimisation of the task's chosen needles (only when the study asks for
        dose; None otherwise).
    task_dose_aim_met : bool or None
        Whether that optimisation met the aims.
    task_dose_reason : str or None
        Why there is no dose (e.g. no feasible needle); "" when there is.
    worker : str
        ``host:pid`` of the process that ran the task.
    finished_utc : str
        ISO 8601 time the row was made, UTC, to the second.

    Raises
    ------
    ValueError
        A status other than ``ok`` or ``failed``.
    """

    task: str
    case: str
    design: str
    target: str
    status: str
    reason: str
    reached_steered: bool | None
    reached_straight: bool | None
    n_candidates: int | None
    n_feasible: int | None
    best_is_steered: bool | None
    steered_hole: str | None
    steered_reach_error_mm: float | None
    steered_clearance_mm: float | None
    steered_peak_tension_n: float | None
    steered_insertion_depth_mm: float | None
    steered_hole_distance_mm: float | None
    steered_model: str | None
    straight_hole: str | None
    straight_reach_error_mm: float | None
    straight_clearance_mm: float | None
    straight_insertion_depth_mm: float | None
    straight_hole_distance_mm: float | None
    task_scene_s: float | None
    task_plan_s: float | None
    task_cpu_s: float | None
    task_hrctv_d90_gy: float | None
    task_dose_aim_met: bool | None
    task_dose_reason: str | None
    worker: str
    finished_utc: str

    def __post_init__(self) -> None:
        if self.status not in ("ok", "failed"):
            raise ValueError(f"row status must be 'ok' or 'failed', got {self.status!r}")


def task_threads() -> int:
    """Return the threads a task's numerical work may use: 1 inside a Dask worker (limits set there), else 2.

    In a worker, numba runs this thread's kernels on one thread and HiGHS on one
    (:func:`reachplan.planner.study.workers.limit_threads`); the study's parallelism is its workers.

    Returns
    -------
    int
        1 in a Dask worker's task, 2 in this process.
    """
    if "distributed" in sys.modules:  # a worker has imported it; a plain process need not pay for the import
        from reachplan.planner.study.workers import limit_threads, on_worker

        if on_worker():
            limit_threads(1)
            return 1
    return 2


def _worker_name() -> str:
    return f"{socket.gethostname()}:{os.getpid()}"


def _now() -> str:
    return datetime.now(UTC).replace(microsecond=0).isoformat()


def failed_rows(task: StudyTask, reason: str) -> tuple[StudyRow, ...]:
    """Return the rows recording a failed task: one per requested target (one with target "" when unknown).

    Parameters
    ----------
    task : StudyTask
        The task that failed.
    reason : str
        Why (whitespace collapsed, cut at 500 characters).

    Returns
    -------
    tuple of StudyRow
        Rows with status ``failed`` and every metric None.
    """
    reason = " ".join(reason.split())[:500] or "failed without a message"
    none: dict[str, object] = {f.name: None for f in dataclasses.fields(StudyRow) if str(f.type).endswith("| None")}
    worker, now = _worker_name(), _now()
    return tuple(StudyRow(task.key, task.case.case_id, task.design, t, "failed", reason, worker=worker,
                          finished_utc=now, **none)  # type: ignore[arg-type]
                 for t in (task.targets or ("",)))


#: Scenes this process has loaded, most recently used last (at most ``_SCENE_CACHE_SIZE``).
_SCENES: OrderedDict[tuple[str, int, tuple[str, ...] | None, str], tuple[Scene, StructureSet]] = OrderedDict()
_SCENE_CACHE_SIZE = 4
_SCENE_LOCK = threading.Lock()


def load_scene(case: Case, targets: tuple[str, ...] | None,
               config: PlanConfig) -> tuple[Scene, StructureSet, float]:
    """Return the case's scene and structures from this process's cache, and the seconds spent loading them.

    They are loaded on first use; the seconds are 0 when they were cached.

    The cache key holds the file's modification time, so an edited case is reloaded, and the configuration
    without its designs (a scene does not depend on them).

    Parameters
    ----------
    case : Case
        The case to load.
    targets : tuple of str or None
        Target ROI names; None = every ``Target*`` ROI.
    config : PlanConfig
        The plan configuration (its designs do not matter).

    Returns
    -------
    scene : Scene
        Organs, targets and template pose (LPS mm).
    structures : StructureSet
        The case's structures as read.
    seconds : float, s
        Loading time; 0 when cached.
    """
    from reachplan.imaging.rtstruct import read_rtstruct
    from reachplan.planner.case.scene import build_scene

    t = time.perf_counter()
    key = (str(case.rtstruct), case.rtstruct.stat().st_mtime_ns, targets, repr(dataclasses.replace(config, designs=())))
    with _SCENE_LOCK:  # one load at a time per process; other threads wanting the same case wait for it
        hit = _SCENES.get(key)
        if hit is not None:
            _SCENES.move_to_end(key)
            return (*hit, 0.0)
        structures = read_rtstruct(case.rtstruct, None)
        scene = build_scene(structures, None if targets is None else list(targets), config=config)
        _SCENES[key] = (scene, structures)
        while len(_SCENES) > _SCENE_CACHE_SIZE:
            _SCENES.popitem(last=False)
    return scene, structures, time.perf_counter() - t


def _num(v: float) -> float:
    return round(float(v), 4)


@dataclass(frozen=True)
class DoseOutcome:
    """The dwell-time optimisation of a task's needles.

    Parameters
    ----------
    d90_gy : float or None, Gy
        HR-CTV D90 (per fraction, rounded to 1e-4); None when there is no dose.
    aim_met : bool or None
        Whether the aims were met; None without a dose.
    reason : str
        Why there is no dose ("" when there is).
    """

    d90_gy: float | None
    aim_met: bool | None
    reason: str


def task_dose(result: PlanResult, structures: StructureSet) -> DoseOutcome:
    """Choose one needle per target and optimise their dwell times on the HR-CTV (no export).

    Parameters
    ----------
    result : PlanResult
        The task's plan.
    structures : StructureSet
        The case's structures (the HR-CTV and organs at risk).

    Returns
    -------
    DoseOutcome
        D90 and aims, or the reason the optimisation failed.
    """
    from reachplan.planner.delivery import plan_delivery

    try:
        opt = plan_delivery(result, structures, None, planned_dose=False).optimisation
    except ReachplanError as exc:
        return DoseOutcome(None, None, " ".join(str(exc).split()))
    if not opt.success:
        return DoseOutcome(None, None, opt.reason)
    return DoseOutcome(_num(opt.target.d90_gy), bool(opt.aim_met), "")


def rows_from_result(task: StudyTask, result: PlanResult, scene_s: float, plan_s: float,
                     cpu_s: float, dose: DoseOutcome | None = None) -> tuple[StudyRow, ...]:
    """Return the task's rows (one per target, in ranking order) from a plan result.

    Parameters
    ----------
    task : StudyTask
        The task.
    result : PlanResult
        Its plan.
    scene_s : float, s
        Time spent loading the case (0 when cached).
    plan_s : float, s
        Time planning the task's targets.
    cpu_s : float, s
        CPU time of the whole task.
    dose : DoseOutcome or None
        The dwell-time optimisation; None when the study asks for no dose.

    Returns
    -------
    tuple of StudyRow
        Status ``ok``, numbers rounded to 1e-4.
    """
    rows = []
    worker, now = _worker_name(), _now()
    for target, cands in result.ranking.items():
        st, sr = result.best(target, True), result.best(target, False)
        feas = [c for c in cands if c.feasible]
        reason = "" if feas else (cands[0].reason if cands else "no candidate")
        rows.append(StudyRow(
            task=task.key, case=task.case.case_id, design=task.design, target=target, status="ok", reason=reason,
            reached_steered=st is not None, reached_straight=sr is not None, n_candidates=len(cands),
            n_feasible=len(feas), best_is_steered=bool(feas and feas[0].steered),
            steered_hole=None if st is None else st.hole_id,
            steered_reach_error_mm=None if st is None else _num(st.reach_error_mm),
            steered_clearance_mm=None if st is None else _num(st.clearance_mm),
            steered_peak_tension_n=None if st is None else _num(st.peak_tension_n),
            steered_insertion_depth_mm=None if st is None else _num(st.insertion_depth_mm),
            steered_hole_distance_mm=None if st is None else _num(st.hole_distance_mm),
            steered_model=None if st is None else st.model.label,
            straight_hole=None if sr is None else sr.hole_id,
            straight_reach_error_mm=None if sr is None else _num(sr.reach_error_mm),
            straight_clearance_mm=None if sr is None else _num(sr.clearance_mm),
            straight_insertion_depth_mm=None if sr is None else _num(sr.insertion_depth_mm),
            straight_hole_distance_mm=None if sr is None else _num(sr.hole_distance_mm),
            task_scene_s=_num(scene_s), task_plan_s=_num(plan_s), task_cpu_s=_num(cpu_s),
            task_hrctv_d90_gy=None if dose is None else dose.d90_gy,
            task_dose_aim_met=None if dose is None else dose.aim_met,
            task_dose_reason=None if dose is None else dose.reason, worker=worker,
            finished_utc=now))
    return tuple(rows)


def run_task(task: StudyTask, config: PlanConfig) -> tuple[StudyRow, ...]:
    """Plan one task as ``reachplan plan --no-export`` would and return its rows.

    The ranking, and with ``task.dose`` also the dwell-time optimisation.

    An expected failure (unreadable case, missing ROI, unknown design...) becomes failed rows with the
    reason; anything else propagates (the driver records it as a failure too).

    Parameters
    ----------
    task : StudyTask
        The task.
    config : PlanConfig
        The plan configuration; its designs are replaced by the task's.

    Returns
    -------
    tuple of StudyRow
        One per target.
    """
    from reachplan.planner.case.search import plan

    cpu = time.process_time()
    task_threads()
    try:
        designs = () if task.design == STRAIGHT else (task.design,)
        cfg = dataclasses.replace(config, designs=designs)
        _ = cfg.rod_designs  # a typed error for an unknown preset, before loading the case (plan() reuses them)
        scene, structures, scene_s = load_scene(task.case, task.targets, cfg)
        t = time.perf_counter()
        result = plan(scene, cfg)
        plan_s = time.perf_counter() - t
        dose = task_dose(result, structures) if task.dose else None
        return rows_from_result(task, result, scene_s, plan_s, time.process_time() - cpu, dose)
    except ReachplanError as exc:
        return failed_rows(task, f"{type(exc).__name__}: {exc}")


def _rtstruct_in(folder: Path) -> Path | None:
    """Return the one RT Structure Set directly in ``folder`` (``RS*.dcm`` first, else any RTSTRUCT .dcm), or None."""
    found = sorted(folder.glob("RS*.dcm"))
    if not found:
        from pydicom import dcmread

        for p in sorted(folder.glob("*.dcm")):
            try:
                if dcmread(p, stop_before_pixels=True, specific_tags=["Modality"]).get("Modality") == "RTSTRUCT":
                    found.append(p)
            except Exception:  # any unreadable file is simply not a structure set
                continue
    if len(found) > 1:
        raise StudyError(f"case folder {folder} holds {len(found)} RT Structure Sets "
                             f"({', '.join(p.name for p in found)}); keep one per case folder")
    return found[0] if found else None


def discover_cases(paths: Sequence[Path]) -> tuple[Case, ...]:
    """Find the cases in folders.

    A folder holding an RT Structure Set is a case (named after the folder); a folder without one contributes
    each of its sub-folders that holds one (a cohort folder).

    Parameters
    ----------
    paths : sequence of Path
        Case folders or cohort folders.

    Returns
    -------
    tuple of Case
        In the order found (sub-folders sorted by name).

    Raises
    ------
    StudyError
        A path is missing, holds no case, or two cases have the same folder name.
    """
    cases: list[Case] = []
    for path in (Path(p) for p in paths):
        if not path.is_dir():
            raise StudyError(f"case folder {path} does not exist; give folders holding an RS*.dcm file")
        rs = _rtstruct_in(path)
        if rs is not None:
            cases.append(Case(path.resolve().name, rs.resolve()))
            continue
        sub = [(d, _rtstruct_in(d)) for d in sorted(path.iterdir()) if d.is_dir() and not d.name.startswith(".")]
        found = [Case(d.resolve().name, r.resolve()) for d, r in sub if r is not None]
        if not found:
            raise StudyError(f"{path} holds no RT Structure Set, nor do its sub-folders; give case folders")
        cases += found
    ids = [c.case_id for c in cases]
    dup = sorted({i for i in ids if ids.count(i) > 1})
    if dup:
        raise StudyError(f"two case folders are both called {dup[0]!r}; case folder names must be unique")
    return tuple(cases)
