"""Implant studies at scale: stylet designs compared against one shared straight arm, the CPU cost per case, a study
on a process-based Dask cluster reached by its scheduler's address (one numba and one HiGHS thread per worker,
kernels loaded before the first case), and the reuse of identical organs between a worker's cases."""

from __future__ import annotations

import argparse
import csv
import dataclasses
import json
import os
import statistics
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from reachplan.planner.case.config import PlanConfig
from reachplan.planner.cli.study import IMPLANT_CASES, add_arguments
from reachplan.planner.study.implant import ImplantCase, ImplantStudySpec, case_row, run_implant_study
from reachplan.planner.study.workers import (
    ALLOCATOR_ENV,
    WORKER_DASK_CONFIG,
    WORKER_ENV,
    WorkerSetup,
    worker_config,
)

DESIGNS = ("15ga-30j-tip", "13ga-20j-tip")
SEEDS = (0, 1, 2, 3)


def _arm(n: int, d90: float, steered: tuple[tuple[str, float, float], ...] = ()) -> dict[str, Any]:
    """An arm's plan.json section: ``n`` needles, of which ``steered`` (design, peak N, limit N) are steered."""
    needles = [{"kind": "steered", "design": d, "peak_tension_n": p, "tension_limit_n": lim,
                "tension_reserve_n": lim - p} for d, p, lim in steered]
    needles += [{"kind": "straight", "design": "", "peak_tension_n": 0.0, "tension_limit_n": None,
                 "tension_reserve_n": None}] * (n - len(steered))
    return {"n_needles": n, "needles": needles, "aims_met": d90 >= 85.0, "hrctv_d90_eqd2_gy": d90,
            "hrctv_d98_eqd2_gy": d90 - 5.0, "oar_d2cc_eqd2_gy": {}, "candidates": 10, "reason": ""}


def planted(task: ImplantCase, spec: ImplantStudySpec) -> dict[str, Any]:
    """Per seed s: straight 5 needles, D90 85 + s; the first design saves s % 2 needles (a steered needle at 6 N of
    10), the second saves one needle in every case (at 8 N of 10) and gains 1 Gy."""
    s = task.seed
    straight = _arm(5, 85.0 + s)
    first = _arm(5 - s % 2, 85.0 + s, (("15ga-30j-tip", 6.0, 10.0),) if s % 2 else ())
    second = _arm(4, 86.0 + s, (("13ga-20j-tip", 8.0, 10.0),))
    implant = {"straight": straight, "steered": first}
    return {"row": dataclasses.asdict(case_row(task, implant, 0.1 * (s + 1), 1.0 + s)), "implant": implant,
            "designs": {"13ga-20j-tip": second},
            "cpu_s": {"case": 0.5, "scene": 1.0 + s, "candidates": 2.0, "arms": 3.0 + s, "check": 0.25}}


