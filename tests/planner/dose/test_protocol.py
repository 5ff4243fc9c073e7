"""The protocol as data: the built-in EMBRACE II file, user files, bad files, and each aim reported against a plan.

The structure set here is made in the test: an HR-CTV cylinder, a bladder and a 1 cm³ rectum drawn as contours,
rasterised by the planner's own masks; the dose of a line of dwells comes from TG-43 and the metrics the report
shows are checked against a sort of the voxel doses done here.
"""

from __future__ import annotations

import json
import math
import re
import warnings
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from reachplan import ReachplanError
from reachplan.imaging.errors import DicomQuirkWarning
from reachplan.imaging.types import Contour, Roi, StructureSet
from reachplan.planner.cli import build_parser, main
from reachplan.planner.cli.plan import check_plan_arguments
from reachplan.planner.delivery import Delivery
from reachplan.planner.dose.aims import Aims
from reachplan.planner.dose.coverage import structure_metrics, voxel_volume_cc
from reachplan.planner.dose.dwells import DwellSet, dose_on_grid
from reachplan.planner.dose.evaluation import (
    SMALL_ORGAN_METRIC,
    AimsTable,
    emit,
    evaluate_aims,
    protocol_json,
    site_warning,
)
from reachplan.planner.dose.protocol import load_protocol
from reachplan.planner.dose.structures import planning_structures
from reachplan.planner.dose.tg43 import Tg43Kernel
from reachplan.planner.errors import ProtocolError, ProtocolSiteWarning, SmallOrganWarning
from reachplan.planner.implant.dwells import optimise_dwell_times
from reachplan.planner.lookup import get_source, protocol_file, protocol_names
from reachplan.planner.report.terminal import aims_rows, format_rows

SK = 40000.0
BUILTIN = protocol_file("embrace_ii").text

PROSTATE = """
name = "Prostate HDR boost (test)"
site = "prostate"
source = "made up for this test"
target_names = ["Prostate", "CTV"]
headroom_eqd2_gy = 2.0
[fractionation]
brachytherapy_fractions = 1
ebrt_dose_gy = 46.0
ebrt_fractions = 23
[alpha_beta_gy]
target = 1.5
organ = 3.0
[target]
d90 = { aim_min = 100.0, limit_min = 95.0 }
d98 = { aim_min = 90.0 }
[gtv]
d98 = { aim_min = 100.0, limit_min = 95.0 }
[organs]
rectum = { aim_max = 75.0, limit_max = 80.0 }
[points."Urethra point"]
match = ["urethra"]
aim_max = 120.0
"""


def _disc(z: float, cx: float, cy: float, r: float) -> Contour:
    t = np.linspace(0.0, 2 * np.pi, 48, endpoint=False)
    return Contour(np.stack([cx + r * np.cos(t), cy + r * np.sin(t), np.full_like(t, z)], 1), "CLOSED_PLANAR")


def _cylinder(number: int, name: str, cx: float, cy: float, r: float, z0: float, z1: float) -> Roi:
    return Roi(number, name, tuple(_disc(z, cx, cy, r) for z in np.arange(z0, z1 + 1e-9, 2.0)))


@pytest.fixture(scope="module")
def case() -> SimpleNamespace:
    """HR-CTV (r 15 mm), a bladder anterior and a rectum of 1 cm³ posterior; a line of dwells on the axis."""
    rois = (_cylinder(1, "HR-CTV", 0.0, 0.0, 15.0, 0.0, 30.0), _cylinder(2, "Bladder", 0.0, -28.0, 10.0, 6.0, 26.0),
            _cylinder(3, "Rectum", 0.0, 22.0, 4.0, 8.0, 28.0))
    planning = planning_structures(StructureSet(rois, "1.2.3"), None, "HR-CTV", ["Bladder", "Rectum"], ())
    kernel = Tg43Kernel(get_source("gammamed_plus_hdr"))
    z = np.arange(2.0, 29.0, 2.5)
    dwells = DwellSet(np.stack([np.zeros_like(z), np.zeros_like(z), z], 1), np.tile([0.0, 0.0, 1.0], (len(z), 1)),
                      np.full(len(z), 12.0), np.ones(len(z), int))
    dose = dose_on_grid(planning.grid, dwells, kernel, SK)
    return SimpleNamespace(planning=planning, kernel=kernel, dose=dose, vox=voxel_volume_cc(planning.grid))


