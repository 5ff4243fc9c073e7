"""Benchmark: planning time against ranking fidelity, for fixed-model policies and the scene policy.

On the built-in clinical case of each seed (``--cases N``: seeds 0 .. N - 1, default 0-4; seed 0 is the demo's
case, its tandem an obstacle as in ``reachplan demo``), the steering search
(:func:`reachplan.planner.case.search.plan`) runs once per policy:

``kinematic``
    every candidate keeps the screening model's numbers (``refine_top`` 0);
``tissue_rod@4mm``, ``tissue_rod@4+8mm``
    every feasible steered candidate re-solved with that rung of the ladder (``--models reference`` with that rung
    as the reference);
``scene``
    the default: each candidate the cheapest model its margins allow, the reference near the ranking's decision
    (:mod:`reachplan.planner.case.fidelity`);
``reference``
    every feasible steered candidate re-solved with the reference (``--models reference``), the yardstick.

Fidelity against the reference policy, per target: the top-ranked candidate identical (hole, straight or steered,
design), Kendall's tau between the two rankings over the union of both top 10s (a candidate one of them does not
hold feasible ranks last in it), and the largest reach and clearance difference over the reference's top 10
(clearance compared up to the ranking's cap + 1 mm, beyond which both are the distance field's estimate and the
score ignores it). Time: the plan stage's wall and CPU seconds (the scene built once per seed, not counted; the
memoised in-tissue solves cleared before each policy).

Run: ``reachplan bench fidelity --out DIR [--quick] [--install]``. Writes ``fidelity.csv`` (one row per seed and
policy), ``fidelity.png`` (time against fidelity, medians over the seeds) and, with the error table
(``--table 1``, default), ``model_errors_tissue.json`` (the planner's package data,
:mod:`reachplan.planner.bench.fidelity_errors`) and ``model_errors_tissue.csv``.
"""

from __future__ import annotations

import argparse
import dataclasses
import statistics
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from matplotlib.figure import Figure

from reachplan.planner.bench._util import load_avg
from reachplan.planner.bench.common import settings, write_csv, write_json, write_png
from reachplan.planner.case.config import DEFAULT_OARS, PlanConfig, PlanModels
from reachplan.planner.case.fidelity import RUNG_BY_NAME
from reachplan.planner.case.scene import Scene
from reachplan.planner.steering.candidates import Candidate
from reachplan.rod_model.design import PRESET_NAMES

INSTALLS = {"fidelity.csv": "docs/fidelity.csv", "fidelity.png": "docs/fidelity.png",
            "model_errors_tissue.json": "planner/case/model_errors_tissue.json",
            "model_errors_tissue.csv": "docs/model_errors_tissue.csv"}
#: The policies, cheapest first; ``reference`` is the yardstick.
POLICIES: tuple[str, ...] = ("kinematic", "tissue_rod@4mm", "tissue_rod@4+8mm", "scene", "reference")
TOP_N = 10


@dataclass(frozen=True)
class FidelitySettings:
    """What the benchmark runs.

    Parameters
    ----------
    cases : int
        Clinical case seeds ``0 .. cases - 1``.
    policies : tuple of str
        Of :data:`POLICIES` (``reference`` is always run: it is the yardstick).
    table : int
        1: also measure the in-tissue error table (every preset at :attr:`moduli_pa`); 0: skip it.
    moduli_pa : tuple of float, Pa
        The table's moduli.
    designs : tuple of str
        The table's designs.
    workers : int
        Processes measuring the table.
    """

    cases: int = 5
    policies: tuple[str, ...] = POLICIES
    table: int = 1
    moduli_pa: tuple[float, ...] = (1e5, 1.9e5, 1e6, 1e7)
    designs: tuple[str, ...] = PRESET_NAMES
    workers: int = 2


QUICK = FidelitySettings(cases=1, policies=("kinematic", "scene", "reference"), table=0)


def _scene(seed: int, folder: Path) -> Scene:
    """Write the clinical case of ``seed``, read it back and make its scene as ``reachplan demo`` does."""
    from reachplan.imaging.clinical import clinical_case, write_clinical
    from reachplan.imaging.dicom_io import read_series
    from reachplan.imaging.rtstruct import read_rtstruct
    from reachplan.planner.case.scene import build_scene

    files = write_clinical(folder, clinical_case(seed))
    volume = read_series(files.ct_dir)
    structures = read_rtstruct(files.rtstruct_path, volume)
    targets = tuple(n for n in structures.names if n.casefold().startswith("target"))
    return build_scene(structures, targets, grid=volume.grid, config=PlanConfig(oar_names=(*DEFAULT_OARS, "Tandem")))


