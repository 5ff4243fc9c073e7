"""Benchmark: design-study throughput on 1 and 2 Dask worker processes, and a cohort-scale estimate.

Runs one small study (``--cases`` phantom variants x ``--designs`` x ``--targets``, the default schedule family,
as ``reachplan study`` runs it) three ways: in this process (the reference rows), on a local Dask cluster of 1
worker process and of 2 worker processes (clusters started before the clock starts; each worker's first-task
warm-up, i.e. imports and shape banks, is inside the timing). Checks the three give the same rows, reports
the speed-up of 2 workers over 1, and estimates from the measured per-target planning cost, per-case loading
cost and per-worker warm-up the wall time of a study of ``--est-cases`` patients x ``--est-designs`` designs x
``--est-targets`` targets on ``--est-workers`` workers, by simulating Dask's dynamic assignment (each task
to the first free worker in case-major order; a worker loads a case the first time it runs one of its tasks).

Run: ``reachplan bench study --out DIR [--quick] [--cases N] [--targets N] [--designs N] [--install]``. Writes
``study_runs.csv``, ``study_estimate.csv`` and ``study_benchmark.png`` under ``--out`` (with the cohort and the
three studies' folders); ``--install`` copies the three results to ``docs/``. ``--quick``: 2 cases x 1 design x
1 target, one run per cluster size (the speed-up is then noise: a smoke run).
"""

from __future__ import annotations

import argparse
import itertools
import os
import shutil
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from matplotlib.figure import Figure

from reachplan.planner.bench.common import BenchError, settings, write_csv, write_png
from reachplan.planner.case.config import PlanConfig
from reachplan.planner.study import StudySpec, discover_cases, run_study
from reachplan.planner.study.cohort import make_cohort

DESIGNS = ("15ga-30j-tip", "13ga-20j-tip", "15ga-20j-mid")
TARGETS = ("Target_65_000", "Target_65_120", "Target_80_090", "Target_80_210", "Target_65_240", "Target_80_330")
RUN_COLUMNS = ["task_scene_s", "task_plan_s", "task_cpu_s", "worker", "finished_utc"]
INSTALLS = {name: f"docs/{name}" for name in ("study_runs.csv", "study_estimate.csv", "study_benchmark.png")}
RUNS_HEADER = ("engine", "workers", "tasks", "rows", "wall_s", "cluster_start_s", "load_avg_1min", "cpu_utilisation",
               "same_rows_as_in_process")


@dataclass(frozen=True)
class StudySettings:
    """What the study benchmark measures and estimates.

    Every field but ``draws`` has a command-line option of its name (``--est-cases`` for ``est_cases``).

    Parameters
    ----------
    cases : int
        Phantom cases of the measured study.
    targets : int
        The first ``targets`` of :data:`TARGETS`.
    designs : int
        The first ``designs`` of :data:`DESIGNS`.
    repeat : int
        Alternating 1- and 2-worker runs (best kept).
    est_cases, est_designs, est_targets, est_workers : int
        The estimated study: patients, designs, targets and workers.
    draws : int
        Simulated draws of the estimate.
    """

    cases: int = 4
    targets: int = 4
    designs: int = 3
    repeat: int = 2
    est_cases: int = 100
    est_designs: int = 7
    est_targets: int = 10
    est_workers: int = 32
    draws: int = 200


QUICK = StudySettings(cases=2, targets=1, designs=1, repeat=1, draws=50)


@dataclass(frozen=True)
class StudyRun:
    """One timed run of the study.

    Parameters
    ----------
    engine : str
        ``in-process`` or ``LocalCluster``.
    workers : int
        Worker processes; 0 is the in-process reference.
    wall_s : float, s
        Wall time of the study.
    cluster_start_s : float, s
        Time to start the cluster (0 in process).
    load_avg_1min : float
        1-minute load average after the run.
    cpu_utilisation : float
        CPU seconds the tasks got / (workers x wall seconds).
    same_rows : bool
        The rows equal the in-process run's (timings and workers aside).
    """

    engine: str
    workers: int
    wall_s: float
    cluster_start_s: float
    load_avg_1min: float
    cpu_utilisation: float
    same_rows: bool