def test_designs_share_the_straight_arm_and_cost_is_summarised(tmp_path: Path) -> None:
    """designs.csv: one row per case x design against the same straight arm; summary.json's designs block holds
    each design's mean saving (and its interval, closed form), its steered cases and tension reserve, and the best
    design; its cost block the per-case CPU distribution and the stage medians."""
    spec = ImplantStudySpec(SEEDS, PlanConfig(designs=DESIGNS))
    res = run_implant_study(spec, tmp_path / "s", workers=0, task_fn=planted)
    with (tmp_path / "s" / "designs.csv").open(encoding="utf-8", newline="") as f:
        rows = list(csv.DictReader(f))
    assert [(r["case"], r["design"]) for r in rows] == [(f"clinical_{s}", d) for s in SEEDS for d in DESIGNS]
    assert {r["straight_needles"] for r in rows} == {"5"}  # one straight arm, shared
    first = [r for r in rows if r["design"] == DESIGNS[0]]
    assert [int(r["needles_saved"]) for r in first] == [s % 2 for s in SEEDS]
    assert [r["min_tension_reserve_n"] for r in first] == ["" if s % 2 == 0 else "4.0" for s in SEEDS]
    doc = json.loads((tmp_path / "s" / "summary.json").read_text(encoding="utf-8"))
    assert doc == res.doc
    by = doc["designs"]["by_design"]
    saved = [float(s % 2) for s in SEEDS]
    half = 3.182 * statistics.stdev(saved) / 2.0  # t(0.975, 3) from a printed table, n = 4
    assert by[DESIGNS[0]]["needles_saved"]["mean"] == pytest.approx(0.5)
    assert by[DESIGNS[0]]["needles_saved"]["ci95"] == pytest.approx([0.5 - half, 0.5 + half], abs=2e-3)
    assert by[DESIGNS[1]]["needles_saved"]["mean"] == 1.0 and by[DESIGNS[1]]["d90_gained_gy"]["mean"] == 1.0
    assert by[DESIGNS[0]]["cases_using_steered"] == 2 and by[DESIGNS[1]]["cases_using_steered"] == 4
    assert by[DESIGNS[1]]["tension_reserve_n"] == {"median": 2.0, "min": 2.0}
    assert doc["designs"]["best"] == DESIGNS[1]
    # cases.csv's steered arm is the first design's
    assert [r.needles_saved for r in res.rows] == [s % 2 for s in SEEDS]
    cost = doc["cost"]
    assert cost["cpu_s_per_case"] == {"median": 2.5, "mean": 2.5, "max": 4.0, "n": 4}
    assert cost["stage_cpu_s_median"] == {"case": 0.5, "scene": 2.5, "candidates": 2.0, "arms": 4.5, "check": 0.25}


def test_implant_without_a_count_plans_the_cohort_size() -> None:
    parser = argparse.ArgumentParser()
    add_arguments(parser)
    assert parser.parse_args(["--implant", "--out", "o"]).implant == IMPLANT_CASES == 30
    assert parser.parse_args(["--implant", "4", "--out", "o"]).implant == 4


def probe(task: ImplantCase, spec: ImplantStudySpec) -> dict[str, Any]:
    """A worker's task that reports its process: threads, set-up, kernels (pickled by value: workers cannot import
    this test module)."""
    import numba

    from reachplan.planner.study.tasks import task_threads

    threads = task_threads()
    tasks_before = len(os.listdir("/proc/self/task"))
    from scipy.optimize._highspy import _core as highs

    h = highs._Highs()  # a solve that asks HiGHS for 4 threads: the worker's one-thread scheduler holds
    h.setOptionValue("output_flag", False)
    h.setOptionValue("threads", 4)
    lp = highs.HighsLp()
    lp.num_col_, lp.num_row_ = 1, 0
    lp.col_cost_, lp.col_lower_, lp.col_upper_ = np.ones(1), np.zeros(1), np.ones(1)
    h.passModel(lp)
    h.run()
    from distributed import get_worker

    from reachplan.planner.geometry import distance_field

    part = planted(task, spec)
    part["probe"] = {"threads": threads, "numba_threads": numba.get_num_threads(), "pid": os.getpid(),
                     "os_threads_grew": len(os.listdir("/proc/self/task")) - tasks_before,
                     "setup": get_worker().reachplan_setup,
                     "distance_loaded": all(bool(k.overloads) for k in (distance_field._edt, distance_field._sample,
                                                                        distance_field._parity_votes))}
    return part


class _ByValue:
    """A task function that pickles by value (cloudpickle): worker processes cannot import this test module."""

    def __init__(self, fn: Any) -> None:
        self.fn = fn

    def __call__(self, *args: Any) -> Any:
        return self.fn(*args)

    def __reduce__(self) -> tuple[Any, tuple[bytes]]:
        import cloudpickle

        return cloudpickle.loads, (cloudpickle.dumps(self.fn),)


