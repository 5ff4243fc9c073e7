"""Brachy RT Plan reading: real Eclipse exports, pydicom's test plans, and generated quirky plans."""

from __future__ import annotations

import hashlib
import io
import warnings
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from pydicom.data import get_testdata_file
from pydicom.dataset import Dataset, FileMetaDataset
from pydicom.filebase import DicomBytesIO
from pydicom.filewriter import write_dataset
from pydicom.sequence import Sequence
from pydicom.uid import ExplicitVRLittleEndian, ImplicitVRLittleEndian, generate_uid

from reachplan.imaging.errors import CorruptFileError, DicomQuirkWarning, NoDicomError
from reachplan.imaging.rtplan import PlanQuirkWarning, channel_paths, read_rtplan
from reachplan.imaging.rtstruct import read_rtstruct


def _sha(p: Path) -> str:
    return hashlib.sha256(p.read_bytes()).hexdigest()


def _read_quiet(path: Path):  # type: ignore[no-untyped-def]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DicomQuirkWarning)
        return read_rtplan(path)


def test_eclipse_hdr(reference_file: Callable[[str], Path]) -> None:
    rp = reference_file("tps_examples/hdr/RP.HDR.dcm")
    before = _sha(rp)
    plan = _read_quiet(rp)
    assert _sha(rp) == before
    assert plan.quirks == ("invalid value (Invalid value for VR UI: 'UNKNOWN'.)",)  # the Study Instance UID
    assert plan.is_brachy and plan.treatment_type == "HDR" and plan.technique == "INTRACAVITARY"
    assert [c.number for c in plan.channels] == [1, 2, 3]
    assert [c.n_dwells for c in plan.channels] == [15, 5, 5]
    assert [c.roi_number for c in plan.channels] == [18, 16, 17]
    assert [c.total_time_s for c in plan.channels] == pytest.approx([271.4, 101.0, 100.7], abs=1e-6)
    for c in plan.channels:  # the dwell times add up to the channel's total time
        assert c.dwell_times_s.sum() == pytest.approx(c.total_time_s, rel=1e-9)
    assert plan.channels[0].dwell_times_s[0] == pytest.approx(36.3, abs=1e-6)
    assert plan.channels[0].dwell_relative_mm[:3] == pytest.approx([7.5, 12.5, 17.5])
    src = plan.source()
    assert src.air_kerma_rate_u == 40700.0 and src.active_length_mm == 3.5
    assert "GammaMed Plus HDR" in src.isotope_name and src.reference_date == "20180320"
    assert plan.n_fractions == 1 and plan.n_pulses == 1
    refs = {r.description: r for r in plan.dose_references}
    assert refs["PtA_left"].tps_dose_gy == pytest.approx(6.002, abs=5e-4)
    assert refs["PtA_right"].tps_dose_gy == pytest.approx(6.136, abs=5e-4)
    assert refs["PtA_left"].position_mm == pytest.approx([19.0747446756398, -12.5, 22.7609705458502])


def test_eclipse_pdr(reference_file: Callable[[str], Path]) -> None:
    plan = _read_quiet(reference_file("tps_examples/pdr/RP.PDR.dcm"))
    assert plan.treatment_type == "PDR" and plan.n_pulses == 43 and plan.quirks == ()
    assert [c.n_dwells for c in plan.channels] == [12, 5, 4]
    assert [c.roi_number for c in plan.channels] == [6, 5, 4]
    assert [c.total_time_s for c in plan.channels] == pytest.approx([276.3, 69.0, 54.6], abs=1e-6)
    # FinalCumulativeTimeWeight = ChannelTotalTime x pulses: the dwell times are per pulse
    assert plan.channels[0].final_weight == pytest.approx(276.3 * 43, rel=1e-9)
    assert plan.channels[0].dwell_times_s.sum() == pytest.approx(276.3, rel=1e-9)
    refs = {r.description: r for r in plan.dose_references}
    assert refs["PT A RIGHT"].tps_dose_gy == pytest.approx(22.537, abs=5e-4)
    assert refs["PT A LEFT"].tps_dose_gy == pytest.approx(23.173, abs=5e-4)
    assert refs["ctv"].position_mm is None


