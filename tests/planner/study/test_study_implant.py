"""Implant study over a cohort of clinical cases: per-case rows, failures as rows, resume, Dask, and the paired
t-interval against its closed form (and its coverage on simulated cohorts)."""

from __future__ import annotations

import csv
import dataclasses
import json
import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from reachplan.planner.case.config import DEFAULT_OARS, PlanConfig
from reachplan.planner.cli import main
from reachplan.planner.cli.study import COARSE_FAMILY
from reachplan.planner.errors import StudyError
from reachplan.planner.steering.steered import ScheduleFamily
from reachplan.planner.study import LOOPBACK_HTTP
from reachplan.planner.study.implant import (
    ImplantCase,
    ImplantRow,
    ImplantStudySpec,
    run_implant_study,
)
from reachplan.planner.study.statistics import t_interval
from reachplan.planner.study.workers import WorkerSetup

#: Student t quantiles t(0.975, df) from a printed table (NIST/SEMATECH e-Handbook, 1.3.6.7.2), not from scipy.
T975 = {1: 12.706, 2: 4.303, 3: 3.182, 4: 2.776, 9: 2.262}
#: columns that depend on where and how fast a case ran, not on what it computed
RUN_COLUMNS = ("seconds", "cpu_seconds", "worker")
FAILING_SEED, NO_STEERED_SEED = 2, 4
SEEDS = (0, 1, 2, 3, 4, 5)


def _arm(n: int, d90: float) -> dict[str, object]:
    return {"n_needles": n, "needles": [{}] * n, "aims_met": d90 >= 85.0, "hrctv_d90_eqd2_gy": d90,
            "hrctv_d98_eqd2_gy": d90 - 5.0, "oar_d2cc_eqd2_gy": {"Bladder": 70.0}, "candidates": 10 * n,
            "reason": ""}


def planted(task: ImplantCase, spec: ImplantStudySpec) -> dict[str, Any]:
    """A planted case (no planning): steering saves ``seed % 2`` needles and gains ``1 + seed / 2`` Gy of D90.

    Seed 2 raises; seed 4's steered arm has no implant.
    """
    from reachplan.planner.study.implant import case_row

    s = task.seed
    if s == FAILING_SEED:
        raise RuntimeError("planted failure in the worker")
    straight = _arm(4 + s % 3, 80.0 + s)
    steered = ({"needles": [], "aims_met": False, "candidates": 0, "reason": "no candidate needle reaches the HR-CTV"}
               if s == NO_STEERED_SEED else _arm(4 + s % 3 - s % 2, 80.0 + s + 1.0 + s / 2))
    implant = {"straight": straight, "steered": steered}
    return {"row": dataclasses.asdict(case_row(task, implant, 0.01, 0.01)), "implant": implant}


def _not_called(task: ImplantCase, spec: ImplantStudySpec) -> dict[str, Any]:
    raise AssertionError(f"case {task.key} was planned again")


def _csv(path: Path) -> list[dict[str, str]]:
    with path.open(encoding="utf-8", newline="") as f:
        return list(csv.DictReader(f))


def _closed_form(d: list[float]) -> tuple[float, float, float]:
    n = len(d)
    mean = sum(d) / n
    s = math.sqrt(sum((x - mean) ** 2 for x in d) / (n - 1))
    half = T975[n - 1] * s / math.sqrt(n)
    return mean, mean - half, mean + half


# ------------------------------------------------------------------------------------------------ statistics

def test_t_interval_matches_the_closed_form() -> None:
    """mean ± t(0.975, n-1) s / √n with the table's quantile, for a few cohorts; degenerate cohorts say so."""
    for d in ([1.0, 2.0, 3.0, 4.0], [0.0, 1.0, 1.0, 1.0], [-2.0, 5.0], [3.0, 1.0, 4.0, 1.0, 5.0, 9.0, 2.0, 6.0, 5.0,
                                                                            3.0]):
        st = t_interval(d)
        mean, low, high = _closed_form(d)
        assert st.n == len(d) and st.mean == pytest.approx(mean)
        assert st.low == pytest.approx(low, abs=2e-3) and st.high == pytest.approx(high, abs=2e-3)
        assert st.low < st.mean < st.high
    same = t_interval([2.0, 2.0, 2.0])
    assert (same.low, same.mean, same.high) == (2.0, 2.0, 2.0)  # no spread: the interval is the mean
    one = t_interval([1.5])
    assert one.mean == 1.5 and one.low is None and one.high is None
    assert t_interval([]).mean is None
    with pytest.raises(StudyError):
        t_interval([1.0, float("nan")])
    with pytest.raises(StudyError):
        t_interval([1.0, 2.0], level=1.0)


