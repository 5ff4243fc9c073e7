"""Benchmark: design-study throughput on 1 and 2 Dask worker processes, and a cohort-scale estimate.

Runs one small study (``--cases`` phantom variants x ``--designs`` x ``--targets``, the default schedule family,
as ``reachplan study`` runs it) three ways: in this process (the reference rows), on a local Dask cluster of 1
worker process and of 2 worker processes (clusters started before the clock starts; each worker's first-task
warm-up, i.e. imports and shape banks, is inside the timing). Checks the three give the same rows, reports
the speed-up of 2 workers over 1, and estimates from the measured per-target planning cost, per-case loading
cost and per-worker warm-up the wall time of a study of ``--est-cases`` patients x ``--est-designs`` designs x
``--est-targets`` targets on ``--est-workers`` workers, by simulating Dask's dynamic assignment (each task
to the first free worker in case-major order; a worker loads a case the first time it runs one of its tasks).

Usage::

    python benchmarks/study.py --out results/study [--cases 4] [--targets 4]

Writes ``study_runs.csv``, ``study_estimate.csv`` and ``study_benchmark.png`` under ``--out``.
"""

from __future__ import annotations

import argparse
import csv
import itertools
import os
import shutil
import time
from pathlib import Path
from typing import Any

import numpy as np

from reachplan.planner.pipeline import PlanConfig
from reachplan.planner.study import StudySpec, discover_cases, run_study
from reachplan.planner.study.cohort import make_cohort

DESIGNS = ("15ga-30j-tip", "13ga-20j-tip", "15ga-20j-mid")
TARGETS = ("Target_65_000", "Target_65_120", "Target_80_090", "Target_80_210", "Target_65_240", "Target_80_330")
RUN_COLUMNS = ["task_scene_s", "task_plan_s", "task_cpu_s", "worker", "finished_utc"]