def _run(scene: Scene, policy: str) -> tuple[list[Candidate], dict[str, tuple[Candidate, ...]], float, float]:
    """Plan ``scene`` under ``policy``: (candidates, ranking, wall s, CPU s)."""
    from reachplan.planner.case.search import plan

    models = None
    if policy == "kinematic":
        config = PlanConfig(refine_top=0)
    elif policy in ("scene", "reference"):
        config = PlanConfig(models=policy)
    else:  # a fixed rung: the reference policy with that rung as the reference
        rung_model = RUNG_BY_NAME[policy].model()
        assert rung_model is not None
        config, models = PlanConfig(models="reference"), PlanModels.for_config(PlanConfig())
        models = dataclasses.replace(models, reference=rung_model)
    from reachplan.planner.steering.steered import forget_insertions

    forget_insertions()  # the in-tissue solves are memoised: no policy may reuse another's
    t0, c0 = time.perf_counter(), time.process_time()
    result = plan(scene, config, models=models)
    return list(result.candidates), dict(result.ranking), time.perf_counter() - t0, time.process_time() - c0


def _key(c: Candidate) -> tuple[str, bool, str]:
    return c.hole_id, c.steered, c.design_name


def compare(ref: dict[str, tuple[Candidate, ...]], other: dict[str, tuple[Candidate, ...]],
            cap_mm: float = 6.0) -> dict[str, float]:
    """Return a policy's ranking fidelity against the reference policy's.

    Parameters
    ----------
    ref : dict of str to tuple of Candidate
        Ranked candidates per target under the reference policy.
    other : dict of str to tuple of Candidate
        The same under the policy compared.
    cap_mm : float, mm
        Clearances are compared up to this.

    Returns
    -------
    dict of str to float
        ``top1_same`` (fraction of targets), ``kendall_tau`` (mean over targets), ``worst_tau``,
        ``worst_reach_err_mm``, ``worst_clearance_err_mm``.
    """
    from scipy.stats import kendalltau

    same, taus, reach, clear = [], [], [0.0], [0.0]
    for target, ranked in ref.items():
        top = [c for c in ranked if c.feasible][:TOP_N]
        theirs = [c for c in other.get(target, ()) if c.feasible]
        order = {_key(c): i for i, c in enumerate(theirs)}
        same.append(bool(top) and bool(theirs) and _key(top[0]) == _key(theirs[0]))
        mine = {_key(c): i for i, c in enumerate(c for c in ranked if c.feasible)}
        union = list(dict.fromkeys([_key(c) for c in top] + [_key(c) for c in theirs[:TOP_N]]))
        a = [mine.get(k, len(mine)) for k in union]
        b = [order.get(k, len(theirs)) for k in union]
        taus.append(float(kendalltau(a, b).statistic) if len(union) > 1 else 1.0)
        for c in top:
            o = next((x for x in theirs if _key(x) == _key(c)), None)
            if o is not None:
                reach.append(abs(o.reach_error_mm - c.reach_error_mm))
                clear.append(abs(min(o.clearance_mm, cap_mm) - min(c.clearance_mm, cap_mm)))
    tau = [t if np.isfinite(t) else 1.0 for t in taus]
    return {"top1_same": float(np.mean(same)), "kendall_tau": float(np.mean(tau)), "worst_tau": float(min(tau)),
            "worst_reach_err_mm": max(reach), "worst_clearance_err_mm": max(clear)}


def _resolves(cands: list[Candidate]) -> int:
    return sum(1 for c in cands if c.steered and c.model.insertion == "tissue_rod")


