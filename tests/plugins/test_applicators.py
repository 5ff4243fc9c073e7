"""Applicators as a type: recognition by whole ROI names, hand assignment, channel geometry against closed forms,
channels from a brachy RT Plan, a stand-in kind that is one file plus its registration, and the errors."""

from __future__ import annotations

import textwrap
import tomllib
import warnings
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from importlib.metadata import EntryPoint, entry_points
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest

from reachplan.imaging.names import rename
from reachplan.imaging.types import Contour, Roi, StructureSet
from reachplan.plugins import registry
from reachplan.plugins.applicators import (
    BUILTIN_KINDS,
    Applicator,
    applicators_from_rtplan,
    applicators_from_structures,
    check_applicator_kind,
    kind_of_name,
    name_table,
)
from reachplan.plugins.errors import ApplicatorError

REPO = Path(__file__).resolve().parents[2]


def tube_roi(number: int, name: str, base: np.ndarray, tip: np.ndarray, radius_mm: float = 3.0,
             stations: int = 21, per_ring: int = 24) -> Roi:
    """A straight tube from ``base`` to ``tip``: closed circles perpendicular to its axis at even stations."""
    u = (tip - base) / np.linalg.norm(tip - base)
    e1 = np.cross(u, [1.0, 0.0, 0.0] if abs(u[0]) < 0.9 else [0.0, 1.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(u, e1)
    t = np.linspace(0.0, 2 * np.pi, per_ring, endpoint=False)
    ring = radius_mm * (np.outer(np.cos(t), e1) + np.outer(np.sin(t), e2))
    return Roi(number, name, tuple(Contour(c + ring) for c in np.linspace(base, tip, stations)))


def circle_roi(number: int, name: str) -> Roi:
    return tube_roi(number, name, np.array([0.0, 0.0, -30.0]), np.array([0.0, 0.0, 60.0]), 15.0)


def test_whole_tg263_style_names_and_synonyms_are_recognised() -> None:
    names = {"Applicator_Tandem": "tandem", "tandem": "tandem", "IU Tube": "tandem", "LT OVOID": "ovoid",
             "right ovoid": "ovoid", "Ovoid_L": "ovoid", "Ring": "ring", "Vaginal_Cylinder": "cylinder",
             "Cylinder": "cylinder", "Obturator": "obturator", "vaginal-obturator": "obturator",
             # not applicators: organs, needle channels of a plan, a name that only contains a kind's name
             "Bladder": None, "Uterus": None, "Applicator1": None, "Tandem_PRV": None, "Ovoid_Boost": None}
    table = name_table(BUILTIN_KINDS)
    assert {n: kind_of_name(n, BUILTIN_KINDS, table) for n in names} == names
    rois = tuple(circle_roi(i, n) for i, n in enumerate(names, start=1))
    found = applicators_from_structures(StructureSet(rois, "1.2.3"), BUILTIN_KINDS)
    assert [(a.name, a.kind) for a in found] == [(n, k) for n, k in names.items() if k is not None]
    assert [a.roi_number for a in found] == [i for i, k in enumerate(names.values(), start=1) if k is not None]


def test_a_standard_name_given_by_hand_is_recognised_and_assign_overrides() -> None:
    rois = (circle_roi(1, "VC_30mm"), tube_roi(2, "IU_1", np.zeros(3), np.array([0.0, -20.0, 80.0])),
            tube_roi(3, "Tandem", np.zeros(3), np.array([0.0, 0.0, 50.0])), circle_roi(4, "Bladder"))
    ss = rename(StructureSet(rois, "1.2.3"), {"VC_30mm": "Obturator"})  # --oar Obturator=VC_30mm
    assert [(a.name, a.kind) for a in applicators_from_structures(ss, BUILTIN_KINDS)] == \
        [("VC_30mm", "obturator"), ("Tandem", "tandem")]
    # --applicator tandem=IU_1 --applicator ring=Tandem (case of the ROI name ignored)
    found = applicators_from_structures(ss, BUILTIN_KINDS, {"iu_1": "tandem", "Tandem": "ring"})
    assert [(a.name, a.kind) for a in found] == [("VC_30mm", "obturator"), ("IU_1", "tandem"), ("Tandem", "ring")]
    ring = found[2]
    assert ring.channels == () and not ring.loadable and ring.obstacle and "skeleton" in ring.notes[0]
    with pytest.raises(ApplicatorError, match="unknown applicator kind 'tandom'"):
        applicators_from_structures(ss, BUILTIN_KINDS, {"IU_1": "tandom"})
    with pytest.raises(ApplicatorError, match="no ROI named 'IU_2'"):
        applicators_from_structures(ss, BUILTIN_KINDS, {"IU_2": "tandem"})


@pytest.mark.parametrize("axis", [None, np.array([0.0, 0.0, 1.0]), np.array([0.0, 0.3, -1.0])])
def test_tandem_channel_is_the_axis_of_a_straight_tube(axis: np.ndarray | None) -> None:
    base, tip = np.array([2.0, 5.0, -10.0]), np.array([-4.0, -30.0, 95.0])  # tilted 18 degrees anteriorly
    roi = tube_roi(7, "Tandem", base, tip, radius_mm=3.0)
    (tandem,) = applicators_from_structures(StructureSet((roi,), "1.2.3"), BUILTIN_KINDS, axis=axis)
    assert tandem.kind == "tandem" and tandem.loadable and tandem.obstacle and tandem.roi_number == 7
    assert tandem.notes == ()
    (line,) = tandem.channels
    want = np.array([base, tip]) if axis is None or axis[2] > 0 else np.array([tip, base])
    assert np.allclose(line[[0, -1]], want, atol=1e-6)  # from the end nearer the template, along the axis
    u = (tip - base) / np.linalg.norm(tip - base)
    rel = line - base
    assert np.max(np.linalg.norm(rel - np.outer(rel @ u, u), axis=1)) < 0.02  # every point on the axis
    assert not line.flags.writeable


def test_obturator_channel_uses_its_closed_contours_and_ring_and_ovoid_say_why_none() -> None:
    obturator = circle_roi(1, "Obturator")
    stray = Contour(np.array([[50.0, 0.0, 0.0], [60.0, 0.0, 200.0]]), "OPEN_NONPLANAR")  # ignored: not the wall
    obturator = Roi(1, "Obturator", (*obturator.contours, stray))
    ovoid = tube_roi(2, "Ovoid_R", np.array([-20.0, 0.0, 50.0]), np.array([-20.0, 0.0, 70.0]), 8.0)
    ob, ov = applicators_from_structures(StructureSet((obturator, ovoid), "1.2.3"), BUILTIN_KINDS)
    assert np.allclose(ob.channels[0], [[0.0, 0.0, -30.0], [0.0, 0.0, 60.0]], atol=1e-9)
    assert not ob.obstacle and not ob.loadable  # the template's needles run through the obturator
    assert ov.channels == () and ov.obstacle and not ov.loadable and "handle" in ov.notes[0]


def test_channels_from_an_eclipse_plan(reference_file: Callable[[str], Path]) -> None:
    from reachplan.imaging.rtplan import channel_paths, read_rtplan
    from reachplan.imaging.rtstruct import read_rtstruct

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        plan = read_rtplan(reference_file("tps_examples/hdr/RP.HDR.dcm"))
    rs = read_rtstruct(reference_file("tps_examples/hdr/RS.HDR.dcm"))
    found = applicators_from_rtplan(plan, BUILTIN_KINDS, rs)
    assert [(a.kind, a.name, a.roi_name, a.plan_channels) for a in found] == [
        ("tandem", "tandem", "tandem", (1,)), ("ovoid", "right ovoid", "right ovoid", (2,)),
        ("ovoid", "left ovoid", "left ovoid", (3,))]
    paths = channel_paths(plan, rs)
    for a in found:  # the channel ROI's line, written tip first, read base to tip
        assert np.array_equal(a.channels[0], paths[a.plan_channels[0]][::-1])
        assert a.how == "its channel contour"
    assert [a.loadable for a in found] == [True, True, True]  # a plan's ring and ovoid channels are loaded too
    # the structure set alone: its channel ROIs (open lines) are the same channels, curved as drawn
    from_rs = {a.name: a for a in applicators_from_structures(rs, BUILTIN_KINDS)}
    for a in found:
        assert np.allclose(from_rs[a.name].channels[0], a.channels[0], atol=1e-9) and from_rs[a.name].loadable
    # without the structure set: the dwell positions, base (largest distance from the tip) first
    tandem = applicators_from_rtplan(plan, BUILTIN_KINDS)[0]
    ch = plan.channels[0]
    assert tandem.how == "its dwell positions" and len(tandem.channels[0]) == ch.n_dwells
    assert np.array_equal(tandem.channels[0][0], ch.dwell_positions_mm[np.argmax(ch.dwell_relative_mm)])
    # a kind given by hand: the right ovoid seats the template as an obturator would
    from reachplan.planner.errors import PlanInputError
    from reachplan.planner.geometry.template import pose_from_rtplan

    only = {"obturator": BUILTIN_KINDS["obturator"]}
    with pytest.raises(PlanInputError, match="no channel is named as a tandem, obturator or cylinder"):
        pose_from_rtplan(plan, rs, 60.0, only)
    pose = pose_from_rtplan(plan, rs, 60.0, only, {"right ovoid": "obturator"})
    assert "channel 2 'right ovoid' (its channel contour; template 60 mm behind its tip)" in pose.method
    tip = paths[2][0]
    m = pose.patient_from_template
    assert np.allclose(m[:3, 3] + 60.0 * m[:3, 2], tip, atol=1e-9)


def test_applicator_and_kind_checks() -> None:
    line = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 10.0]])
    with pytest.raises(ValueError, match="loadable without a channel"):
        Applicator("tandem", "T", None, None, (), True, True)
    with pytest.raises(ValueError, match="at least two points"):
        Applicator("tandem", "T", None, None, (line[:1],), True, False)
    with pytest.raises(ValueError, match="shape"):
        Applicator("tandem", "T", None, None, (line[:, :2],), True, False)
    with pytest.raises(ValueError, match="one RT Plan channel number per channel"):
        Applicator("tandem", "T", None, None, (line,), True, False, plan_channels=(1, 2))
    with pytest.raises(ValueError, match="kind and a name"):
        Applicator("", "T", None, None, (line,), True, False)
    for k in BUILTIN_KINDS.values():
        check_applicator_kind(k)
    with pytest.raises(TypeError, match="does not implement"):
        check_applicator_kind(SimpleNamespace(name="x", description="", roi_names=("X",)))
    with pytest.raises(ApplicatorError, match="claim the same ROI name"):
        name_table({**BUILTIN_KINDS, "other": _Stand("other", roi_names=("Tandem",))})