def test_channel_paths_from_structure_set(reference_file: Callable[[str], Path]) -> None:
    plan = _read_quiet(reference_file("tps_examples/hdr/RP.HDR.dcm"))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DicomQuirkWarning)
        ss = read_rtstruct(reference_file("tps_examples/hdr/RS.HDR.dcm"))
    paths = channel_paths(plan, ss)
    assert sorted(paths) == [1, 2, 3]
    assert paths[1].shape == (23, 3)  # tandem, written tip first
    assert paths[1][0] == pytest.approx([-0.83, -35.28, 53.44], abs=0.01)
    # every dwell lies on its channel (within 1 mm)
    for c in plan.channels:
        d = np.min(np.linalg.norm(c.dwell_positions_mm[:, None] - paths[c.number][None], axis=2), axis=1)
        seg = np.diff(paths[c.number], axis=0)
        assert d.max() < max(1.0, float(np.linalg.norm(seg, axis=1).max()))


def test_pydicom_beam_plan_is_read_not_brachy() -> None:
    with pytest.warns(PlanQuirkWarning, match="missing Frame of Reference UID"):
        plan = read_rtplan(Path(get_testdata_file("rtplan.dcm")))
    assert not plan.is_brachy
    assert plan.channels == () and plan.n_beams == 1 and plan.n_fractions == 30
    assert [r.description for r in plan.dose_references] == ["iso", "PTV"]
    assert all(r.tps_dose_gy is None for r in plan.dose_references)


def test_truncated_and_wrong_objects() -> None:
    with pytest.raises(CorruptFileError, match="truncated"):
        read_rtplan(Path(get_testdata_file("rtplan_truncated.dcm")))
    with pytest.raises(NoDicomError, match="not an RT Plan"):
        read_rtplan(Path(get_testdata_file("CT_small.dcm")))
    with pytest.raises(NoDicomError, match="not a file"):
        read_rtplan(Path("/nonexistent/RP.dcm"))


# --- generated plans ----------------------------------------------------------------------------------


