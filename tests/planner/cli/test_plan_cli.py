"""``reachplan plan`` from a structure set alone (no CT), and its input errors."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from reachplan.imaging.phantom import write_phantom
from reachplan.planner.cli import main


@pytest.fixture(scope="module")
def rtstruct(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return write_phantom(tmp_path_factory.mktemp("phantom")).rtstruct_path


def test_plan_from_structures_alone_with_roi_and_point_targets(rtstruct: Path, tmp_path: Path,
                                                                capsys: pytest.CaptureFixture[str],
                                                                monkeypatch: pytest.MonkeyPatch) -> None:
    import reachplan.planner.run.outputs as outputs  # the writer of a case's files

    written: list[str] = []
    write_json = outputs.atomic_write_json

    def counting(path: Path, obj: object) -> None:
        written.append(Path(path).name)
        write_json(path, obj)

    monkeypatch.setattr(outputs, "atomic_write_json", counting)
    code = main(["plan", "--rtstruct", str(rtstruct), "--targets", "Target_80_030", "35,10,80",
                 "--out", str(tmp_path), "--no-export", "--json"])
    assert code == 0
    doc = json.loads(capsys.readouterr().out)
    # plan.json is written once, with the final paths from the start (the run is staged in a hidden folder)
    assert written.count("plan.json") == 1
    saved = (tmp_path / "plan.json").read_text()
    assert "staging" not in saved and json.loads(saved)["report"] == str(tmp_path / "report.html") == doc["report"]
    assert isinstance(json.loads(saved)["warnings"], list)
    assert set(doc["targets"]) == {"Target_80_030", "point_1"}
    point = doc["targets"]["point_1"]["candidates"][0]
    assert point["tip_position_mm"] == pytest.approx([35.0, 10.0, 80.0], abs=2.0)
    assert (tmp_path / "plan.json").is_file() and (tmp_path / "overview.png").is_file()


@pytest.mark.parametrize(("targets", "message"), [
    (["NoSuchOrgan"], "no ROI named 'NoSuchOrgan'"),
    (["1,2,x"], "a point is three numbers"),
    (["nan,0,0"], "all finite"),
    (["0,inf,0"], "all finite"),
])
def test_plan_input_errors_are_one_line_exit_2(rtstruct: Path, tmp_path: Path, targets: list[str], message: str,
                                               capsys: pytest.CaptureFixture[str]) -> None:
    code = main(["plan", "--rtstruct", str(rtstruct), "--targets", *targets, "--out", str(tmp_path), "--quiet"])
    err = capsys.readouterr().err.strip()
    assert code == 2 and message in err and "\n" not in err and "Traceback" not in err


@pytest.mark.parametrize(("spec", "message"), [("PtX", "NAME=X,Y,Z"), ("=1,2,3", "NAME=X,Y,Z"),
                                               ("PtX=1,2", "three finite numbers")])
def test_bad_reference_point_is_one_line_exit_2(rtstruct: Path, tmp_path: Path, spec: str, message: str,
                                                capsys: pytest.CaptureFixture[str]) -> None:
    code = main(["plan", "--rtstruct", str(rtstruct), "--targets", "Target_80_030", "--reference-point", spec,
                 "--out", str(tmp_path), "--quiet"])
    err = capsys.readouterr().err.strip()
    assert code == 2 and message in err and err.count("\n") == 0


def test_tension_reserve_reaches_the_plan_config(rtstruct: Path, tmp_path: Path,
                                                 monkeypatch: pytest.MonkeyPatch) -> None:
    """``--tension-reserve`` on ``plan`` and ``demo`` (issue 26.5): 0.1 by default, 0 allows the full limit."""
    import reachplan.planner.cli.plan as plan_cli
    from reachplan.planner.cli import build_parser

    seen = []

    def capture(inputs: object, config: object, out: Path, quiet: bool, **kwargs: object) -> tuple[None, dict]:
        seen.append(config)
        return None, {}

    monkeypatch.setattr(plan_cli, "plan_and_write", capture)
    for given, expected in (([], 0.1), (["--tension-reserve", "0"], 0.0)):
        assert main(["plan", "--rtstruct", str(rtstruct), "--targets", "Target_80_030", "--out",
                     str(tmp_path / str(expected)), "--quiet", *given]) == 0
        assert seen[-1].plan.tension_reserve == expected
    demo = build_parser().parse_args(["demo", "--out", str(tmp_path / "d"), "--tension-reserve", "0.25"])
    assert demo.tension_reserve == 0.25
    with pytest.raises(SystemExit) as exc:  # argparse refuses a reserve outside [0, 0.9]
        main(["plan", "--rtstruct", str(rtstruct), "--targets", "Target_80_030", "--out", str(tmp_path / "x"),
              "--tension-reserve", "1"])
    assert exc.value.code == 2
