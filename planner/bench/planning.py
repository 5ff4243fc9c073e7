"""Planning benchmark: the whole phantom plan, and the insertion models' speed against accuracy.

Run: ``reachplan bench planning --out DIR [--quick] [--install]``. Writes ``planning_timings.csv``,
``insertion_models.csv`` and ``insertion_models.png`` (time per path, log axis, against tip error relative to
the finest ``tissue_beam`` solve), plus ``workspace.png``; ``--install`` copies the figures to ``docs/``.
Medians over repeats: the machines are shared and noisy.
"""

from __future__ import annotations

import argparse
import csv
import dataclasses
import shutil
import statistics
import tempfile
import time
from pathlib import Path

import fcl
import numpy as np
from matplotlib.figure import Figure

from reachplan.imaging.dicom_io import read_series
from reachplan.imaging.files import atomic_write_bytes
from reachplan.imaging.phantom import write_phantom
from reachplan.imaging.rtstruct import read_rtstruct
from reachplan.planner.pipeline import PlanConfig, build_scene, plan
from reachplan.planner.ranking import RankWeights
from reachplan.planner.report.workspace import workspace_figure
from reachplan.planner.steering.insertion import KinematicInsertion, TissueBeamInsertion
from reachplan.planner.steering.schedule import TensionSchedule
from reachplan.planner.steering.steered import shape_bank
from reachplan.rod_model.design import preset

DOCS = Path(__file__).resolve().parents[1] / "docs"


class _CountingFcl:
    """Counts FCL narrow-phase queries (distance + collide) while active."""

    def __init__(self) -> None:
        self.n = 0
        self._distance, self._collide = fcl.distance, fcl.collide

    def __enter__(self) -> _CountingFcl:
        def distance(*a: object) -> float:
            self.n += 1
            return self._distance(*a)

        def collide(*a: object) -> int:
            self.n += 1
            return self._collide(*a)

        fcl.distance, fcl.collide = distance, collide
        return self

    def __exit__(self, *exc: object) -> None:
        fcl.distance, fcl.collide = self._distance, self._collide


def _median_time(fn, repeats: int) -> tuple[float, object]:  # type: ignore[no-untyped-def]
    times, out = [], None
    for _ in range(repeats):
        t = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t)
    return statistics.median(times), out


def plan_timings(out: Path, repeats: int) -> list[dict[str, object]]:
    with tempfile.TemporaryDirectory() as tmp:
        files = write_phantom(Path(tmp) / "phantom")
        volume = read_series(files.ct_dir)
        structures = read_rtstruct(files.rtstruct_path, volume)
    scene = build_scene(structures, grid=volume.grid)
    rows: list[dict[str, object]] = []
    n_holes, n_targets = len(scene.template.needle_holes), len(scene.targets)
    for label, cfg in (("screening (kinematic, no re-solve, no robustness)", PlanConfig(refine_top=0, robust_top=0)),
                       ("full (re-solve top-1 per target, robustness top-2)", PlanConfig())):
        n_sched = len(cfg.family.schedules(preset(cfg.designs[0])))
        shape_bank.cache_clear()
        plan(dataclasses.replace(scene, targets=scene.targets[:1]), cfg)  # warm caches (curvature tables)
        with _CountingFcl() as counter:
            t, result = _median_time(lambda cfg=cfg: plan(scene, cfg), repeats)
        queries = counter.n / repeats
        paths = n_holes * n_targets * n_sched  # steered paths matched, per design
        rerank, _ = _median_time(lambda r=result: r.rerank(RankWeights(per_newton=0.5)), 20)  # type: ignore[attr-defined]
        rows.append({"plan": label, "holes": n_holes, "targets": n_targets, "schedules": n_sched,
                     "median_s": round(t, 3), "paths_per_s": round(paths / t), "fcl_queries": round(queries),
                     "fcl_queries_per_s": round(queries / t), "rerank_ms": round(rerank * 1e3, 2)})
    atomic_write_bytes(out / "workspace.png", workspace_figure(scene, PlanConfig()))
    return rows


def insertion_models(out: Path, quick: bool) -> list[dict[str, object]]:
    design = preset("15ga-30j-tip")
    schedules = [TensionSchedule.ramp(o, 20.0, f * design.max_tension_n, 0.0)
                 for o in (0.0, 40.0) for f in (0.5, 1.0)]
    depth = 150.0
    reference = TissueBeamInsertion(grid_mm=0.125 if not quick else 0.25, step_mm=0.125 if not quick else 0.25)
    ref_tips = np.array([reference.insert_one(design, s, depth)[-1] for s in schedules])
    rows: list[dict[str, object]] = []
    variants: list[tuple[str, object, bool]] = [
        (f"kinematic step {h} mm (batched)", KinematicInsertion(step_mm=h), True) for h in (4.0, 1.0, 0.25)]
    variants += [(f"tissue_beam grid {h} mm", TissueBeamInsertion(grid_mm=h, step_mm=h), False)
                 for h in ((1.0, 0.5) if quick else (1.0, 0.5, 0.25))]
    for label, model, batched in variants:
        if batched:
            t, tips = _median_time(lambda m=model: m.insert_array(design, schedules * 25, depth)[:, -1], 3)  # type: ignore[attr-defined]
            per_path = t / (len(schedules) * 25)
            tips = np.asarray(tips)[: len(schedules)]
        else:
            t, tips = _median_time(lambda m=model: np.array([m.insert_one(design, s, depth)[-1]  # type: ignore[attr-defined]
                                                             for s in schedules]), 1)
            per_path = t / len(schedules)
        err = np.linalg.norm(np.asarray(tips) - ref_tips, axis=1)
        rows.append({"model": label, "ms_per_path": round(per_path * 1e3, 4), "median_tip_error_mm": round(
            float(np.median(err)), 4), "max_tip_error_mm": round(float(err.max()), 4)})
    fig = Figure(figsize=(7, 4.5))
    ax = fig.add_subplot()
    for r in rows:
        kin = str(r["model"]).startswith("kinematic")
        ax.plot(r["ms_per_path"], r["max_tip_error_mm"], "o" if kin else "s", color="C0" if kin else "C3")
        ax.annotate(str(r["model"]), (r["ms_per_path"], r["max_tip_error_mm"]), fontsize=7,
                    xytext=(4, 4), textcoords="offset points")
    ax.set(xscale="log", xlabel="time per path (ms, log)", ylabel="max tip error vs finest tissue_beam (mm)",
           title=f"insertion models, {design.name}, {depth:.0f} mm, ramps to 5-10 N")
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(out / "insertion_models.png", dpi=110)
    return rows


def _write_csv(path: Path, rows: list[dict[str, object]]) -> None:
    with path.open("w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)


def run(args: argparse.Namespace) -> int:
    out: Path = args.out
    out.mkdir(parents=True, exist_ok=True)
    timing = plan_timings(out, 1 if args.quick else 3)
    _write_csv(out / "planning_timings.csv", timing)
    models = insertion_models(out, args.quick)
    _write_csv(out / "insertion_models.csv", models)
    for r in timing + models:
        print(r)
    if args.install:
        for name in ("insertion_models.png", "workspace.png"):
            shutil.copy(out / name, DOCS / name)
    return 0