def _cluster_run(spec: StudySpec, out: Path, workers: int) -> tuple[Any, float, float]:
    """Run the study on a fresh loopback LocalCluster of ``workers`` processes: (result, wall s, start s)."""
    from distributed import Client, LocalCluster

    t0 = time.perf_counter()
    with LocalCluster(n_workers=workers, threads_per_worker=1, processes=True, host="127.0.0.1",
                      dashboard_address=None) as cluster, Client(cluster) as client:
        client.wait_for_workers(workers)
        start_s = time.perf_counter() - t0
        t1 = time.perf_counter()
        res = run_study(spec, out, client=client)
        return res, time.perf_counter() - t1, start_s


def _utilisation(table: Any, workers: int, wall_s: float) -> float:
    """CPU seconds the tasks got / (workers x wall seconds): 1 = every worker computing all the time."""
    tasks = {r["task"]: r["task_cpu_s"] for r in table.to_pylist()}
    return float(sum(tasks.values())) / (workers * wall_s)


def simulate(task_costs_s: np.ndarray, scene_s: float, n_cases: int, workers: int, warmup_s: float,
             cache: int = 4) -> float:
    """Simulate the makespan of case-major tasks given in order to the first free worker.

    Parameters
    ----------
    task_costs_s : (n_cases * designs,) float, s
        Cost of each task, case-major.
    scene_s : float, s
        What a worker pays to load a case not among its last ``cache`` cases.
    n_cases : int
        Cases of the study.
    workers : int
        Workers.
    warmup_s : float, s
        Each worker's start-up, paid once.
    cache : int
        Cases a worker keeps loaded.

    Returns
    -------
    float, s
        The makespan.
    """
    per_case = len(task_costs_s) // n_cases
    free = np.full(workers, warmup_s)
    recent: list[list[int]] = [[] for _ in range(workers)]
    for k, cost in enumerate(task_costs_s):
        w = int(np.argmin(free))
        case = k // per_case
        load = 0.0 if case in recent[w] else scene_s
        recent[w] = ([c for c in recent[w] if c != case] + [case])[-cache:]
        free[w] += load + cost
    return float(free.max())


