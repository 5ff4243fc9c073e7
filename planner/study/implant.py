"""Straight against steered implants over a cohort of clinical cases: needles saved and HR-CTV D90 gained by steering.

The cohort is seeds of the built-in clinical case (:func:`reachplan.imaging.clinical.clinical_case`). One task per
case: the worker builds the case in memory (no DICOM is written), its scene and planning structures on the case's
image grid, and both implant arms with their Pareto curves (:func:`reachplan.planner.implant.case.plan_implants`, as
``reachplan demo`` does: the tandem is an intracavitary channel and an organ to keep needles off). Tasks run on
Dask as the design study's do (:func:`reachplan.planner.study.run_study`: a loopback ``LocalCluster`` of worker
processes, a given scheduler, or this process with ``workers=0``).

Results stream to ``OUT/parts/<case>.json`` (the case's row and both arms' plan.json ``implant`` section),
written atomically as cases finish, so a stopped study resumes where it stopped. A case that fails, or one of
whose arms has no implant, is a row with status ``failed`` and the reason; the study goes on. At the end:
``cases.csv`` (one row per case), ``summary.json`` and ``summary.png``.

Confidence intervals are paired Student t-intervals on the per-case differences (steered minus straight,
cases where both arms have an implant): ``mean ± t(1 - α/2, n - 1) · s / √n`` with ``s`` the sample standard
deviation (ddof 1). Sources: NIST/SEMATECH e-Handbook of Statistical Methods, section 1.3.5.2 "Confidence
Limits for the Mean"; J. A. Rice, *Mathematical Statistics and Data Analysis*, 3rd ed. (2007), section 11.3
"Comparing Paired Samples" (the paired t-interval is the one-sample interval on the differences). The
interval assumes roughly normal differences; with few cases it is wider than a percentile bootstrap and,
unlike it, keeps its nominal coverage for small cohorts.
"""

from __future__ import annotations

import dataclasses
import io
import json
import os
import socket
import time
from collections.abc import Callable, Iterator, Mapping, Sequence
from contextlib import ExitStack
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from reachplan import ReachplanError
from reachplan.imaging.files import atomic_write_bytes, atomic_write_json
from reachplan.planner.case.config import DEFAULT_AIR_KERMA_U, PlanConfig
from reachplan.planner.errors import StudyError
from reachplan.planner.study.cost import cost_json
from reachplan.planner.study.designs import designs_json, part_design_rows, write_designs

if TYPE_CHECKING:
    from reachplan.planner.implant.case import DesignArms
    from reachplan.planner.implant.settings import ImplantSettings

ARMS = ("straight", "steered")
PARTS = "parts"
CASES_CSV = "cases.csv"
SUMMARY_JSON = "summary.json"
SUMMARY_PNG = "summary.png"
MANIFEST_VERSION = 2  # 2: one straight + steered arm per stylet design (1: one arm screening every design)


# ------------------------------------------------------------------------------------------------ statistics

@dataclass(frozen=True)
class PairedStat:
    """Mean of a paired difference over the cases and its two-sided t confidence interval (same unit).

    Parameters
    ----------
    mean : float or None, same unit as the differences
        Mean difference; None when no case gives one.
    low, high : float or None
        Interval bounds; None when fewer than two cases give a difference (no spread to estimate).
    n : int
        Cases that give a difference.
    level : float
        The interval's confidence level, in (0, 1).
    """

    mean: float | None
    low: float | None
    high: float | None
    n: int
    level: float


