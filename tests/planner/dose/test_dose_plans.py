"""Secondary check of real TPS plans, the RT Dose writer, and the ``reachplan dose`` command."""

from __future__ import annotations

import hashlib
import json
import shutil
import warnings
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pydicom
import pytest

from reachplan.imaging.errors import DicomQuirkWarning, OutputExistsError
from reachplan.imaging.rtplan import channel_paths, read_rtplan
from reachplan.imaging.rtstruct import read_rtstruct
from reachplan.imaging.types import Grid
from reachplan.planner.cli import main
from reachplan.planner.dose.dwells import DwellSet, dose_on_grid, grid_points_mm, plan_dwells
from reachplan.planner.dose.plan_check import check_points
from reachplan.planner.dose.tg43 import Tg43Kernel
from reachplan.planner.lookup import all_sources, get_source
from reachplan.plugins.exporters.rtdose import DoseContext, read_rtdose_grid, write_rtdose
from reachplan.plugins.sources.identify import recognise_source


def _files(reference_file: Callable[[str], Path], kind: str) -> tuple[Path, Path]:
    """The Eclipse example plan and structure set of ``kind`` (``"hdr"`` or ``"pdr"``)."""
    return (reference_file(f"tps_examples/{kind}/RP.{kind.upper()}.dcm"),
            reference_file(f"tps_examples/{kind}/RS.{kind.upper()}.dcm"))


def _load(reference_file: Callable[[str], Path], kind: str):  # type: ignore[no-untyped-def]
    rp, rs = _files(reference_file, kind)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DicomQuirkWarning)
        plan = read_rtplan(rp)
        ss = read_rtstruct(rs)
    return rp, rs, plan, ss


@pytest.mark.parametrize(("case", "source"), [("hdr", "gammamed_plus_hdr"), ("pdr", "gammamed_plus_pdr")])
def test_tps_point_doses_within_0_2_percent(reference_file: Callable[[str], Path], case: str, source: str) -> None:
    _, _, plan, ss = _load(reference_file, case)
    src = plan.source()
    assert recognise_source(all_sources(), *src.labels(), plan.machine_name) == source
    dwells = plan_dwells(plan, channel_paths(plan, ss))
    assert len(dwells) == plan.n_dwells
    checks = check_points(plan, dwells, Tg43Kernel(get_source(source)), src.air_kerma_rate_u)
    assert len(checks) == 2
    for c in checks:
        assert c.tps_gy is not None and c.diff_percent is not None
        assert abs(c.diff_percent) < 0.2, (c.name, c.dose_gy, c.tps_gy)
    # the check discriminates: another source's data (VS2000) misses by well over 0.2 %
    wrong = check_points(plan, dwells, Tg43Kernel(get_source("varisource_vs2000_hdr")), src.air_kerma_rate_u)
    assert max(abs(c.diff_percent or 0.0) for c in wrong) > 0.5


def test_source_direction_matters(reference_file: Callable[[str], Path]) -> None:
    """Reversed channel paths (θ = 0 toward the base) change the Point A dose: the convention is tested."""
    _, _, plan, ss = _load(reference_file, "pdr")
    paths = channel_paths(plan, ss)
    kernel = Tg43Kernel(get_source("gammamed_plus_pdr"))
    sk = plan.source().air_kerma_rate_u
    good = check_points(plan, plan_dwells(plan, paths), kernel, sk)
    flipped = check_points(plan, plan_dwells(plan, {k: v[::-1] for k, v in paths.items()}), kernel, sk)
    assert [abs(c.diff_percent or 0) for c in good] < [abs(c.diff_percent or 0) for c in flipped]


def _grid(oblique: bool = False) -> Grid:
    a = np.eye(4)
    if oblique:
        c, s = np.cos(0.3), np.sin(0.3)
        a[:3, :3] = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])
    a[:3, :3] = a[:3, :3] @ np.diag([2.0, 2.5, 3.0])
    a[:3, 3] = [-20.0, -25.0, -12.0]
    return Grid((6, 9, 11), a)