def test_t_interval_covers_the_true_mean_at_its_level() -> None:
    """On 4000 simulated cohorts of 5 normal differences the 95 % interval holds the true mean 95 ± 1.5 % of the
    time (a normal-quantile interval would hold it only about 88 % of the time at n = 5)."""
    rng = np.random.default_rng(11)
    hits = 0
    for _ in range(4000):
        st = t_interval(rng.normal(1.7, 2.0, size=5))
        assert st.low is not None and st.high is not None
        hits += st.low <= 1.7 <= st.high
    assert abs(hits / 4000 - 0.95) < 0.015


# ------------------------------------------------------------------------------------------------ the study

@pytest.fixture()
def spec() -> ImplantStudySpec:
    return ImplantStudySpec(SEEDS)


def test_rows_failures_and_summary(spec: ImplantStudySpec, tmp_path: Path) -> None:
    """One CSV row per case; a case that raises and a case whose arm has no implant are rows with their reasons;
    the summary's intervals are the closed form on the paired cases and contain their means."""
    res = run_implant_study(spec, tmp_path / "s", workers=0, task_fn=planted)
    rows = _csv(tmp_path / "s" / "cases.csv")
    assert [r["case"] for r in rows] == [f"clinical_{s}" for s in SEEDS]
    assert list(rows[0]) == [f.name for f in dataclasses.fields(ImplantRow)]
    by_seed = {int(r["seed"]): r for r in rows}
    assert by_seed[FAILING_SEED]["status"] == "failed"
    assert "RuntimeError: planted failure in the worker" in by_seed[FAILING_SEED]["reason"]
    assert by_seed[NO_STEERED_SEED]["status"] == "failed"
    assert by_seed[NO_STEERED_SEED]["reason"] == "steered arm: no candidate needle reaches the HR-CTV"
    assert by_seed[NO_STEERED_SEED]["straight_needles"] == "5" and by_seed[NO_STEERED_SEED]["steered_needles"] == ""
    paired = [s for s in SEEDS if s not in (FAILING_SEED, NO_STEERED_SEED)]
    for s in paired:
        r = by_seed[s]
        assert r["status"] == "ok" and r["reason"] == ""
        assert int(r["straight_needles"]) - int(r["steered_needles"]) == int(r["needles_saved"]) == s % 2
        assert float(r["d90_gained_gy"]) == pytest.approx(1.0 + s / 2)
        assert json.loads(r["straight_oar_d2cc_eqd2_gy"]) == {"Bladder": 70.0}
    doc = json.loads((tmp_path / "s" / "summary.json").read_text(encoding="utf-8"))
    assert doc["cases"] == len(SEEDS) and doc["paired_cases"] == len(paired)
    assert set(doc["failed"]) == {f"clinical_{FAILING_SEED}", f"clinical_{NO_STEERED_SEED}"}
    saved = [float(s % 2) for s in paired]  # 0, 1, 1, 1 (seeds 0, 1, 3, 5)
    got = doc["needles_saved"]
    assert got["n"] == len(paired) and got["mean"] == pytest.approx(np.mean(saved), abs=1e-4)
    assert got["test"] == "Wilcoxon signed-rank" and got["ci95"][0] <= got["mean"] <= got["ci95"][1]
    # three tied positive differences: W+ = 6, tie-corrected variance 3.5 - 0.5 = 3, z = 3 / sqrt(3)
    assert got["p_value"] == pytest.approx(math.erfc(math.sqrt(3) / math.sqrt(2)), abs=1e-6)
    assert got["other_tests"][0]["p_value"] == pytest.approx(0.25)  # exact sign test: 2 / 2^3
    mean, low, high = _closed_form([1.0 + s / 2 for s in paired])
    got = doc["d90_gain_gy"]
    assert got["test"] == "paired t" and got["mean"] == pytest.approx(mean, abs=1e-4)
    assert got["ci95"] == pytest.approx([low, high], abs=2e-3)
    assert doc["power"]["cases_paired_t"] is not None and len(doc["assumptions"]) >= 4
    assert set(doc["strata"]) == {"parametrial_extension", "bladder_filling", "uterine_version", "tumour_volume"}
    # aims met (D90 >= 85 Gy here): straight 85 (seed 5); steered 85.5 (seed 3), 88.5 (seed 5); none for failures
    assert doc["aims_met"] == {"straight": 1, "steered": 2}
    # like for like: only seed 5 meets every aim in both arms (one case: no statistic); seed 3 only with steering
    assert doc["needles_saved_both_meet_aims"] is None
    assert doc["only_steered_meets_aims"] == ["clinical_3"] and doc["only_straight_meets_aims"] == []
    assert res.summary.n_paired == len(paired)
    assert (tmp_path / "s" / "summary.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    part = json.loads((tmp_path / "s" / "parts" / "clinical_0.json").read_text(encoding="utf-8"))
    assert part["implant"]["straight"]["n_needles"] == 4


def test_resume_plans_only_what_is_missing_or_failed(spec: ImplantStudySpec, tmp_path: Path) -> None:
    out = tmp_path / "s"
    first = run_implant_study(spec, out, workers=0, task_fn=planted)
    again = run_implant_study(spec, out, workers=0, task_fn=_not_called)
    assert again.n_resumed == len(SEEDS) and again.rows == first.rows
    (out / "parts" / "clinical_1.json").unlink()
    retried = run_implant_study(spec, out, workers=0, task_fn=_not_called, retry_failed=True)
    assert retried.n_resumed == len(SEEDS) - 3  # the removed case and the two failed ones
    replanned = {r.case: r.reason for r in retried.rows if "AssertionError: case" in r.reason}
    assert set(replanned) == {"clinical_1", f"clinical_{FAILING_SEED}", f"clinical_{NO_STEERED_SEED}"}
    with pytest.raises(StudyError, match="another study"):
        run_implant_study(ImplantStudySpec((0, 1)), out, workers=0, task_fn=planted)


def test_dask_gives_the_serial_rows(spec: ImplantStudySpec, tmp_path: Path) -> None:
    """The same rows on a Dask LocalCluster (2 workers; threads, as worker processes cannot import this test
    module's planted task), the failing case recorded, not raised."""
    import distributed  # a runtime dependency: this test must run, not skip

    serial = run_implant_study(spec, tmp_path / "serial", workers=0, task_fn=planted)
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=False, dashboard_address=None,
                                  scheduler_kwargs=LOOPBACK_HTTP) as cluster, distributed.Client(cluster) as client:
        on_dask = run_implant_study(spec, tmp_path / "dask", client=client, task_fn=planted,
                                    worker_setup=WorkerSetup(groups=()))  # the kernels: test_study_scale

    def strip(rows: tuple[ImplantRow, ...]) -> list[dict[str, object]]:
        return [{k: v for k, v in dataclasses.asdict(r).items() if k not in RUN_COLUMNS} for r in rows]

    assert strip(on_dask.rows) == strip(serial.rows)


