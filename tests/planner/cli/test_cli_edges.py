"""The command line's edges (issue 14): bad plans, bad arguments and bad output places get a typed error (exit 2) or
a named warning in the JSON, before any work and without partial output; JSON never holds NaN; an escaping exception
is an "internal error" with its own exit code."""

from __future__ import annotations

import argparse
import hashlib
import json
import math
import shutil
import warnings
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pydicom
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from reachplan.imaging.files import json_safe
from reachplan.imaging.phantom import PhantomFiles, write_phantom
from reachplan.planner.cli import INTERNAL_ERROR_EXIT, main
from reachplan.planner.cli.edges import ArgumentError, finite, print_json, staged_folder
from reachplan.planner.cli.plan import _targets
from reachplan.planner.errors import PlanInputError


def _hashes(*paths: Path) -> dict[str, str]:
    files = [f for p in paths for f in ([p] if p.is_file() else sorted(p.rglob("*")))]
    return {str(f): hashlib.sha256(f.read_bytes()).hexdigest() for f in files if f.is_file()}


def _run(args: list[str], capsys: pytest.CaptureFixture[str]) -> tuple[int, str, str]:
    capsys.readouterr()
    with warnings.catch_warnings():
        warnings.simplefilter("always")
        code = main(args)
    out, err = capsys.readouterr()
    assert "Traceback" not in err
    return code, out, err


def _one_error_line(err: str, command: str) -> str:
    lines = [ln for ln in err.strip().splitlines() if ": warning: " not in ln]
    assert len(lines) == 1 and lines[0].startswith(f"reachplan {command}: error:"), err
    return lines[0]


# --- dose: one test per family of broken plans ---------------------------------------------------------------


def _channel(ds: Any) -> Any:
    return ds.ApplicationSetupSequence[0].ChannelSequence[0]


def _weights(ds: Any, k: int, factor: float) -> None:
    cps = _channel(ds).BrachyControlPointSequence
    cps[k].CumulativeTimeWeight = float(cps[k - 2].CumulativeTimeWeight) * factor


PLAN_FAMILIES: list[tuple[str, Callable[[Any], None], str]] = [
    ("negative channel total time", lambda ds: setattr(_channel(ds), "ChannelTotalTime", "-5"),
     "ChannelTotalTime is -5 s"),
    ("channel total time 1e30 s", lambda ds: setattr(_channel(ds), "ChannelTotalTime", "1e30"),
     "ChannelTotalTime is 1e+30 s"),
    ("NaN final cumulative weight", lambda ds: setattr(_channel(ds), "FinalCumulativeTimeWeight", "nan"),
     "FinalCumulativeTimeWeight is nan"),
    ("zero final cumulative weight", lambda ds: setattr(_channel(ds), "FinalCumulativeTimeWeight", "0"),
     "Final Cumulative Time Weight is 0"),
    ("decreasing cumulative weights", lambda ds: _weights(ds, 3, 0.5), "Cumulative Time Weight decreases"),
    ("negative dwell weight", lambda ds: setattr(_channel(ds).BrachyControlPointSequence[1], "CumulativeTimeWeight",
                                                 "-3"), "negative or infinite"),
    ("NaN dose reference point", lambda ds: setattr(ds.DoseReferenceSequence[0], "DoseReferencePointCoordinates",
                                                    ["nan", "0", "0"]), "DoseReferencePointCoordinates"),
    ("isotope against the data", lambda ds: setattr(ds.SourceSequence[0], "SourceIsotopeName", "Co-60"),
     "no TG-43 data is registered for Co-60"),
    ("negative air kerma rate", lambda ds: setattr(ds.SourceSequence[0], "ReferenceAirKermaRate", "-40700"),
     "ReferenceAirKermaRate is -40700"),
]


