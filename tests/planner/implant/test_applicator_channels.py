"""Applicator channels follow the drawn applicator: on the built-in clinical case (the demo's) every tandem dwell lies
in the drawn tandem, checked against the case's own description of the tube (its analytic axis and solid, not the
contours the planner read); the first dwell lies the afterloader's tip offset back from the channel's end."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pytest

from reachplan._arrays import arc_length_mm
from reachplan.imaging.case_spec import PhantomStructure
from reachplan.imaging.clinical import clinical_case, structure_set
from reachplan.planner.dose.structures import PlanningStructures, planning_structures
from reachplan.planner.implant.candidates import applicator_channels, applicator_dwell_arclengths
from reachplan.planner.implant.settings import ImplantSettings
from reachplan.plugins.applicators import (
    BUILTIN_KINDS,
    Applicator,
    applicators_from_structures,
    principal_chord,
    roi_points,
)


@dataclass(frozen=True, eq=False)
class Demo:
    tandem: PhantomStructure  # the case's own description: a swept tube (axis samples, radius 3 mm)
    applicators: tuple[Applicator, ...]
    planning: PlanningStructures
    contour_points: np.ndarray  # (n, 3) every point of the Tandem ROI the planner read


@pytest.fixture(scope="module")
def demo() -> Demo:
    case = clinical_case(0)  # the demo's case
    ss = structure_set(case.spec, ("Tandem", "CTV_HR"))  # the contours the demo writes to its RT Structure Set
    applicators = applicators_from_structures(ss, BUILTIN_KINDS)
    tandem = next(s for s in case.spec.structures if s.name == "Tandem")
    return Demo(tandem, applicators, planning_structures(ss, None, "HR-CTV", [], applicators),
                roi_points(ss.get("Tandem")))


def along(path: np.ndarray, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Arc length (mm) of each point's foot on the polyline ``path``, and its distance (mm) to it."""
    a, ab = path[:-1], np.diff(path, axis=0)
    t = np.clip(np.einsum("psk,sk->ps", points[:, None] - a[None], ab) / np.einsum("sk,sk->s", ab, ab), 0.0, 1.0)
    d = np.linalg.norm(points[:, None] - (a[None] + t[..., None] * ab[None]), axis=2)
    k = np.argmin(d, axis=1)
    s = arc_length_mm(path)
    seg = np.linalg.norm(ab, axis=1)
    return s[k] + t[np.arange(len(k)), k] * seg[k], d[np.arange(len(k)), k]


def test_every_tandem_dwell_lies_in_the_drawn_tandem(demo: Demo) -> None:
    (ch,) = applicator_channels(demo.applicators, demo.planning, ImplantSettings())
    dwells = ch.dwell_positions_mm
    assert ch.name == "Tandem" and len(dwells) >= 20
    axis = np.asarray(demo.tandem.shapes[0].samples_mm)  # type: ignore[attr-defined]
    _, off_axis = along(axis, dwells)
    assert np.max(off_axis) < 1.0  # within 1 mm of the drawn tube's axis (the tube is 3 mm in radius)
    assert np.all(demo.tandem.contains(dwells))
    # the straight chord the channel used to be leaves the bent tandem by up to 13 mm
    chord = principal_chord(demo.contour_points, None)
    assert chord is not None and np.max(along(chord, axis)[1]) > 12.0


def test_dwells_follow_the_channel_by_arc_length_from_the_tip_offset(demo: Demo) -> None:
    (tandem,) = (a for a in demo.applicators if a.kind == "tandem")
    path = tandem.channels[0]
    length = float(arc_length_mm(path)[-1])
    for offset in (3.5, 7.0):
        settings = ImplantSettings(applicator_tip_offset_mm=offset)
        (ch,) = applicator_channels(demo.applicators, demo.planning, settings)
        s, d = along(path, ch.dwell_positions_mm)
        assert np.max(d) < 1e-6  # on the channel's path
        assert s[0] == pytest.approx(length - offset, abs=1e-6)  # the deepest, the tip offset back from the end
        assert np.allclose(np.diff(s), -settings.dwell_step_mm, atol=1e-6)  # deepest first, one step apart


def test_the_source_axis_at_each_dwell_points_toward_the_channels_end(demo: Demo) -> None:
    """TG-43's anisotropy is not symmetric: the source's long axis must point toward the tip (PS3.3 C.8.8.15.14)."""
    (ch,) = applicator_channels(demo.applicators, demo.planning, ImplantSettings())
    path = ch.path_mm
    s, _ = along(path, ch.dwell_positions_mm)
    arc = arc_length_mm(path)
    ahead = np.column_stack([np.interp(s + 0.5, arc, path[:, k]) - np.interp(s - 0.5, arc, path[:, k])
                             for k in range(3)])
    ahead /= np.linalg.norm(ahead, axis=1)[:, None]
    assert np.min(np.sum(ch.dwell_directions * ahead, axis=1)) > 0.99


def test_dwell_arc_lengths_of_a_channel() -> None:
    settings = ImplantSettings(dwell_step_mm=2.5, applicator_tip_offset_mm=3.5)
    assert np.allclose(applicator_dwell_arclengths(20.0, settings), [16.5, 14.0, 11.5, 9.0, 6.5, 4.0, 1.5])
    assert np.allclose(applicator_dwell_arclengths(6.0, settings), [2.5, 0.0])
    assert len(applicator_dwell_arclengths(3.0, settings)) == 0  # shorter than the offset: no dwell
    with pytest.raises(ValueError, match="tip offsets"):
        ImplantSettings(applicator_tip_offset_mm=-1.0)
