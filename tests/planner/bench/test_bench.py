"""``reachplan bench``: every target runs from the installed package, writes real CSV + PNG into ``--out``, and
``--install`` writes only into a reachplan source checkout (never into this repository from a test)."""

from __future__ import annotations

import csv
import json
import struct
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from reachplan.planner.bench import dose, models, planning
from reachplan.planner.bench.common import BenchError, install, source_checkout, write_csv, write_png
from reachplan.planner.cli import bench, main

REPO = Path(__file__).resolve().parents[3]
PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


def _owned_files() -> list[Path]:
    return [REPO / dest for t in bench.TARGETS for dest in bench._load(t.module).INSTALLS.values()]


@pytest.fixture(autouse=True)
def _outside_the_repository(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Iterator[None]:
    """Run from a temporary folder (the default ``--repo`` is the current one) and check afterwards that no file a
    benchmark owns in this checkout was touched."""
    monkeypatch.chdir(tmp_path)
    before = {p: p.stat().st_mtime_ns for p in _owned_files() if p.exists()}
    yield
    assert {p: p.stat().st_mtime_ns for p in _owned_files() if p.exists()} == before


def _read_csv(path: Path) -> tuple[list[str], list[dict[str, str]]]:
    with path.open(newline="", encoding="utf-8") as fh:
        reader = csv.DictReader(fh)
        return list(reader.fieldnames or ()), list(reader)


def _png_size(path: Path) -> tuple[int, int]:
    """(width, height) in pixels from the IHDR chunk; asserts the PNG signature."""
    data = path.read_bytes()
    assert data[:8] == PNG_SIGNATURE, f"{path.name} is not a PNG"
    assert data[12:16] == b"IHDR"
    width, height = struct.unpack(">II", data[16:24])
    return width, height


def _assert_real_png(path: Path) -> None:
    width, height = _png_size(path)
    assert width >= 300 and height >= 200
    assert path.stat().st_size > 10_000  # a chart, not an empty canvas


def test_every_target_is_a_subcommand_installed_with_the_package(capsys: pytest.CaptureFixture[str]) -> None:
    assert [t.name for t in bench.TARGETS] == ["models", "planning", "dose", "imaging", "study", "studycost", "startup",
                                              "firstrun", "distance", "dosekernel", "implant", "report", "factors",
                                              "joints", "fidelity", "demo", "band", "reconstruct"]
    for target in bench.TARGETS:
        module = bench._load(target.module)
        assert callable(module.run)
        for name, dest in module.INSTALLS.items():  # owned files: package data or docs/, relative to a checkout
            assert Path(dest).parts[0] in {"docs", "rod_model", "planner"} and not Path(dest).is_absolute()
            assert Path(dest).name == name
        with pytest.raises(SystemExit) as exc:
            main(["bench", target.name])  # --out is required
        assert exc.value.code == 2
    capsys.readouterr()


def test_factors_quick_writes_a_table_the_planner_reads(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    import json

    from reachplan.planner.steering.factors import FactorCurve, design_key, factor_table
    from reachplan.rod_model.design import preset

    out = tmp_path / "out"
    assert main(["bench", "factors", "--quick", "--out", str(out)]) == 0
    capsys.readouterr()
    entry = json.loads((out / "curvature_factors.json").read_text())["designs"][0]
    curve = FactorCurve(entry["design"], entry["key"], tuple(entry["moduli_pa"]), tuple(entry["factors"]),
                        tuple(entry["rms_mm"]))
    assert curve.key == design_key(preset("15ga-30j-tip"))
    packaged = factor_table()[curve.key]  # the same fit as the packaged table's, at the same modulus
    assert curve.factors[0] == pytest.approx(packaged(curve.moduli_pa[0]), abs=1e-3)
    _, rows = _read_csv(out / "curvature_factors.csv")
    assert len(rows) == 1 and float(rows[0]["rms_mm"]) < 2.0
    assert (out / "curvature_factors.png").stat().st_size > 10_000


def _quick(target: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> Path:
    """Run ``reachplan bench TARGET --quick`` into a fresh folder (exit status 0, output swallowed); return it."""
    out = tmp_path / "out"
    assert main(["bench", target, "--quick", "--out", str(out)]) == 0
    capsys.readouterr()
    return out


def test_models_quick_writes_the_chart_and_its_table(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = _quick("models", tmp_path, capsys)
    header, rows = _read_csv(out / "rod_models.csv")
    assert header == list(models.ROW_COLUMNS)
    default = {r["model"]: r for r in rows if r["resolution"].endswith("(default)")}
    assert set(default) == {"constant_curvature", "planar_beam", "cosserat_rod", "two_tube_cosserat"}
    # against the reference (the same two-tube model at 16x finer steps): the default resolution has converged,
    # while a constant curvature misses the tube's bending by millimetres
    assert float(default["two_tube_cosserat"]["max_tip_error_mm"]) < 1e-3
    assert float(default["constant_curvature"]["max_tip_error_mm"]) > 1.0
    assert all(float(r["median_ms"]) > 0 for r in rows)
    header, cases = _read_csv(out / "rod_models_stability.csv")
    assert header == list(models.STABILITY_COLUMNS) and cases
    assert all(c["reason"] for c in cases if c["success"] == "False")
    for name in ("rod_models_pareto.png", "rod_models_stability.png"):
        _assert_real_png(out / name)
    assert (out / "model_errors.json").stat().st_size > 0
    # friction: the default resolution converged against itself at 8 steps/mm; friction opens a loop
    header, frows = _read_csv(out / "rod_models_friction.csv")
    assert header == list(models.FRICTION_COLUMNS) and [r["model"] for r in frows] == [models.FRICTION_MODEL]
    assert float(frows[0]["max_tip_error_mm"]) < 1e-3
    summary = json.loads((out / "summary.json").read_text(encoding="utf-8"))
    widths = {k: v for k, v in summary.items() if k.startswith("loop_width_mm_")}
    assert len(widths) == len(models.QUICK.friction_presets) and all(v > 0 for v in widths.values())
    # honesty: a straight column below the Euler load stays straight; above it, and at 5000 N, the solver says
    # it failed (with the reason) rather than returning a shape
    header, honest = _read_csv(out / "rod_models_honesty.csv")
    assert header == list(models.HONESTY_COLUMNS)
    by_case = {r["case"]: r for r in honest}
    below = by_case["15ga-20j-tip, axial 0.9 P_euler(tube)"]
    assert below["converged"] == "True" and abs(float(below["tip_x_mm"])) + abs(float(below["tip_y_mm"])) < 1e-3
    for case in ("15ga-20j-tip, axial 1.1 P_euler(tube)", "15ga-20j-tip, 5000 N tension"):
        assert by_case[case]["converged"] == "False" and by_case[case]["reason"]
    # in tissue: one row per modulus, schedule (two plateaus per onset) and depth; a missing tip always carries
    # the failure's reason; the in-tissue models are on the speed/accuracy chart
    header, points = _read_csv(out / "rod_models_tissue.csv")
    assert header == list(models.TISSUE_COLUMNS)
    q = models.QUICK
    assert len(points) == len(q.tissue_moduli_pa) * 2 * len(q.tissue_onsets_mm) * len(q.tissue_depths_mm)
    for p in points:
        assert np.isfinite(float(p["tissue_rod_tip_mm"])) == (p["status"] == "ok"), p
    in_tissue = [r for r in rows if "tissue" in r["model"]]
    assert len(in_tissue) == 2 and all(float(r["median_ms"]) > 0 for r in in_tissue)
    _assert_real_png(out / "rod_models_tissue.png")


def test_joints_quick_reports_every_published_row_with_its_role(tmp_path: Path,
                                                                capsys: pytest.CaptureFixture[str]) -> None:
    from reachplan.planner.bench import joints
    from reachplan.rod_model.calibrate import CALIBRATION_ROWS, VALIDATION_ROWS

    out = _quick("joints", tmp_path, capsys)
    header, rows = _read_csv(out / "joints_rows.csv")
    assert header == list(joints.ROW_COLUMNS)
    roles = {(r.preset, "calibration") for r in CALIBRATION_ROWS} | {(r.preset, "validation") for r in VALIDATION_ROWS}
    for variant in {r["variant"] for r in rows}:
        assert {(r["preset"], r["role"]) for r in rows if r["variant"] == variant} == roles
    _, family = _read_csv(out / "joints_family.csv")
    # every calibration of the family reproduces the row it is built on
    assert family and all(abs(float(f["15ga-20j-tip"]) - 9.87) < 1e-6 for f in family)
    _, conv = _read_csv(out / "joints_convergence.csv")
    assert max(float(c["tip_error_mm"]) for c in conv) < 0.02
    _assert_real_png(out / "joints_trend.png")


def test_dose_quick_writes_csv_and_png(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = _quick("dose", tmp_path, capsys)
    header, rows = _read_csv(out / "dose_benchmark.csv")
    assert header == list(dose.COLUMNS)
    assert rows[0]["variant"] == "float64 dense" and rows[0]["max_rel_err"] == ""
    chunked = [r for r in rows[1:] if r["variant"] == "float32 chunked"]
    assert {r["workers"] for r in chunked} == {"1", "2"}
    # float32 chunks against the float64 evaluation of the same kernel: single precision, not a different dose
    assert all(0.0 <= float(r["max_rel_err"]) < 1e-4 for r in chunked)
    assert all(float(r["mpairs_per_s"]) > 0 for r in rows)
    _assert_real_png(out / "dose_benchmark.png")


def test_planning_insertion_rows_and_writers_on_a_tiny_input(tmp_path: Path) -> None:
    # the whole quick planning run takes about ten seconds; its parts on a tiny input instead
    s = planning.PlanningSettings(reference_step_mm=2.0, rod_steps_mm=(8.0,), depth_mm=40.0)
    rows = planning.insertion_models(s)
    assert [r["model"] for r in rows][-2:] == ["tissue_rod step 8.0 mm",
                                               "tissue_rod step 2.0 mm, extrapolated (planner)"]
    # the planner's reference is the benchmark's reference at 1 RK4 step per mm instead of 2: the same to 0.01 mm
    assert 0.0 <= float(rows[-1]["max_tip_error_mm"]) < 0.01 < float(rows[-2]["max_tip_error_mm"])
    kinematic = [r for r in rows if str(r["model"]).startswith("kinematic")]
    assert len(kinematic) == 3 and all(0.0 < float(r["max_tip_error_mm"]) < 10.0 for r in kinematic)
    write_csv(tmp_path / "insertion_models.csv", planning.INSERTION_COLUMNS, rows)
    header, back = _read_csv(tmp_path / "insertion_models.csv")
    assert header == list(planning.INSERTION_COLUMNS)
    assert [float(r["ms_per_path"]) for r in back] == pytest.approx([float(r["ms_per_path"]) for r in rows])
    timing = [{"plan": "screening", "holes": 62, "targets": 1, "schedules": 110, "median_s": 0.5}]
    write_csv(tmp_path / "planning_timings.csv", planning.TIMING_COLUMNS, timing)
    header, back = _read_csv(tmp_path / "planning_timings.csv")
    assert header == list(planning.TIMING_COLUMNS)
    assert back[0]["holes"] == "62" and back[0]["rerank_ms"] == ""  # a missing column is an empty cell
    write_png(tmp_path / "insertion_models.png", planning.insertion_figure(rows))
    _assert_real_png(tmp_path / "insertion_models.png")


def test_install_outside_a_checkout_is_one_typed_line(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "out"
    assert main(["bench", "models", "--install", "--out", str(out)]) == 2  # cwd: no pyproject.toml
    err = capsys.readouterr().err
    assert "pyproject.toml" in err and "--repo" in err and err.count("\n") == 1
    assert not out.exists()  # refused before running
    site = Path(models.__file__).resolve().parents[2]  # the installed package: never written into
    with pytest.raises(BenchError, match=r"no pyproject\.toml"):
        source_checkout(site)
    other = tmp_path / "other"
    other.mkdir()
    (other / "pyproject.toml").write_text('[project]\nname = "notreachplan"\n', encoding="utf-8")
    assert main(["bench", "dose", "--install", "--repo", str(other), "--out", str(out)]) == 2
    assert "not reachplan" in capsys.readouterr().err


def _fake_checkout(tmp_path: Path) -> Path:
    repo = tmp_path / "checkout"
    (repo / "docs").mkdir(parents=True)
    (repo / "pyproject.toml").write_text('[project]\nname = "reachplan"\n', encoding="utf-8")
    return repo


def test_install_refuses_quick_numbers(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    repo = _fake_checkout(tmp_path)
    assert main(["bench", "dose", "--quick", "--install", "--repo", str(repo), "--out", str(tmp_path / "o")]) == 2
    assert "drop --quick" in capsys.readouterr().err
    assert list((repo / "docs").iterdir()) == []


def test_install_copies_the_owned_files_into_the_checkout(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    repo = _fake_checkout(tmp_path)
    out = tmp_path / "out"
    argv = ["bench", "dose", "--voxels", "1000", "--dwells", "10", "--repeat", "1", "--install", "--repo", str(repo),
            "--out", str(out)]
    assert main(argv) == 0
    assert "installed" in capsys.readouterr().out
    for name, dest in dose.INSTALLS.items():
        assert (repo / dest).read_bytes() == (out / name).read_bytes()
    _, rows = _read_csv(repo / "docs" / "dose_benchmark.csv")
    side = round(1000 ** (1 / 3))
    assert int(rows[0]["chunk_pairs"]) == side**3 * 10  # the options replaced the full-size defaults
    assert install(out, source_checkout(repo), {}) == []
    assert np.isfinite([float(r["seconds"]) for r in rows]).all()


def test_report_sizes_by_part_and_the_summary_on_a_tiny_report(tmp_path: Path) -> None:
    # the whole report benchmark runs the demo's pipeline first (minutes); its measuring parts on a tiny report
    from reachplan.planner.bench import report as report_bench
    from reachplan.planner.report import figures
    from reachplan.planner.report.html import Figure, Interactive, Report, Section, render_html

    fig = {"data": [{"type": "scatter3d", "x": [1.0] * 500, "y": [2.0] * 500, "z": [3.0] * 500}], "layout": {}}
    canvas = figures.Figure(figsize=(2, 1))
    canvas.add_subplot().plot([0, 1], [1, 0])
    png = figures.png_bytes(canvas, dpi=50)
    html = render_html(Report("t", "s", (Section("A", "a", (Figure(png, "line"), Interactive(fig, "view"))),)))
    parts = report_bench.html_parts(html)
    assert parts["total"] == len(html.encode("utf-8")) == sum(v for k, v in parts.items() if k != "total")
    assert parts["plotly_js"] > 1e6 and parts["view_3d"] > 500 * 3 * 4  # the bundle; 1500 numbers
    assert abs(parts["images"] - len('src="data:image/png;base64,"') - 4 * ((len(png) + 2) // 3)) <= 0
    rows = [{"run": i, "report_s": s, "report_cpu_s": s / 2, "comparison_s": 1.0,
             **{f"bytes_{k}": v for k, v in parts.items()}, "load_avg_1min": 1.0}
            for i, s in enumerate((4.0, 2.0, 3.0))]
    summary = report_bench.summarise(rows)
    assert summary["median_report_s"] == 3.0 and summary["within_limit_wall"] is True
    assert summary["bytes_total"] == parts["total"]
    write_png(tmp_path / "report_benchmark.png", report_bench._figure(rows, summary))
    _assert_real_png(tmp_path / "report_benchmark.png")


def test_demo_stages_split_the_wall_time_of_a_plan_document() -> None:
    from reachplan.planner.bench.demo import STAGES, stage_times

    doc = {"phantom_s": {"write": 1.0, "read": 0.5}, "implant": {"straight": {"seconds": 4.0},
                                                                 "steered": {"seconds": 6.0}, "candidates": []},
           "timings": {"scene_s": 2.0, "plan_s": 3.0, "delivery_s": 12.5, "report_s": 1.5}}
    stages = stage_times(doc, wall_s=25.0)
    assert tuple(stages) == STAGES
    assert stages["implant"] == 10.0 and stages["delivery (no implant)"] == 2.5  # an older plan.json: the arms' sum
    assert sum(stages.values()) == pytest.approx(25.0) and stages["other"] == pytest.approx(4.5)
    # the arms run at once: the implant's own wall time counts, not the arms' sum
    stages = stage_times({**doc, "implant": {**doc["implant"], "seconds": 7.0}}, wall_s=25.0)
    assert stages["implant"] == 7.0 and stages["delivery (no implant)"] == 5.5


def test_firstrun_reports_cold_minus_warm_per_measurement(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The table and chart of ``bench firstrun``, with the child runs replaced (the real ones take minutes)."""
    import argparse

    from reachplan.planner.bench import firstrun

    calls: list[list[str]] = []

    def fake_child(argv: list[str], cache_dir: str) -> dict[str, float]:
        calls.append(argv)
        cold = len(calls) % 2 == 1
        demo = "demo" in argv
        out = {"wall_s": (30.0 if cold else 25.0) if demo else (9.0 if cold else 1.0), "cpu_s": 40.0 if cold else 28.0}
        if demo:
            out.update(main_cpu_s=31.0 if cold else 27.0, waited_s=1.5 if cold else 0.0)
        return out

    monkeypatch.setattr(firstrun, "_child", fake_child)
    assert firstrun.run(argparse.Namespace(out=tmp_path, quick=True, repeat=None)) == 0
    assert len(calls) == 4 and "--case" in calls[0] and "pilot" in calls[0]
    with (tmp_path / "firstrun.csv").open() as f:
        rows = {(r["what"], r["run"]): r for r in csv.DictReader(f)}
    demo, kernels = rows["demo", "median"], rows["kernels", "median"]
    assert float(demo["penalty_wall_s"]) == 5.0 and float(demo["penalty_main_cpu_s"]) == 4.0
    assert float(demo["cold_waited_s"]) == 1.5 and float(demo["penalty_cpu_s"]) == 12.0
    assert float(kernels["penalty_wall_s"]) == 8.0
    assert (tmp_path / "firstrun.png").stat().st_size > 0


def test_band_compares_the_band_model_with_the_reference_on_one_case() -> None:
    from reachplan.planner.bench.band import QUICK, _figure, compare

    rows = compare(QUICK)  # one case, two scales: six short rod insertions
    assert [r["scale"] for r in rows] == pytest.approx([1 / 3, 3.0], abs=1e-4)
    for r in rows:  # the band model's change of the tip follows the reference's (docs/mechanics.md: within 0.09 mm)
        assert r["difference_mm"] < 0.15 and abs(r["reference_lateral_mm"]) > 0.3
        assert r["band_cpu_s"] > 0 and r["reference_cpu_s"] > 0
    assert len(_figure(rows).axes) == 2
