"""Design studies: cohort variants, the part-file ledger (resume, exactly once), failures recorded, and the
same rows on a real Dask ``LocalCluster`` (2 worker processes on loopback), also when a worker dies."""

from __future__ import annotations

import dataclasses
import json
import math
import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import pytest

from reachplan.imaging.solids import Cylinder
from reachplan.planner.case.config import PlanConfig
from reachplan.planner.cli import main
from reachplan.planner.cli.study import COARSE_FAMILY
from reachplan.planner.errors import PlanInputError
from reachplan.planner.steering.steered import ScheduleFamily
from reachplan.planner.study import (
    KILL_AFTER_PARTS_ENV,
    LOOPBACK_HTTP,
    StudyRow,
    StudySpec,
    StudyTask,
    discover_cases,
    run_study,
    run_task,
)
from reachplan.planner.study.cohort import make_cohort, perturbation, perturbed_spec

if TYPE_CHECKING:
    import pyarrow as pa

pytestmark = pytest.mark.slow

DESIGNS = ("15ga-30j-tip", "straight")
TARGETS = ("Target_65_000", "Target_80_090")
#: columns that depend on where and when a task ran, not on what it computed
RUN_COLUMNS = ["task_scene_s", "task_plan_s", "task_cpu_s", "worker", "finished_utc"]


def _config() -> PlanConfig:
    return PlanConfig(family=ScheduleFamily(**COARSE_FAMILY))  # the CLI's --family coarse: 6 schedules


def _result_rows(table: pa.Table) -> list[dict[str, object]]:
    return table.drop_columns(RUN_COLUMNS).to_pylist()


