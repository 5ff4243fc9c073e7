"""The interactive 3-D view of the report: organs, needles, dwell positions and the template, as a plotly figure.

The figure is plain JSON-ready data (``{"data": [...], "layout": {...}}``) in plotly.js's schema: no Python
plotly object is built, and :func:`reachplan.planner.report.html.render_html` embeds plotly.js once, so the
report stays one file that works offline. One trace per organ and per needle (toggled from the legend), plus
the target points, the template holes and the dwell positions of the delivered plan.

Coordinates are mm, DICOM patient coordinates (LPS). The view opens as the operator sees the patient, from the
feet along the needles (patient left on the right, anterior at the top: the radiological convention of the axial
slices); buttons turn it to the other named views, and its title says which one is shown.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import trimesh

from reachplan.planner.case.scene import Scene
from reachplan.planner.report.figures import (
    STEERED_COLOUR,
    STRAIGHT_COLOUR,
    TARGET_COLOUR,
    VIEW_FACES,
    light_mesh,
    organ_colour,
)
from reachplan.planner.steering.candidates import Candidate, TissueBand

#: Named views: (name, camera eye direction, camera up direction), LPS. Looking along -eye with ``up`` at the
#: top, plotly's right-handed camera puts ``-eye × up`` on the right: from the feet, +x (patient left) is on the
#: right and -y (anterior) at the top; from the front, the patient's left on the right; from the left,
#: anterior on the left (the conventions of the axial, coronal and sagittal slices).
CAMERAS: tuple[tuple[str, tuple[float, float, float], tuple[float, float, float]], ...] = (
    ("the patient's feet (operator's view)", (0.0, 0.0, -2.0), (0.0, -1.0, 0.0)),
    ("the front (anterior)", (0.0, -2.0, 0.0), (0.0, 0.0, 1.0)),
    ("the patient's left", (2.0, 0.0, 0.0), (0.0, 0.0, 1.0)),
    ("anterior-oblique, from the feet", (1.0, -1.4, -1.0), (0.0, 0.0, 1.0)),
)

#: Organs drawn but hidden until switched on from the legend.
HIDDEN_ORGANS = ("Bone", "Obturator")


@dataclass(frozen=True, eq=False)
class Needle3d:
    """A needle to draw.

    Parameters
    ----------
    label : str
        Its entry in the legend.
    path_mm : (n, 3) float, mm, LPS
        Centreline from base to tip.
    steered : bool
        Drawn as a steered needle (solid cyan) or a straight one (dashed orange).
    implant : bool
        A needle of the delivered implant (trace ``meta`` ``implant``, drawn thicker); when any is drawn, the
        other needles (each target's best candidates) start hidden.
    """

    label: str
    path_mm: np.ndarray
    steered: bool
    implant: bool = False

    @staticmethod
    def of(c: Candidate, note: str = "") -> Needle3d:
        """Return a candidate's needle, labelled by kind, hole and target.

        Parameters
        ----------
        c : Candidate
            The candidate.
        note : str
            Appended to the label.

        Returns
        -------
        Needle3d
            Its path (mm, LPS) and kind.
        """
        kind = "steered" if c.steered else "straight"
        return Needle3d(f"{kind} {c.hole_id} → {c.target}{note}", c.path_mm, c.steered)


def _r(a: np.ndarray, digits: int = 1) -> list[float]:
    return [float(v) for v in np.round(np.asarray(a, dtype=float), digits)]


def _camera(i: int) -> dict[str, Any]:
    _, eye, up = CAMERAS[i]
    return {"eye": dict(zip("xyz", eye, strict=True)), "up": dict(zip("xyz", up, strict=True)),
            "center": {"x": 0, "y": 0, "z": 0}}


def _title(i: int) -> str:
    return f"viewed from {CAMERAS[i][0]} — drag to turn, click a legend entry to hide or show it"


def scene_figure(scene: Scene, needles: Sequence[Needle3d], *, dwell_positions_mm: np.ndarray | None = None,
                 dwell_times_s: np.ndarray | None = None, dwell_labels: Sequence[str] | None = None,
                 max_faces: int = VIEW_FACES, meshes: Mapping[str, trimesh.Trimesh] | None = None) -> dict[str, Any]:
    """Return the plotly figure (JSON-ready dict) of a plan in 3-D.

    Parameters
    ----------
    scene : Scene
        The plan's scene; every mesh in ``scene.meshes`` (mm, LPS) is one trace (Bone and Obturator start hidden).
    needles : sequence of Needle3d
        One trace each.
    dwell_positions_mm : (m, 3) float, mm, LPS, optional
        Active dwell positions of the delivered plan (one trace, marker size by time).
    dwell_times_s : (m,) float, s, optional
        Their dwell times.
    dwell_labels : sequence of str, optional
        m strings naming each dwell's needle (hover text).
    max_faces : int
        Each organ is decimated to about this many faces (:func:`reachplan.planner.report.figures.light_mesh`) to
        keep the report small.
    meshes : mapping of str to trimesh.Trimesh, optional
        Pre-decimated meshes by name (default: decimated here).

    Returns
    -------
    dict of str to object
        ``data`` (traces; each has ``meta`` = ``organ``, ``implant``, ``needle``, ``targets``, ``template`` or
        ``dwells``) and ``layout``; coordinates in mm, LPS.
    """
    data: list[dict[str, Any]] = []
    for name, mesh in scene.meshes.items():
        light = meshes[name] if meshes is not None and name in meshes else light_mesh(mesh, max_faces)
        v, f = light.vertices, np.asarray(light.faces)
        data.append({
            "type": "mesh3d", "name": name, "meta": "organ", "showlegend": True, "color": organ_colour(name),
            "opacity": 0.45 if name.casefold().startswith(("target", "hr-ctv")) else 0.25,
            "x": _r(v[:, 0]), "y": _r(v[:, 1]), "z": _r(v[:, 2]),
            "i": f[:, 0].tolist(), "j": f[:, 1].tolist(), "k": f[:, 2].tolist(), "flatshading": True,
            "hoverinfo": "name", "visible": "legendonly" if name in HIDDEN_ORGANS else True,
        })
    any_implant = any(n.implant for n in needles)
    for n in needles:
        p = np.asarray(n.path_mm, dtype=float)
        data.append({
            "type": "scatter3d", "mode": "lines", "name": n.label, "meta": "implant" if n.implant else "needle",
            "x": _r(p[:, 0]), "y": _r(p[:, 1]), "z": _r(p[:, 2]), "hoverinfo": "name",
            "visible": "legendonly" if any_implant and not n.implant else True,
            "line": {"color": STEERED_COLOUR if n.steered else STRAIGHT_COLOUR, "width": 9 if n.implant else 5,
                     "dash": "solid" if n.steered else "dash"},
        })
    pts = np.array([t.position_mm for t in scene.targets], dtype=float).reshape(-1, 3)
    data.append({"type": "scatter3d", "mode": "markers", "name": "target points", "meta": "targets",
                 "x": _r(pts[:, 0]), "y": _r(pts[:, 1]), "z": _r(pts[:, 2]),
                 "text": [t.name for t in scene.targets], "hoverinfo": "text",
                 "marker": {"color": TARGET_COLOUR, "size": 5, "symbol": "cross"}})
    m = scene.patient_from_template
    xy = np.array([h.xy_mm for h in scene.template.holes], dtype=float)
    holes = xy[:, :1] * m[:3, 0] + xy[:, 1:2] * m[:3, 1] + m[:3, 3]
    data.append({"type": "scatter3d", "mode": "markers", "name": f"template {scene.template.name}",
                 "meta": "template", "x": _r(holes[:, 0]), "y": _r(holes[:, 1]), "z": _r(holes[:, 2]),
                 "text": [h.hole_id for h in scene.template.holes], "hoverinfo": "text",
                 "marker": {"color": "#555555", "size": 2.5}})
    if dwell_positions_mm is not None and len(dwell_positions_mm):
        d = np.asarray(dwell_positions_mm, dtype=float).reshape(-1, 3)
        t = np.zeros(len(d)) if dwell_times_s is None else np.asarray(dwell_times_s, dtype=float)
        labels = list(dwell_labels) if dwell_labels is not None else [""] * len(d)
        data.append({"type": "scatter3d", "mode": "markers", "name": "dwell positions (delivered plan)",
                     "meta": "dwells", "x": _r(d[:, 0]), "y": _r(d[:, 1]), "z": _r(d[:, 2]),
                     "text": [f"{lab}: {ti:.1f} s" for lab, ti in zip(labels, t, strict=True)], "hoverinfo": "text",
                     "marker": {"color": "#111111", "size": _r(2 + 6 * t / max(float(t.max()), 1e-9))}})
    axis = {"showbackground": False, "gridcolor": "#dddddd", "zeroline": False}
    buttons = [{"label": f"from {name.split(' (')[0]}", "method": "relayout",
                "args": [{"scene.camera": _camera(i), "title.text": _title(i)}]} for i, (name, _, _) in
               enumerate(CAMERAS)]
    layout = {
        "title": {"text": _title(0), "font": {"size": 13}},
        "height": 720, "margin": {"l": 0, "r": 0, "t": 40, "b": 0},
        "legend": {"itemsizing": "constant", "font": {"size": 11}},
        "scene": {"aspectmode": "data", "camera": _camera(0),
                  "xaxis": {**axis, "title": {"text": "x: R → L (mm)"}},
                  "yaxis": {**axis, "title": {"text": "y: A → P (mm)"}},
                  "zaxis": {**axis, "title": {"text": "z: I → S (mm)"}}},
        "updatemenus": [{"type": "buttons", "direction": "right", "x": 0.0, "y": 1.0, "xanchor": "left",
                         "yanchor": "top", "pad": {"t": 4}, "buttons": buttons}],
    }
    return {"data": data, "layout": layout}


def with_tissue_bands(figure: dict[str, Any], bands: Sequence[tuple[str, TissueBand]]) -> dict[str, Any]:
    """Return ``figure`` with each steered needle's tissue band drawn: a ribbon through its paths, and its edges.

    The ribbon joins the band's paths from the softest tissue to the stiffest (translucent, the steered needles'
    colour); the softest and stiffest paths are one dotted trace (a gap between them) named with their moduli at
    the tip. Both are in one legend group: a click on either hides or shows the band.

    Parameters
    ----------
    figure : dict of str to object
        A figure of :func:`scene_figure` (not changed).
    bands : sequence of (str, TissueBand)
        The needle's label and its band (paths mm, LPS, each hole to tip, the same number of points); bands
        without paths (not computed) are left out.

    Returns
    -------
    dict of str to object
        A new figure: ``figure``'s traces, then per band a ``mesh3d`` ribbon and a ``scatter3d`` of its two edge
        paths, ``meta`` = ``tissue band``.
    """
    traces: list[dict[str, Any]] = []
    for label, band in bands:
        paths = [np.asarray(p, dtype=float) for p in band.paths_mm]
        if len(paths) < 2 or len({len(p) for p in paths}) != 1:
            continue
        n = len(paths[0])
        v = np.vstack(paths)
        i, j = np.meshgrid(np.arange(len(paths) - 1), np.arange(n - 1), indexing="ij")
        a = (i * n + j).ravel()  # quad (a, a + 1, a + n + 1, a + n) between path i and i + 1, points j and j + 1
        faces = np.concatenate([np.column_stack([a, a + 1, a + n + 1]), np.column_stack([a, a + n + 1, a + n])])
        group = f"band {label}"
        lo, hi = band.moduli_pa[0] / 1e6, band.moduli_pa[-1] / 1e6
        traces.append({"type": "mesh3d", "name": f"tissue band {label} ({lo:.3g}-{hi:.3g} MPa)",
                       "meta": "tissue band", "legendgroup": group, "showlegend": True, "color": STEERED_COLOUR,
                       "opacity": 0.3, "flatshading": True, "x": _r(v[:, 0]), "y": _r(v[:, 1]), "z": _r(v[:, 2]),
                       "i": faces[:, 0].tolist(), "j": faces[:, 1].tolist(), "k": faces[:, 2].tolist(),
                       "hoverinfo": "name"})
        soft, stiff = paths[0], paths[-1]
        edges = {axis: [*_r(soft[:, k]), None, *_r(stiff[:, k])] for k, axis in enumerate("xyz")}
        traces.append({"type": "scatter3d", "mode": "lines", "meta": "tissue band", "legendgroup": group,
                       "name": f"{label}: softest / stiffest path ({lo:.3g} / {hi:.3g} MPa at the tip)",
                       "showlegend": True, **edges, "connectgaps": False, "hoverinfo": "name",
                       "line": {"color": STEERED_COLOUR, "width": 3, "dash": "dot"}})
    return {**figure, "data": [*figure["data"], *traces]}