def t_interval(diffs: Sequence[float] | np.ndarray, level: float = 0.95) -> PairedStat:
    """Return the mean of the paired differences ``diffs`` and its Student t confidence interval.

    ``mean ± t(1 - α/2, n - 1) · s / √n`` with ``α = 1 - level`` and ``s`` the sample standard deviation
    (NIST/SEMATECH e-Handbook of Statistical Methods, 1.3.5.2; Rice 2007, 11.3).

    Parameters
    ----------
    diffs : (n,) float
        Per-case differences (steered minus straight), in their own unit.
    level : float
        Confidence level, in (0, 1).

    Returns
    -------
    PairedStat
        Mean and interval, in the unit of ``diffs``.

    Raises
    ------
    StudyError
        ``level`` outside (0, 1) or a difference that is not finite.
    """
    from scipy.stats import t as student_t

    if not 0.0 < level < 1.0:
        raise StudyError(f"confidence level must be in (0, 1), got {level}")
    d = np.asarray(diffs, dtype=float).ravel()
    if not np.all(np.isfinite(d)):
        raise StudyError("a paired difference is not finite; check the cases' results")
    n = len(d)
    if n == 0:
        return PairedStat(None, None, None, 0, level)
    mean = float(d.mean())
    if n == 1:
        return PairedStat(mean, None, None, 1, level)
    half = float(student_t.ppf(0.5 + level / 2.0, n - 1)) * float(d.std(ddof=1)) / np.sqrt(n)
    return PairedStat(mean, mean - half, mean + half, n, level)


@dataclass(frozen=True)
class ImplantCohortSummary:
    """Needles saved and D90 gained by steering over a cohort.

    Parameters
    ----------
    needles_saved : PairedStat
        Straight-arm needles minus steered-arm needles of each case's chosen implant, over the cases where both
        arms have an implant.
    d90_gained_gy : PairedStat
        Steered minus straight HR-CTV D90 (EQD2, Gy), over the same cases.
    aims_met_straight, aims_met_steered : int
        Cases whose chosen implant meets every aim, per arm (an arm without an implant does not).
    n_cases : int
        All cases.
    n_paired : int
        Cases with both arms planned.
    """

    needles_saved: PairedStat
    d90_gained_gy: PairedStat
    aims_met_straight: int
    aims_met_steered: int
    n_cases: int
    n_paired: int


def summarise_implants(cases: Sequence[Mapping[str, object]], level: float = 0.95) -> ImplantCohortSummary:
    """Summarise a cohort from each case's plan.json ``implant`` section (paired t-intervals, see the module).

    Parameters
    ----------
    cases : sequence of mapping
        One plan.json ``implant`` section per case: ``straight`` and ``steered`` with ``n_needles``,
        ``hrctv_d90_eqd2_gy`` (Gy) and ``aims_met``.
    level : float
        Confidence level of the intervals.

    Returns
    -------
    ImplantCohortSummary
        Needles saved, D90 gained and aims met.

    Raises
    ------
    StudyError
        No case, or a case whose arms have no chosen implant.
    """
    if not cases:
        raise StudyError("no case to summarise: give at least one plan.json implant section")
    for k, case in enumerate(cases):
        if not all("n_needles" in _arm(case, a) for a in ARMS):
            raise StudyError(f"case {k + 1}: both arms need a chosen implant (n_needles); plan it again")
    return _summary([_arm_values(c) for c in cases], level)


def _arm_values(implant: Mapping[str, object]) -> dict[str, Any]:
    """Needles, D90 and aims met of each arm of a plan.json ``implant`` section (None where an arm has no plan)."""
    out: dict[str, Any] = {}
    for arm in ARMS:
        a = _arm(implant, arm)
        planned = "n_needles" in a
        out[f"{arm}_needles"] = int(a["n_needles"]) if planned else None
        out[f"{arm}_hrctv_d90_eqd2_gy"] = float(a["hrctv_d90_eqd2_gy"]) if planned else None
        out[f"{arm}_aims_met"] = bool(a.get("aims_met")) if planned else False
    return out


def _arm(implant: Mapping[str, object], arm: str) -> Mapping[str, Any]:
    a = implant.get(arm)
    return a if isinstance(a, Mapping) else {}


def _summary(rows: Sequence[Mapping[str, Any]], level: float) -> ImplantCohortSummary:
    paired = [r for r in rows if all(r[f"{a}_needles"] is not None for a in ARMS)]
    saved = [r["straight_needles"] - r["steered_needles"] for r in paired]
    gained = [r["steered_hrctv_d90_eqd2_gy"] - r["straight_hrctv_d90_eqd2_gy"] for r in paired]
    return ImplantCohortSummary(t_interval(saved, level), t_interval(gained, level),
                                sum(bool(r["straight_aims_met"]) for r in rows),
                                sum(bool(r["steered_aims_met"]) for r in rows), len(rows), len(paired))


