"""The centre line of an applicator ROI against known curves: a bent tube drawn as circles across it or cut on axial
slices (the sections computed by the imaging room's sweep, a second geometry), a drawn channel line, and ROIs that
give no honest line."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from reachplan.imaging.sweep import Sweep
from reachplan.imaging.types import Contour, Roi, StructureSet
from reachplan.plugins.applicators import BUILTIN_KINDS, applicators_from_structures, roi_centreline
from reachplan.plugins.applicators.centreline import order_nodes, polygon_centroid


def bent_axis(straight_mm: float, radius_mm: float, bend_deg: float, after_mm: float,
              tilt_deg: float = 0.0, step_mm: float = 0.1) -> np.ndarray:
    """A tube's axis: along +z, an arc of ``radius_mm`` bending ``bend_deg`` toward -y, straight again; the whole
    tilted about x by ``tilt_deg``. (n, 3) mm, base first, about ``step_mm`` apart."""
    line = [np.array([0.0, 0.0, z]) for z in np.arange(0.0, straight_mm, step_mm)]
    centre = np.array([0.0, -radius_mm, straight_mm])
    for t in np.arange(0.0, np.radians(bend_deg), step_mm / radius_mm):
        line.append(centre + radius_mm * np.array([0.0, np.cos(t), np.sin(t)]))
    b = np.radians(bend_deg)
    end, d = centre + radius_mm * np.array([0.0, np.cos(b), np.sin(b)]), np.array([0.0, -np.sin(b), np.cos(b)])
    line += [end + s * d for s in np.arange(0.0, after_mm + 1e-9, step_mm)]
    c, s = np.cos(np.radians(tilt_deg)), np.sin(np.radians(tilt_deg))
    return np.array(line) @ np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]]).T


def distance_to_curve(points: np.ndarray, curve: np.ndarray) -> np.ndarray:
    """Distance (mm) of each point to the polyline ``curve`` (segment by segment)."""
    a, ab = curve[:-1], np.diff(curve, axis=0)
    t = np.clip(np.einsum("psk,sk->ps", points[:, None] - a[None], ab) / np.einsum("sk,sk->s", ab, ab), 0.0, 1.0)
    return np.min(np.linalg.norm(points[:, None] - (a[None] + t[..., None] * ab[None]), axis=2), axis=1)


def circles_roi(axis_mm: np.ndarray, radius_mm: float = 3.0, every: int = 20) -> Roi:
    """Closed circles perpendicular to the axis at every ``every``-th sample (the ends included)."""
    idx = sorted({*range(0, len(axis_mm), every), len(axis_mm) - 1})
    out = []
    for i in idx:
        u = axis_mm[min(i + 1, len(axis_mm) - 1)] - axis_mm[max(i - 1, 0)]
        u /= np.linalg.norm(u)
        e1 = np.cross(u, [1.0, 0.0, 0.0])
        e1 /= np.linalg.norm(e1)
        e2 = np.cross(u, e1)
        t = np.linspace(0.0, 2 * np.pi, 36, endpoint=False)
        out.append(Contour(axis_mm[i] + radius_mm * (np.outer(np.cos(t), e1) + np.outer(np.sin(t), e2))))
    return Roi(1, "Tandem", tuple(out))


def axial_roi(axis_mm: np.ndarray, radius_mm: float = 3.0, slice_mm: float = 2.5) -> Roi:
    """The tube (rounded ends) cut on axial slices: one closed contour per section, as a planning system draws it."""
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(axis_mm, axis=0), axis=1))])
    into_cap = np.maximum(np.maximum(radius_mm - s, s - s[-1] + radius_mm), 0.0)  # hemispherical ends
    r = np.sqrt(np.clip(radius_mm ** 2 - into_cap ** 2, 0.0, None))
    sweep = Sweep(axis_mm, r, r, (1.0, 0.0, 0.0))
    zs = np.arange(np.floor(axis_mm[:, 2].min()) - 1.25, axis_mm[:, 2].max() + slice_mm, slice_mm)
    return Roi(1, "Tandem", tuple(Contour(np.column_stack([p, np.full(len(p), z)]))
                                  for z in zs for p in sweep.cross_section(float(z))))


@pytest.mark.parametrize("build", [circles_roi, axial_roi])
def test_a_tube_bent_35_degrees_gives_its_curve(build) -> None:  # type: ignore[no-untyped-def]
    """Within 0.5 mm of the true axis everywhere, from end to end, base (along +z) first; drawn either way."""
    axis = bent_axis(40.0, 40.0, 35.0, 30.0, tilt_deg=30.0)  # 30 degrees off the slices' normal, then 65
    line, notes = roi_centreline(build(axis))
    assert line is not None and notes == () and np.all(np.isfinite(line))
    assert np.max(distance_to_curve(line, axis)) < 0.5
    # it covers the whole tube: its ends where the drawn tube ends (the slices see a rounded end to within a mm)
    assert np.max(distance_to_curve(axis[10:-10], line)) < 0.5
    assert np.linalg.norm(line[0] - axis[0]) < 1.0 and np.linalg.norm(line[-1] - axis[-1]) < 1.0
    straight = np.linalg.norm(axis[-1] - axis[0])
    assert np.max(distance_to_curve(line, np.array([axis[0], axis[-1]]))) > 0.1 * straight  # not its chord


def test_a_slice_that_cuts_the_tube_twice_gives_two_nodes_in_order() -> None:
    """A tube bent back on itself cuts the upper slices in two sections; the nodes are ordered up one leg and
    down the other (the longest path of their spanning tree), not across."""
    axis = bent_axis(30.0, 15.0, 150.0, 20.0)
    roi = axial_roi(axis)
    z = np.array([c.points_mm[0, 2] for c in roi.contours])
    assert max(np.count_nonzero(z == v) for v in z) == 2
    nodes = np.array([polygon_centroid(c.points_mm)[0] for c in roi.contours])
    order = order_nodes(nodes)
    assert len(order) >= len(nodes) - 1
    arc = np.array([np.argmin(np.linalg.norm(axis - n, axis=1)) for n in nodes[order]])
    assert np.all(np.diff(arc) > 0) or np.all(np.diff(arc) < 0)  # monotonic along the true axis
    line, _ = roi_centreline(roi)
    assert line is not None and line[-1, 1] < -25.0  # it ends on the far leg
    # the apex lies along the slices (one long section there, its centroid inside the bend): the drawn wall of the
    # slices around it places the line
    assert np.max(distance_to_curve(line, axis)) < 0.75 and np.max(distance_to_curve(axis[10:-10], line)) < 0.75


@pytest.mark.parametrize(("bend", "tilt"), [(110.0, 0.0), (120.0, 20.0)])
def test_a_tube_bent_past_the_slices_stays_within_a_millimetre(bend: float, tilt: float) -> None:
    """Bent beyond 90 degrees, parts of the tube lie along the slices; the wall fit keeps the line on its axis."""
    axis = bent_axis(30.0, 22.0, bend, 25.0, tilt_deg=tilt)
    line, _ = roi_centreline(axial_roi(axis))
    assert line is not None
    assert np.percentile(distance_to_curve(line, axis), 95) < 0.5 and np.max(distance_to_curve(line, axis)) < 1.0


def test_polygon_centroid_of_an_oblique_ellipse_is_its_centre() -> None:
    t = np.linspace(0.0, 2 * np.pi, 400, endpoint=False)
    e1, e2 = np.array([1.0, 0.0, 0.5]), np.array([0.0, 1.0, 0.0])
    centre = np.array([3.0, -2.0, 7.0])
    pts = centre + np.outer(7.0 * np.cos(t), e1 / np.linalg.norm(e1)) + np.outer(3.0 * np.sin(t), e2)
    c, area = polygon_centroid(pts)
    assert np.allclose(c, centre, atol=1e-9) and area == pytest.approx(np.pi * 21.0, rel=1e-3)
    shifted = np.vstack([pts[:100], pts[100:101].repeat(50, axis=0), pts[101:]])  # vertices bunched on one side
    assert np.allclose(polygon_centroid(shifted)[0], centre, atol=1e-9)  # area, not vertex, centroid


def test_an_open_centre_line_roi_is_the_channel_as_drawn() -> None:
    axis = bent_axis(20.0, 30.0, 40.0, 15.0, step_mm=2.0)
    drawn = Roi(1, "Tandem", (Contour(axis[::-1], "OPEN_NONPLANAR"),), interpreted_type="BRACHY_CHANNEL")
    (tandem,) = applicators_from_structures(StructureSet((drawn,), "1.2.3"), BUILTIN_KINDS)
    assert tandem.loadable and np.array_equal(tandem.channels[0], axis)  # written tip first, read base to tip
    rng = np.random.default_rng(5)
    points = Roi(1, "Tandem", tuple(Contour(p[None], "POINT") for p in rng.permutation(axis)))
    line, _ = roi_centreline(points)
    assert line is not None and np.allclose(line, axis)  # single points are ordered along the curve
    # a stray point beside a tube drawn around the axis does not stand for the channel
    tube = circles_roi(axis)
    with_point = Roi(1, "Tandem", (*tube.contours, Contour(axis[:1] + 50.0, "POINT")))
    line, _ = roi_centreline(with_point)
    assert line is not None and np.allclose(line, roi_centreline(tube)[0])
    # an ovoid or ring drawn as a line is its channel too; a MARKER line beside it is not
    ovoid = Roi(2, "Ovoid_L", (Contour(axis, "OPEN_NONPLANAR"),))
    marker = Roi(3, "LT OVOID", (Contour(axis, "OPEN_PLANAR"),), interpreted_type="MARKER")
    ov, mk = applicators_from_structures(StructureSet((ovoid, marker), "1.2.3"), BUILTIN_KINDS)
    assert ov.loadable and np.array_equal(ov.channels[0], axis)
    assert mk.channels == () and not mk.loadable and "MARKER" in mk.notes[0]


@pytest.mark.parametrize(("contours", "says"), [
    ((), "no closed contour"),
    ((Contour(np.array([[0.0, 0.0, 5.0], [1.0, 0.0, 5.0], [1.0, 1.0, 5.0], [0.0, 1.0, 5.0]])),), "one slice"),
    ((Contour(np.array([[0.0, 0.0, 5.0], [9.0, 0.0, 5.0], [9.0, 1.0, 5.0]])),
      Contour(np.array([[20.0, 0.0, 5.0], [29.0, 0.0, 5.0], [29.0, 1.0, 5.0]]))), "one slice"),
    ((Contour(np.array([[1.0, 2.0, 3.0]]), "POINT"),), "single point"),
    ((Contour(np.array([[1.0, 2.0, 3.0], [1.0, 2.0, 3.0]]), "OPEN_NONPLANAR"),), "single point"),
])
def test_a_degenerate_roi_gives_no_channel_and_says_why(contours: tuple[Contour, ...], says: str) -> None:
    roi = Roi(4, "Tandem", contours)
    line, notes = roi_centreline(roi)
    assert line is None and says in notes[0] and "'Tandem'" in notes[0]
    (tandem,) = applicators_from_structures(StructureSet((roi,), "1.2.3"), BUILTIN_KINDS)
    assert tandem.channels == () and not tandem.loadable and says in tandem.notes[0]


@settings(max_examples=60, deadline=None)
@given(st.lists(st.tuples(st.integers(-3, 3), st.integers(3, 8), st.floats(0.0, 6.0), st.floats(-9.0, 9.0),
                          st.sampled_from(["CLOSED_PLANAR", "OPEN_NONPLANAR", "POINT"])), min_size=1, max_size=8))
def test_any_drawing_gives_a_finite_line_or_a_note(parts: list[tuple[int, int, float, float, str]]) -> None:
    """Whatever is drawn (slices, sizes, degenerate polygons, lines, points, mixed): a finite line of two or more
    points, or none and a note; never NaN, never an exception."""
    contours = []
    for k, n, radius, shift, kind in parts:
        t = np.linspace(0.0, 2 * np.pi, n, endpoint=False)
        pts = np.column_stack([shift + radius * np.cos(t), radius * np.sin(t), np.full(n, 2.5 * k)])
        contours.append(Contour(pts[:1] if kind == "POINT" else pts, kind))
    line, notes = roi_centreline(Roi(1, "Tandem", tuple(contours)), np.array([0.0, 0.0, 1.0]))
    if line is None:
        assert notes and all(isinstance(x, str) and x for x in notes)
    else:
        assert line.shape[1] == 3 and len(line) >= 2 and np.all(np.isfinite(line))