def _cluster_run(spec: StudySpec, out: Path, workers: int) -> tuple[Any, float, float]:
    """(result, study wall s, cluster start s) on a fresh loopback LocalCluster of ``workers`` processes."""
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
    """Makespan (s) of case-major tasks, ``task_costs_s`` (n_cases * designs,) in order, each given to the first
    free worker; a worker pays ``scene_s`` for a case not among its last ``cache`` cases, and ``warmup_s`` once."""
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
    """Makespan (s) when worker ``k`` runs the ``k``-th contiguous block of the case-major tasks, as
    :func:`reachplan.planner.study.run_study` prefers (loading each case of its block once), without work stealing
    (which only shortens it)."""
    per_case = len(task_costs_s) // n_cases
    edges = np.arange(workers + 1) * len(task_costs_s) // workers
    spans = [warmup_s + task_costs_s[a:b].sum() + scene_s * len(set(range(a // per_case, (b - 1) // per_case + 1)))
             for a, b in itertools.pairwise(edges.tolist()) if b > a]
    return float(max(spans))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--cases", type=int, default=4)
    ap.add_argument("--targets", type=int, default=4, help=f"how many of {len(TARGETS)} phantom targets")
    ap.add_argument("--repeat", type=int, default=2, help="alternating 1- and 2-worker runs (best is kept)")
    ap.add_argument("--est-cases", type=int, default=100)
    ap.add_argument("--est-designs", type=int, default=7)
    ap.add_argument("--est-targets", type=int, default=10)
    ap.add_argument("--est-workers", type=int, default=32)
    args = ap.parse_args(argv)
    out: Path = args.out
    out.mkdir(parents=True, exist_ok=True)
    cohort = out / "cohort"
    if not (cohort / "cohort.json").exists():
        make_cohort(cohort, args.cases, seed=1, case="pilot")
    cases = discover_cases([cohort])[: args.cases]
    spec = StudySpec(cases, DESIGNS, TARGETS[: args.targets], PlanConfig())
    t = time.perf_counter()
    shutil.rmtree(out / "serial", ignore_errors=True)
    serial = run_study(spec, out / "serial", workers=0)
    serial_s = time.perf_counter() - t
    ref = serial.table.drop_columns(RUN_COLUMNS)
    runs: list[tuple[str, int, float, float, float, float, bool]] = [
        ("in-process", 0, serial_s, 0.0, os.getloadavg()[0], _utilisation(serial.table, 1, serial_s), True)]
    for rep in range(args.repeat):
        for n in (1, 2):
            shutil.rmtree(out / f"w{n}", ignore_errors=True)
            res, wall, start = _cluster_run(spec, out / f"w{n}", n)
            runs.append(("LocalCluster", n, wall, start, os.getloadavg()[0], _utilisation(res.table, n, wall),
                         res.table.drop_columns(RUN_COLUMNS).equals(ref)))
            if n == 1 and rep == 0:
                one = res
    best = {n: min(r[2] for r in runs if r[1] == n and r[0] == "LocalCluster") for n in (1, 2)}
    speedup = best[1] / best[2]
    same = all(r[6] for r in runs)
    with open(out / "study_runs.csv", "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["engine", "workers", "tasks", "rows", "wall_s", "cluster_start_s", "load_avg_1min",
                    "cpu_utilisation", "same_rows_as_in_process"])
        for engine, n, wall, start, load, util, ok in runs:
            w.writerow([engine, n, serial.n_tasks, serial.table.num_rows, round(wall, 2), round(start, 2),
                        round(load, 2), round(util, 3), ok])

    # per-task costs from the in-process run, as CPU time (what a dedicated core would take)
    tasks = {r["task"]: r for r in serial.table.to_pylist()}
    n_t = len(spec.targets or ())
    work = np.array([r["task_plan_s"] + r["task_scene_s"] for r in tasks.values()])
    cpu = np.array([r["task_cpu_s"] for r in tasks.values()])
    plan_cpu = cpu * np.array([r["task_plan_s"] for r in tasks.values()]) / work
    per_target = plan_cpu / n_t
    scene = np.array([c - p for c, p, r in zip(cpu, plan_cpu, tasks.values(), strict=True) if r["task_scene_s"] > 0])
    # a fresh worker's start-up (imports on the first task) plus Dask's overheads: the 1-worker run's wall time
    # outside its tasks' own (wall-clock) timings
    one_tasks = {r["task"]: r for r in one.table.to_pylist()}
    one_wall = next(r[2] for r in runs if r[1] == 1)
    warmup_s = max(0.0, one_wall - sum(r["task_plan_s"] + r["task_scene_s"] for r in one_tasks.values()))
    n_tasks = args.est_cases * args.est_designs
    rng = np.random.default_rng(0)
    sims = []
    for _ in range(200):
        costs, load = args.est_targets * rng.choice(per_target, n_tasks), float(rng.choice(scene))
        sims.append((simulate(costs, load, args.est_cases, args.est_workers, warmup_s),
                     simulate_blocks(costs, load, args.est_cases, args.est_workers, warmup_s)))
    draws, blocks = np.array(sims).T
    mean_task = args.est_targets * per_target.mean()
    ideal = (n_tasks * mean_task + args.est_cases * scene.mean()) / args.est_workers
    estimate = {
        "measured_per_target_plan_s_mean": per_target.mean(),
        "measured_per_target_plan_s_p90": np.quantile(per_target, 0.9),
        "measured_case_load_s_mean": scene.mean(), "measured_worker_warmup_s": warmup_s,
        "est_tasks": n_tasks, "est_task_s_mean": mean_task, "est_cpu_hours": (n_tasks * mean_task
                                                                              + args.est_cases * scene.mean()) / 3600,
        "est_wall_ideal_s": ideal, "est_wall_simulated_median_s": np.median(draws),
        "est_wall_simulated_p95_s": np.quantile(draws, 0.95),
        "est_wall_case_blocks_median_s": np.median(blocks), "est_wall_case_blocks_p95_s": np.quantile(blocks, 0.95),
        "speedup_2_over_1": speedup,
    }
    with open(out / "study_estimate.csv", "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["quantity", "value"])
        for k, v in estimate.items():
            w.writerow([k, round(float(v), 3)])

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (a, b) = plt.subplots(1, 2, figsize=(10, 4), constrained_layout=True)
    a.bar(["in-process", "1 worker", "2 workers"], [serial_s, best[1], best[2]], color=["grey", "C0", "C1"])
    a.axhline(best[1] / 2, ls="--", c="k", lw=1, label="ideal 2-worker time")
    a.set_ylabel("study wall time (s)")
    a.set_title(f"{serial.n_tasks} tasks ({len(cases)} cases x {len(DESIGNS)} designs x {n_t} targets): "
                f"speed-up {speedup:.2f}x", fontsize=9)
    a.legend(fontsize=8)
    b.hist(draws / 60, bins=30, alpha=0.7, label="first free worker (no case affinity)")
    b.hist(blocks / 60, bins=30, alpha=0.7, label="case blocks per worker (as run_study prefers)")
    b.axvline(ideal / 60, c="k", ls="--", lw=1, label="total work / workers")
    b.set_xlabel("simulated wall time (min)")
    b.set_title(f"{args.est_cases} patients x {args.est_designs} designs x {args.est_targets} targets on "
                f"{args.est_workers} workers", fontsize=9)
    b.legend(fontsize=8)
    fig.savefig(out / "study_benchmark.png", dpi=110)
    plt.close(fig)

    for engine, n, wall, start, load, util, ok in runs:
        print(f"{engine:>12} workers={n}: {wall:7.2f} s (cluster start {start:.2f} s, load {load:.2f}, "
              f"CPU utilisation {util:.2f}, same rows {ok})")
    print(f"same rows as in-process: {same}; speed-up 2 over 1 worker: {speedup:.2f}x")
    for k, v in estimate.items():
        print(f"{k:>36}: {float(v):.3f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
