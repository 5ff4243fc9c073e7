"""Planning benchmark: the whole phantom plan, and the insertion models' speed against accuracy.

Run: ``reachplan bench planning --out DIR [--quick] [--install]``. Writes ``planning_timings.csv``,
``insertion_models.csv`` and ``insertion_models.png`` (time per path, log axis, against tip error relative to
the in-tissue Cosserat rod ``tissue_rod`` at 1 and 2 mm insertion steps, extrapolated), plus ``workspace.png``;
``--install`` copies all four to ``docs/``.
Medians over repeats: the machines are shared and noisy. ``--quick`` plans two targets once and uses coarse
insertion steps.
"""

from __future__ import annotations

import argparse
import dataclasses
import statistics
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass, replace
from functools import partial
from pathlib import Path
from typing import TypeVar

import fcl
import numpy as np
from matplotlib.figure import Figure

from reachplan.imaging.dicom_io import read_series
from reachplan.imaging.files import atomic_write_bytes
from reachplan.imaging.phantom import write_phantom
from reachplan.imaging.rtstruct import read_rtstruct
from reachplan.planner.bench.common import settings, write_csv, write_png
from reachplan.planner.case.config import PlanConfig
from reachplan.planner.case.scene import build_scene
from reachplan.planner.case.search import plan
from reachplan.planner.ranking import RankWeights
from reachplan.planner.report.workspace import workspace_figure
from reachplan.planner.steering.kinematic import KinematicInsertion
from reachplan.planner.steering.schedule import TensionSchedule
from reachplan.planner.steering.steered import shape_bank
from reachplan.planner.steering.tissue_rod import PLANNER_REFERENCE, TissueRodInsertion, forget_runs
from reachplan.rod_model.design import RodDesign, preset

INSTALLS = {name: f"docs/{name}" for name in ("planning_timings.csv", "insertion_models.csv", "insertion_models.png",
                                               "workspace.png")}
TIMING_COLUMNS = ("plan", "holes", "targets", "schedules", "median_s", "paths_per_s", "fcl_queries",
                  "fcl_queries_per_s", "rerank_ms")
INSERTION_COLUMNS = ("model", "ms_per_path", "median_tip_error_mm", "max_tip_error_mm")
T = TypeVar("T")


@dataclass(frozen=True)
class PlanningSettings:
    """What the planning benchmark measures.

    Parameters
    ----------
    repeats : int
        Plan repeats (the median is kept).
    targets : int or None
        How many phantom targets (``None``: all).
    reference_step_mm : float, mm
        The reference ``tissue_rod`` insertion step (extrapolated with twice that step, 2 RK4 steps per mm).
    rod_steps_mm : tuple of float, mm
        Insertion steps of the plain ``tissue_rod`` (1 RK4 step per mm) compared with it.
    depth_mm : float, mm
        Insertion depth.
    """

    repeats: int = 3
    targets: int | None = None
    reference_step_mm: float = 1.0
    rod_steps_mm: tuple[float, ...] = (8.0, 4.0, 2.0)
    depth_mm: float = 150.0


QUICK = PlanningSettings(repeats=1, targets=2, reference_step_mm=4.0, rod_steps_mm=(8.0,))


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


def _median_time(fn: Callable[[], T], repeats: int) -> tuple[float, T]:
    """(median wall time in s of ``repeats`` calls, the last call's result)."""
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t)
    return statistics.median(times), out


def plan_timings(out: Path, s: PlanningSettings) -> list[dict[str, object]]:
    """Time the screening and the full plan of the phantom (median of ``s.repeats``); also writes ``workspace.png``.

    Parameters
    ----------
    out : Path
        The results folder.
    s : PlanningSettings
        Repeats and targets.

    Returns
    -------
    list of dict of str to object
        One row each (:data:`TIMING_COLUMNS`, s).
    """
    with tempfile.TemporaryDirectory() as tmp:
        files = write_phantom(Path(tmp) / "phantom")
        volume = read_series(files.ct_dir)
        structures = read_rtstruct(files.rtstruct_path, volume)
    scene = build_scene(structures, grid=volume.grid)
    if s.targets is not None:
        scene = dataclasses.replace(scene, targets=scene.targets[: s.targets])
    rows: list[dict[str, object]] = []
    n_holes, n_targets = len(scene.template.needle_holes), len(scene.targets)
    for label, cfg in (("screening (kinematic, no re-solve, no robustness)", PlanConfig(refine_top=0, robust_top=0)),
                       ("full (re-solve top-1 per target, robustness top-2)", PlanConfig())):
        n_sched = len(cfg.family.schedules(cfg.rod_designs[0]))
        shape_bank.cache_clear()
        plan(dataclasses.replace(scene, targets=scene.targets[:1]), cfg)  # warm caches (curvature tables)
        with _CountingFcl() as counter:
            t, result = _median_time(partial(plan, scene, cfg), s.repeats)
        queries = counter.n / s.repeats
        paths = n_holes * n_targets * n_sched  # steered paths matched, per design
        rerank, _ = _median_time(partial(result.rerank, RankWeights(per_newton=0.5)), 20)
        rows.append({"plan": label, "holes": n_holes, "targets": n_targets, "schedules": n_sched,
                     "median_s": round(t, 3), "paths_per_s": round(paths / t), "fcl_queries": round(queries),
                     "fcl_queries_per_s": round(queries / t), "rerank_ms": round(rerank * 1e3, 2)})
    atomic_write_bytes(out / "workspace.png", workspace_figure(scene, PlanConfig()))
    return rows


