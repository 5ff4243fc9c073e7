"""Source decay: one rule (imaging.source_strength) for dose and inspect; genuine plans with placeholder dates."""

from __future__ import annotations

import json
import warnings
from collections.abc import Callable
from datetime import datetime
from pathlib import Path

import numpy as np
import pydicom
import pytest

from reachplan.imaging.brachy_plan import BrachySource
from reachplan.imaging.errors import CalibrationDateWarning, InvalidValueError
from reachplan.imaging.source_strength import DecayWindow, source_strength
from reachplan.planner.cli import main
from reachplan.plugins.exporters.rtdose import read_rtdose_grid

IR192 = 73.83


def _src(date: str = "20180320", time: str = "000000", half: float | None = IR192) -> BrachySource:
    return BrachySource(1, "Ir-192", "LINE", "", 40700.0, date, time, half, 3.5, 0.9)


def test_decayed_across_a_plausible_interval_only() -> None:
    got = source_strength(_src(), "20180419")  # 30 days after calibration
    assert got.decayed and got.elapsed_days == 30.0 and not got.note
    assert got.treatment_u == pytest.approx(40700.0 * 2 ** (-30 / IR192), rel=1e-12)
    # the window's edge (2 half-lives = 147.66 d: 147 days is inside, 148 outside)
    assert source_strength(_src(), "20180814").decayed
    for plan_date, words in (("20180815", "148 days after"), ("20180319", "1 days before"),
                             ("19010101", "42812 days before"), ("", "no RT Plan Date"),
                             ("2018", "is not a date")):
        with pytest.warns(CalibrationDateWarning) as seen:
            got = source_strength(_src(), plan_date, label="RP.dcm")
        assert len(seen) == 1 and str(seen[0].message) == got.note
        assert not got.decayed and got.treatment_u == 40700.0
        assert "used as written (not decayed)" in got.note and words in got.note and "RP.dcm" in got.note
    # a wider window, and one that allows a day back
    assert source_strength(_src(), "20180815", window=DecayWindow(3.0)).decayed
    back = source_strength(_src(), "20180319", window=DecayWindow(2.0, 1.0))
    assert back.decayed and back.treatment_u == pytest.approx(40700.0 * 2 ** (1 / IR192))
    with pytest.raises(ValueError, match="max_forward_half_lives"):
        DecayWindow(-1.0)


def test_unknown_reference_date_or_half_life_is_used_as_written() -> None:
    for src, words in ((_src(date="", time=""), "no Source Strength Reference Date"),
                       (_src(date="2018-03-20"), "not a date"), (_src(half=None), "no half-life")):
        with pytest.warns(CalibrationDateWarning, match=words):
            got = source_strength(src, "20180419")
        assert not got.decayed and got.treatment_u == 40700.0 and words in got.to_json()["decay_note"]
    # no half-life on the calibration day itself: nothing to decay, no warning
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert source_strength(_src(half=None), "20180320").decayed


def test_a_treatment_date_overrides_the_window_within_bounds() -> None:
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # the user's date: no warning
        far = source_strength(_src(), "19010101", datetime(2018, 12, 1))
    assert far.decayed and far.treatment_u == pytest.approx(40700.0 * 2 ** (-far.elapsed_days / IR192))
    assert far.elapsed_days == pytest.approx(256.0) and "--treatment-date" in far.treatment_date
    for when in (datetime(1950, 1, 1), datetime(2030, 1, 1)):
        with pytest.raises(InvalidValueError, match="give a date within"):
            source_strength(_src(), "20180320", when)
    with pytest.raises(InvalidValueError, match="not a date"):
        source_strength(_src(date="2018-03-20"), "20180320", datetime(2018, 4, 1))


# --- reachplan dose on the genuine Eclipse plans, as written and with placeholder dates --------------------------


def _copy(src: Path, dst: Path, edit: Callable[[pydicom.Dataset], None]) -> Path:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        ds = pydicom.dcmread(src)
    edit(ds)
    ds.save_as(dst)
    return dst


def _dose_json(rp: Path, rs: Path, out: Path, capsys: pytest.CaptureFixture[str]) -> dict:
    with warnings.catch_warnings():
        warnings.simplefilter("always")  # recorded into the JSON by main
        assert main(["dose", "--plan", str(rp), "--structures", str(rs), "--points", "--json", "--out", str(out)]) == 0
    return json.loads(capsys.readouterr().out)


