"""Organ distance benchmark: the distance-field screen against FCL alone on the built-in phantom.

Run: ``reachplan bench distance --out DIR [--quick]``. Builds the phantom scene once (organs with their
distance fields), then, in turns, ``--repeat`` times (3; 1 with ``--quick``), plans the whole phantom three
ways: with the screen (exact: FCL only for the organs that can be the nearest), with the banded screen (the
field's estimate beyond the ranking's clearance cap + 1 mm) and with FCL alone (fields removed). Also the raw
rates: field samples per second (random points in the organs' reach, one call) and field and FCL
path-clearance queries per second (clear candidate paths against every organ), and on those pairs the largest
difference between the field's estimate and FCL's clearance, beside the field's error bound.
Writes ``distance.csv`` and ``distance.png``; goal (issue 19): >= 10 M samples/s, same ranking.
"""

from __future__ import annotations

import argparse
import dataclasses
import statistics
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from reachplan.planner.bench._util import load_avg, write_csv

GOAL_SAMPLES_PER_S = 10e6


def _ranking_key(result: object) -> dict[str, list[tuple[str, str, bool]]]:
    return {t: [(c.hole_id, c.reason, c.steered) for c in cs] for t, cs in result.ranking.items()}  # type: ignore[attr-defined]


#: results this target owns in a source checkout (``reachplan bench distance --install``)
INSTALLS = {"distance.csv": "docs/speed/distance.csv", "distance.png": "docs/speed/distance.png"}


