"""Unusable brachy plans (issue 28): ``dose`` and ``plan --rtplan`` refuse them, ``inspect`` warns with the same words.

Each variant of the Eclipse HDR plan breaks one thing: a channel whose control points are gone (271 s of treatment
time that used to be dropped silently), an isotope without TG-43 data (Cs-137), no source strength, no Source
Sequence, no Application Setup Sequence. One shared check (``reachplan.planner.dose.plan_usable``) gives both the
error and the warning, so the messages are compared for equality.
"""

from __future__ import annotations

import hashlib
import json
import warnings
from collections.abc import Callable
from pathlib import Path

import pydicom
import pytest
from pydicom.dataset import Dataset

from reachplan.imaging.brachy_plan import plan_problems
from reachplan.imaging.rtplan import read_rtplan
from reachplan.planner.cli import main
from reachplan.planner.dose.plan_usable import usable_problems


def _cs137(ds: Dataset) -> None:
    ds.SourceSequence[0].SourceIsotopeName = "Cs-137"
    ds.SourceSequence[0].SourceIsotopeHalfLife = 10987.0


def _no_control_points(ds: Dataset) -> None:
    del ds.ApplicationSetupSequence[0].ChannelSequence[0].BrachyControlPointSequence


VARIANTS: dict[str, tuple[Callable[[Dataset], None], str]] = {
    "no_control_points": (_no_control_points, "channel(s) 1 have no control points but 271.4 s of Channel Total "
                                              "Time: their dwells are unknown"),
    "cs137": (_cs137, "no TG-43 data is registered for Cs-137"),
    "zero_strength": (lambda ds: setattr(ds.SourceSequence[0], "ReferenceAirKermaRate", 0.0),
                      "source 1 has no Reference Air Kerma Rate (0 or missing)"),
    "no_source_sequence": (lambda ds: delattr(ds, "SourceSequence"), "the plan has no Source Sequence"),
    "no_application_setups": (lambda ds: delattr(ds, "ApplicationSetupSequence"),
                              "the plan has no Application Setup Sequence"),
}


@pytest.fixture(scope="module")
def variants(tmp_path_factory: pytest.TempPathFactory, reference_file: Callable[[str], Path]) -> dict[str, Path]:
    root = tmp_path_factory.mktemp("plans")
    out = {}
    for name, (edit, _) in VARIANTS.items():
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            ds = pydicom.dcmread(reference_file("tps_examples/hdr/RP.HDR.dcm"))
        edit(ds)
        (root / name).mkdir()
        out[name] = root / name / "RP.dcm"
        ds.save_as(out[name])
    return out


def _sha(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def _run(args: list[str], capsys: pytest.CaptureFixture[str]) -> tuple[int, str, str]:
    with warnings.catch_warnings():
        warnings.simplefilter("always")
        code = main(args)
    out, err = capsys.readouterr()
    return code, out, err


@pytest.mark.parametrize("name", list(VARIANTS))
def test_dose_refuses_and_inspect_warns_with_the_same_message(
    name: str, variants: dict[str, Path], reference_file: Callable[[str], Path], tmp_path: Path,
    capsys: pytest.CaptureFixture[str]
) -> None:
    rp, rs = variants[name], reference_file("tps_examples/hdr/RS.HDR.dcm")
    before = (_sha(rp), _sha(rs))
    code, out, err = _run(["inspect", str(rp), "--json"], capsys)
    assert code == 0
    warned = [w for w in json.loads(out)["warnings"] if w.startswith("UnusablePlanWarning: ")]
    assert len(warned) == 1 and VARIANTS[name][1] in warned[0] and str(rp) in warned[0]
    message = warned[0].removeprefix(f"UnusablePlanWarning: {rp}: ")
    code, out, err = _run(["dose", "--plan", str(rp), "--structures", str(rs), "--spacing", "8", "--json",
                           "--out", str(tmp_path / "RD.dcm")], capsys)
    assert code == 2 and out == ""
    assert err.strip().splitlines()[-1] == f"reachplan dose: error: {rp}: {message}"
    assert list(tmp_path.iterdir()) == [] and (_sha(rp), _sha(rs)) == before


def test_the_tps_plan_itself_has_no_problem(reference_file: Callable[[str], Path]) -> None:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        for rel in ("tps_examples/hdr/RP.HDR.dcm", "tps_examples/pdr/RP.PDR.dcm"):
            plan = read_rtplan(reference_file(rel))
            assert plan_problems(plan) == () and usable_problems(plan) == ()


def test_a_channel_without_control_points_and_without_time_is_only_a_quirk(
    tmp_path: Path, reference_file: Callable[[str], Path]
) -> None:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        ds = pydicom.dcmread(reference_file("tps_examples/hdr/RP.HDR.dcm"))
    channel = ds.ApplicationSetupSequence[0].ChannelSequence[0]
    del channel.BrachyControlPointSequence
    channel.ChannelTotalTime = 0.0
    ds.save_as(tmp_path / "RP.dcm")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        plan = read_rtplan(tmp_path / "RP.dcm")
    assert plan_problems(plan) == ()
    assert "a channel without control points and with 0 s (nothing to deliver; ignored)" in plan.quirks


def test_plan_refuses_an_rtplan_whose_channel_has_no_control_points(
    variants: dict[str, Path], reference_file: Callable[[str], Path], tmp_path: Path,
    capsys: pytest.CaptureFixture[str]
) -> None:
    rs = reference_file("tps_examples/hdr/RS.HDR.dcm")
    code, _, err = _run(["plan", "--rtstruct", str(rs), "--rtplan", str(variants["no_control_points"]),
                         "--targets", "HR-CTV", "--no-export", "--allow-no-oars", "--out", str(tmp_path / "out"),
                         "--quiet"], capsys)
    assert code == 2 and VARIANTS["no_control_points"][1] in err and "--rtplan" in err
    assert not (tmp_path / "out").exists()