@pytest.mark.parametrize(("bits", "oblique"), [(16, False), (32, False), (16, True)])
def test_rtdose_round_trip(tmp_path: Path, bits: int, oblique: bool) -> None:
    grid = _grid(oblique)
    dw = DwellSet([[0.0, 0.0, 0.0], [0.0, 0.0, -5.0]], [[0, 0, 1.0], [0, 0, 1.0]], [20.0, 30.0])
    dose = dose_on_grid(grid, dw, Tg43Kernel(get_source("gammamed_plus_hdr")), 40000.0)
    out = write_rtdose(tmp_path / "rd.dcm", dose, grid, DoseContext("1.2.3.4", referenced_plan_uid="1.2.3.5"),
                       bits=bits)
    back, grid2 = read_rtdose_grid(out)
    scaling = float(pydicom.dcmread(out).DoseGridScaling)
    assert np.max(np.abs(back - dose)) <= 0.5 * scaling * (1 + 1e-6)
    assert scaling <= dose.max() / (2**bits - 1) * (1 + 1e-6)
    assert grid2.shape == grid.shape
    assert np.allclose(grid2.patient_from_index, grid.patient_from_index, atol=1e-6)
    assert np.allclose(grid_points_mm(grid2), grid_points_mm(grid), atol=1e-5)
    ds = pydicom.dcmread(out)
    assert ds.DoseUnits == "GY" and ds.ReferencedRTPlanSequence[0].ReferencedSOPInstanceUID == "1.2.3.5"


def test_rtdose_passes_dciodvfy(tmp_path: Path, dciodvfy: Callable[[Path], list[str]]) -> None:
    grid = _grid()
    dose = np.linspace(0, 12.0, int(np.prod(grid.shape))).reshape(grid.shape)
    out = write_rtdose(tmp_path / "rd.dcm", dose, grid, DoseContext("1.2.3.4", referenced_plan_uid="1.2.3.5"))
    text = "\n".join(dciodvfy(out))
    assert "RTDose" in text
    assert "Error" not in text, text


def test_rtdose_never_overwrites_foreign_files(tmp_path: Path) -> None:
    grid = _grid()
    other = tmp_path / "notes.dcm"
    other.write_bytes(b"not ours")
    with pytest.raises(OutputExistsError, match="not an RT Dose written by reachplan"):
        write_rtdose(other, np.zeros(grid.shape), grid, DoseContext("1.2.3"))
    assert other.read_bytes() == b"not ours"
    ours = write_rtdose(tmp_path / "rd.dcm", np.ones(grid.shape), grid, DoseContext("1.2.3"))
    write_rtdose(ours, np.full(grid.shape, 2.0), grid, DoseContext("1.2.3"))  # our own file: replaced
    assert read_rtdose_grid(ours)[0].max() == pytest.approx(2.0)
    sheared = Grid(grid.shape, grid.patient_from_index @ np.array(
        [[1, 0, 0.3, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1.0]]))
    with pytest.raises(ValueError, match="normal"):
        write_rtdose(tmp_path / "x.dcm", np.zeros(grid.shape), sheared, DoseContext("1.2.3"))
    assert not list(tmp_path.glob(".*tmp"))


def _sha(p: Path) -> str:
    return hashlib.sha256(p.read_bytes()).hexdigest()


def test_cli_points_json_and_like(reference_file: Callable[[str], Path], tmp_path: Path,
                                  capsys: pytest.CaptureFixture[str]) -> None:
    rp, rs, plan, ss = _load(reference_file, "hdr")
    hashes = (_sha(rp), _sha(rs))
    out = tmp_path / "RD.dcm"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DicomQuirkWarning)
        code = main(["dose", "--plan", str(rp), "--structures", str(rs), "--points", "--spacing", "4",
                     "--out", str(out), "--json"])
    assert code == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["out"] == str(out) and isinstance(doc["warnings"], list)
    assert [d["name"] for d in doc["points"]] == ["PtA_left", "PtA_right"]
    for d in doc["points"]:
        assert set(d) == {"name", "position_mm", "dose_gy", "tps_gy", "diff_percent"}
        assert abs(d["diff_percent"]) < 0.2
        assert d["dose_gy"] == pytest.approx(d["tps_gy"], rel=2e-3)
    assert (_sha(rp), _sha(rs)) == hashes
    # the written RT Dose is the computed dose on its grid
    back, grid = read_rtdose_grid(out)
    assert grid.spacing_mm == pytest.approx([4.0, 4.0, 4.0])
    dwells = plan_dwells(plan, channel_paths(plan, ss))
    expect = dose_on_grid(grid, dwells, Tg43Kernel(get_source("gammamed_plus_hdr")), 40700.0)
    # voxels next to dwells are stored at 10 x the plan's setup dose (6.0016 Gy, 1 fraction)
    assert expect.max() > 10 * plan.setup_doses_gy[0][1]
    expect = np.minimum(expect, 10 * plan.setup_doses_gy[0][1])
    scaling = float(pydicom.dcmread(out).DoseGridScaling)
    assert np.max(np.abs(back - expect)) <= 0.5 * scaling * 1.001 + 1e-6 * expect.max()
    # --like reuses that grid exactly
    out2 = tmp_path / "RD2.dcm"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DicomQuirkWarning)
        assert main(["dose", "--plan", str(rp), "--structures", str(rs), "--like", str(out),
                     "--out", str(out2)]) == 0
    back2, grid2 = read_rtdose_grid(out2)
    assert grid2.shape == grid.shape and np.allclose(grid2.patient_from_index, grid.patient_from_index)
    assert np.allclose(back2, back, atol=2 * scaling)