# ------------------------------------------------------------------------------------------------ one case

@dataclass(frozen=True)
class ImplantCase:
    """One task: the clinical case of ``seed`` (``key`` names it and its part file).

    Parameters
    ----------
    seed : int
        Seed of :func:`reachplan.imaging.clinical.clinical_case`.
    """

    seed: int

    @property
    def key(self) -> str:
        """Return ``clinical_<seed>`` (the case's default id)."""
        return f"clinical_{self.seed}"


@dataclass(frozen=True)
class ImplantStudySpec:
    """What an implant study plans: both arms on the clinical case of each seed.

    Parameters
    ----------
    seeds : tuple of int
        One case per seed, each once.
    config : PlanConfig
        The plan configuration (schedule family, template); its ``designs`` (at least one) are compared: a
        straight + steered arm each, the straight arm shared (:mod:`reachplan.planner.study.designs`); the first
        design's arm is the case's ``steered`` arm.
    settings : ImplantSettings or None
        The implant settings (None: the defaults).
    source : str
        Name of the TG-43 source data.
    modality : str
        The case's image series (``CT`` or ``MR``; the planning grid is its grid).

    Raises
    ------
    ValueError
        No seed or a repeated one, or no stylet design.
    """

    seeds: tuple[int, ...]
    config: PlanConfig = field(default_factory=PlanConfig)
    settings: ImplantSettings | None = None
    source: str = "gammamed_plus_hdr"
    modality: str = "CT"

    def __post_init__(self) -> None:
        if not self.seeds or len(set(self.seeds)) != len(self.seeds):
            raise ValueError("an implant study needs at least one case, each seed once")
        if not self.config.designs:
            raise ValueError("the steered arm needs at least one stylet design")

    def tasks(self) -> tuple[ImplantCase, ...]:
        """One task per seed, in seed order.

        Returns
        -------
        tuple of ImplantCase
            The tasks.
        """
        return tuple(ImplantCase(s) for s in self.seeds)

    def manifest(self) -> dict[str, Any]:
        """Return what identifies the study's results (JSON-ready); a resumed study must match it.

        Returns
        -------
        dict of str to JSON value
            Version, kind, seeds, configuration, settings, source and modality.
        """
        doc = {"version": MANIFEST_VERSION, "kind": "implant", "seeds": list(self.seeds),
               "config": dataclasses.asdict(self.config),
               "settings": None if self.settings is None else dataclasses.asdict(self.settings),
               "source": self.source, "modality": self.modality}
        return dict(json.loads(json.dumps(doc)))