@pytest.mark.parametrize(("label", "edit", "match"), PLAN_FAMILIES, ids=[f[0] for f in PLAN_FAMILIES])
def test_broken_plan_is_a_typed_error_and_writes_nothing(
    reference_file: Callable[[str], Path], tmp_path: Path, capsys: pytest.CaptureFixture[str], label: str,
    edit: Callable[[Any], None], match: str
) -> None:
    rp, rs = reference_file("tps_examples/hdr/RP.HDR.dcm"), reference_file("tps_examples/hdr/RS.HDR.dcm")
    hdr = rp.parent  # nothing may be written there either
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        ds = pydicom.dcmread(rp)
        edit(ds)
        ds.save_as(tmp_path / "RP.dcm")
    before = _hashes(tmp_path / "RP.dcm", hdr)
    out = tmp_path / "out" / "RD.dcm"
    code, stdout, err = _run(["dose", "--plan", str(tmp_path / "RP.dcm"), "--structures", str(rs),
                              "--points", "--json", "--spacing", "6", "--out", str(out)], capsys)
    assert code == 2 and stdout == ""
    line = _one_error_line(err, "dose")
    assert match in line and "RP.dcm" in line
    assert not out.exists() and not list(tmp_path.glob("out/.*"))
    assert _hashes(tmp_path / "RP.dcm", hdr) == before
    code, _, err = _run(["inspect", str(tmp_path / "RP.dcm")], capsys)
    if label != "isotope against the data":  # a Co-60 plan is a valid file; only the data chosen for it is wrong
        assert code == 2 and match in _one_error_line(err, "inspect")


