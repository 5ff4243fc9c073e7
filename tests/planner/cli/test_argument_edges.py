"""Arguments checked before any work (issue 28): empty list items, negative coordinates, targets outside the patient,
and the series chosen with ``plan --series-uid``.
"""

from __future__ import annotations

import argparse
import functools
import time
from pathlib import Path

import numpy as np
import pydicom
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from reachplan.imaging.meshing import roi_contains
from reachplan.imaging.phantom import PhantomFiles, write_phantom
from reachplan.imaging.rtstruct import read_rtstruct
from reachplan.imaging.types import Roi
from reachplan.planner.cli import build_parser, main
from reachplan.planner.cli.points import NEGATIVE_VALUE, TargetOutsideError, check_targets_inside, comma_items
from reachplan.planner.errors import PlanInputError
from reachplan.planner.steering.candidates import Target


@pytest.fixture(scope="module")
def phantom(tmp_path_factory: pytest.TempPathFactory) -> PhantomFiles:
    return write_phantom(tmp_path_factory.mktemp("phantom"))


@functools.lru_cache(maxsize=1)
def _parser() -> argparse.ArgumentParser:
    return build_parser()


def _run(args: list[str], capsys: pytest.CaptureFixture[str]) -> tuple[int, str]:
    code = main(args)
    return code, capsys.readouterr().err


# --- lists --------------------------------------------------------------------------------------------------------


@pytest.mark.parametrize(("tensions", "item"), [("1,,2", "item 2 of 3"), (",1", "item 1 of 2"), ("1,", "item 2 of 2"),
                                                (" ", "item 1 of 1")])
def test_rod_tensions_with_an_empty_item_are_an_error_not_dropped(tensions: str, item: str,
                                                                   capsys: pytest.CaptureFixture[str]) -> None:
    code, err = _run(["rod", "--preset", "15ga-30j-tip", f"--tensions={tensions}", "--json"], capsys)
    assert code == 2 and f"{item} is empty" in err and "\n" not in err.strip()


@settings(max_examples=100, deadline=None)
@given(st.lists(st.sampled_from(["1", "2.5", " 3 ", "", " "]), min_size=1, max_size=6))
def test_comma_items_refuses_exactly_the_lists_with_an_empty_item(items: list[str]) -> None:
    text = ",".join(items)
    try:
        got = comma_items(text, "--x")
    except PlanInputError as exc:
        assert any(not t.strip() for t in items) and "--x" in str(exc)
        return
    assert got == [t.strip() for t in items] and all(got)


@pytest.mark.parametrize("target", ["1,,2", "1,2,", ""])
def test_plan_targets_with_an_empty_item_are_an_error(phantom: PhantomFiles, tmp_path: Path, target: str,
                                                      capsys: pytest.CaptureFixture[str]) -> None:
    code, err = _run(["plan", "--rtstruct", str(phantom.rtstruct_path), "--targets", target, "--out",
                      str(tmp_path / "out"), "--quiet"], capsys)
    assert code == 2 and "error" in err and not (tmp_path / "out").exists()


# --- negative coordinates -----------------------------------------------------------------------------------------


@pytest.mark.parametrize("option", ["--targets", "--template-origin", "--template-axis"])
def test_a_point_starting_with_a_minus_sign_is_a_value_with_or_without_equals(option: str) -> None:
    parser = build_parser()
    base = ["plan", "--rtstruct", "RS.dcm", "--out", "o"] + ([] if option == "--targets" else ["--targets", "X"])
    spaced = parser.parse_args([*base, option, "-20,0,90"])
    joined = parser.parse_args([*base, f"{option}=-20,0,90"])
    dest = option.lstrip("-").replace("-", "_")
    value = getattr(spaced, dest)
    assert value == getattr(joined, dest) and value in ("-20,0,90", ["-20,0,90"])


@pytest.mark.parametrize("spelling", [["--target", "-20,0,90"], ["--target=-20,0,90"], ["--targets", "-20,0,90"]])
def test_target_and_targets_both_take_a_negative_point(spelling: list[str]) -> None:
    args = _parser().parse_args(["plan", "--rtstruct", "RS.dcm", *spelling, "--out", "o"])
    assert args.targets == ["-20,0,90"]


def test_several_negative_points_after_targets() -> None:
    args = build_parser().parse_args(["plan", "--rtstruct", "RS.dcm", "--targets", "-20,0,90", "-1.5e1,-3,80",
                                      "HR-CTV", "--out", "o"])
    assert args.targets == ["-20,0,90", "-1.5e1,-3,80", "HR-CTV"]


@settings(max_examples=100, deadline=None)
@given(st.tuples(st.floats(-500, -1e-3), st.floats(-500, 500), st.floats(-500, 500)))
def test_any_negative_first_coordinate_parses(point: tuple[float, float, float]) -> None:
    spec = ",".join(repr(v) for v in point)
    assert NEGATIVE_VALUE.match(spec)
    args = _parser().parse_args(["plan", "--rtstruct", "RS.dcm", "--targets", spec, "--out", "o"])
    assert args.targets == [spec]