@dataclass(frozen=True)
class ImplantRow:
    """One case of an implant study (a row of ``cases.csv``).

    ``status`` is ``ok`` (both arms have a chosen implant) or ``failed`` (``reason`` says why: the error that
    stopped the case, or each arm without an implant and its reason). Doses are EQD2 totals, Gy.

    Parameters
    ----------
    case : str
        The case's key (``clinical_<seed>``).
    seed : int
        Its seed.
    status, reason : str
        ``ok`` or ``failed``, and why.
    straight_needles, steered_needles : int or None
        Needles of each arm's chosen implant; None without one.
    straight_aims_met, steered_aims_met : bool
        Whether it meets every aim.
    straight_hrctv_d90_eqd2_gy, steered_hrctv_d90_eqd2_gy : float or None, Gy
        HR-CTV D90.
    straight_hrctv_d98_eqd2_gy, steered_hrctv_d98_eqd2_gy : float or None, Gy
        HR-CTV D98.
    straight_oar_d2cc_eqd2_gy, steered_oar_d2cc_eqd2_gy : str
        Organ D2cm³ (Gy) as a JSON object by organ; "" without.
    straight_candidates, steered_candidates : int or None
        Candidate channels of each arm.
    straight_note, steered_note : str
        The arm's own note (e.g. no budget meets every aim).
    needles_saved : int or None
        Straight minus steered needles, when both arms have an implant.
    d90_gained_gy : float or None, Gy
        Steered minus straight HR-CTV D90, when both arms have an implant.
    seconds, cpu_seconds : float or None, s
        Wall and CPU time of the whole case (build, scene, both arms).
    worker : str
        ``host:pid`` of the process that planned it.

    Raises
    ------
    ValueError
        A status other than ``ok`` or ``failed``.
    """

    case: str
    seed: int
    status: str
    reason: str = ""
    straight_needles: int | None = None
    steered_needles: int | None = None
    straight_aims_met: bool = False
    steered_aims_met: bool = False
    straight_hrctv_d90_eqd2_gy: float | None = None
    steered_hrctv_d90_eqd2_gy: float | None = None
    straight_hrctv_d98_eqd2_gy: float | None = None
    steered_hrctv_d98_eqd2_gy: float | None = None
    straight_oar_d2cc_eqd2_gy: str = ""
    steered_oar_d2cc_eqd2_gy: str = ""
    straight_candidates: int | None = None
    steered_candidates: int | None = None
    straight_note: str = ""
    steered_note: str = ""
    needles_saved: int | None = None
    d90_gained_gy: float | None = None
    seconds: float | None = None
    cpu_seconds: float | None = None
    worker: str = ""

    def __post_init__(self) -> None:
        if self.status not in ("ok", "failed"):
            raise ValueError(f"row status must be 'ok' or 'failed', got {self.status!r}")


def _one_line(text: str) -> str:
    return " ".join(text.split())[:500] or "failed without a message"


def failed_case(task: ImplantCase, reason: str) -> dict[str, Any]:
    """Return the part of a case that failed: its row (status ``failed``, the reason) and no implant.

    Parameters
    ----------
    task : ImplantCase
        The case.
    reason : str
        Why it failed (whitespace collapsed, cut at 500 characters).

    Returns
    -------
    dict of str to object
        ``{"row": ImplantRow as a dict, "implant": None}``.
    """
    row = ImplantRow(task.key, task.seed, "failed", _one_line(reason), worker=f"{socket.gethostname()}:{os.getpid()}")
    return {"row": dataclasses.asdict(row), "implant": None}


def case_row(task: ImplantCase, implant: Mapping[str, Any], seconds: float | None = None,
             cpu_seconds: float | None = None) -> ImplantRow:
    """Return the row of a case from its plan.json ``implant`` section (both arms).

    Parameters
    ----------
    task : ImplantCase
        The case.
    implant : mapping
        Its plan.json ``implant`` section.
    seconds : float or None, s
        Wall time of the case.
    cpu_seconds : float or None, s
        CPU time of the case.

    Returns
    -------
    ImplantRow
        Status ``failed`` when an arm has no implant.
    """
    values = _arm_values(implant)
    extra: dict[str, Any] = {}
    missing = []
    for arm in ARMS:
        a = _arm(implant, arm)
        note = _one_line(str(a.get("reason", ""))) if a.get("reason") else ""
        if values[f"{arm}_needles"] is None:
            missing.append(f"{arm} arm: {note or 'no implant'}")
        oar = a.get("oar_d2cc_eqd2_gy")
        extra.update({f"{arm}_hrctv_d98_eqd2_gy": a.get("hrctv_d98_eqd2_gy"),
                      f"{arm}_oar_d2cc_eqd2_gy": json.dumps(oar, sort_keys=True) if oar else "",
                      f"{arm}_candidates": a.get("candidates"), f"{arm}_note": note})
    paired = not missing
    return ImplantRow(
        task.key, task.seed, "ok" if paired else "failed", "; ".join(missing), **values, **extra,
        needles_saved=values["straight_needles"] - values["steered_needles"] if paired else None,
        d90_gained_gy=round(values["steered_hrctv_d90_eqd2_gy"] - values["straight_hrctv_d90_eqd2_gy"], 3)
        if paired else None,
        seconds=None if seconds is None else round(seconds, 3),
        cpu_seconds=None if cpu_seconds is None else round(cpu_seconds, 3),
        worker=f"{socket.gethostname()}:{os.getpid()}")