def test_builtin_kinds_are_declared_in_pyproject() -> None:
    project = tomllib.loads((REPO / "pyproject.toml").read_text(encoding="utf-8"))["project"]
    declared = project["entry-points"]["reachplan.applicators"]
    assert set(declared) == set(BUILTIN_KINDS)
    for name, target in declared.items():
        assert EntryPoint(name, target, "reachplan.applicators").load() is BUILTIN_KINDS[name]


# --- a new kind: one file plus its registration ------------------------------------------------------------


@dataclass(frozen=True)
class _Stand:
    name: str
    description: str = "stand-in"
    roi_names: tuple[str, ...] = ("Stand_In",)
    obstacle: bool = True
    loadable: bool = False

    def channels_from_roi(self, roi: Roi, axis: np.ndarray | None) -> tuple[tuple[np.ndarray, ...], tuple[str, ...]]:
        return (), ()

    def channels_from_plan(self, channel: Any, path_mm: np.ndarray | None) -> tuple[np.ndarray, ...]:
        return ()


STAND_IN = '''\
"""An interstitial ring (a stand-in third-party kind): its channel is the closed loop through its contours' centres."""
from dataclasses import dataclass

import numpy as np

from reachplan.plugins.applicators import KindSpec, roi_points


@dataclass(frozen=True)
class InterstitialRing(KindSpec):
    def channels_from_roi(self, roi, axis):
        centres = np.array([c.points_mm.mean(axis=0) for c in roi.contours])
        return ((centres,) if len(centres) >= 2 else ()), ("stand-in: contour centres in order",)


INTERSTITIAL_RING = InterstitialRing("interstitial_ring", "a stand-in kind", ("Interstitial_Ring", "Ring_IS"),
                                     obstacle=True, loadable=True)
BROKEN = object()
'''