def test_1950_calibration_date_is_a_named_warning_in_the_json(
    reference_file: Callable[[str], Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    rs = reference_file("tps_examples/hdr/RS.HDR.dcm")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        ds = pydicom.dcmread(reference_file("tps_examples/hdr/RP.HDR.dcm"))
        ds.SourceSequence[0].SourceStrengthReferenceDate = "19500101"
        ds.save_as(tmp_path / "RP.dcm")
    code, stdout, err = _run(["dose", "--plan", str(tmp_path / "RP.dcm"), "--structures", str(rs),
                              "--json", "--spacing", "6", "--out", str(tmp_path / "RD.dcm")], capsys)
    assert code == 0
    doc = json.loads(stdout)
    named = [w for w in doc["warnings"] if w.startswith("CalibrationDateWarning")]
    assert named and "1950-01-01" in named[0]
    assert "CalibrationDateWarning" in err


def test_dose_checks_source_and_output_before_reading(
    reference_file: Callable[[str], Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    base = ["dose", "--plan", str(reference_file("tps_examples/hdr/RP.HDR.dcm")),
            "--structures", str(reference_file("tps_examples/hdr/RS.HDR.dcm"))]
    (tmp_path / "folder").mkdir()
    for extra, match in [
        (["--source", "nope", "--out", str(tmp_path / "a.dcm")], "no TG-43 source named 'nope'"),
        (["--out", str(tmp_path / "folder")], "is a folder"),
        (["--spacing", "0.01", "--out", str(tmp_path / "a.dcm")], "--spacing must be in"),
        (["--margin", "-1", "--out", str(tmp_path / "a.dcm")], "--margin must be in"),
    ]:
        code, _, err = _run(base + extra, capsys)
        assert code == 2 and match in _one_error_line(err, "dose"), err
    for bad in ("nan", "inf"):
        with pytest.raises(SystemExit) as exc:  # argparse refuses non-finite numbers
            main([*base, "--spacing", bad, "--out", str(tmp_path / "a.dcm")])
        assert exc.value.code == 2
    assert not (tmp_path / "a.dcm").exists()


# --- plan: arguments and outputs are checked before any work -------------------------------------------------


@pytest.fixture(scope="module")
def case(tmp_path_factory: pytest.TempPathFactory) -> PhantomFiles:
    return write_phantom(tmp_path_factory.mktemp("case"))


@pytest.mark.parametrize(("extra", "match"), [
    (["--targets", "nan,0,0"], "three finite coordinates"),
    (["--targets", "0,inf,0"], "three finite coordinates"),
    (["--targets", "Target_80_030", "--target-roi", "NoSuchCTV"], "NoSuchCTV"),
    (["--targets", "Target_80_030", "--source", "nope"], "no TG-43 source named 'nope'"),
    (["--targets", "Target_80_030", "--design", "99ga-1j-tip"], "99ga-1j-tip"),
    (["--targets", "Target_80_030", "--template", "nope"], "nope"),
    (["--targets", "Target_80_030", "--applicator-tip-offset", "-1"], "--applicator-tip-offset must be in [0, inf]"),
])
def test_plan_arguments_are_checked_before_any_work(case: PhantomFiles, tmp_path: Path, extra: list[str], match: str,
                                                    capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "out"
    code, _, err = _run(["plan", "--rtstruct", str(case.rtstruct_path), "--out", str(out), "--quiet", *extra], capsys)
    assert code == 2 and match in _one_error_line(err, "plan")
    assert not out.exists() and [p.name for p in tmp_path.iterdir()] == []


def test_demo_checks_the_applicator_tip_offset_before_any_work(tmp_path: Path,
                                                               capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "out"
    code, _, err = _run(["demo", "--out", str(out), "--quiet", "--applicator-tip-offset", "-2"], capsys)
    assert code == 2 and "--applicator-tip-offset must be in [0, inf], got -2" in _one_error_line(err, "demo")
    assert not out.exists()


def test_plan_refuses_an_input_folder_or_a_file_as_output(case: PhantomFiles, tmp_path: Path,
                                                           capsys: pytest.CaptureFixture[str]) -> None:
    before = _hashes(case.ct_dir, case.rtstruct_path)
    args = ["plan", "--ct", str(case.ct_dir), "--rtstruct", str(case.rtstruct_path), "--targets", "Target_80_030",
            "--quiet"]
    for out, match in [(case.ct_dir, "input folder"), (case.ct_dir / "sub", "input folder"),
                       (case.rtstruct_path, "existing file")]:
        code, _, err = _run([*args, "--out", str(out)], capsys)
        assert code == 2 and match in _one_error_line(err, "plan")
    assert _hashes(case.ct_dir, case.rtstruct_path) == before
    assert not (case.ct_dir / "sub").exists()


def test_unwritable_output_is_refused_before_work(case: PhantomFiles, tmp_path: Path,
                                                  capsys: pytest.CaptureFixture[str]) -> None:
    blocker = tmp_path / "file"
    blocker.write_text("x")
    code, _, err = _run(["plan", "--rtstruct", str(case.rtstruct_path), "--targets", "Target_80_030", "--quiet",
                         "--out", str(blocker / "out")], capsys)
    assert code == 2 and "is a file, not a folder" in _one_error_line(err, "plan")


# --- rod and inspect arguments ----------------------------------------------------------------------------


@pytest.mark.parametrize("extra", [["--roll", "nan"], ["--roll", "inf"], ["--tolerance", "-1", "--model", "auto"],
                                   ["--tolerance", "nan", "--model", "auto"], ["--tension", "nan"]])
def test_rod_refuses_non_finite_or_negative_numbers(extra: list[str], capsys: pytest.CaptureFixture[str]) -> None:
    code, out, err = _run(["rod", "--preset", "15ga-30j-tip", "--tension", "1", *extra, "--json"], capsys)
    assert code == 2 and out == ""
    _one_error_line(err, "rod")


def test_inspect_synonyms_binary_file_is_a_typed_error(case: PhantomFiles, tmp_path: Path,
                                                       capsys: pytest.CaptureFixture[str]) -> None:
    table = tmp_path / "syn.csv"
    table.write_bytes(bytes(range(256)) * 4)
    code, _, err = _run(["inspect", str(case.rtstruct_path), "--synonyms", str(table)], capsys)
    assert code == 2 and "not UTF-8 CSV" in _one_error_line(err, "inspect")


# --- the last resort, JSON, staging ---------------------------------------------------------------------------


def test_an_escaping_exception_is_an_internal_error_with_its_own_exit_code(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    import reachplan.planner.cli.plugins as plugins_cli

    def boom(args: argparse.Namespace) -> int:
        raise KeyError("simulated bug")

    monkeypatch.setattr(plugins_cli, "run", boom)
    code, out, err = _run(["plugins"], capsys)
    assert code == INTERNAL_ERROR_EXIT and code not in (0, 1, 2) and out == ""
    assert err.strip().startswith("reachplan plugins: internal error: KeyError") and err.count("\n") == 1


def test_print_json_writes_null_for_values_that_cannot_be_computed(capsys: pytest.CaptureFixture[str]) -> None:
    import numpy as np

    print_json({"a": [1.0, float("nan")], "b": {"c": float("inf"), "d": np.float64(-np.inf)}, "e": 2}, "x")
    out, err = capsys.readouterr()
    doc = json.loads(out)
    assert doc["a"] == [1.0, None] and doc["b"] == {"c": None, "d": None} and doc["e"] == 2
    assert doc["not_computable"] == [".a[1]: not a finite number", ".b.c: not a finite number",
                                     ".b.d: not a finite number"]
    assert "NaN" not in out and "Infinity" not in out
    assert "$.a[1]" not in err and ".a[1]" in err and ".b.c" in err


@settings(max_examples=200, deadline=None)
@given(st.lists(st.one_of(st.floats(), st.text(max_size=8), st.sampled_from(["nan", "inf", "-inf", "1e999"])),
                min_size=1, max_size=4))
def test_target_points_parse_to_finite_coordinates_or_a_typed_error(parts: list[Any]) -> None:
    spec = ",".join(str(p) for p in parts)
    try:
        names, points = _targets([spec])
    except PlanInputError as exc:
        assert "\n" not in str(exc)
        return
    for p in points:
        assert all(math.isfinite(v) and abs(v) <= 1e5 for v in p.position_mm)
    assert len(names) + len(points) == 1


@settings(max_examples=200, deadline=None)
@given(st.floats(), st.one_of(st.none(), st.floats(-1e3, 1e3)), st.one_of(st.none(), st.floats(-1e3, 1e3)))
def test_finite_accepts_exactly_the_finite_numbers_in_range(value: float, lo: float | None, hi: float | None) -> None:
    ok = math.isfinite(value) and (lo is None or value >= lo) and (hi is None or value <= hi)
    try:
        assert finite(value, "--x", lo=lo, hi=hi) == value and ok
    except ArgumentError as exc:
        assert not ok and "--x" in str(exc)


@given(st.recursive(st.floats() | st.integers() | st.text(max_size=3),
                    lambda c: st.lists(c, max_size=3) | st.dictionaries(st.text(max_size=3), c, max_size=3),
                    max_leaves=12))
def test_json_safe_output_always_serialises_without_nan(doc: Any) -> None:
    json.dumps(json_safe(doc), allow_nan=False)


def test_staged_folder_leaves_nothing_on_failure_and_merges_on_success(tmp_path: Path) -> None:
    out = tmp_path / "new" / "out"
    with pytest.raises(RuntimeError), staged_folder(out) as stage:
        (stage / "plan.json").write_text("{}")
        raise RuntimeError("failed half way")
    assert not (tmp_path / "new").exists()
    keep = tmp_path / "old"
    with staged_folder(keep) as stage:  # an earlier run: its files are recorded as reachplan's
        (stage / "plan.json").write_text("old")
    (keep / "export").mkdir(parents=True)
    (keep / "export" / "mine.txt").write_text("user file")
    with staged_folder(keep) as stage:
        (stage / "export").mkdir()
        (stage / "export" / "RP.dcm").write_text("new")
        (stage / "plan.json").write_text("new")
    assert (keep / "plan.json").read_text() == "new" and (keep / "export" / "RP.dcm").read_text() == "new"
    assert (keep / "export" / "mine.txt").read_text() == "user file"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["old"]
    assert sorted(p.name for p in keep.iterdir()) == [".reachplan-files.json", "export", "plan.json"]
    shutil.rmtree(keep)


def test_error_messages_are_one_line_without_embedded_tracebacks(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    import reachplan.planner.cli.plugins as plugins_cli
    from reachplan.imaging.dicom_files import parsing

    def nested(args: argparse.Namespace) -> int:  # what pydicom raises for a damaged nested sequence
        with parsing(Path("RP.dcm")):
            raise OSError("With tag (300A,0230) got exception: No tag to read at file position 170A\n"
                          "Traceback (most recent call last):\n  File \"x.py\", line 1, in <module>\n")
        return 0

    monkeypatch.setattr(plugins_cli, "run", nested)
    code, _, err = _run(["plugins"], capsys)
    line = _one_error_line(err, "plugins")
    assert code == 2 and "No tag to read at file position 170A" in line and "Traceback" not in err