def plan_case(seed: int, spec: ImplantStudySpec, threads: int = 2) -> tuple[DesignArms, dict[str, float]]:
    """Build the clinical case of ``seed`` in memory and plan its implant arms on it (as ``reachplan demo``).

    The straight arm once and one straight + steered arm per design of ``spec.config.designs``
    (:func:`~reachplan.planner.implant.case.plan_design_arms`), with the GTV_res and the protocol's dose points as
    the demo plans them. Organs whose contours an earlier case of this process
    had (the generated cases' pelvic bone) are not meshed again (:func:`~reachplan.planner.case.scene.build_scene`
    ``reuse``).

    Parameters
    ----------
    seed : int
        Seed of :func:`~reachplan.imaging.clinical.clinical_case`.
    spec : ImplantStudySpec
        Configuration, settings, source and modality.
    threads : int
        Arms planned at once (1 on a study worker: one core each).

    Returns
    -------
    arms : DesignArms
        The straight arm and each design's arm (by design name), with their Pareto curves.
    cpu_s : dict of str to float
        CPU time of this process per stage, s: ``case`` (the anatomy and its contours), ``scene`` (meshes, organs,
        template pose, planning masks), then :class:`DesignArms`'s ``candidates``, ``arms`` and ``check``.
    """
    from reachplan.imaging.clinical import clinical_case, image_grid, structure_set
    from reachplan.planner.case.scene import build_scene
    from reachplan.planner.delivery import case_point_limits
    from reachplan.planner.dose.aims import Aims
    from reachplan.planner.dose.structures import gtv_structure, planning_structures
    from reachplan.planner.implant.case import plan_design_arms
    from reachplan.planner.lookup import get_source

    c0 = time.process_time()
    case = clinical_case(seed, modality=spec.modality)
    structures = structure_set(case.spec)
    grid = image_grid(case.spec)
    c1 = time.process_time()
    targets = [n for n in structures.names if n.casefold().startswith("target")]
    scene = build_scene(structures, targets, grid=grid, config=spec.config, reuse=True)
    config = dataclasses.replace(spec.config, oar_names=tuple(o.name for o in scene.organs))
    planning = planning_structures(structures, grid, "HR-CTV", config.oar_names, scene.applicators)
    c2 = time.process_time()
    arms = plan_design_arms(scene, planning, config, get_source(spec.source), DEFAULT_AIR_KERMA_U, spec.settings,
                            gtv_structure(structures, planning.grid), steered={d: (d,) for d in spec.config.designs},
                            threads=threads, points=case_point_limits(structures, Aims()))
    return arms, {"case": round(c1 - c0, 3), "scene": round(c2 - c1, 3), **arms.cpu_s}


def run_case(task: ImplantCase, spec: ImplantStudySpec) -> dict[str, Any]:
    """Plan one case (the worker's task).

    An expected failure (any :class:`ReachplanError`, e.g. no target volume) becomes the failed row; anything
    else propagates and is recorded by the study the same way. In a Dask worker the case runs on one thread
    (:func:`~reachplan.planner.study.tasks.task_threads`).

    Parameters
    ----------
    task : ImplantCase
        The case.
    spec : ImplantStudySpec
        The study.

    Returns
    -------
    dict of str to object
        ``{"row": ImplantRow as a dict, "implant": plan.json's implant section or None}`` (the first design's arm
        is its ``steered``), ``designs``: each further design's arm section by design, and ``cpu_s``: the CPU time
        per stage (:func:`plan_case`).
    """
    from reachplan.planner.implant.case import ImplantComparison
    from reachplan.planner.study.tasks import task_threads

    t, cpu = time.perf_counter(), time.process_time()
    try:
        arms, stages = plan_case(task.seed, spec, task_threads())
    except ReachplanError as exc:
        return failed_case(task, f"{type(exc).__name__}: {exc}")
    first, *others = spec.config.designs
    implant = ImplantComparison(arms.straight, arms.steered[first], arms.candidates, arms.seconds).to_json()
    row = case_row(task, implant, time.perf_counter() - t, time.process_time() - cpu)
    return {"row": dataclasses.asdict(row), "implant": implant,
            "designs": {d: arms.steered[d].to_json() for d in others}, "cpu_s": stages}