def test_study_on_a_process_cluster_by_scheduler_address(tmp_path: Path) -> None:
    """Two cases on a process-based LocalCluster reached by its address (as an external ``dask scheduler``): each
    worker process set up once (one numba thread, HiGHS held to one thread, the distance kernels loaded before the
    first case), the same rows as in this process."""
    import cloudpickle
    import distributed

    from reachplan.planner.study import LOOPBACK_HTTP

    cloudpickle.register_pickle_by_value(sys.modules[probe.__module__])
    spec = ImplantStudySpec((0, 1), PlanConfig(designs=DESIGNS))
    try:
        with worker_config(), distributed.LocalCluster(
                n_workers=1, threads_per_worker=1, processes=True, host="127.0.0.1", dashboard_address=None,
                scheduler_kwargs=LOOPBACK_HTTP, env=dict(WORKER_ENV)) as cluster:
            res = run_implant_study(spec, tmp_path / "d", scheduler=cluster.scheduler_address, task_fn=_ByValue(probe),
                                    worker_setup=WorkerSetup(("distance",)))
    finally:
        cloudpickle.unregister_pickle_by_value(sys.modules[probe.__module__])
    serial = run_implant_study(spec, tmp_path / "s", workers=0, task_fn=planted)
    assert [r.needles_saved for r in res.rows] == [r.needles_saved for r in serial.rows]
    probes = [json.loads((tmp_path / "d" / "parts" / f"clinical_{s}.json").read_text())["probe"] for s in (0, 1)]
    for p in probes:
        assert p["threads"] == 1 and p["numba_threads"] == 1 and p["os_threads_grew"] == 0, p
        assert p["pid"] != os.getpid() and p["distance_loaded"]
        assert p["setup"]["highs_threads"] == 1 and p["setup"]["kernel_groups"] == ["distance"]
        assert p["setup"]["env"]["NUMBA_NUM_THREADS"] == "1"
        assert {k: p["setup"]["env"][k] for k in ALLOCATOR_ENV} == ALLOCATOR_ENV  # not Dask's 64 kiB trim
        assert p["setup"]["dask"] == WORKER_DASK_CONFIG  # no profiler, slower monitors
    assert probes[0]["setup"] == probes[1]["setup"]  # one worker, set up once


def test_identical_organs_are_meshed_once_per_process() -> None:
    """build_scene(reuse=True) takes the mesh of a ROI whose contours and grid it met before, and only then."""
    from reachplan.imaging.clinical import clinical_case, image_grid, structure_set
    from reachplan.imaging.types import Contour, Roi, StructureSet
    from reachplan.planner.case.scene import mesh_structures

    case = clinical_case(0)
    grid = image_grid(case.spec)
    (roi,) = structure_set(case.spec, ("Obturator",)).rois
    ss = StructureSet((roi,), "in-memory")
    a = mesh_structures(ss, ["Obturator"], grid, reuse=True)["Obturator"]
    b = mesh_structures(ss, ["Obturator"], grid, reuse=True)["Obturator"]
    fresh = mesh_structures(ss, ["Obturator"], grid)["Obturator"]
    assert a is b and fresh is not a
    assert np.array_equal(fresh.vertices, a.vertices) and np.array_equal(fresh.faces, a.faces)
    moved = Roi(roi.number, roi.name, tuple(Contour(c.points_mm + np.array([0.5, 0.0, 0.0])) for c in roi.contours),
                roi.normalized_name, roi.interpreted_type, roi.color)
    c = mesh_structures(StructureSet((moved,), "in-memory"), ["Obturator"], grid, reuse=True)["Obturator"]
    assert c is not a and np.allclose(c.vertices.mean(axis=0), a.vertices.mean(axis=0) + np.array([0.5, 0.0, 0.0]),
                                      atol=1e-6)