def run(args: argparse.Namespace) -> int:
    """Run ``reachplan bench distance`` into ``args.out``: ``distance.csv`` and ``distance.png``.

    Parameters
    ----------
    args : argparse.Namespace
        ``out`` and ``quick`` (one repeat, fewer paths).

    Returns
    -------
    int
        0 (the rankings' agreement and the rates are in the table).
    """
    from reachplan.planner.case.config import PlanConfig

    out: Path = args.out  # made by the bench command
    repeat = 1 if args.quick else 3
    cfg = PlanConfig(refine_top=0, robust_top=0)
    scene, banded, bare, build_s = _scenes(cfg.weights.clearance_cap_mm + 1.0)
    t_screen, t_band, t_fcl, res_screen, res_band, res_fcl = _timed_plans(scene, banded, bare, cfg, repeat)
    same = _ranking_key(res_screen) == _ranking_key(res_fcl)
    identical = res_screen.to_json() == res_fcl.to_json()
    same_banded = _ranking_key(res_band) == _ranking_key(res_fcl)

    # raw rates and the largest difference, on the candidate paths that were collision-checked
    clear = [c.path_mm for c in res_fcl.candidates if np.isfinite(c.clearance_mm) and not c.collides]
    paths = clear[:: max(1, len(clear) // (60 if args.quick else 400))]
    f0 = scene.organs[0].field
    assert f0 is not None
    samples_per_s, samples_per_cpu_s = _sample_rates(f0)
    q = _path_queries(paths, scene.organs, radius=1.0)
    row = {
        "plan_fcl_only_s": round(statistics.median(t_fcl), 3),
        "plan_banded_screen_s": round(statistics.median(t_band), 3),
        "ratio_fcl_to_banded": round(statistics.median(t_fcl) / statistics.median(t_band), 2),
        "same_ranking_banded": same_banded,
        "plan_exact_screen_s": round(statistics.median(t_screen), 3),
        "same_plan_json_exact": identical,
        "same_ranking_exact": same,
        "field_samples_per_s": round(samples_per_s),
        "field_samples_per_cpu_s": round(samples_per_cpu_s),
        "field_path_queries_per_s": round(q.n_pairs / q.field_s),
        "fcl_path_queries_per_s": round(q.n_pairs / q.fcl_s),
        "max_abs_diff_mm": round(q.worst_mm, 3),
        "error_bound_mm": round(q.worst_bound_mm, 3),
        "field_build_s": round(build_s, 3),
        "pairs_timed": q.n_pairs,
        "pairs_compared": q.n_compared,
        "repeats": repeat,
        "load_avg_1min": round(load_avg(), 2),
    }
    write_csv(out / "distance.csv", [row])
    for k, v in row.items():
        print(f"{k:<26} {v}")
    _plot(out / "distance.png", row, samples_per_s, same_banded, q.worst_mm)
    return 0


def _scenes(band_mm: float) -> tuple[Any, Any, Any, float]:
    """Build the phantom's scene three ways: exact screen, banded screen and FCL alone (no fields).

    Parameters
    ----------
    band_mm : float, mm
        The banded fields' reach (the ranking's clearance cap + 1 mm).

    Returns
    -------
    exact, banded, bare : Scene
        Organs with full distance fields, with the planner's banded fields, and without fields.
    build_s : float, s
        Time to build the banded fields of every organ.
    """
    from reachplan.imaging.dicom_io import read_series
    from reachplan.imaging.phantom import write_phantom
    from reachplan.imaging.rtstruct import read_rtstruct
    from reachplan.planner.case.scene import build_scene
    from reachplan.planner.geometry.collision import with_distance_field

    with tempfile.TemporaryDirectory() as tmp:
        files = write_phantom(Path(tmp) / "phantom")
        volume = read_series(files.ct_dir)
        structures = read_rtstruct(files.rtstruct_path, volume)
    scene = build_scene(structures, grid=volume.grid)
    bare = dataclasses.replace(scene, organs=tuple(dataclasses.replace(o, field=None) for o in scene.organs))
    t0 = time.perf_counter()
    for o in bare.organs:
        with_distance_field(o, band_mm)
    build_s = time.perf_counter() - t0
    # the planner's scene is banded (the field's estimate beyond the ranking's cap + 1 mm); the exact variant
    # asks FCL for every organ that can be the nearest
    exact = dataclasses.replace(scene, organs=tuple(with_distance_field(o) for o in bare.organs))
    return exact, scene, bare, build_s


def _timed_plans(scene: Any, banded: Any, bare: Any, cfg: Any,
                 repeat: int) -> tuple[list[float], list[float], list[float], Any, Any, Any]:
    """Plan the three scenes ``repeat`` times in turns (after one warm-up plan of one target).

    Returns
    -------
    t_screen, t_band, t_fcl : list of float, s
        Wall time of each plan: exact screen, banded screen, FCL alone.
    res_screen, res_band, res_fcl : PlanResult
        The last plan of each.
    """
    from reachplan.planner.case.search import plan

    plan(dataclasses.replace(scene, targets=scene.targets[:1]), cfg)  # warm caches and kernels
    t_screen: list[float] = []
    t_fcl: list[float] = []
    t_band: list[float] = []
    res_screen = res_fcl = res_band = None
    for _ in range(repeat):
        t0 = time.perf_counter()
        res_band = plan(banded, cfg)
        t_band.append(time.perf_counter() - t0)
        t0 = time.perf_counter()
        res_screen = plan(scene, cfg)
        t_screen.append(time.perf_counter() - t0)
        t0 = time.perf_counter()
        res_fcl = plan(bare, cfg)
        t_fcl.append(time.perf_counter() - t0)
    return t_screen, t_band, t_fcl, res_screen, res_band, res_fcl


def _sample_rates(field: Any) -> tuple[float, float]:
    """Time one call sampling a field at 2 M random points in its box; return samples per wall and CPU second."""
    rng = np.random.default_rng(0)
    pts = field.origin_mm + rng.uniform(0, 1, (2_000_000, 3)) * (np.array(field.values_mm.shape) - 1) * field.pitch_mm
    field.sample(pts[:10])
    t0, c0 = time.perf_counter(), time.process_time()
    field.sample(pts)
    return len(pts) / (time.perf_counter() - t0), len(pts) / max(time.process_time() - c0, 1e-9)


@dataclasses.dataclass(frozen=True)
class _Queries:
    """Path-clearance queries timed against every organ, and the field's largest error on them.

    Parameters
    ----------
    n_pairs : int
        Path-organ pairs queried.
    n_compared : int
        Pairs clear of the organ and within the field's reach (where the estimate is compared).
    field_s, fcl_s : float, s
        Total time of the field's and FCL's queries.
    worst_mm, worst_bound_mm : float, mm
        Largest ``|estimate - FCL|`` and the field's error bound on that pair.
    """

    n_pairs: int
    n_compared: int
    field_s: float
    fcl_s: float
    worst_mm: float
    worst_bound_mm: float


def _path_queries(paths: list[np.ndarray], organs: tuple[Any, ...], radius: float) -> _Queries:
    """Query the clearance of every path (``(n, 3)`` float, mm, LPS) to every organ with its field and with FCL."""
    from reachplan.planner.geometry.collision import path_clearance

    worst = 0.0
    worst_bound = 0.0
    n_pairs = 0
    n_diff = 0
    t_fcl_q = 0.0
    t_field_q = 0.0
    for p in paths:
        for organ in organs:
            f = organ.field
            assert f is not None
            t0 = time.perf_counter()
            est, _, _ = f.path_clearance(p, radius)
            t_field_q += time.perf_counter() - t0
            t0 = time.perf_counter()
            exact = path_clearance(p, radius, organ).clearance_mm
            t_fcl_q += time.perf_counter() - t0
            n_pairs += 1
            if exact > 0 and est < f.reach_mm - radius - 1e-6:  # clear of the organ, within the field's reach
                n_diff += 1
                if abs(est - exact) > worst:
                    worst, worst_bound = abs(est - exact), f.error_mm + 0.5 * f.pitch_mm
    return _Queries(n_pairs, n_diff, t_field_q, t_fcl_q, worst, worst_bound)


def _plot(path: Path, row: dict[str, Any], samples_per_s: float, same_banded: bool, worst: float) -> None:
    """Draw the rates against the goal and the three plans' times into ``path`` (PNG)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (a1, a2) = plt.subplots(1, 2, figsize=(8, 3.4))
    a1.bar(["field\nsamples/s", "field\npath queries/s", "FCL\npath queries/s"],
           [samples_per_s, row["field_path_queries_per_s"], row["fcl_path_queries_per_s"]])
    a1.axhline(GOAL_SAMPLES_PER_S, color="red", ls=":", label="10 M samples/s goal")
    a1.set_yscale("log")
    a1.legend(fontsize=8)
    a2.bar(["screen\n(exact)", "screen\n(banded)", "FCL only"],
           [row["plan_exact_screen_s"], row["plan_banded_screen_s"], row["plan_fcl_only_s"]])
    a2.set_ylabel("phantom plan, s (median)")
    a2.set_title(f"same ranking: {same_banded}; max |diff| {worst:.2f} mm", fontsize=9)
    fig.suptitle(f"organ distance (load {load_avg():.1f})", fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