# ------------------------------------------------------------------------------------------------ the study

@dataclass(frozen=True, eq=False)
class ImplantStudyResult:
    """A finished implant study.

    Parameters
    ----------
    out : Path
        The folder holding ``cases.csv``, ``summary.json``, ``summary.png`` and ``parts/``.
    rows : tuple of ImplantRow
        One per case, in seed order.
    summary : ImplantCohortSummary
        Needles saved, D90 gained, aims met.
    n_resumed : int
        Cases already done before this run.
    wall_s : float, s
        Wall time of this run.
    doc : dict
        ``summary.json`` as written (with ``cost`` and ``designs``).
    """

    out: Path
    rows: tuple[ImplantRow, ...]
    summary: ImplantCohortSummary
    n_resumed: int
    wall_s: float
    doc: dict[str, Any] = field(default_factory=dict)


CaseFn = Callable[[ImplantCase, ImplantStudySpec], dict[str, Any]]


def run_implant_study(spec: ImplantStudySpec, out: Path, *, scheduler: str | None = None,
                      workers: int | None = None, client: Any = None, retry_failed: bool = False,
                      level: float = 0.95, quiet: bool = True, task_fn: CaseFn = run_case,
                      worker_setup: Any = None) -> ImplantStudyResult:
    """Run (or resume) an implant study into the folder ``out``: ``cases.csv``, ``summary.json``, ``summary.png``.

    Parameters
    ----------
    spec : ImplantStudySpec
        Seeds, plan configuration, implant settings, source and modality.
    out : Path
        The study's folder: new, empty, or holding this study (then it resumes).
    scheduler : str or None
        A Dask scheduler's address; None starts a loopback cluster of worker processes.
    workers : int or None
        Worker processes of that cluster (one per CPU by default); 0 plans every case in this process.
    client : distributed.Client or None
        A client already connected; then ``scheduler`` and ``workers`` are not used.
    retry_failed : bool
        Plan again the cases a previous run recorded as failed.
    level : float
        Confidence level of the intervals.
    quiet : bool
        No progress bar.
    task_fn : callable (ImplantCase, ImplantStudySpec) -> dict
        The function a worker runs per case (default :func:`run_case`; must be importable by workers).
    worker_setup : WorkerSetup or None
        How Dask workers are set up (:func:`reachplan.planner.study.setup_workers`); None: one thread per numerical
        library and every kernel loaded.

    Returns
    -------
    ImplantStudyResult
        Rows, summary and times.

    Raises
    ------
    StudyError
        ``out`` holds another study or unrelated files; Dask is missing.
    """
    from tqdm import tqdm

    from reachplan.planner.study import check_manifest, dask_client, dask_results, serial_results
    from reachplan.planner.study.summary import write_dataclass_csv

    out = Path(out)
    t0 = time.perf_counter()
    check_manifest(out, spec.manifest())
    tasks = spec.tasks()
    done = _read_parts(out)
    todo = [t for t in tasks if t.key not in done or (retry_failed and done[t.key]["row"]["status"] == "failed")]
    with ExitStack() as stack:
        results: Iterator[tuple[ImplantCase, dict[str, Any]]]
        if not todo:
            results = iter(())
        elif client is None and scheduler is None and workers == 0:
            results = serial_results(todo, spec, task_fn, failed_case)
        else:
            if client is None:
                client = stack.enter_context(dask_client(scheduler, workers, len(todo)))
            results = dask_results(client, todo, spec, task_fn, failed_case, worker_setup)
        bar = stack.enter_context(tqdm(total=len(todo), desc="implant cases", unit="case", disable=quiet or not todo))
        for task, part in results:
            atomic_write_json(out / PARTS / f"{task.key}.json", part)
            done[task.key] = part
            bar.update()
    rows = tuple(ImplantRow(**done[t.key]["row"]) for t in tasks)
    summary = _summary([dataclasses.asdict(r) for r in rows], level)
    write_dataclass_csv(ImplantRow, rows, out / CASES_CSV)
    design_rows = [r for t in tasks for r in part_design_rows(t.key, t.seed, done[t.key], spec.config.designs)]
    write_designs(design_rows, out)
    wall = time.perf_counter() - t0
    doc = {**summary_json(summary, rows, wall), "cost": cost_json([done[t.key] for t in tasks]),
           "designs": designs_json(design_rows, spec.config.designs, t_interval, level)}
    atomic_write_json(out / SUMMARY_JSON, doc)
    summary_figure(rows, summary, out / SUMMARY_PNG)
    return ImplantStudyResult(out, rows, summary, len(tasks) - len(todo), wall, doc)