def _run_error(args: list[str], capsys: pytest.CaptureFixture[str]) -> str:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DicomQuirkWarning)
        assert main(args) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and err.startswith("reachplan dose: error:")
    return err


def test_cli_errors(reference_file: Callable[[str], Path], tmp_path: Path,
                    capsys: pytest.CaptureFixture[str]) -> None:
    rp_hdr, rs_hdr = _files(reference_file, "hdr")
    rp = tmp_path / "RP.dcm"
    rs = tmp_path / "RS.dcm"
    shutil.copy(rp_hdr, rp)
    shutil.copy(rs_hdr, rs)
    before = (_sha(rp), _sha(rs))
    assert "one of the inputs" in _run_error(
        ["dose", "--plan", str(rp), "--structures", str(rs), "--out", str(rp)], capsys)
    beam = Path(pydicom.data.get_testdata_file("rtplan.dcm"))
    assert "not a brachytherapy plan" in _run_error(
        ["dose", "--plan", str(beam), "--structures", str(rs), "--out", str(tmp_path / "a.dcm")], capsys)
    assert "spacing" in _run_error(
        ["dose", "--plan", str(rp), "--structures", str(rs), "--spacing", "0", "--out", str(tmp_path / "b.dcm")],
        capsys)
    ct = Path(pydicom.data.get_testdata_file("CT_small.dcm"))
    assert "RT Structure Set" in _run_error(
        ["dose", "--plan", str(rp), "--structures", str(ct), "--out", str(tmp_path / "c.dcm")], capsys)
    assert (_sha(rp), _sha(rs)) == before
    assert not (tmp_path / "a.dcm").exists() and not (tmp_path / "c.dcm").exists()