@pytest.fixture(scope="module")
def cohort(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("cohort")
    make_cohort(out, 2, seed=7, case="pilot")
    return out


@pytest.fixture(scope="module")
def spec(cohort: Path) -> StudySpec:
    return StudySpec(discover_cases([cohort]), DESIGNS, TARGETS, _config())


@pytest.fixture(scope="module")
def reference(spec: StudySpec, tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, pa.Table]:
    """The study run serially in this process: the rows every other way of running it must reproduce."""
    out = tmp_path_factory.mktemp("serial") / "study"
    res = run_study(spec, out, workers=0)
    return out, res.table


# ------------------------------------------------------------------------------------------------- cohort


def test_cohort_variants_are_deterministic_and_scale_volumes_exactly() -> None:
    ref = perturbed_spec(perturbation(0, 0))
    assert perturbation(3, 5) == perturbation(3, 5) and perturbation(3, 5) != perturbation(3, 6)
    p = perturbation(3, 5)
    var = perturbed_spec(p)
    scale = dict(p.scale)
    # axial scaling by k multiplies an ellipsoid's (and a z-cylinder's) volume by k^2; z extents are unchanged
    for name in ("Bladder", "Rectum", "HR-CTV"):
        assert var.get(name).analytic_volume_mm3 == pytest.approx(ref.get(name).analytic_volume_mm3 * scale[name] ** 2)
    for a, b in zip(ref.targets, var.targets, strict=True):
        (ca,), (cb,) = a.shapes, b.shapes
        assert isinstance(ca, Cylinder) and isinstance(cb, Cylinder)
        assert (ca.z0_mm, ca.z1_mm) == (cb.z0_mm, cb.z1_mm)
        ra, rb = math.hypot(*ca.center_xy_mm), math.hypot(*cb.center_xy_mm)
        assert rb == pytest.approx(ra * p.target_radius_scale, abs=1e-5)
        turn = math.degrees(math.atan2(cb.center_xy_mm[1], cb.center_xy_mm[0])
                            - math.atan2(ca.center_xy_mm[1], ca.center_xy_mm[0]))
        assert (turn - p.target_rotation_deg + 180) % 360 - 180 == pytest.approx(0, abs=1e-6)
    # the side walls move apart (or together) by the same amount on both sides
    walls = sorted(np.mean([s.bounds()[:, 0] for s in var.get("Bone").shapes], axis=1))
    ref_walls = sorted(np.mean([s.bounds()[:, 0] for s in ref.get("Bone").shapes], axis=1))
    assert walls[0] == pytest.approx(ref_walls[0] - p.bone_shift_mm)
    assert walls[-1] == pytest.approx(ref_walls[-1] + p.bone_shift_mm)


# ------------------------------------------------------------------------------------------- serial + ledger


def test_serial_study_has_one_row_per_case_design_target(spec: StudySpec, reference: tuple[Path, pa.Table]) -> None:
    out, table = reference
    keys = list(zip(table["case"].to_pylist(), table["design"].to_pylist(), table["target"].to_pylist(), strict=True))
    assert sorted(keys) == sorted((c.case_id, d, t) for c in spec.cases for d in DESIGNS for t in TARGETS)
    assert set(table["status"].to_pylist()) == {"ok"}
    assert sorted(p.name for p in (out / "parts").iterdir()) == sorted(f"{t.key}.parquet" for t in spec.tasks())
    # straight rows carry no steered candidate; the steered design reaches at least what straight needles do
    rows = table.to_pylist()
    assert not any(r["reached_steered"] for r in rows if r["design"] == "straight")
    by = {(r["case"], r["target"], r["design"]): r for r in rows}
    for (case, target, _), r in by.items():
        assert r["reached_straight"] == by[(case, target, "straight")]["reached_straight"]
        if r["reached_steered"]:
            assert r["steered_reach_error_mm"] <= spec.config.reach_tolerance_mm
    # the summary is the table's own arithmetic
    summary = {s.design: s for s in run_study(spec, out, workers=0).summaries}
    for design in DESIGNS:
        sel = [r for r in rows if r["design"] == design]
        assert summary[design].reach_rate_any == pytest.approx(
            np.mean([r["reached_steered"] or r["reached_straight"] for r in sel]), abs=1e-4)
    assert (out / "summary.png").stat().st_size > 0 and (out / "summary.csv").read_text().startswith("design,")


def test_resume_recomputes_only_missing_tasks(spec: StudySpec, reference: tuple[Path, pa.Table]) -> None:
    out, table = reference
    before = {p.name: p.stat().st_mtime_ns for p in (out / "parts").iterdir()}
    again = run_study(spec, out, workers=0)
    assert again.n_resumed == again.n_tasks == 4
    assert {p.name: p.stat().st_mtime_ns for p in (out / "parts").iterdir()} == before
    victim = out / "parts" / f"{spec.tasks()[1].key}.parquet"
    victim.unlink()
    resumed = run_study(spec, out, workers=0)
    assert resumed.n_resumed == 3
    assert _result_rows(resumed.table) == _result_rows(table)


def test_killed_run_resumes_with_every_row_once(spec: StudySpec, cohort: Path, reference: tuple[Path, pa.Table],
                                                tmp_path: Path) -> None:
    out = tmp_path / "study"
    cmd = [sys.executable, "-m", "reachplan.planner.cli", "study", "--cases", str(cohort), "--designs", *DESIGNS,
           "--targets", *TARGETS, "--family", "coarse", "--workers", "0", "--quiet", "--out", str(out)]
    # the process kills itself (SIGKILL) right after its first part file: no timing involved
    env = {**os.environ, KILL_AFTER_PARTS_ENV: "1"}
    proc = subprocess.run(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, env=env, timeout=600)
    assert proc.returncode == -signal.SIGKILL, proc.stderr.decode(errors="replace")[-2000:]
    n_done = len(list((out / "parts").glob("*.parquet")))
    assert n_done == 1, "the run should have been killed after its first part file"
    assert not (out / "study.parquet").exists()
    res = run_study(spec, out, workers=0)
    assert res.n_resumed == n_done
    assert _result_rows(res.table) == _result_rows(reference[1])


def test_other_study_in_out_folder_is_refused(spec: StudySpec, reference: tuple[Path, pa.Table]) -> None:
    with pytest.raises(PlanInputError, match="another study"):
        run_study(dataclasses.replace(spec, designs=("15ga-20j-tip",)), reference[0], workers=0)


def _explode(task: StudyTask, config: PlanConfig) -> Sequence[StudyRow]:
    if task.design == "straight":
        raise RuntimeError("simulated solver crash")
    return run_task(task, config)


def test_failing_tasks_are_recorded_and_the_study_goes_on(cohort: Path, tmp_path: Path) -> None:
    bad = tmp_path / "bad_case"
    bad.mkdir()
    (bad / "RS.bad.dcm").write_bytes(b"this is not DICOM")
    good = discover_cases([cohort])[:1]
    spec = StudySpec((*good, *discover_cases([bad])), DESIGNS, TARGETS, _config())
    res = run_study(spec, tmp_path / "study", workers=0, task_fn=_explode)
    rows = res.table.to_pylist()
    assert len(rows) == 2 * 2 * 2 and res.n_failed_tasks == 3
    ok = [r for r in rows if r["status"] == "ok"]
    assert {(r["case"], r["design"]) for r in ok} == {(good[0].case_id, "15ga-30j-tip")}
    assert all("simulated solver crash" in r["reason"] for r in rows if r["design"] == "straight")
    assert all("bad_case" not in r["reason"] or "RS.bad.dcm" in r["reason"] for r in rows if r["case"] == "bad_case")
    assert all(r["reached_steered"] is None for r in rows if r["status"] == "failed")
    # a retry runs only the failed tasks again
    again = run_study(spec, tmp_path / "study", workers=0, retry_failed=True)
    assert again.n_resumed == 1 and again.n_failed_tasks == 2  # the broken case still fails; straight now works


def test_dose_is_what_the_plan_command_computes(cohort: Path, tmp_path: Path) -> None:
    from reachplan.imaging.rtstruct import read_rtstruct
    from reachplan.planner.case.scene import build_scene
    from reachplan.planner.case.search import plan
    from reachplan.planner.delivery import plan_delivery

    case = discover_cases([cohort])[0]
    res = run_study(StudySpec((case,), DESIGNS, TARGETS, _config(), dose=True), tmp_path / "study", workers=0)
    rows = {(r["design"], r["target"]): r for r in res.table.to_pylist()}
    # the same case planned and delivered directly, as `reachplan plan` does
    structures = read_rtstruct(case.rtstruct, None)
    cfg = dataclasses.replace(_config(), designs=("15ga-30j-tip",))
    opt = plan_delivery(plan(build_scene(structures, list(TARGETS), config=cfg), cfg), structures, None).optimisation
    for target in TARGETS:
        steered = rows[("15ga-30j-tip", target)]
        assert steered["task_hrctv_d90_gy"] == pytest.approx(opt.target.d90_gy, abs=1e-3)
        assert steered["task_dose_aim_met"] == opt.aim_met and steered["task_dose_reason"] == ""
        straight = rows[("straight", target)]
        if not any(r["reached_straight"] for r in rows.values()):  # no feasible straight needle: no dose, and why
            assert straight["task_hrctv_d90_gy"] is None and "no feasible needle" in straight["task_dose_reason"]
    summary = {s.design: s for s in res.summaries}
    assert summary["15ga-30j-tip"].median_hrctv_d90_gy == pytest.approx(opt.target.d90_gy, abs=1e-3)
    assert summary["15ga-30j-tip"].dose_aim_met_rate == float(opt.aim_met)


# -------------------------------------------------------------------------------------------------- CLI


def test_cli_resumes_the_same_study(cohort: Path, reference: tuple[Path, pa.Table],
                                    capsys: pytest.CaptureFixture[str]) -> None:
    code = main(["study", "--cases", str(cohort), "--designs", *DESIGNS, "--targets", *TARGETS, "--family", "coarse",
                 "--workers", "0", "--out", str(reference[0]), "--json"])
    assert code == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["tasks"] == doc["resumed"] == 4 and doc["rows"] == 8 and doc["failed_tasks"] == 0
    assert [d["design"] for d in doc["designs"]] == sorted(DESIGNS)


def test_cli_rejects_missing_cases(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["study", "--cases", str(tmp_path / "nowhere"), "--out", str(tmp_path / "o"), "--workers", "0"]) == 2
    assert "does not exist" in capsys.readouterr().err


# ------------------------------------------------------------------------------------------------- Dask


@pytest.fixture(scope="module")
def client() -> Iterator[Any]:
    import distributed  # a runtime dependency: the cluster tests must run, not skip
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True, host="127.0.0.1",
                                  dashboard_address=None, scheduler_kwargs=LOOPBACK_HTTP) as cluster, \
            distributed.Client(cluster) as c:
        yield c


