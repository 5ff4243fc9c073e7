"""Orientation of the report's figures, read from the figures' own coordinates (not from the files' existence).

The template map and the axial slices must show the patient the same way (seen from the feet: patient left on
the right, anterior at the top), so that a user cannot swap bladder-side and rectum-side holes.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from matplotlib.text import Text

from reachplan.imaging.phantom import write_phantom
from reachplan.imaging.rtstruct import read_rtstruct
from reachplan.planner.case.scene import Scene, build_scene
from reachplan.planner.report import figures


@pytest.fixture(scope="module")
def scene(tmp_path_factory: pytest.TempPathFactory) -> Scene:
    rs = write_phantom(tmp_path_factory.mktemp("phantom")).rtstruct_path
    return build_scene(read_rtstruct(rs, None), ["Target_80_030"])


def _display(ax: object, xy: np.ndarray) -> np.ndarray:
    """Data coordinates -> display pixels (x to the right, y up), after the figure is drawn."""
    ax.figure.canvas.draw()  # type: ignore[attr-defined]
    return ax.transData.transform(np.asarray(xy, dtype=float))  # type: ignore[attr-defined]


def _letters(ax: object) -> dict[str, tuple[float, float]]:
    """Orientation letters by text, at their axes-fraction positions."""
    return {t.get_text(): t.get_position() for t in ax.texts  # type: ignore[attr-defined]
            if isinstance(t, Text) and t.get_gid() == "orientation"}


def _organ_centre_px(ax: object, name: str) -> np.ndarray:
    lines = [ln for ln in ax.lines if ln.get_gid() == f"organ:{name}"]  # type: ignore[attr-defined]
    assert lines, f"no {name} outline in the {ax.get_gid()} view"  # type: ignore[attr-defined]
    pts = np.concatenate([ln.get_xydata() for ln in lines])
    return np.nanmean(_display(ax, pts), axis=0)  # outlines are segments separated by NaN rows


def test_template_map_and_axial_slice_put_the_bladder_side_at_the_top(scene: Scene) -> None:
    m = scene.patient_from_template
    tmap = figures.template_map_figure(scene, [])
    ax_t = tmap.axes[0]
    holes = [h for h in scene.template.holes if h.kind == "needle"]
    xy = np.array([h.xy_mm for h in holes])
    patient = xy @ m[:2, :3] + m[:3, 3]  # hole centres in LPS mm
    px = _display(ax_t, xy)
    # anterior holes (small LPS y) are drawn higher, and the patient's left holes (large LPS x) further right
    assert np.corrcoef(-patient[:, 1], px[:, 1])[0, 1] > 0.95
    assert np.corrcoef(patient[:, 0], px[:, 0])[0, 1] > 0.95
    anterior = px[np.argsort(patient[:, 1])[:5], 1].mean()
    posterior = px[np.argsort(patient[:, 1])[-5:], 1].mean()
    assert anterior > posterior

    fig = figures.slice_figure(scene, "Target_80_030", None, None)
    axial = next(a for a in fig.axes if a.get_gid() == "axial")
    bladder, rectum = _organ_centre_px(axial, "Bladder"), _organ_centre_px(axial, "Rectum")
    # bladder (anterior) above rectum (posterior) on screen: the same side as the template's anterior holes
    assert bladder[1] > rectum[1]
    lps_bladder = scene.meshes["Bladder"].centroid
    lps_rectum = scene.meshes["Rectum"].centroid
    assert lps_bladder[1] < lps_rectum[1]  # the phantom's bladder is anterior (LPS -y) of its rectum
    # the patient's left is on the right in both views
    left_right_px = _display(axial, np.array([[-50.0, 0.0], [50.0, 0.0]]))
    assert left_right_px[1, 0] > left_right_px[0, 0]

    # and both say so on their edges
    for ax in (ax_t, axial):
        letters = _letters(ax)
        assert letters["A"][1] > 0.9 and letters["P"][1] < 0.1
        assert letters["L"][0] > 0.9 and letters["R"][0] < 0.1


def test_every_slice_view_is_labelled_with_its_directions(scene: Scene) -> None:
    fig = figures.slice_figure(scene, "Target_80_030", None, None)
    expected = {"axial": ("R", "L", "P", "A"), "coronal": ("R", "L", "I", "S"), "sagittal": ("A", "P", "I", "S")}
    for ax in fig.axes:
        left, right, bottom, top = expected[ax.get_gid()]
        letters = _letters(ax)
        assert letters[left][0] < 0.1 and letters[right][0] > 0.9
        assert letters[bottom][1] < 0.1 and letters[top][1] > 0.9
        # the letters agree with the data: the 'top' end of the vertical axis is where the letter says
        (_, y0), (_, y1) = _display(ax, np.array([[0.0, -10.0], [0.0, 10.0]]))
        positive_up = y1 > y0
        assert positive_up == (top in {"P", "S"})


def test_a_flipped_pose_flips_the_template_map(scene: Scene) -> None:
    """Derived from the pose, not assumed: a template turned 180° about its axis is drawn turned back."""
    import dataclasses

    turn = np.diag([-1.0, -1.0, 1.0, 1.0])
    flipped = dataclasses.replace(scene, patient_from_template=scene.patient_from_template @ turn)
    ax = figures.template_map_figure(flipped, []).axes[0]
    xy = np.array([h.xy_mm for h in flipped.template.holes])
    patient = xy @ flipped.patient_from_template[:2, :3] + flipped.patient_from_template[:3, 3]
    px = _display(ax, xy)
    assert np.corrcoef(-patient[:, 1], px[:, 1])[0, 1] > 0.95
    assert np.corrcoef(patient[:, 0], px[:, 0])[0, 1] > 0.95


def test_isodose_lines_are_drawn_at_the_levels_asked(scene: Scene) -> None:
    """A single dwell: the 100 % line lies where the dose equals the prescription (read from the contour)."""
    point = np.array(next(t.position_mm for t in scene.targets))
    src = point + np.array([0.0, 0.0, 0.0])

    def dose_at(p: np.ndarray) -> np.ndarray:  # inverse square, 1 Gy at 10 mm
        return 100.0 / np.maximum(np.sum((p - src) ** 2, axis=1), 1.0)

    overlay = figures.DoseOverlay(dose_at, 1.0, src[None], np.array([20.0]))
    fig = figures.slice_figure(scene, "Target_80_030", None, None, dose=overlay)
    axial = next(a for a in fig.axes if a.get_gid() == "axial")
    for pct in (50, 100, 200):
        sets = [c for c in axial.collections if c.get_gid() == f"isodose:{pct}"]
        assert sets, f"no {pct} % line"
        verts = np.concatenate([p.vertices for c in sets for p in c.get_paths()])
        r = np.linalg.norm(verts - src[:2], axis=1)
        expected = 10.0 / np.sqrt(pct / 100.0)  # 100 / r² = pct/100
        assert np.allclose(r, expected, rtol=0.08), (pct, r.min(), r.max(), expected)
    dwell = [c for c in axial.collections if c.get_gid() == "dwells"]
    assert dwell and np.allclose(dwell[0].get_offsets()[0], src[:2])


def test_rendered_figures_are_png(scene: Scene, tmp_path: Path) -> None:
    assert figures.template_map(scene, []).startswith(b"\x89PNG")
