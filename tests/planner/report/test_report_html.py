"""The HTML builder (plain data -> one self-contained document) and the report's small helpers."""

from __future__ import annotations

import base64
import io
import re
from types import SimpleNamespace

import matplotlib.image as mpimg
import numpy as np
import pytest
from matplotlib.figure import Figure as MplFigure

from reachplan.planner.case.result import choose_needles
from reachplan.planner.report import charts, figures
from reachplan.planner.report.build import _runs, models_used
from reachplan.planner.report.html import Figure, Paragraph, Report, Section, Table, render_html
from reachplan.planner.steering.candidates import Candidate
from reachplan.planner.steering.insertion import STRAIGHT


def _png(colour: str = "red") -> bytes:
    fig = MplFigure(figsize=(2, 1))
    fig.patch.set_facecolor(colour)
    return figures.png_bytes(fig, dpi=50)


def _report() -> Report:
    return Report("t <1>", "sub & title", (
        Section("One", "one", (Paragraph("a <b>bold</b> claim"),
                               Table(("name", "value"), (("x<y", "1.0"), ("z", "2.5")), "tab", numeric=(1,)))),
        Section("Two", "two", (Figure(_png(), "a red square", alt="red"),
                               Table(("k",), (("v",),), "hidden", collapsed=True))),
    ))


def test_render_escapes_text_and_embeds_images_as_data_uris() -> None:
    doc = render_html(_report(), footer="f")
    assert "a &lt;b&gt;bold&lt;/b&gt; claim" in doc and "<b>bold" not in doc
    assert "<td>x&lt;y</td>" in doc and '<td class="num">2.5</td>' in doc
    srcs = re.findall(r'src="([^"]*)"', doc)
    assert len(srcs) == 1 and srcs[0].startswith("data:image/png;base64,")
    png = base64.b64decode(srcs[0].split(",", 1)[1])
    img = mpimg.imread(io.BytesIO(png), format="png")
    assert img[..., 0].mean() > 0.9 and img[..., 1].mean() < 0.1  # the red square survived the round trip
    assert "<script" not in doc and "http://" not in doc and "https://" not in doc
    assert "default-src 'none'" in doc  # the browser may load nothing but the embedded images
    assert "<details><summary>hidden</summary>" in doc
    assert doc.count('<section id="') == 2 and 'href="#two"' in doc


def test_plain_data_is_validated() -> None:
    with pytest.raises(ValueError, match="row 0 has 1 cells"):
        Table(("a", "b"), (("only one",),))
    with pytest.raises(ValueError, match="numeric column"):
        Table(("a",), (("1",),), numeric=(3,))
    with pytest.raises(ValueError, match="not a PNG"):
        Figure(b"GIF89a...", "gif")
    with pytest.raises(ValueError, match="anchor"):
        Section("S", "has space", ())
    with pytest.raises(ValueError, match="unique anchors"):
        Report("r", "", (Section("a", "x", ()), Section("b", "x", ())))


def _cand(target: str, hole: str, steered: bool, feasible: bool = True) -> Candidate:
    path = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 50.0]])
    return Candidate(target, hole, 10.0, 0.5, 5.0, "Bladder", 50.0, steered, 0.0, STRAIGHT, not feasible, True,
                     "" if feasible else "collides", path)


def test_choose_needles_of_a_kind_takes_each_targets_best_on_a_free_hole() -> None:
    result = SimpleNamespace(ranking={  # the part of PlanResult choose_needles reads
        "T1": (_cand("T1", "A", True), _cand("T1", "B", False, feasible=False), _cand("T1", "C", False)),
        "T2": (_cand("T2", "A", True), _cand("T2", "D", True), _cand("T2", "C", False)),
        "T3": (_cand("T3", "E", True, feasible=False),),
    })
    steered = choose_needles(result, steered=True)  # type: ignore[arg-type]
    straight = choose_needles(result, steered=False)  # type: ignore[arg-type]
    assert [(c.target, c.hole_id) for c in steered] == [("T1", "A"), ("T2", "D")]  # A is taken: T2 gets D
    assert [(c.target, c.hole_id) for c in straight] == [("T1", "C")]  # T2's straight would reuse C: none
    either = choose_needles(result)  # type: ignore[arg-type]
    assert [(c.target, c.hole_id) for c in either] == [("T1", "A"), ("T2", "D")]


def test_schedule_runs_drop_repeated_breakpoints() -> None:
    sched = np.array([[0.0, 0.0, 90.0], [5.0, 10.0, 90.0], [10.0, 10.0, 90.0], [15.0, 4.0, 90.0]])
    assert _runs(sched) == [(0.0, 0.0, 90.0), (5.0, 10.0, 90.0), (15.0, 4.0, 90.0)]


def test_speed_accuracy_chart_marks_the_models_used() -> None:
    from reachplan.rod_model.select import error_table

    rows = error_table()
    plain = mpimg.imread(io.BytesIO(charts.speed_accuracy(rows, {})), format="png")
    marked = mpimg.imread(io.BytesIO(charts.speed_accuracy(rows, {"planar_beam": "screening"})), format="png")
    assert plain.shape == marked.shape and plain.std() > 0.05
    assert np.abs(plain - marked).sum() > 100  # the ring and the label are drawn