def _read_parts(out: Path) -> dict[str, dict[str, Any]]:
    """Case key -> finished part (row and implant) of every case already in ``out/parts``."""
    folder = out / PARTS
    if not folder.is_dir():
        return {}
    parts = {}
    for p in sorted(folder.glob("*.json")):
        if p.name.startswith("."):
            continue
        try:
            parts[p.stem] = json.loads(p.read_text(encoding="utf-8"))
        except (OSError, ValueError):
            raise StudyError(f"part file {p} cannot be read; delete it to plan that case again") from None
    return parts


def _stat_json(s: PairedStat) -> dict[str, Any]:
    def r(v: float | None) -> float | None:
        return None if v is None else round(v, 4)

    return {"mean": r(s.mean), "ci_low": r(s.low), "ci_high": r(s.high), "n": s.n}


def summary_json(summary: ImplantCohortSummary, rows: Sequence[ImplantRow], wall_s: float) -> dict[str, Any]:
    """Return ``summary.json``: paired differences with their intervals, aims met per arm, failed cases.

    Parameters
    ----------
    summary : ImplantCohortSummary
        The cohort's summary.
    rows : sequence of ImplantRow
        The cases.
    wall_s : float, s
        Wall time of the run.

    Returns
    -------
    dict of str to JSON value
        Numbers rounded (4 decimals for the statistics, 3 for seconds).
    """
    secs = [r.seconds for r in rows if r.seconds is not None]
    return {
        "cases": summary.n_cases, "paired_cases": summary.n_paired,
        "interval": f"two-sided {100 * summary.needles_saved.level:g} % paired Student t-interval on the per-case "
                    "differences (NIST/SEMATECH e-Handbook 1.3.5.2; Rice 2007, 11.3)",
        "needles_saved": _stat_json(summary.needles_saved),
        "d90_gained_gy": _stat_json(summary.d90_gained_gy),
        "aims_met": {"straight": summary.aims_met_straight, "steered": summary.aims_met_steered},
        "failed": {r.case: r.reason for r in rows if r.status == "failed"},
        "mean_case_seconds": round(float(np.mean(secs)), 3) if secs else None,
        "wall_s": round(wall_s, 3),
    }


def format_summary(summary: ImplantCohortSummary, rows: Sequence[ImplantRow]) -> str:
    """Return a plain-text table: one line per case, then the paired differences with their intervals.

    Parameters
    ----------
    summary : ImplantCohortSummary
        Paired differences and aims met, printed last.
    rows : sequence of ImplantRow
        One line each.

    Returns
    -------
    str
        The table (D90 in Gy EQD2).
    """
    def v(x: object, fmt: str = "") -> str:
        return "-" if x is None else format(x, fmt)

    lines = [f"{'case':<14} {'needles':>11} {'D90 Gy (EQD2)':>15} {'aims met':>11}  note",
             f"{'':<14} {'strt':>5} {'steer':>5} {'strt':>7} {'steer':>7} {'strt':>5} {'steer':>5}"]
    for r in rows:
        lines.append(f"{r.case:<14} {v(r.straight_needles):>5} {v(r.steered_needles):>5} "
                     f"{v(r.straight_hrctv_d90_eqd2_gy, '.1f'):>7} {v(r.steered_hrctv_d90_eqd2_gy, '.1f'):>7} "
                     f"{'yes' if r.straight_aims_met else 'no':>5} {'yes' if r.steered_aims_met else 'no':>5}  "
                     f"{r.reason[:60]}")

    def stat(name: str, s: PairedStat, unit: str) -> str:
        if s.mean is None:
            return f"{name}: no case with both arms planned"
        ci = "CI needs 2 cases" if s.low is None else f"{100 * s.level:g} % CI {s.low:+.2f} .. {s.high:+.2f}"
        return f"{name}: mean {s.mean:+.2f}{unit} ({ci}; {s.n} cases, paired t)"

    lines += ["", stat("needles saved by steering", summary.needles_saved, ""),
              stat("D90 gained by steering", summary.d90_gained_gy, " Gy"),
              f"aims met: straight {summary.aims_met_straight}/{summary.n_cases}, "
              f"steered {summary.aims_met_steered}/{summary.n_cases}"]
    return "\n".join(lines)