def _table(case: SimpleNamespace, aims: Aims, points: tuple[tuple[str, float], ...] = ()) -> AimsTable:
    rx = aims.prescription_gy
    ps = case.planning
    target = structure_metrics("HR-CTV", case.dose[ps.target.mask], case.vox, rx, aims.alpha_beta_target_gy,
                               aims.fractionation)
    oars = [structure_metrics(o.name, case.dose[o.mask], case.vox, rx, aims.alpha_beta_oar_gy, aims.fractionation)
            for o in ps.oars]
    volumes = {o.name: float(o.mask.sum()) * case.vox for o in ps.oars}
    return evaluate_aims(aims, target, oars, organ_volumes_cc=volumes, points=points)


def test_the_builtin_embrace_ii_file_is_exactly_the_default_aims() -> None:
    assert "embrace_ii" in protocol_names()
    for spec in (None, "embrace_ii", "EMBRACE II", "embrace-ii"):
        assert load_protocol(spec) == Aims()
    a = load_protocol()
    # the numbers of the reference notes (ESGO/ESTRO table, EMBRACE II), written out here once more
    assert (a.target_d90_eqd2_gy, a.target_d90_max_eqd2_gy, a.target_d90_limit_eqd2_gy) == (90.0, 95.0, 85.0)
    assert (a.target_d98_eqd2_gy, a.gtv_d98_eqd2_gy, a.gtv_d98_limit_eqd2_gy) == (75.0, 95.0, 90.0)
    assert [(o, a.oar_eqd2_gy(o), a.oar_eqd2_gy(o, "limit")) for o in ("Bladder", "Rectum", "Colon_Sigmoid",
                                                                            "Bowel_Small")] == \
        [("Bladder", 80, 90), ("Rectum", 65, 75), ("Colon_Sigmoid", 70, 75), ("Bowel_Small", 70, 75)]
    rv = next(p for p in a.points if p.name == "ICRU recto-vaginal")
    assert (rv.aim_max_eqd2_gy, rv.limit_max_eqd2_gy) == (65.0, 75.0) and rv.matches("ICRU rectum")
    point_a = next(p for p in a.points if p.name == "Point A")
    assert point_a.aim_max_eqd2_gy is None and all(point_a.matches(n) for n in ("Point A left", "PtA_right",
                                                                                   "PT A LEFT"))
    assert (a.fractionation.n_fractions, a.fractionation.ebrt_dose_gy, a.fractionation.ebrt_fractions) == (4, 45, 25)
    assert "10.1016/j.ctro.2018.01.001" in a.source and a.origin == "built-in protocol embrace_ii"


def test_a_user_file_of_another_site_changes_the_plans_aims(tmp_path: Path, case: SimpleNamespace) -> None:
    path = tmp_path / "prostate.toml"
    path.write_text(PROSTATE, encoding="utf-8")
    aims = load_protocol(str(path))
    assert aims.name == "Prostate HDR boost (test)" and aims.origin == str(path) and aims != Aims()
    # the prescription follows the file: one fraction after 46 Gy / 23 fx, α/β 1.5, to D90 100 Gy EQD2
    ebrt = 46.0 * (2.0 + 1.5) / (2.0 + 1.5)
    d = aims.prescription_gy
    assert math.isclose(d * (d + 1.5) / 3.5 + ebrt, 100.0, rel_tol=1e-9)
    assert aims.oar_eqd2_gy("Rectum") == 75.0 and aims.oar_eqd2_gy("Bladder") is None
    # the dwell optimiser plans to it: another prescription, another plan
    ours = optimise_dwell_times([np.array([[0.0, 0.0, -20.0], [0.0, 0.0, 30.0]])], case.planning, case.kernel, SK,
                                aims)
    embrace = optimise_dwell_times([np.array([[0.0, 0.0, -20.0], [0.0, 0.0, 30.0]])], case.planning, case.kernel,
                                   SK, Aims())
    assert ours.dwells.times_s.sum() > 1.5 * embrace.dwells.times_s.sum()  # 1 fraction of ~10 Gy, not 4 of ~7
    table = _table(case, aims)
    assert table.protocol == aims.name and [r.label for r in table.results][:2] == ["HR-CTV D90", "HR-CTV D98"]
    assert "Bladder D2cm³" in [r.label for r in table.results]  # reported, with no aim of this protocol
    assert next(r for r in table.results if r.label == "Bladder D2cm³").aim_met is None
    # the HR-CTV is not a prostate target: the warning says which protocol's aims were used
    text = site_warning(aims, "HR-CTV")
    assert text.startswith("ProtocolSiteWarning:") and "Prostate HDR boost (test) (prostate) aims were used" in text
    assert site_warning(Aims(), "CTV_HR") == "" and site_warning(aims, "prostate") == ""
    with pytest.warns(ProtocolSiteWarning, match="aims were used"):
        emit([text, text])
    assert protocol_json(aims)["origin"] == str(path)