def test_cli_refuses_mixed_studies(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["study", "--implant", "2", "--cases", str(tmp_path), "--out", str(tmp_path / "o")]) == 2
    assert "--implant builds its own clinical cases" in capsys.readouterr().err
    assert main(["study", "--implant", "2", "--designs", "straight", "--out", str(tmp_path / "o")]) == 2
    assert "straight arm" in capsys.readouterr().err
    assert main(["study", "--implant", "0", "--out", str(tmp_path / "o")]) == 2


# ------------------------------------------------------------------------------------------------ a real case

@pytest.mark.slow
def test_clinical_case_end_to_end(tmp_path: Path) -> None:
    """One clinical case planned for real in a reduced configuration (coarse schedules, 1 needle at most)."""
    from reachplan.planner.implant.settings import ImplantSettings

    config = PlanConfig(family=ScheduleFamily(**COARSE_FAMILY), oar_names=(*DEFAULT_OARS, "Tandem"))
    settings = ImplantSettings(max_needles=1, rolls=2, steered_per_hole=1, selection_target_points=150,
                               final_target_points=400, exhaustive_max_selections=0)
    res = run_implant_study(ImplantStudySpec((0,), config, settings), tmp_path / "s", workers=0)
    (row,) = res.rows
    assert row.status == "ok", row.reason
    part = json.loads((tmp_path / "s" / "parts" / "clinical_0.json").read_text(encoding="utf-8"))
    for arm in ("straight", "steered"):
        n, d90, d98 = (getattr(row, f"{arm}_{k}") for k in ("needles", "hrctv_d90_eqd2_gy", "hrctv_d98_eqd2_gy"))
        assert n == 1 and n == sum(nd["kind"] != "intracavitary" for nd in part["implant"][arm]["needles"])
        assert 0 < d98 <= d90 < 400  # D98 of a volume never exceeds its D90
        assert set(json.loads(getattr(row, f"{arm}_oar_d2cc_eqd2_gy"))) >= {"Bladder", "Rectum"}
    assert row.steered_candidates > row.straight_candidates  # the steered arm holds the straight candidates too
    assert row.needles_saved == row.straight_needles - row.steered_needles
    assert res.summary.needles_saved.n == 1 and res.summary.needles_saved.ci95 is None  # one case: no interval