def insertion_models(s: PlanningSettings) -> list[dict[str, object]]:
    """Time each insertion model variant and measure its tip error at ``s.depth_mm`` against the reference.

    The reference is the in-tissue Cosserat rod (gel, 0.19 MPa) at ``s.reference_step_mm`` insertion steps,
    Richardson-extrapolated with twice that step; the kinematic model runs with the planner's curvature factor
    for the gel (1.27, fitted to that rod), so its error is the tip-following approximation's; the rod (1 RK4
    step per mm) at coarser insertion steps, and the planner's reference re-solve (2 mm steps extrapolated with
    4 mm ones), say what the insertion step costs.

    Parameters
    ----------
    s : PlanningSettings
        Reference step, rod steps and depth.

    Returns
    -------
    list of dict of str to object
        One row per variant (:data:`INSERTION_COLUMNS`; ms per path, tip errors in mm).
    """
    design = preset("15ga-30j-tip")
    schedules = [TensionSchedule.ramp(o, 20.0, f * design.max_tension_n, 0.0)
                 for o in (0.0, 40.0) for f in (0.5, 1.0)]
    depth = s.depth_mm
    reference = replace(PLANNER_REFERENCE, step_mm=s.reference_step_mm,
                        rod_model=replace(PLANNER_REFERENCE.rod_model, steps_per_mm=2.0))
    ref_tips = _tips(reference, design, schedules, depth)
    rows: list[dict[str, object]] = []
    for h in (4.0, 1.0, 0.25):
        kin = KinematicInsertion(step_mm=h)
        t, paths = _median_time(partial(kin.insert_array, design, schedules * 25, depth), 3)
        rows.append(_insertion_row(f"kinematic step {h} mm, factor {kin.factor_for(design):.2f} (batched)",
                                   t / (len(schedules) * 25), paths[: len(schedules), -1], ref_tips))
    for h in s.rod_steps_mm:
        rod = replace(PLANNER_REFERENCE, step_mm=h, richardson=False)
        t, tips = _median_time(partial(_tips, rod, design, schedules, depth), 1)
        rows.append(_insertion_row(f"tissue_rod step {h} mm", t / len(schedules), tips, ref_tips))
    t, tips = _median_time(partial(_tips, PLANNER_REFERENCE, design, schedules, depth), 1)
    rows.append(_insertion_row(f"tissue_rod step {PLANNER_REFERENCE.step_mm} mm, extrapolated (planner)",
                               t / len(schedules), tips, ref_tips))
    return rows


def _tips(model: TissueRodInsertion, design: RodDesign, schedules: list[TensionSchedule],
          depth_mm: float) -> np.ndarray:
    """Tip positions (n, 3), mm, template frame, of one insertion per schedule (NaN where it fails)."""
    forget_runs()  # timed from a cold memo: the models share runs at one step size
    paths = [model.insert_one(design, sc, depth_mm) for sc in schedules]
    return np.array([p[-1] if isinstance(p, np.ndarray) else np.full(3, np.nan) for p in paths])


def _insertion_row(label: str, s_per_path: float, tips: np.ndarray, ref_tips: np.ndarray) -> dict[str, object]:
    err = np.linalg.norm(np.asarray(tips) - ref_tips, axis=1)
    return {"model": label, "ms_per_path": round(s_per_path * 1e3, 4),
            "median_tip_error_mm": round(float(np.median(err)), 4), "max_tip_error_mm": round(float(err.max()), 4)}


def insertion_figure(rows: list[dict[str, object]]) -> Figure:
    """Time per path (log) against the worst tip error of each insertion model variant.

    Parameters
    ----------
    rows : list of dict of str to object
        The rows of :func:`insertion_models` (ms, mm).

    Returns
    -------
    matplotlib.figure.Figure
    """
    fig = Figure(figsize=(7, 4.5))
    ax = fig.subplots()
    for r in rows:
        kin = str(r["model"]).startswith("kinematic")
        x, y = float(r["ms_per_path"]), float(r["max_tip_error_mm"])  # type: ignore[arg-type]
        ax.plot(x, y, "o" if kin else "s", color="C0" if kin else "C3")
        ax.annotate(str(r["model"]), (x, y), fontsize=7, xytext=(4, 4), textcoords="offset points")
    ax.set(xscale="log", xlabel="time per path (ms, log)",
           ylabel="max tip error vs tissue_rod, 1 + 2 mm steps extrapolated (mm)",
           title="insertion models in the gel (0.19 MPa), 15ga-30j-tip, 150 mm, ramps to 5-10 N")
    ax.grid(alpha=0.3)
    fig.tight_layout()
    return fig


def run(args: argparse.Namespace) -> int:
    """Run ``reachplan bench planning`` (``--quick``: two targets, coarse grids) into ``args.out``.

    Writes ``planning_timings.csv``, ``insertion_models.csv`` and ``insertion_models.png``.

    Parameters
    ----------
    args : argparse.Namespace
        Options of ``reachplan bench planning``: ``out`` and ``quick``.

    Returns
    -------
    int
        The exit status (0).
    """
    s = settings(args, PlanningSettings(), QUICK)
    out: Path = args.out
    timing = plan_timings(out, s)
    write_csv(out / "planning_timings.csv", TIMING_COLUMNS, timing)
    models = insertion_models(s)
    write_csv(out / "insertion_models.csv", INSERTION_COLUMNS, models)
    write_png(out / "insertion_models.png", insertion_figure(models))
    for r in timing + models:
        print(r)
    return 0