@pytest.fixture
def stand_in_registered(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Iterator[None]:
    """Write the stand-in kind's one file and register it (and a broken one) beside the installed kinds."""
    (tmp_path / "standin_ring.py").write_text(textwrap.dedent(STAND_IN), encoding="utf-8")
    monkeypatch.syspath_prepend(str(tmp_path))
    extra = [EntryPoint("interstitial_ring", "standin_ring:INTERSTITIAL_RING", "reachplan.applicators"),
             EntryPoint("broken", "standin_ring:BROKEN", "reachplan.applicators")]
    monkeypatch.setattr(registry, "entry_points",
                        lambda group: [*entry_points(group=group), *(e for e in extra if e.group == group)])
    registry.refresh()
    yield
    monkeypatch.undo()
    registry.refresh()


@pytest.mark.usefixtures("stand_in_registered")
def test_a_stand_in_kind_is_one_file_and_its_registration() -> None:
    from reachplan.planner.lookup import applicator_kinds

    kinds = applicator_kinds()
    assert set(kinds) == {*BUILTIN_KINDS, "interstitial_ring"}
    broken = next(i for i in registry.info("applicators") if i.name == "broken")
    assert not broken.available and "does not implement" in broken.reason
    # recognised from a structure set by its own names, built with its own channel rule
    rois = (circle_roi(1, "Ring IS"), circle_roi(2, "Tandem"), circle_roi(3, "Bladder"))
    found = applicators_from_structures(StructureSet(rois, "1.2.3"), kinds)
    assert [(a.name, a.kind) for a in found] == [("Ring IS", "interstitial_ring"), ("Tandem", "tandem")]
    assert found[0].loadable and found[0].channels[0].shape == (21, 3)
    assert kind_of_name("interstitial-ring", kinds) == "interstitial_ring"
    assert kind_of_name("Interstitial_Ring", BUILTIN_KINDS) is None
    # and carried through to the planner: no organ at risk for dose, a loadable channel of the implant
    from reachplan.planner.dose.structures import planning_structures
    from reachplan.planner.implant.candidates import applicator_channels
    from reachplan.planner.implant.settings import ImplantSettings

    hrctv = tube_roi(4, "HR-CTV", np.array([0.0, 0.0, -30.0]), np.array([0.0, 0.0, 60.0]), 25.0)
    ss = StructureSet((*rois, hrctv), "1.2.3")
    planning = planning_structures(ss, None, "HR-CTV", ["Bladder", "Ring IS"])
    assert [o.name for o in planning.oars] == ["Bladder"]
    channels = applicator_channels(found, planning, ImplantSettings())
    assert [c.name for c in channels] == ["Ring IS", "Tandem"]
    assert all(c.kind == "intracavitary" and len(c.dwell_positions_mm) >= 2 for c in channels)


def test_applicator_option_parsing() -> None:
    from reachplan.planner.cli.edges import ArgumentError, applicator_assignments

    rois = ["Tandem", "IU_1", "A=B"]
    assert applicator_assignments(["tandem=iu_1", " ring = A=B "], BUILTIN_KINDS, rois) == \
        {"IU_1": "tandem", "A=B": "ring"}
    for spec, msg in (("tandem", "write KIND=ROI_NAME"), ("=IU_1", "write KIND=ROI_NAME"),
                      ("tandom=IU_1", "unknown applicator kind 'tandom'"), ("tandem=IU_2", "no ROI named 'IU_2'")):
        with pytest.raises(ArgumentError, match=msg):
            applicator_assignments([spec], BUILTIN_KINDS, rois)
    with pytest.raises(ArgumentError, match="twice"):
        applicator_assignments(["tandem=IU_1", "ring=iu_1"], BUILTIN_KINDS, rois)