def test_models_used_names_each_rod_models_role() -> None:
    from reachplan.planner.steering.kinematic import KINEMATIC
    from reachplan.planner.steering.tissue_rod import TISSUE_ROD

    cands = [SimpleNamespace(model=m) for m in [STRAIGHT, KINEMATIC.info, KINEMATIC.info, TISSUE_ROD.info]]
    used = models_used(SimpleNamespace(candidates=cands))  # type: ignore[arg-type]
    assert used == {"planar_beam": f"screening with {KINEMATIC.name} (2 candidates)",
                    "two_tube_cosserat": f"reference re-solve with {TISSUE_ROD.name} (1 candidates)"}


def test_interactive_figures_embed_plotly_once_and_escape_their_data() -> None:
    from reachplan.planner.report.html import Interactive

    fig = {"data": [{"type": "scatter3d", "name": "</script><b>x", "x": [1], "y": [2], "z": [3]}], "layout": {}}
    doc = render_html(Report("t", "s", (Section("A", "a", (Interactive(fig, "one"), Interactive(fig, "two"))),)))
    assert doc.count("<script>") == 3  # plotly.js once, then one call per figure
    assert 'Plotly.newPlot("plot-1"' in doc and 'Plotly.newPlot("plot-2"' in doc
    assert "</script><b>" not in doc and "<\\/script><b>x" in doc  # data cannot end the script element
    assert "script-src 'unsafe-inline'" in doc and "://" not in doc.split("<script>")[0]
    assert "<script" not in render_html(_report())  # no interactive figure: no script at all
    with pytest.raises(ValueError, match="data"):
        Interactive({"layout": {}}, "no traces")


def test_delivered_dvh_marks_each_aim_where_the_aims_put_it() -> None:
    from reachplan.planner.dose.aims import Aims
    from reachplan.planner.dose.coverage import Dvh

    aims = Aims()
    dose = np.linspace(0.0, 30.0, 301)
    dvhs = [("HR-CTV", Dvh(dose, 60.0 * np.exp(-dose / 10))), ("Rectum", Dvh(dose, 50.0 * np.exp(-dose / 2))),
            ("Uterus", Dvh(dose, 70.0 * np.exp(-dose / 5)))]
    ax = charts.dvh_aims_figure(dvhs, aims).axes[0]
    marks = {ln.get_gid(): ln.get_xydata()[0] for ln in ax.lines if (ln.get_gid() or "").startswith(("aim", "limit"))}
    assert np.allclose(marks["aim:D90"], (aims.prescription_gy, 0.9 * 60.0))
    assert np.allclose(marks["limit:Rectum"], (aims.oar_gy("Rectum"), 2.0))
    assert "limit:Uterus" not in marks  # no limit, no mark
    assert ax.get_yscale() == "log"


def test_3d_cameras_follow_the_slices_convention() -> None:
    """plotly's camera looks along -eye with ``up`` at the top and ``-eye × up`` to the right (checked by eye in
    headless Chromium: from the front, the phantom's left-sided target is on the right)."""
    from reachplan.planner.report.view3d import CAMERAS

    expected = {"the patient's feet": ("L", "A"), "the front": ("L", "S"), "the patient's left": ("P", "S")}
    for name, eye, up in CAMERAS:
        key = next((k for k in expected if name.startswith(k)), None)
        if key is None:
            continue
        right = np.cross(-np.asarray(eye), np.asarray(up))
        assert (figures.direction_letter(right), figures.direction_letter(np.asarray(up))) == expected[key], name


def test_light_mesh_keeps_every_part_of_a_large_mesh_near_its_surface() -> None:
    """Two fine spheres 60 mm apart (81,920 faces each): the 3-D view's mesh keeps both, within the budget.

    Quadric decimation alone stopped early on the 243k-face pelvic bone and dropped parts of it; clustering first
    (:func:`figures.cluster_vertices`) must keep every part. Checked against the spheres' closed form.
    """
    import trimesh

    radius_mm, centres = 20.0, np.array([[-30.0, 0.0, 0.0], [30.0, 0.0, 0.0]])
    parts = [trimesh.creation.icosphere(subdivisions=6, radius=radius_mm).apply_translation(c) for c in centres]
    big = trimesh.util.concatenate(parts)
    assert len(big.faces) > figures.CLUSTER_FACTOR * figures.VIEW_FACES
    light = figures.light_mesh(big)
    assert len(light.faces) <= 1.05 * figures.VIEW_FACES
    v = np.asarray(light.vertices)
    d = np.linalg.norm(v[:, None, :] - centres[None], axis=2)
    assert np.all(np.abs(d.min(axis=1) - radius_mm) < 1.5)  # every vertex on one of the spheres
    for c in range(2):  # each sphere still there, all round: its vertices span its whole diameter on every axis
        own = v[np.argmin(d, axis=1) == c] - centres[c]
        assert len(own) > 100
        np.testing.assert_array_less(2 * radius_mm - 4.0, own.max(axis=0) - own.min(axis=0))
    flat = trimesh.Trimesh([[0, 0, 0], [1, 0, 0], [2, 0, 0]], [[0, 1, 2]], process=False)
    assert figures.cluster_vertices(flat, 10) is flat  # no area: nothing to cluster
