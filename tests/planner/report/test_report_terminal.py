"""What the terminal shows: the plan summary, ``--version``, ``--quiet`` on every command, and error lines that
never share a line with a progress bar."""

from __future__ import annotations

import re
import sys
from types import SimpleNamespace

import numpy as np
import pytest
from tqdm import tqdm

from reachplan import ReachplanError, __version__
from reachplan.planner.case.config import PlanConfig
from reachplan.planner.case.result import PlanResult
from reachplan.planner.cli import COMMAND_MODULES, build_parser, main
from reachplan.planner.dose.aims import Aims
from reachplan.planner.report.terminal import format_summary
from reachplan.planner.steering.candidates import Candidate
from reachplan.planner.steering.insertion import STRAIGHT
from reachplan.planner.steering.kinematic import KINEMATIC
from reachplan.rod_model.design import preset


def _cand(target: str, hole: str, steered: bool, tension_n: float = 0.0, worst_mm: float = 1.0) -> Candidate:
    design = preset("15ga-30j-tip") if steered else None
    path = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 50.0]])
    return Candidate(target, hole, 10.0, 0.5, 5.0, "Bladder", 50.0, steered, tension_n,
                     KINEMATIC.info if steered else STRAIGHT, False, True, "", path, design=design,
                     worst_reach_mm=worst_mm, worst_clearance_mm=4.0, worst_case="roll +10 deg")


def _result() -> tuple[PlanResult, float]:
    limit = preset("15ga-30j-tip").max_tension_n
    ranking = {  # name order, as the ranking keeps it
        "T_a": (_cand("T_a", "Aa", False), _cand("T_a", "Bb", True, 0.8 * limit)),
        "T_b": (_cand("T_b", "Cc", True, 0.9999 * limit, worst_mm=3.5),),
    }
    cands = tuple(c for cs in ranking.values() for c in cs)
    return PlanResult(cands, ranking, PlanConfig()), limit


def _comparison() -> SimpleNamespace:

    aims = Aims()
    rectum = dict((k.casefold(), v) for k, v in aims.oar_d2cc_eqd2_gy)["rectum"]
    rows = (SimpleNamespace(arm="straight", n_needles=1, d90_eqd2_gy=aims.target_d90_eqd2_gy + 1, aim_met=False,
                            oar_d2cc_eqd2_gy=(("Rectum", rectum + 5.0), ("Bladder", 10.0))),
            SimpleNamespace(arm="steered", n_needles=2, d90_eqd2_gy=aims.target_d90_eqd2_gy + 3, aim_met=True,
                            oar_d2cc_eqd2_gy=(("Rectum", rectum - 5.0), ("Bladder", 10.0))))
    return SimpleNamespace(aims=aims, rows=lambda: rows)


def test_summary_headers_carry_units_and_targets_keep_the_users_order() -> None:
    result, limit = _result()
    text = format_summary(result, targets=["T_b", "T_a"], comparison=_comparison(),  # type: ignore[arg-type]
                          files=[("report", "out/report.html"), ("plan", "out/plan.json"),
                                 ("device instructions", "out/export/x_device.json")])
    lines = text.splitlines()
    assert lines[0].startswith("RESEARCH USE ONLY")  # the statement leads, with or without an insert list
    head = next(ln for ln in lines if ln.startswith("target"))
    for column in ("from centre", "reach error", "clearance", "reach margin"):
        assert re.search(rf"{column} \(mm\)", head), column
    assert "peak / reserve (N)" in head and " r" not in head.split("target")[0]
    rows = [ln for ln in lines if ln.startswith(("T_a", "T_b"))]
    assert [r.split()[0] for r in rows] == ["T_b", "T_a"]  # the order given, not the name order
    # margins, not flags: T_b's steered needle is 1.5 mm over the 2 mm tolerance and has no tension left
    t_b = rows[0]
    assert "none feasible" in t_b  # no straight needle for T_b
    steered_b = lines[lines.index(t_b) + 1].split()
    assert steered_b[:2] == ["steered*", "Cc"] and steered_b[5] == "-1.5"
    assert steered_b[6:9] == [f"{0.9999 * limit:.1f}", "/", "0.0"]
    steered_a = lines[lines.index(rows[1]) + 1].split()
    assert steered_a[:2] == ["steered", "Bb"] and steered_a[5] == "+1.0"
    assert steered_a[6:9] == [f"{0.8 * limit:.1f}", "/", f"{0.2 * limit:.1f}"]
    assert not any("!" in ln for ln in lines)  # no flag on every row
    assert "straight*" in rows[1]  # the top-ranked needle of T_a is marked and the mark is explained
    assert any(ln.startswith("* ranked first") for ln in lines)