def summary_figure(rows: Sequence[ImplantRow], summary: ImplantCohortSummary, path: Path) -> None:
    """Needles and D90 of each arm per case (lines join a case's arms), and the mean differences with their CIs.

    Parameters
    ----------
    rows : sequence of ImplantRow
        The cases.
    summary : ImplantCohortSummary
        The cohort's summary.
    path : Path
        The PNG file to write (atomically).
    """
    from matplotlib.figure import Figure

    fig = Figure(figsize=(12.0, 4.0), layout="constrained")
    ax_n, ax_d, ax_ns, ax_dg = fig.subplots(1, 4)
    for ax, col, label in ((ax_n, "needles", "needles in the chosen implant"),
                           (ax_d, "hrctv_d90_eqd2_gy", "HR-CTV D90 (Gy EQD2)")):
        for k, r in enumerate(rows):
            ys = [getattr(r, f"{a}_{col}") for a in ARMS]
            if any(y is None for y in ys):
                continue
            dx = 0.2 * (k / max(len(rows) - 1, 1) - 0.5)  # spread the cases apart: equal counts would hide each other
            ax.plot([dx, 1 + dx], ys, "-", color="0.6", lw=0.8)
            for x, a in enumerate(ARMS):
                ax.plot([x + dx], [ys[x]], "o", color=f"C{x}",
                        mfc=f"C{x}" if getattr(r, f"{a}_aims_met") else "white")
        ax.set_xticks([0, 1], list(ARMS))
        ax.set_xlim(-0.4, 1.4)
        ax.set_ylabel(label)
    ax_n.yaxis.get_major_locator().set_params(integer=True)
    ax_n.set_title("per case (filled: aims met)", fontsize=9)
    ax_d.axhline(85.0, color="grey", lw=0.8, ls="--")
    ax_d.set_title("EMBRACE II aim D90 >= 85 Gy (dashed)", fontsize=9)
    pct = f"{100 * summary.needles_saved.level:g} %"
    for ax, col, st, label in ((ax_ns, "needles_saved", summary.needles_saved, "needles saved by steering"),
                               (ax_dg, "d90_gained_gy", summary.d90_gained_gy, "D90 gained by steering (Gy)")):
        diffs = [getattr(r, col) for r in rows if getattr(r, col) is not None]
        ax.plot(np.linspace(-0.15, 0.15, len(diffs)) if len(diffs) > 1 else [0.0] * len(diffs), diffs, "o",
                color="0.5", ms=4, label="cases")
        if st.mean is not None:
            err = None if st.low is None or st.high is None else [[st.mean - st.low], [st.high - st.mean]]
            ax.errorbar([0.45], [st.mean], yerr=err, fmt="s", color="C2", capsize=6, label=f"mean, {pct} CI")
        ax.axhline(0.0, color="grey", lw=0.8)
        ax.set_xticks([])
        ax.set_xlim(-0.5, 0.9)
        ax.set_ylabel(label)
        ax.legend(fontsize=7, loc="best")
    ax_ns.yaxis.get_major_locator().set_params(integer=True)
    ax_ns.set_title(f"paired t-interval, {summary.n_paired} of {summary.n_cases} cases", fontsize=9)
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110)
    atomic_write_bytes(path, buf.getvalue())