def test_local_cluster_gives_the_same_rows(cohort: Path, reference: tuple[Path, pa.Table], client: Any,
                                           tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    import pyarrow.parquet as pq

    out = tmp_path / "study"
    code = main(["study", "--cases", str(cohort), "--designs", *DESIGNS, "--targets", *TARGETS, "--family", "coarse",
                 "--scheduler", client.scheduler.address, "--out", str(out), "--json"])
    assert code == 0 and json.loads(capsys.readouterr().out)["resumed"] == 0
    table = pq.read_table(out / "study.parquet")
    assert _result_rows(table) == _result_rows(reference[1])
    assert len(set(table["worker"].to_pylist())) == 2  # both worker processes took part


def test_worker_killed_mid_study_loses_and_repeats_nothing(spec: StudySpec, reference: tuple[Path, pa.Table],
                                                           client: Any, tmp_path: Path) -> None:
    """A worker killed while a task runs and another is done: the study still has every row exactly once.

    Each worker takes one case's tasks in order; with the straight needles first (a fast task) and the stylet second
    (seconds), a part is written while both workers are still busy: the moment to kill one. The rows are compared
    in any order (the task order differs from the reference's).
    """
    fast_first = dataclasses.replace(spec, designs=tuple(sorted(spec.designs, key=lambda d: d != "straight")))
    out = tmp_path / "study"
    pids = client.run(os.getpid)  # worker address -> process id
    done: dict[str, Any] = {}
    runner = threading.Thread(target=lambda: done.update(result=run_study(fast_first, out, client=client)))
    runner.start()
    killed = None
    deadline = time.monotonic() + 60
    while killed is None and time.monotonic() < deadline and runner.is_alive():
        busy = [a for a, keys in client.processing().items() if keys and a in pids]
        if busy and list((out / "parts").glob("*.parquet")):  # mid-study: a task done, others running
            killed = busy[0]
            os.kill(pids[killed], signal.SIGKILL)
        time.sleep(0.02)
    runner.join(timeout=120)
    assert killed is not None, "no worker was busy mid-study"
    assert not runner.is_alive()
    res = done["result"]
    assert res.n_failed_tasks == 0

    def rows(table: pa.Table) -> list[str]:
        return sorted(json.dumps(r, sort_keys=True, default=str) for r in _result_rows(table))

    assert rows(res.table) == rows(reference[1])  # every row exactly once, none failed


def test_clinical_cohort_uses_the_clinical_case_of_each_seed(tmp_path: Path) -> None:
    from reachplan.imaging.clinical import sample_params

    (case,) = make_cohort(tmp_path / "c", 1, seed=5)
    doc = json.loads((case / "case.json").read_text())
    assert doc["seed"] == 5 and doc["params"] == json.loads(json.dumps(dataclasses.asdict(sample_params(5))))
    assert json.loads((tmp_path / "c" / "cohort.json").read_text())["kind"] == "clinical"
    assert (case / "RS.phantom.dcm").is_file() and len(list((case / "CT").glob("*.dcm"))) > 50
