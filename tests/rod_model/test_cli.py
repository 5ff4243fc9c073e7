"""``reachplan rod`` through planner.cli.main."""

from __future__ import annotations

import json

import pytest

from reachplan.planner.cli import main
from reachplan.rod_model.cosserat import TWO_TUBE_COSSERAT
from reachplan.rod_model.design import preset

pytestmark = pytest.mark.usefixtures("builtin_models")


def test_rod_json_single(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["rod", "--preset", "15ga-20j-tip", "--tension", "9.9", "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    d = preset("15ga-20j-tip")
    r = TWO_TUBE_COSSERAT.solve(d, d.loads(9.9))
    assert doc["model"] == "two_tube_cosserat"
    assert doc["converged"] is True
    assert doc["tip_deflection_mm"] == pytest.approx(r.tip_deflection_mm, abs=1e-6)  # type: ignore[union-attr]
    assert len(doc["tip_position_mm"]) == 3
    assert len(doc["positions_mm"]) == len(doc["s_mm"])
    for key in ("residual", "solve_ms", "max_tension_n"):
        assert key in doc


def test_rod_json_sweep_and_roll(capsys: pytest.CaptureFixture[str]) -> None:
    argv = ["rod", "--preset", "15ga-20j-mid", "--tensions", "0,5,10", "--roll", "90", "--model", "planar_beam",
            "--json"]
    assert main(argv) == 0
    docs = json.loads(capsys.readouterr().out)
    assert [d["tension_n"] for d in docs] == [0.0, 5.0, 10.0]
    assert all(d["model"] == "planar_beam" for d in docs)
    assert docs[0]["tip_deflection_mm"] == 0.0
    tip = docs[2]["tip_position_mm"]
    assert abs(tip[0]) < 1e-6 and tip[1] > 5.0  # rolled 90°: bends toward +y


def test_rod_auto_picks_a_model_within_tolerance(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["rod", "--preset", "15ga-20j-tip", "--tension", "5", "--model", "auto", "--tolerance", "0.5",
                 "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["model"] in ("planar_beam", "cosserat_rod", "two_tube_cosserat")


@pytest.mark.parametrize(("argv", "message"), [
    (["--preset", "nope", "--tension", "1"], "unknown preset"),
    (["--preset", "15ga-20j-tip"], "exactly one of"),
    (["--preset", "15ga-20j-tip", "--tensions", "1,x"], "comma-separated"),
    (["--preset", "15ga-20j-tip", "--tension", "1", "--model", "no_such_model"], "no_such_model"),
    (["--preset", "15ga-20j-tip", "--tension", "1", "--model", "auto", "--tolerance", "1e-9"], "within"),
])
def test_rod_errors_are_one_line(argv: list[str], message: str, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["rod", *argv, "--json"]) == 2
    err = capsys.readouterr().err
    assert message in err
    assert err.count("\n") == 1