@pytest.mark.parametrize(("edit", "key", "words"), [
    (lambda t: t.replace("limit_min = 85.0", "limit_min = 92.0"), "target.d90.limit_min", "above the planning aim"),
    (lambda t: t.replace("rectum = { aim_max = 65.0, limit_max = 75.0 }",
                         "rectum = { aim_max = 65.0, limit_max = 60.0 }"), "organs.rectum.limit_max", "below"),
    (lambda t: t.replace("bladder = { aim_max = 80.0", "bladder = { aim_max = -80.0"), "organs.bladder.aim_max",
     "> 0"),
    (lambda t: t.replace('name = "EMBRACE II"\n', ""), "name", "missing"),
    (lambda t: t.replace("ebrt_fractions = 25", ""), "fractionation.ebrt_fractions", "missing"),
    (lambda t: t.replace("aim_max = 65.0\nlimit_max", "aim_maxx = 65.0\nlimit_max"),
     'points."ICRU recto-vaginal".aim_maxx', "unknown key"),
    (lambda t: t.replace("target = 10.0", 'target = "ten"'), "alpha_beta_gy.target", "finite number"),
    (lambda t: t + "\n[[[", "", "not valid TOML"),
])
def test_a_bad_file_is_a_typed_error_naming_the_file_and_the_key(tmp_path: Path, edit, key: str,
                                                                  words: str) -> None:
    path = tmp_path / "bad.toml"
    path.write_text(edit(BUILTIN), encoding="utf-8")
    with pytest.raises(ProtocolError) as err:
        load_protocol(path)
    message = str(err.value)
    assert str(path) in message and key in message and words in message
    assert isinstance(err.value, ReachplanError) and err.value.exit_code == 2