def _anonymised(src: Path, dst: Path, **source_attrs: object) -> Path:
    """Copy of a plan whose source and machine names say nothing (as pyTG43's anonymised inputs)."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        ds = pydicom.dcmread(src)
        ds.SourceSequence[0].SourceIsotopeName = "isotope"
        ds.TreatmentMachineSequence[0].TreatmentMachineName = "txmachine"
        for k, v in source_attrs.items():
            setattr(ds.SourceSequence[0], k, v)
        ds.save_as(dst)
    return dst


def test_cli_unidentifiable_source_needs_option(
    reference_file: Callable[[str], Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    rp_hdr, rs = _files(reference_file, "hdr")
    # HDR, 3.5 mm, Ir-192 by half-life, placeholder manufacturer: three registered sources fit
    rp = _anonymised(rp_hdr, tmp_path / "RP.dcm", SourceManufacturer="manufacturer")
    err = _run_error(["dose", "--plan", str(rp), "--structures", str(rs), "--out", str(tmp_path / "a.dcm")], capsys)
    assert "--source" in err and "flexisource_hdr" in err and "spec_m19_hdr" in err
    assert "no TG-43 source named" in _run_error(
        ["dose", "--plan", str(rp), "--structures", str(rs), "--source", "nope", "--out", str(tmp_path / "a.dcm")],
        capsys)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DicomQuirkWarning)
        assert main(["dose", "--plan", str(rp), "--structures", str(rs), "--source", "gammamed_plus_hdr",
                     "--points", "--json", "--spacing", "10", "--out", str(tmp_path / "b.dcm")]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert all(abs(d["diff_percent"]) < 0.2 for d in doc["points"])
    # an isotope without registered data is an error, whatever the names say (no Ir-192 data for Cs-137)
    cs = _anonymised(rp_hdr, tmp_path / "cs.dcm", SourceIsotopeName="Cs-137",
                     SourceIsotopeHalfLife="10987")
    assert "no TG-43 data is registered for Cs-137" in _run_error(
        ["dose", "--plan", str(cs), "--structures", str(rs), "--out", str(tmp_path / "c.dcm")], capsys)
    assert "Cs-137" in _run_error(["dose", "--plan", str(cs), "--structures", str(rs), "--source",
                                   "gammamed_plus_hdr", "--out", str(tmp_path / "c.dcm")], capsys)
    # a named source that contradicts the plan's active length
    bad = _anonymised(rp_hdr, tmp_path / "bad.dcm", SourceIsotopeName="GammaMed Plus HDR",
                      ActiveSourceLength="5")
    assert "active length" in _run_error(
        ["dose", "--plan", str(bad), "--structures", str(rs), "--out", str(tmp_path / "d.dcm")], capsys)


@pytest.mark.parametrize("kind", ["hdr", "pdr"])
def test_cli_infers_the_source_of_anonymised_eclipse_plans(
    kind: str, reference_file: Callable[[str], Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """The shared Eclipse examples, anonymised: the source is inferred and the TPS point doses recomputed to 0.1 %."""
    rp_tps, rs = _files(reference_file, kind)
    rp = _anonymised(rp_tps, tmp_path / "RP.dcm")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DicomQuirkWarning)
        assert main(["dose", "--plan", str(rp), "--structures", str(rs), "--spacing", "10",
                     "--out", str(tmp_path / "a.dcm")]) == 0
        out = capsys.readouterr().out
        assert f"gammamed_plus_{kind}: inferred from Ir-192, {kind.upper()}" in out
        assert main(["dose", "--plan", str(rp), "--structures", str(rs), "--points", "--json", "--spacing", "10",
                     "--out", str(tmp_path / "b.dcm")]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert len(doc["points"]) == 2 and all(abs(d["diff_percent"]) < 0.1 for d in doc["points"])


def test_cli_decays_the_strength_to_the_treatment_date(
    reference_file: Callable[[str], Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    rp, rs = _files(reference_file, "hdr")
    args = ["dose", "--plan", str(rp), "--structures", str(rs), "--spacing", "10",
            "--points", "--json"]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DicomQuirkWarning)
        assert main([*args, "--out", str(tmp_path / "a.dcm")]) == 0
        at_plan = json.loads(capsys.readouterr().out)
        # one half-life (73.83 d, the plan's) after the reference date 2018-03-20 00:00: half the dose
        assert main([*args, "--treatment-date", "20180601195512", "--out", str(tmp_path / "b.dcm")]) == 0
        later = json.loads(capsys.readouterr().out)
        assert main(["dose", "--plan", str(rp), "--structures", str(rs),
                     "--spacing", "10", "--json", "--treatment-date", "20180601195512",
                     "--out", str(tmp_path / "c.dcm")]) == 0
        summary = json.loads(capsys.readouterr().out)
    for a, b in zip(at_plan["points"], later["points"], strict=True):
        assert b["dose_gy"] == pytest.approx(0.5 * a["dose_gy"], rel=1e-6)  # 73 d 19:55:12 = 73.83 d
    assert summary["air_kerma_reference_u"] == 40700.0
    assert summary["air_kerma_treatment_u"] == pytest.approx(40700.0 * 2 ** (-summary["elapsed_days"] / 73.83))
    assert "not a date" in _run_error([*args, "--treatment-date", "2018-06-02", "--out", str(tmp_path / "d.dcm")],
                                      capsys)


def test_rtdose_absolute_frame_offsets(tmp_path: Path) -> None:
    """An RD whose GridFrameOffsetVector holds patient z (first value non-zero) gives the same grid."""
    grid = _grid()
    out = write_rtdose(tmp_path / "rd.dcm", np.ones(grid.shape), grid, DoseContext("1.2.3"))
    ds = pydicom.dcmread(out)
    z0 = float(ds.ImagePositionPatient[2])
    ds.GridFrameOffsetVector = [f"{z0 + float(v):.4f}" for v in ds.GridFrameOffsetVector]
    ds.save_as(tmp_path / "abs.dcm")
    _, grid2 = read_rtdose_grid(tmp_path / "abs.dcm")
    assert np.allclose(grid2.patient_from_index, grid.patient_from_index, atol=1e-4)