def test_an_unknown_option_is_still_an_option() -> None:
    with pytest.raises(SystemExit) as exc:
        build_parser().parse_args(["plan", "--rtstruct", "RS.dcm", "--targets", "X", "--out", "o", "-z"])
    assert exc.value.code == 2


# --- targets outside the patient ----------------------------------------------------------------------------------


@pytest.mark.parametrize(("point", "where", "images"), [("-2000,0,90", "outside the image volume", True),
                                                        ("0,0,1790", "outside the body contour", False),
                                                        ("-110,0,90", "outside the body contour", False)])
def test_a_target_outside_the_images_or_body_stops_plan_before_any_work(
    phantom: PhantomFiles, tmp_path: Path, point: str, where: str, images: bool, capsys: pytest.CaptureFixture[str]
) -> None:
    start = time.perf_counter()
    ct = ["--ct", str(phantom.ct_dir)] if images else []
    code, err = _run(["plan", *ct, "--rtstruct", str(phantom.rtstruct_path), "--targets", point,
                      "--out", str(tmp_path / "out"), "--quiet"], capsys)
    assert code == 2 and where in err and "--allow-outside-body" in err and "point_1" in err
    assert not (tmp_path / "out").exists() and [p.name for p in tmp_path.iterdir()] == []
    assert time.perf_counter() - start < 60  # reading the series only: no planning


def test_target_points_are_checked_against_the_body_without_images(phantom: PhantomFiles) -> None:
    structures = read_rtstruct(phantom.rtstruct_path)
    inside, outside = Target("point_1", (0.0, 0.0, 90.0)), Target("point_2", (0.0, 400.0, 90.0))
    check_targets_inside([inside], None, structures)
    with pytest.raises(TargetOutsideError, match=r"point_2 \(0,400,90 mm\) lies outside the body contour"):
        check_targets_inside([inside, outside], None, structures)
    check_targets_inside([outside], None, structures, allow_outside_body=True)


@pytest.fixture(scope="module")
def body(phantom: PhantomFiles) -> Roi:
    return read_rtstruct(phantom.rtstruct_path).get("Body")


@settings(max_examples=20, deadline=None)
@given(st.lists(st.tuples(st.floats(-130, 130), st.floats(-130, 130), st.floats(-25, 175)), min_size=1,
                max_size=40))
def test_inside_the_body_contour_agrees_with_the_phantoms_analytic_ellipse(
    body: Roi, points: list[tuple[float, float, float]]
) -> None:
    p = np.array(points)
    r = (p[:, 0] / 95.0) ** 2 + (p[:, 1] / 90.0) ** 2  # the pilot phantom's body: elliptic cylinder, z -30 to 180 mm
    clear = np.abs(r - 1.0) >= 0.03  # within about 1.5 mm of the outline a polygon of the ellipse may go either way
    assert np.array_equal(roi_contains(body, p)[clear], (r < 1.0)[clear])


def test_without_images_or_body_a_target_far_from_every_contour_is_refused(phantom: PhantomFiles) -> None:
    from dataclasses import replace

    structures = read_rtstruct(phantom.rtstruct_path)
    no_body = replace(structures, rois=tuple(r for r in structures.rois if r.normalized_name != "Body"))
    check_targets_inside([Target("point_1", (0.0, 0.0, 90.0))], None, no_body)
    with pytest.raises(TargetOutsideError, match="beyond every contour"):
        check_targets_inside([Target("point_1", (0.0, 0.0, 1700.0))], None, no_body)


# --- several series in one folder ---------------------------------------------------------------------------------


def test_plan_series_uid_chooses_among_several_series(phantom: PhantomFiles, tmp_path: Path,
                                                      capsys: pytest.CaptureFixture[str]) -> None:
    both = tmp_path / "images"
    for sub, uid in (("a", None), ("b", "1.2.826.0.1.3680043.10.1.2828")):
        (both / sub).mkdir(parents=True)
        for k, src in enumerate(sorted(phantom.ct_dir.iterdir())[::12]):  # 8 slices are enough to read
            ds = pydicom.dcmread(src)
            if uid is not None:
                ds.SeriesInstanceUID = uid
                ds.SOPInstanceUID = f"{uid}.{k + 1}"
            ds.save_as(both / sub / src.name)
    first = str(pydicom.dcmread(next((both / "a").iterdir())).SeriesInstanceUID)
    args = ["plan", "--ct", str(both), "--rtstruct", str(phantom.rtstruct_path), "--out", str(tmp_path / "out"),
            "--quiet", "--targets", "-2000,0,90"]
    code, err = _run(args, capsys)
    assert code == 2 and "holds 2 image series" in err and "--series-uid UID" in err
    code, err = _run([*args, "--series-uid", first], capsys)  # read; then the point is outside its volume
    assert code == 2 and "outside the image volume" in err
    code, err = _run([*args, "--series-uid", "1.2.3.4"], capsys)
    assert code == 2 and "no image series with SeriesInstanceUID 1.2.3.4" in err
    assert not (tmp_path / "out").exists()