def test_an_unknown_name_or_missing_file_is_a_typed_error_before_any_work(tmp_path: Path,
                                                                         capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(ProtocolError, match=r"no protocol named 'embrace_iii'.*embrace_ii"):
        load_protocol("embrace_iii")
    with pytest.raises(ProtocolError, match=r"nope\.toml does not exist"):
        load_protocol(str(tmp_path / "nope.toml"))
    # on the command line: exit 2, one line, before the output folder is made or a case written
    out = tmp_path / "out"
    assert main(["demo", "--out", str(out), "--protocol", "embrace_iii", "--quiet"]) == 2
    assert "no protocol named 'embrace_iii'" in capsys.readouterr().err and not out.exists()
    args = build_parser().parse_args(["plan", "--rtstruct", "rs.dcm", "--targets", "T", "--out", str(out),
                                      "--protocol", "EMBRACE II"])
    check_plan_arguments(args, [])
    assert args.aims == Aims()


def test_an_organ_of_1_cm3_gets_the_warning_and_its_d2cc_is_not_applicable(case: SimpleNamespace) -> None:
    rectum = next(o for o in case.planning.oars if o.name == "Rectum")
    volume = float(rectum.mask.sum()) * case.vox
    assert 0.6 < volume < 1.4  # the 1 cm³ drawn (π 4² × 20 mm), as rasterised
    aims = Aims()
    table = _table(case, aims, points=(("ICRU rectum", 2.0), ("Point A left", 7.0)))
    d2cc = next(r for r in table.results if r.label == "Rectum D2cm³")
    assert d2cc.value_eqd2_gy is None and d2cc.aim_met is None and d2cc.limit_met is None
    assert "not applicable" in d2cc.note
    small = next(r for r in table.results if r.label == f"Rectum {SMALL_ORGAN_METRIC}")
    # independent D0.1cm³: the dose of the k-th hottest voxel, k = ceil(0.1 cm³ / voxel)
    doses = np.sort(case.dose[rectum.mask])[::-1]
    d01 = doses[math.ceil(0.1 / case.vox - 1e-9) - 1]
    assert small.value_eqd2_gy == pytest.approx(aims.fractionation.total_eqd2(d01, 3.0), rel=1e-9)
    assert small.aim_met is None  # no protocol aim for D0.1cm³: reported only
    assert len(table.warnings) == 1 and table.warnings[0].startswith("SmallOrganWarning: organ Rectum is ")
    assert f"{volume:.2f} cm³" in table.warnings[0]
    with pytest.warns(SmallOrganWarning, match="Rectum"):
        emit(table.warnings)
    # the bladder (2 cm³ and more) keeps its D2cm³, checked against a sort of its voxel doses
    bladder = next(o for o in case.planning.oars if o.name == "Bladder")
    bd = np.sort(case.dose[bladder.mask])[::-1]
    expected = aims.fractionation.total_eqd2(bd[math.ceil(2.0 / case.vox - 1e-9) - 1], 3.0)
    b = next(r for r in table.results if r.label == "Bladder D2cm³")
    assert b.value_eqd2_gy == pytest.approx(expected, rel=1e-9)
    assert b.headroom_eqd2_gy == pytest.approx(80.0 - expected) and b.aim_met == (80.0 - expected >= 1.0)
    # JSON: n/a is null, never a number; verdicts per aim
    doc = json.loads(json.dumps(table.to_json()))
    rec = next(a for a in doc["aims"] if a["aim"] == "Rectum D2cm³")
    assert rec["value_eqd2_gy"] is None and rec["planning_aim_met"] is None and rec["headroom_eqd2_gy"] is None
    # the implant part of plan.json loses the number too
    implant = SimpleNamespace(to_json=lambda: {"steered": {"oar_d2cc_eqd2_gy": {"Rectum": 50.0, "Bladder": 70.0},
                                                            "aims_met": True}, "straight": {}})
    delivery = Delivery(None, None, None, None, (), implant=implant,  # type: ignore[arg-type]
                        aims_tables={"steered": table})
    arm = delivery.implant_json()["steered"]  # type: ignore[index]
    assert arm["oar_d2cc_eqd2_gy"] == {"Rectum": None, "Bladder": 70.0} and arm["aims_met"] is table.aims_met
    assert arm["selection_aims_met"] is True  # the selection's own verdict is kept beside it


def test_each_aim_carries_value_aim_limit_headroom_and_both_verdicts(case: SimpleNamespace) -> None:
    aims = Aims()
    table = _table(case, aims, points=(("ICRU rectum", 2.0), ("Point A left", 7.0)))
    d90 = table.results[0]
    v = d90.value_eqd2_gy
    assert d90.label == "HR-CTV D90" and v is not None
    assert d90.headroom_eqd2_gy == pytest.approx(min(v - 90.0, 95.0 - v))
    assert d90.aim_met == (90.0 <= v <= 95.0) and d90.limit_met == (v >= 85.0)
    rv = next(r for r in table.results if r.metric == "point" and "recto-vaginal" in r.label)
    expected = aims.fractionation.total_eqd2(2.0, 3.0)  # 4 × 2 Gy (α/β 3) + 45 Gy / 25 fx
    assert rv.value_eqd2_gy == pytest.approx(4 * 2.0 * 5.0 / 5.0 + 45.0 * (1.8 + 3.0) / 5.0) == expected
    assert rv.headroom_eqd2_gy == pytest.approx(65.0 - expected) and rv.required_headroom_eqd2_gy == 1.0
    assert table.aims_met == all(r.aim_met for r in table.results if r.aim_met is not None)
    doc = table.to_json()
    for rec in doc["aims"]:  # type: ignore[union-attr]
        assert {"value_eqd2_gy", "planning_aim", "hard_limit", "headroom_eqd2_gy", "planning_aim_met",
                "hard_limit_met"} <= set(rec)
    # the terminal (and report) table: one row per aim with aim, limit and a value (headroom) cell
    rows = aims_rows({"delivered": table})
    assert rows[0][:3] == ("aim (Gy EQD2)", "planning aim", "hard limit")
    row = next(r for r in rows if r[0] == "HR-CTV D90")
    assert row[1:3] == ("> 90, < 95", "> 85") and row[3].startswith(f"{v:.1f} ({d90.headroom_eqd2_gy:+.1f}) ")
    assert next(r for r in rows if r[0] == "Rectum D2cm³")[3] == "n/a"
    assert next(r for r in rows if r[0] == "ICRU bladder")[3] == "not placed"
    assert rows[-2][0] == "every planning aim met" and rows[-1][0] == "every hard limit kept"
    assert "HR-CTV D90" in format_rows(rows)


def test_dose_reports_a_genuine_plan_against_the_protocol(reference_file, tmp_path: Path,  # type: ignore[no-untyped-def]
                                                          capsys: pytest.CaptureFixture[str]) -> None:
    """The Eclipse HDR example (one fraction, Point A 6.0 Gy): its HRCTV and Point A against EMBRACE II."""
    rp, rs = reference_file("tps_examples/hdr/RP.HDR.dcm"), reference_file("tps_examples/hdr/RS.HDR.dcm")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DicomQuirkWarning)  # the example's placeholder UID, read anyway
        assert main(["dose", "--plan", str(rp), "--structures", str(rs), "--protocol", "embrace_ii", "--json",
                     "--out", str(tmp_path / "rd.dcm")]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["protocol"]["name"] == "EMBRACE II" and "dvh_method" in doc["protocol"]
    rows = {a["aim"]: a for a in doc["aims"]["aims"]}
    assert {"HRCTV D90", "HRCTV D98"} <= set(rows)  # Eclipse's "HRCTV" is the site's target
    fr = Aims().fractionation
    for point in doc["points"]:  # Point A: the TPS's own dose (one fraction), in EQD2 with 4 such fractions
        rec = rows[f"Point A ({point['name']})"]
        assert rec["value_eqd2_gy"] == pytest.approx(fr.total_eqd2(point["tps_gy"], 10.0), rel=1e-3)
        assert rec["planning_aim_met"] is None and rec["hard_limit"] == "-"
    assert rows["ICRU recto-vaginal"]["value_eqd2_gy"] is None  # the plan has no such point: not placed
    assert not any(w.startswith("ProtocolSiteWarning") for w in doc["warnings"])


def test_a_dose_target_of_another_site_says_which_aims_were_used() -> None:
    """The chain (run_case) on the clinical case's contours, the dose planned on the uterus with a user protocol."""
    import dataclasses

    from reachplan.imaging.clinical import clinical_case, structure_set
    from reachplan.planner.case.config import PlanConfig
    from reachplan.planner.report.terminal import format_summary
    from reachplan.planner.run.case import CaseConfig, CaseInput, run_case
    from reachplan.planner.steering.candidates import Target

    clinical = clinical_case(0)
    spec = dataclasses.replace(clinical.spec, z_range_mm=(-20.0, 140.0))
    rois = ("Bladder", "Rectum", "Tandem", "Obturator", "Uterus")
    aims = dataclasses.replace(Aims(), name="Test protocol", headroom_eqd2_gy=0.5)
    config = CaseConfig(plan=PlanConfig(designs=(), refine_top=0, robust_top=0), target_names=(),
                        target_points=(Target("corpus_L", dict(clinical.targets)["corpus_L"]),),
                        implant=False, target_roi="Uterus", aims=aims)
    with pytest.warns(ProtocolSiteWarning, match="'Uterus' is not a cervix target of Test protocol"):
        case = run_case(CaseInput(structure_set(spec, rois), None, (), "seed 0"), config)
    assert case.delivery is not None and case.delivery.aims is aims
    doc = case.to_json()
    assert doc["protocol"]["name"] == "Test protocol" and doc["protocol"]["headroom_eqd2_gy"] == 0.5
    assert any(w.startswith("ProtocolSiteWarning") and "Test protocol (cervix) aims were used" in w
               for w in doc["warnings"])
    table = doc["delivery"]["aims"]
    assert table["protocol"] == "Test protocol" and table["aims"][0]["aim"] == "Uterus D90"
    assert doc["delivery"]["optimisation"]["aim_met"] is table["aims_met"]
    text = format_summary(case.result, delivery=case.delivery)
    assert "dose aims: Test protocol (cervix;" in text and "warning: ProtocolSiteWarning" in text
    assert re.search(r"^Uterus D90\s+> 90, < 95\s+> 85\s+\d+\.\d \([+-]\d+\.\d\) (yes|NO)/(yes|NO)$", text, re.M)