@pytest.mark.parametrize("kind", ["hdr", "pdr"])
def test_genuine_plans_and_a_1901_plan_date_give_the_tps_point_doses(
        reference_file: Callable[[str], Path], tmp_path: Path, kind: str, capsys: pytest.CaptureFixture[str]) -> None:
    rp = reference_file(f"tps_examples/{kind}/RP.{kind.upper()}.dcm")
    rs = reference_file(f"tps_examples/{kind}/RS.{kind.upper()}.dcm")

    def placeholder(ds: pydicom.Dataset) -> None:
        ds.RTPlanDate = "19010101"  # as anonymisers write it

    docs = [_dose_json(p, rs, tmp_path / f"RD{i}.dcm", capsys)
            for i, p in enumerate((rp, _copy(rp, tmp_path / "RP1901.dcm", placeholder)))]
    for i, doc in enumerate(docs):
        dose, _ = read_rtdose_grid(tmp_path / f"RD{i}.dcm")
        assert np.all(np.isfinite(dose)) and dose.max() > 0
        assert len(doc["points"]) == 2
        for p in doc["points"]:
            assert np.isfinite(p["dose_gy"]) and abs(p["diff_percent"]) < 1.0, p
        assert doc["air_kerma_treatment_u"] == doc["air_kerma_reference_u"]
    assert docs[0]["decayed"] and not [w for w in docs[0]["warnings"] if "CalibrationDateWarning" in w]
    (named,) = [w for w in docs[1]["warnings"] if w.startswith("CalibrationDateWarning")]
    assert not docs[1]["decayed"] and "used as written" in named and docs[1]["decay_note"] in named
    assert [p["dose_gy"] for p in docs[1]["points"]] == [p["dose_gy"] for p in docs[0]["points"]]


def test_a_1950_calibration_date_warns_in_the_words_of_the_dose_computed(
        reference_file: Callable[[str], Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    rp = reference_file("tps_examples/hdr/RP.HDR.dcm")
    rs = reference_file("tps_examples/hdr/RS.HDR.dcm")

    def calibrated_1950(ds: pydicom.Dataset) -> None:
        ds.SourceSequence[0].SourceStrengthReferenceDate = "19500101"

    base = _dose_json(rp, rs, tmp_path / "a.dcm", capsys)
    old = _dose_json(_copy(rp, tmp_path / "RP1950.dcm", calibrated_1950), rs, tmp_path / "b.dcm", capsys)
    (named,) = [w for w in old["warnings"] if w.startswith("CalibrationDateWarning")]
    assert "40700 U is used as written (not decayed)" in named and "1950-01-01" in named
    assert old["air_kerma_treatment_u"] == 40700.0 and not old["decayed"]
    # the warning says "as written", and so the dose is: the same as the plan's own calibration date gives
    assert [p["dose_gy"] for p in old["points"]] == [p["dose_gy"] for p in base["points"]]
    a, _ = read_rtdose_grid(tmp_path / "a.dcm")
    b, _ = read_rtdose_grid(tmp_path / "b.dcm")
    assert b.max() > 0 and np.allclose(a, b)
    # decaying 68 years on purpose is a typed error, and no RT Dose is written
    with warnings.catch_warnings():
        warnings.simplefilter("always")
        code = main(["dose", "--plan", str(tmp_path / "RP1950.dcm"), "--structures", str(rs), "--treatment-date",
                     "20180320", "--out", str(tmp_path / "c.dcm")])
    assert code == 2 and "give a date within" in capsys.readouterr().err and not (tmp_path / "c.dcm").exists()


def test_inspect_states_the_same_rule(reference_file: Callable[[str], Path], tmp_path: Path,
                                      capsys: pytest.CaptureFixture[str]) -> None:
    rp = reference_file("tps_examples/hdr/RP.HDR.dcm")

    def placeholder(ds: pydicom.Dataset) -> None:
        ds.RTPlanDate = "19010101"

    with warnings.catch_warnings():
        warnings.simplefilter("always")
        assert main(["inspect", "--json", str(_copy(rp, tmp_path / "RP.dcm", placeholder))]) == 0
    doc = json.loads(capsys.readouterr().out)
    (plan,) = doc["plans"]
    assert plan["strength"] == "S_K 40700 U on 20180320 000000, used as written (not decayed)"
    (named,) = [w for w in doc["warnings"] if w.startswith("CalibrationDateWarning")]
    assert "used as written" in named and "1901-01-01" in named