def test_summary_says_per_arm_whether_the_aims_are_met_and_where_the_files_are() -> None:
    result, _ = _result()
    text = format_summary(result, comparison=_comparison(),  # type: ignore[arg-type]
                          files=[("report", "out/report.html"), ("device instructions", "out/export/x_device.json")])
    straight = next(ln for ln in text.splitlines() if ln.strip().startswith("straight arm"))
    steered = next(ln for ln in text.splitlines() if ln.strip().startswith("steered arm"))
    assert "aims NOT met" in straight and "Rectum" in straight and "Bladder" not in straight
    assert "aims met" in steered and "NOT" not in steered
    assert f"HR-CTV D90 >= {Aims().target_d90_eqd2_gy:g} Gy" in text
    assert re.search(r"^report\s+out/report.html$", text, re.M)
    assert re.search(r"^device instructions\s+out/export/x_device.json$", text, re.M)
    assert "not computed" in format_summary(result)  # ranked only: says there is no dose



def test_summary_puts_the_implant_arms_first_and_names_the_per_target_plans() -> None:
    """With implant planning, the arms' lines are the whole-HR-CTV implants; per-target plans say what they are."""
    result, _ = _result()

    def metrics(name: str, d90: float = 0.0, d2cc: float = 0.0) -> SimpleNamespace:
        return SimpleNamespace(name=name, d90_eqd2_gy=d90, d2cc_eqd2_gy=d2cc)

    def arm(name: str, n: int, d90: float, met: bool, bladder: float) -> SimpleNamespace:
        plan = SimpleNamespace(n_needles=n, target=metrics("HR-CTV", d90), aims_met=met,
                               oars=(metrics("Bladder", d2cc=bladder),))
        return SimpleNamespace(name=name, plan=plan, reason="")

    implant = SimpleNamespace(arms=(arm("straight", 5, 84.0, False, 95.0), arm("steered", 3, 90.0, True, 79.0)))
    opt = SimpleNamespace(success=True, target=metrics("HR-CTV", 90.0), aim_met=True, oars=(), reason="")
    delivery = SimpleNamespace(implant=implant, optimisation=opt, kind="implant, straight + steered", n_needles=3,
                               aims=Aims(), aims_tables={}, warnings=(), export=SimpleNamespace(handoff=None))
    text = format_summary(result, delivery=delivery, comparison=_comparison())  # type: ignore[arg-type]
    lines = [ln.strip() for ln in text.splitlines()]
    first = next(i for i, ln in enumerate(lines) if ln.startswith("implant, straight "))
    straight, steered = lines[first], lines[first + 1]
    assert re.search(r"\b5 needles\b", straight) and "aims NOT met" in straight and "Bladder 95.0 Gy" in straight
    assert steered.startswith("implant, straight + steered") and re.search(r"\b3 needles\b", steered)
    assert "aims met" in steered and "NOT" not in steered
    assert any(ln.startswith("straight arm (one needle per target)") for ln in lines)
    exported = next(ln for ln in lines if ln.startswith("exported plan (implant, straight + steered)"))
    assert re.search(r"\b3 needles\b", exported) and "aims met" in exported and "NOT" not in exported


def test_version(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exc:
        main(["--version"])
    assert exc.value.code == 0 and capsys.readouterr().out.strip() == f"reachplan {__version__}"


def test_every_command_takes_quiet() -> None:
    parser = build_parser()
    sub = next(a for a in parser._actions if a.dest == "command")
    assert len(sub.choices) == len(COMMAND_MODULES)  # type: ignore[arg-type]
    for name, p in sub.choices.items():  # type: ignore[union-attr]
        assert any("--quiet" in a.option_strings for a in p._actions), name


def test_quiet_silences_a_command_but_not_its_errors(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["plugins"]) == 0
    assert capsys.readouterr().out  # the plugin list
    assert main(["plugins", "--quiet"]) == 0
    assert capsys.readouterr() == ("", "")
    assert main(["inspect", "/nonexistent/folder", "--quiet"]) == 2
    captured = capsys.readouterr()
    assert captured.out == "" and "error" in captured.err


def test_an_error_never_shares_a_line_with_a_progress_bar(monkeypatch: pytest.MonkeyPatch,
                                                          capsys: pytest.CaptureFixture[str]) -> None:
    def failing(args: object) -> int:
        bar = tqdm(total=10, desc="working", file=sys.stderr, leave=False, mininterval=0)
        bar.update(3)  # the bar is on screen, and stays open when the error comes
        raise ReachplanError("something is wrong; do this instead")

    parser = build_parser()
    args = parser.parse_args(["plugins"])
    monkeypatch.setattr(args, "_run", failing)
    monkeypatch.setattr("reachplan.planner.cli.build_parser", lambda: SimpleNamespace(parse_args=lambda _: args))
    assert main([]) == 2
    err = capsys.readouterr().err
    assert "working" in err  # the bar was drawn
    line = next(ln for ln in err.split("\n") if "something is wrong" in ln)
    # what the terminal shows of that line: the text after the last carriage return, alone
    assert line.split("\r")[-1] == "reachplan plugins: error: something is wrong; do this instead"