def _brachy_plan(
    weights: list[float] | None = None,
    total: float | None = 60.0,
    final: float | None = None,
    frame: bool = True,
) -> Dataset:
    """A minimal HDR plan: one channel with three dwells 5 mm apart along -z."""
    w = [0.0, 10.0, 10.0, 30.0, 30.0, 60.0] if weights is None else weights
    ds = Dataset()
    ds.file_meta = FileMetaDataset()
    ds.file_meta.MediaStorageSOPClassUID = "1.2.840.10008.5.1.4.1.1.481.5"
    ds.file_meta.MediaStorageSOPInstanceUID = generate_uid()
    ds.file_meta.TransferSyntaxUID = ImplicitVRLittleEndian
    ds.SOPClassUID = ds.file_meta.MediaStorageSOPClassUID
    ds.SOPInstanceUID = ds.file_meta.MediaStorageSOPInstanceUID
    ds.Modality = "RTPLAN"
    ds.Manufacturer = "Test"
    if frame:
        ds.FrameOfReferenceUID = generate_uid()
    ds.BrachyTreatmentType = "HDR"
    ds.BrachyTreatmentTechnique = "INTERSTITIAL"
    src = Dataset()
    src.SourceNumber = 1
    src.SourceIsotopeName = "Ir-192"
    src.ReferenceAirKermaRate = "40000"
    src.ActiveSourceLength = "3.5"
    ds.SourceSequence = Sequence([src])
    ref = Dataset()
    ref.DoseReferenceNumber = 1
    ref.DoseReferenceDescription = "P1"
    ref.DoseReferenceStructureType = "COORDINATES"
    ref.DoseReferencePointCoordinates = ["10", "0", "-5"]
    ds.DoseReferenceSequence = Sequence([ref])
    fg = Dataset()
    fg.NumberOfFractionsPlanned = 2
    rbas = Dataset()
    rbas.ReferencedBrachyApplicationSetupNumber = 1
    rbas.BrachyApplicationSetupDose = "5"
    fg.ReferencedBrachyApplicationSetupSequence = Sequence([rbas])
    ds.FractionGroupSequence = Sequence([fg])
    ch = Dataset()
    ch.ChannelNumber = 1
    ch.ReferencedROINumber = 7
    ch.SourceMovementType = "STEPWISE"
    if total is not None:
        ch.ChannelTotalTime = str(total)
    ch.FinalCumulativeTimeWeight = str(final if final is not None else w[-1])
    cps = []
    for k, cw in enumerate(w):
        cp = Dataset()
        cp.ControlPointIndex = k
        cp.ControlPointRelativePosition = str(5.0 * (k // 2))
        cp.ControlPoint3DPosition = ["0", "0", str(-5.0 * (k // 2))]
        cp.CumulativeTimeWeight = str(cw)
        item = Dataset()
        item.ReferencedDoseReferenceNumber = 1
        item.CumulativeDoseReferenceCoefficient = f"{0.1 * (k + 1):.1f}"
        cp.BrachyReferencedDoseReferenceSequence = Sequence([item])
        cps.append(cp)
    ch.BrachyControlPointSequence = Sequence(cps)
    ch.NumberOfControlPoints = len(cps)
    setup = Dataset()
    setup.ApplicationSetupNumber = 1
    setup.ChannelSequence = Sequence([ch])
    ds.ApplicationSetupSequence = Sequence([setup])
    return ds


def _write(ds: Dataset, path: Path) -> Path:
    ds.save_as(path, enforce_file_format=True)
    return path


def test_generated_plan_reads_clean(tmp_path: Path) -> None:
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        plan = read_rtplan(_write(_brachy_plan(), tmp_path / "rp.dcm"))
    ch = plan.channels[0]
    assert ch.n_dwells == 3
    assert ch.dwell_times_s == pytest.approx([10.0, 20.0, 30.0])
    assert ch.dwell_positions_mm[:, 2] == pytest.approx([0.0, -5.0, -10.0])
    # TPS dose = last coefficient (0.6) x setup dose (5 Gy) x fractions (2)
    assert plan.dose_references[0].tps_dose_gy == pytest.approx(6.0)
    assert plan.quirks == ()


QUIRKS: list[tuple[str, Callable[[Dataset], None], str]] = [
    ("restarting weights", lambda ds: _set_weights(ds, [0, 10, 0, 20, 0, 30]), "do not accumulate"),
    ("final weight differs", lambda ds: setattr(
        ds.ApplicationSetupSequence[0].ChannelSequence[0], "FinalCumulativeTimeWeight", "120"), "differs"),
    ("no frame of reference", lambda ds: delattr(ds, "FrameOfReferenceUID"), "Frame of Reference"),
    ("transit weight", lambda ds: _set_weights(ds, [0, 10, 12, 30, 30, 60]), "different positions"),
]


def _set_weights(ds: Dataset, w: list[float]) -> None:
    ch = ds.ApplicationSetupSequence[0].ChannelSequence[0]
    for cp, x in zip(ch.BrachyControlPointSequence, w, strict=True):
        cp.CumulativeTimeWeight = str(x)
    ch.FinalCumulativeTimeWeight = str(w[-1])


@pytest.mark.parametrize(("label", "edit", "match"), QUIRKS, ids=[q[0] for q in QUIRKS])
def test_quirks_warn_by_name(tmp_path: Path, label: str, edit: Callable[[Dataset], None], match: str) -> None:
    ds = _brachy_plan()
    edit(ds)
    path = _write(ds, tmp_path / "rp.dcm")
    before = _sha(path)
    with pytest.warns(PlanQuirkWarning, match=match):
        plan = read_rtplan(path)
    assert _sha(path) == before
    assert any(match in q for q in plan.quirks)
    times = plan.channels[0].dwell_times_s
    assert np.all(times >= 0) and np.all(np.isfinite(times))
    if label == "restarting weights":
        assert times == pytest.approx([10.0, 20.0, 30.0])  # weights 10:20:30 of the 60 s total
    if label == "final weight differs":
        assert times == pytest.approx([5.0, 10.0, 15.0])  # the declared final weight normalises


def test_overlong_decimal_string_is_read_with_warning(tmp_path: Path) -> None:
    ds = _brachy_plan()
    path = tmp_path / "rp.dcm"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        ds.ApplicationSetupSequence[0].ChannelSequence[0].ChannelTotalTime = "60.000000000000000001"  # 21 chars
        _write(ds, path)
    with pytest.warns(PlanQuirkWarning, match="over-long decimal strings .* ChannelTotalTime"):
        plan = read_rtplan(path)
    assert plan.channels[0].total_time_s == pytest.approx(60.0)


def test_an_integer_beyond_the_is_range_is_read_as_absent_with_a_warning(tmp_path: Path) -> None:
    # found by the mutation fuzz: Channel Number "1e30" became a Python int no numpy array could hold
    ds = _brachy_plan()
    path = tmp_path / "rp.dcm"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        ds.ApplicationSetupSequence[0].ChannelSequence[0].ChannelNumber = "1e30"
        _write(ds, path)
    with pytest.warns(PlanQuirkWarning, match="1e30"):
        plan = read_rtplan(path)
    assert plan.channels[0].number == 0 and np.asarray([c.number for c in plan.channels]).dtype.kind == "i"


def test_missing_total_time_is_typed_error(tmp_path: Path) -> None:
    path = _write(_brachy_plan(total=None), tmp_path / "rp.dcm")
    with pytest.raises(CorruptFileError, match="Channel Total Time"):
        read_rtplan(path)


def _oncentra(ds: Dataset, raw: bool) -> None:
    contour = Dataset()
    contour.ContourGeometricType = "OPEN_NONPLANAR"
    contour.ContourData = ["0", "0", "5", "0", "0", "-20"]
    roi = Dataset()
    roi.ReferencedROINumber = 12
    roi.ContourSequence = Sequence([contour])
    item = Dataset()
    item.add_new((0x3006, 0x0039), "SQ", Sequence([roi]))
    ds.add_new((0x300F, 0x0010), "LO", "NUCLETRON")
    ch = ds.ApplicationSetupSequence[0].ChannelSequence[0]
    del ch.ReferencedROINumber
    ch.add_new((0x300B, 0x0010), "LO", "NUCLETRON")
    if raw:
        buf = io.BytesIO()
        # an implicit-VR encoded item, as Oncentra files carry it inside an UN element
        item_bytes = DicomBytesIO()
        item_bytes.is_little_endian = True
        item_bytes.is_implicit_VR = True
        write_dataset(item_bytes, item)
        body = item_bytes.getvalue()
        buf.write(b"\xfe\xff\x00\xe0" + len(body).to_bytes(4, "little") + body)
        ds.add_new((0x300F, 0x1000), "UN", buf.getvalue())
        ch.add_new((0x300B, 0x1000), "UN", b"12")
    else:  # explicit VR keeps the SQ VR of the private element
        ds.file_meta.TransferSyntaxUID = ExplicitVRLittleEndian
        ds.add_new((0x300F, 0x1000), "SQ", Sequence([item]))
        ch.add_new((0x300B, 0x1000), "IS", "12")


@pytest.mark.parametrize("raw", [False, True], ids=["sequence", "raw-bytes"])
def test_oncentra_private_catheters(tmp_path: Path, raw: bool) -> None:
    ds = _brachy_plan()
    _oncentra(ds, raw)
    path = _write(ds, tmp_path / "rp.dcm")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        plan = read_rtplan(path)
    assert plan.channels[0].roi_number == 12
    assert len(plan.catheter_paths) == 1 and plan.catheter_paths[0].roi_number == 12
    paths = channel_paths(plan)
    assert paths[1] == pytest.approx(np.array([[0, 0, 5], [0, 0, -20]], dtype=float))
    assert any("raw bytes" in q for q in plan.quirks) == raw
    named = [str(w.message) for w in caught if issubclass(w.category, PlanQuirkWarning)]
    assert all("read anyway" in m for m in named)


# --- property-based: any times and weights give sound dwell times or a typed error ----------------------------

_WEIGHT = st.one_of(st.floats(-10, 1e3), st.sampled_from([float("nan"), float("inf"), -1.0, 0.0]))


@settings(max_examples=80, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(weights=st.lists(_WEIGHT, min_size=6, max_size=6),
       total=st.one_of(st.floats(-10, 1e3), st.sampled_from([float("nan"), float("inf"), 1e30])),
       final=st.one_of(st.none(), _WEIGHT))
def test_any_times_and_weights_give_sound_dwell_times_or_a_typed_error(
    tmp_path_factory: pytest.TempPathFactory, weights: list[float], total: float, final: float | None
) -> None:
    path = tmp_path_factory.mktemp("prop") / "rp.dcm"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        ds = _brachy_plan(weights=[float(f"{w:.6g}") for w in weights], total=float(f"{total:.6g}"),
                          final=None if final is None else float(f"{final:.6g}"))
        _write(ds, path)
        try:
            plan = read_rtplan(path)
        except CorruptFileError as exc:  # InvalidValueError included
            assert "\n" not in str(exc) and "rp.dcm" in str(exc)
            return
    (ch,) = plan.channels
    assert np.all(np.isfinite(ch.dwell_times_s)) and np.all(ch.dwell_times_s >= 0)
    assert 0 <= ch.total_time_s <= 1e7
    assert ch.dwell_times_s.sum() <= ch.total_time_s * (1 + 1e-6) + 1e-9  # never more time than the channel has
