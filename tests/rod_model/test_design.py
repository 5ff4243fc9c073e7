"""Design objects, presets and their validation."""

from __future__ import annotations

from dataclasses import replace

import pytest

from reachplan.rod_model.design import PRESET_NAMES, Calibration, Loads, NeedleSpec, StyletDesign, preset
from reachplan.rod_model.errors import UnknownPresetError


@pytest.mark.parametrize("name", PRESET_NAMES)
def test_presets_build_and_have_one_joint_section(name: str) -> None:
    d = preset(name)
    kinds = [s.kind for s in d.sections()]
    assert kinds.count("joints") == 1
    assert d.sections()[0].start_m == 0.0
    assert d.sections()[-1].end_m == pytest.approx(d.length_mm * 1e-3)
    assert d.max_tension_n == (14.0 if d.stylet.gauge == 13 else 10.0)


def test_placement_and_joint_length() -> None:
    assert preset("15ga-20j-tip").stylet.joint_span_mm == pytest.approx((167.0, 200.0))
    assert preset("15ga-20j-base").stylet.joint_span_mm == pytest.approx((0.0, 33.0))
    assert preset("15ga-20j-mid").stylet.joint_span_mm == pytest.approx((83.5, 116.5))
    assert [s.kind for s in preset("15ga-20j-mid").sections()] == ["tube", "joints", "tube"]
    st = replace(preset("15ga-20j-tip").stylet, joint_start_mm=10.0)
    assert st.joint_span_mm == pytest.approx((10.0, 43.0))


def test_thirteen_gauge_is_stiffer_and_has_larger_arms() -> None:
    a, b = preset("15ga-20j-tip").sections()[0], preset("13ga-20j-tip").sections()[0]
    assert b.ei1 / a.ei1 == pytest.approx(4.47, rel=0.02)  # published ratio of second moments
    assert b.arm_m > a.arm_m
    assert preset("15ga-20j-asym").stylet.disk_arm_mm > preset("15ga-20j-tip").stylet.disk_arm_mm


@pytest.mark.parametrize("bad", ["16ga-20j-tip", "15ga-20j-side", "tip", "15ga-200j-tip"])
def test_unknown_presets_raise_a_typed_error(bad: str) -> None:
    with pytest.raises(UnknownPresetError):
        preset(bad)


def test_validation_messages() -> None:
    with pytest.raises(ValueError, match="gauge"):
        NeedleSpec.for_gauge(14)
    with pytest.raises(ValueError, match="inside the disk"):
        replace(preset("15ga-20j-tip").stylet, disk_arm_mm=0.8)
    with pytest.raises(ValueError, match="does not fit"):
        StyletDesign.for_gauge(15, 150)
    with pytest.raises(ValueError, match="asymmetric"):
        replace(preset("15ga-20j-asym").stylet, tendon_angles_deg=(0.0, 180.0))
    with pytest.raises(ValueError, match="tensions_n"):
        Loads((-1.0,))
    with pytest.raises(ValueError, match="tip_force_n"):
        Loads((1.0,), tip_force_n=(1.0, float("nan"), 0.0))
    with pytest.raises(ValueError, match="joint_stiffness_scale"):
        Calibration(0.0, 0.5)
    with pytest.raises(ValueError, match="does not match"):
        replace(preset("15ga-20j-tip"), needle=NeedleSpec.for_gauge(13))