def simulate_blocks(task_costs_s: np.ndarray, scene_s: float, n_cases: int, workers: int, warmup_s: float) -> float:
    """Simulate the makespan when worker ``k`` runs the ``k``-th contiguous block of the case-major tasks.

    As :func:`reachplan.planner.study.run_study` prefers (loading each case of its block once), without work
    stealing (which only shortens it).

    Parameters
    ----------
    task_costs_s : (n_cases * designs,) float, s
        Cost of each task, case-major.
    scene_s : float, s
        What a worker pays to load each case of its block.
    n_cases : int
        Cases of the study.
    workers : int
        Workers.
    warmup_s : float, s
        Each worker's start-up.

    Returns
    -------
    float, s
        The makespan.
    """
    per_case = len(task_costs_s) // n_cases
    edges = np.arange(workers + 1) * len(task_costs_s) // workers
    spans = [warmup_s + task_costs_s[a:b].sum() + scene_s * len(set(range(a // per_case, (b - 1) // per_case + 1)))
             for a, b in itertools.pairwise(edges.tolist()) if b > a]
    return float(max(spans))


def measure(out: Path, s: StudySettings) -> tuple[list[StudyRun], dict[str, float], np.ndarray, np.ndarray,
                                                 tuple[int, int]]:
    """Run the study in process and on 1- and 2-worker clusters under ``out``, then estimate the large study.

    Parameters
    ----------
    out : Path
        Working folder (the cohort and each run's results go under it).
    s : StudySettings
        What to measure and estimate.

    Returns
    -------
    runs : list of StudyRun
        The in-process run first.
    estimate : dict of str to float
        Quantity -> value (:data:`INSTALLS` ``study_estimate.csv``).
    draws : (s.draws,) float, s
        Simulated wall times of the estimated study, first free worker.
    blocks : (s.draws,) float, s
        The same, case blocks per worker.
    counts : tuple of int
        The in-process study's (tasks, rows).

    Raises
    ------
    BenchError
        The cohort folder under ``out`` holds fewer cases than asked.
    """
    cohort = out / "cohort"
    if not (cohort / "cohort.json").exists():
        make_cohort(cohort, s.cases, seed=1, case="pilot")
    cases = discover_cases([cohort])[: s.cases]
    if len(cases) < s.cases:
        raise BenchError(f"{cohort} holds {len(cases)} cases, fewer than the {s.cases} asked; delete it or use "
                         "another --out")
    spec = StudySpec(cases, DESIGNS[: s.designs], TARGETS[: s.targets], PlanConfig())
    t = time.perf_counter()
    shutil.rmtree(out / "serial", ignore_errors=True)
    serial = run_study(spec, out / "serial", workers=0)
    serial_s = time.perf_counter() - t
    ref = serial.table.drop_columns(RUN_COLUMNS)
    runs = [StudyRun("in-process", 0, serial_s, 0.0, os.getloadavg()[0], _utilisation(serial.table, 1, serial_s),
                     True)]
    one: Any = None
    for _ in range(s.repeat):
        for n in (1, 2):
            shutil.rmtree(out / f"w{n}", ignore_errors=True)
            res, wall, start = _cluster_run(spec, out / f"w{n}", n)
            runs.append(StudyRun("LocalCluster", n, wall, start, os.getloadavg()[0], _utilisation(res.table, n, wall),
                                 res.table.drop_columns(RUN_COLUMNS).equals(ref)))
            if n == 1 and one is None:
                one = res
    best = {n: min(r.wall_s for r in runs if r.workers == n) for n in (1, 2)}

    # per-task costs from the in-process run, as CPU time (what a dedicated core would take)
    tasks = serial.table.to_pylist()
    work = np.array([r["task_plan_s"] + r["task_scene_s"] for r in tasks])
    cpu = np.array([r["task_cpu_s"] for r in tasks])
    plan_cpu = cpu * np.array([r["task_plan_s"] for r in tasks]) / work
    per_target = plan_cpu / len(spec.targets or ())
    scene = np.array([c - p for c, p, r in zip(cpu, plan_cpu, tasks, strict=True) if r["task_scene_s"] > 0])
    # a fresh worker's start-up (imports on the first task) plus Dask's overheads: the 1-worker run's wall time
    # outside its tasks' own (wall-clock) timings
    one_wall = next(r.wall_s for r in runs if r.workers == 1)
    warmup_s = max(0.0, one_wall - sum(r["task_plan_s"] + r["task_scene_s"] for r in one.table.to_pylist()))
    n_tasks = s.est_cases * s.est_designs
    rng = np.random.default_rng(0)
    sims = []
    for _ in range(s.draws):
        costs, load = s.est_targets * rng.choice(per_target, n_tasks), float(rng.choice(scene))
        sims.append((simulate(costs, load, s.est_cases, s.est_workers, warmup_s),
                     simulate_blocks(costs, load, s.est_cases, s.est_workers, warmup_s)))
    draws, blocks = np.array(sims).T
    mean_task = s.est_targets * per_target.mean()
    cpu_s = n_tasks * mean_task + s.est_cases * scene.mean()
    estimate = {
        "measured_per_target_plan_s_mean": per_target.mean(),
        "measured_per_target_plan_s_p90": np.quantile(per_target, 0.9),
        "measured_case_load_s_mean": scene.mean(), "measured_worker_warmup_s": warmup_s,
        "est_tasks": n_tasks, "est_task_s_mean": mean_task, "est_cpu_hours": cpu_s / 3600,
        "est_wall_ideal_s": cpu_s / s.est_workers, "est_wall_simulated_median_s": np.median(draws),
        "est_wall_simulated_p95_s": np.quantile(draws, 0.95),
        "est_wall_case_blocks_median_s": np.median(blocks), "est_wall_case_blocks_p95_s": np.quantile(blocks, 0.95),
        "speedup_2_over_1": best[1] / best[2],
    }
    return runs, {k: float(v) for k, v in estimate.items()}, draws, blocks, (serial.n_tasks, serial.table.num_rows)


def write_results(out: Path, s: StudySettings, runs: list[StudyRun], estimate: dict[str, float], draws: np.ndarray,
                  blocks: np.ndarray, counts: tuple[int, int]) -> None:
    """Write ``study_runs.csv``, ``study_estimate.csv`` and ``study_benchmark.png`` under ``out``.

    Parameters
    ----------
    out : Path
        The results folder.
    s : StudySettings
        What was measured.
    runs : list of StudyRun
        The timed runs (``study_runs.csv``, :data:`RUNS_HEADER`).
    estimate : dict of str to float
        Quantity -> value (``study_estimate.csv``).
    draws : (n,) float, s
        Simulated wall times, first free worker (histogram).
    blocks : (n,) float, s
        Simulated wall times, case blocks per worker (histogram).
    counts : (int, int)
        The in-process study's (tasks, rows).
    """
    n_tasks, n_rows = counts
    write_csv(out / "study_runs.csv", RUNS_HEADER,
              [[r.engine, r.workers, n_tasks, n_rows, round(r.wall_s, 2), round(r.cluster_start_s, 2),
                round(r.load_avg_1min, 2), round(r.cpu_utilisation, 3), r.same_rows] for r in runs])
    write_csv(out / "study_estimate.csv", ("quantity", "value"), [[k, round(v, 3)] for k, v in estimate.items()])
    best = {n: min(r.wall_s for r in runs if r.workers == n) for n in (0, 1, 2)}
    fig = Figure(figsize=(10, 4), layout="constrained")
    a, b = fig.subplots(1, 2)
    a.bar(["in-process", "1 worker", "2 workers"], [best[0], best[1], best[2]], color=["grey", "C0", "C1"])
    a.axhline(best[1] / 2, ls="--", c="k", lw=1, label="ideal 2-worker time")
    a.set_ylabel("study wall time (s)")
    a.set_title(f"{n_tasks} tasks ({s.cases} cases x {s.designs} designs x {s.targets} targets): "
                f"speed-up {estimate['speedup_2_over_1']:.2f}x", fontsize=9)
    a.legend(fontsize=8)
    b.hist(draws / 60, bins=30, alpha=0.7, label="first free worker (no case affinity)")
    b.hist(blocks / 60, bins=30, alpha=0.7, label="case blocks per worker (as run_study prefers)")
    b.axvline(estimate["est_wall_ideal_s"] / 60, c="k", ls="--", lw=1, label="total work / workers")
    b.set_xlabel("simulated wall time (min)")
    b.set_title(f"{s.est_cases} patients x {s.est_designs} designs x {s.est_targets} targets on "
                f"{s.est_workers} workers", fontsize=9)
    b.legend(fontsize=8)
    write_png(out / "study_benchmark.png", fig)


def run(args: argparse.Namespace) -> int:
    """Run ``reachplan bench study`` (``--quick``: 2 cases x 1 design x 1 target) into ``args.out``.

    Parameters
    ----------
    args : argparse.Namespace
        ``out`` (the working folder) and ``quick`` from the command line.

    Returns
    -------
    int
        0; the estimate is printed.
    """
    s = settings(args, StudySettings(), QUICK)
    out: Path = args.out
    runs, estimate, draws, blocks, counts = measure(out, s)
    write_results(out, s, runs, estimate, draws, blocks, counts)
    for r in runs:
        print(f"{r.engine:>12} workers={r.workers}: {r.wall_s:7.2f} s (cluster start {r.cluster_start_s:.2f} s, "
              f"load {r.load_avg_1min:.2f}, CPU utilisation {r.cpu_utilisation:.2f}, same rows {r.same_rows})")
    print(f"same rows as in-process: {all(r.same_rows for r in runs)}; speed-up 2 over 1 worker: "
          f"{estimate['speedup_2_over_1']:.2f}x")
    for k, v in estimate.items():
        print(f"{k:>36}: {v:.3f}")
    return 0