def test_cost_benchmark_writes_the_stages_per_case(tmp_path: Path) -> None:
    """``reachplan bench studycost``'s table and chart from measured rows: the median, the 90th percentile and each
    stage's median over the cases with a time."""
    from reachplan.planner.bench.study_cost import HEADER, STAGES, write_results

    rows = [{"case": f"clinical_{s}", "seed": s, "status": "ok", "cpu_s": 10.0 + 2 * s, "wall_s": 20.0,
             **{f"{k}_cpu_s": float(j + s) for j, k in enumerate(STAGES)}, "straight_needles": 3,
             "steered_needles": 2, "worker": "w", "load_avg_1min": 1.0} for s in range(5)]
    rows.append({**rows[0], "case": "clinical_9", "seed": 9, "status": "failed", "cpu_s": None,
                 **{f"{k}_cpu_s": None for k in STAGES}})
    summary = write_results(tmp_path, rows)
    assert summary["median_cpu_s"] == 14.0 and summary["p90_cpu_s"] == pytest.approx(17.2)  # 16 + 0.6 (18 - 16), linear
    assert summary["median_arms_cpu_s"] == 3.0 + 2.0  # stage 3 of the five, seeds 0-4
    with (tmp_path / "study_cost.csv").open(encoding="utf-8", newline="") as f:
        table = list(csv.DictReader(f))
    assert list(table[0]) == list(HEADER) and len(table) == 6 and table[5]["cpu_s"] == ""
    assert (tmp_path / "study_cost.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def _square(task: ImplantCase, config: object) -> int:
    """A study task that shares nothing with the others."""
    return task.seed * task.seed


def test_a_case_per_task_goes_to_the_first_free_worker(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    """Tasks in blocks prefer a worker each (a case's designs in a row); the implant study's tasks, one per case,
    prefer none, and its cluster's scheduler gives a worker one task at a time (none waits held for a busy worker)."""
    import distributed
    from distributed.diagnostics.plugin import SchedulerPlugin

    import reachplan.planner.study as study
    from reachplan.planner.study.workers import SCHEDULER_DASK_CONFIG

    class Restrictions(SchedulerPlugin):  # type: ignore[misc]
        """Each task's worker restrictions, as the scheduler first sees them."""

        def __init__(self, scheduler: Any) -> None:
            self.scheduler, self.seen = scheduler, {}

        def transition(self, key: Any, start: str, finish: str, *args: Any, **kwargs: Any) -> None:
            if start == "released" and key in self.scheduler.tasks:
                self.seen[str(key)] = set(self.scheduler.tasks[key].worker_restrictions or ())

    monkeypatch.setattr(study, "setup_workers", lambda client, plugin=None: None)  # no kernels in this process
    tasks = [ImplantCase(s) for s in range(4)]
    with worker_config(), distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=False,
                                                   dashboard_address=None) as cluster, distributed.Client(cluster) as c:
        saturation = SCHEDULER_DASK_CONFIG["distributed.scheduler.worker-saturation"]
        assert cluster.scheduler.WORKER_SATURATION == saturation == 1.0
        seen = {}
        for blocks in (True, False):
            plugin = Restrictions(cluster.scheduler)
            cluster.scheduler.add_plugin(plugin, name=f"restrictions-{blocks}")
            out = dict(study.dask_results(c, tasks, None, _square, lambda t, why: -1, blocks=blocks))
            assert {t.seed: v for t, v in out.items()} == {s: s * s for s in range(4)}
            cluster.scheduler.remove_plugin(name=f"restrictions-{blocks}")
            seen[blocks] = list(plugin.seen.values())
        assert len(seen[True]) == 4 and all(len(w) == 1 for w in seen[True])
        assert len({frozenset(w) for w in seen[True]}) == 2  # two blocks of two, one per worker
        assert len(seen[False]) == 4 and all(not w for w in seen[False])

        calls: list[bool] = []
        plain = study.dask_results

        def recorded(*args: Any, blocks: bool = True, **kwargs: Any) -> Any:
            calls.append(blocks)
            return plain(*args, blocks=blocks, **kwargs)

        monkeypatch.setattr(study, "dask_results", recorded)  # what the implant study imports when it runs
        res = run_implant_study(ImplantStudySpec((0, 1), PlanConfig(designs=DESIGNS)), tmp_path / "study",
                                scheduler=cluster.scheduler_address, task_fn=planted)
        assert calls == [False] and len(res.rows) == 2