def _figure(rows: list[dict[str, object]], policies: tuple[str, ...]) -> Figure:
    """Left: plan CPU time against Kendall's tau (top-1 agreement in the legend); right: the worst differences."""
    fig = Figure(figsize=(11, 4.8))
    ax, bx = fig.subplots(1, 2)
    for i, p in enumerate(policies):
        mine = [r for r in rows if r["policy"] == p]
        t = statistics.median(float(r["plan_cpu_s"]) for r in mine)  # type: ignore[arg-type]
        top1 = 100 * statistics.mean(float(r["top1_same"]) for r in mine)  # type: ignore[arg-type]
        tau = statistics.mean(float(r["kendall_tau"]) for r in mine)  # type: ignore[arg-type]
        low = min(float(r["worst_tau"]) for r in mine)  # type: ignore[arg-type]
        reach = max(float(r["worst_reach_err_mm"]) for r in mine)  # type: ignore[arg-type]
        clear = max(float(r["worst_clearance_err_mm"]) for r in mine)  # type: ignore[arg-type]
        ax.errorbar(t, tau, yerr=[[tau - low], [0.0]], fmt="o", color=f"C{i}", ms=9, capsize=3,
                    label=f"{p}: top-1 same {top1:.0f} %")
        bx.plot(t, reach, "o", color=f"C{i}", ms=9, label=f"{p}: reach")
        bx.plot(t, clear, "s", color=f"C{i}", ms=8, mfc="none", label=f"{p}: clearance")
    for x in (ax, bx):
        x.set_xscale("log")
        x.set_xlabel("plan stage, CPU s per case (median over seeds, log)", fontsize=10)
        x.grid(True, which="both", alpha=0.3)
    ax.set_ylabel("Kendall's tau vs reference, top 10 (mean; bar: worst)", fontsize=10)
    ax.set_ylim(0.0, 1.05)
    ax.legend(fontsize=9, loc="lower right")
    bx.set_ylabel("worst difference from the reference, its top 10 (mm)", fontsize=10)
    bx.legend(fontsize=8, ncol=2, loc="center")
    seeds = ", ".join(sorted({str(r["seed"]) for r in rows}))
    fig.suptitle(f"Planning time against ranking fidelity, clinical case seeds {seeds}", fontsize=11)
    fig.tight_layout()
    return fig


def _table(s: FidelitySettings, out: Path) -> None:
    """Measure the in-tissue error table and write its JSON and CSV."""
    from reachplan.planner.bench.fidelity_errors import measure_all

    jobs = [(d, e) for d in s.designs for e in s.moduli_pa]
    rows = measure_all(jobs, s.workers)
    write_json(out / "model_errors_tissue.json",
               {"source": "reachplan bench fidelity: each insertion model's tip against the planner's reference "
                          "in-tissue rod",
                "reference": "tissue_rod, 2 mm insertion steps extrapolated with 4 mm ones (PLANNER_REFERENCE)",
                "schedules": "factor_schedules: 20 mm ramps from 0, 20, 40, 60 mm to 60 / 100 % of the limit",
                "rows": [r.to_json() for r in rows]})
    write_csv(out / "model_errors_tissue.csv",
              ["design", "modulus_pa", "rung", "depth_mm", "max_mm", "rms_mm", "ms_per_insertion"],
              [[r.design, r.modulus_pa, r.rung, d, m, q, round(r.ms_per_insertion, 3)]
               for r in rows for d, m, q in zip(r.depths_mm, r.max_mm, r.rms_mm, strict=True)])


def run(args: argparse.Namespace) -> int:
    """Run ``reachplan bench fidelity`` into ``args.out``.

    Parameters
    ----------
    args : argparse.Namespace
        ``out``, ``quick`` and the target's options.

    Returns
    -------
    int
        0 once the CSV and chart are written.
    """
    s = settings(args, FidelitySettings(), QUICK)
    out: Path = args.out
    if s.table:
        _table(s, out)
    policies = tuple(p for p in POLICIES if p in s.policies or p == "reference")
    rows: list[dict[str, object]] = []
    for seed in range(s.cases):
        with tempfile.TemporaryDirectory() as tmp:
            scene = _scene(seed, Path(tmp))
        runs = {p: _run(scene, p) for p in reversed(policies)}  # the reference first
        for p in policies:
            cands, ranking, wall, cpu = runs[p]
            row: dict[str, object] = {"seed": seed, "policy": p, "plan_s": round(wall, 2), "plan_cpu_s": round(cpu, 2),
                                      "targets": len(ranking), "resolved": _resolves(cands)}
            row.update({k: round(v, 4) for k, v in compare(runs["reference"][1], ranking).items()})
            rows.append(row)
            print(f"seed {seed} {p:17s} plan {wall:6.1f} s wall, {cpu:6.1f} s CPU, {row['resolved']} re-solved; "
                  f"top-1 same {row['top1_same']}, tau {row['kendall_tau']}, reach/clearance err "
                  f"{row['worst_reach_err_mm']}/{row['worst_clearance_err_mm']} mm (load {load_avg():.1f})",
                  flush=True)
        write_csv(out / "fidelity.csv", list(rows[0]), rows)  # after every seed: a long run keeps its rows
    write_png(out / "fidelity.png", _figure(rows, policies))
    return 0
