"""Template pose in the patient and the hole frames (layouts are :mod:`reachplan.plugins.templates`).

Template frame: origin at the template centre (the obturator axis on the template plane), ``x``/``y`` in
the template plane, ``+z`` the insertion direction. A template is placed with a rigid 4x4
``patient_from_template`` (LPS mm).
"""

from __future__ import annotations

import numpy as np

from reachplan.imaging.types import Roi
from reachplan.planner.errors import PlanInputError
from reachplan.plugins.templates import Hole, Template


def hole_frames(
    template: Template, patient_from_template: np.ndarray, holes: tuple[Hole, ...] | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Entry points and insertion directions of holes in the patient.

    Returns
    -------
    entry_mm : (n, 3) float, mm, LPS
    direction : (n, 3) float, unit vectors, LPS (the template's +z)
    """
    holes = template.needle_holes if holes is None else holes
    m = np.asarray(patient_from_template, dtype=float)
    xy = np.array([h.xy_mm for h in holes], dtype=float).reshape(-1, 2)
    local = np.column_stack([xy, np.zeros(len(xy)), np.ones(len(xy))])
    entry = (local @ m.T)[:, :3]
    direction = np.broadcast_to(m[:3, 2] / np.linalg.norm(m[:3, 2]), entry.shape).copy()
    return entry, direction


def check_rigid(patient_from_template: np.ndarray) -> np.ndarray:
    """Validate a rigid 4x4 transform (orthonormal rotation, det +1); returns it as float array."""
    m = np.asarray(patient_from_template, dtype=float)
    if m.shape != (4, 4) or not np.all(np.isfinite(m)):
        raise PlanInputError("patient_from_template must be a finite 4x4 matrix")
    r = m[:3, :3]
    if not np.allclose(r.T @ r, np.eye(3), atol=1e-6) or np.linalg.det(r) < 0 or not np.allclose(m[3], [0, 0, 0, 1]):
        raise PlanInputError("patient_from_template must be rigid (orthonormal rotation, det +1, last row 0 0 0 1)")
    return m


def pose_from_obturator(obturator: Roi, depth_mm: float = 60.0) -> np.ndarray:
    """``patient_from_template`` for a template that sits on the obturator.

    The obturator axis is the principal axis of its contour points; its cranial end (larger patient z,
    the end inside the patient) is the tip, half a contour spacing beyond the last contour. The template
    plane is ``depth_mm`` behind the tip along the axis (how far the obturator is inserted beyond the
    template; 60 mm is our documented default, the
    vaginal length of the phantom); template ``+z`` points along the axis into the patient, template
    ``+x`` is the patient's left (+x LPS) made perpendicular to the axis.

    Returns
    -------
    patient_from_template : (4, 4) float
    """
    pts = np.concatenate([c.points_mm for c in obturator.contours])
    if len(pts) < 4:
        raise PlanInputError(f"ROI {obturator.name!r} has too few points to find the obturator axis")
    centre = pts.mean(axis=0)
    _, _, vt = np.linalg.svd(pts - centre, full_matrices=False)
    axis = vt[0] if vt[0][2] >= 0 else -vt[0]
    proj = (pts - centre) @ axis
    # each planar contour stands for a slab one contour spacing thick: the tip is half a spacing beyond
    # the last contour's plane
    planes = np.unique(np.round([float(np.mean((c.points_mm - centre) @ axis)) for c in obturator.contours], 3))
    half = 0.5 * float(np.median(np.diff(planes))) if len(planes) > 1 else 0.0
    tip = centre + axis * (proj.max() + half)
    origin = tip - axis * depth_mm
    x = np.array([1.0, 0.0, 0.0]) - axis[0] * axis
    if np.linalg.norm(x) < 1e-6:
        raise PlanInputError("the obturator axis is along patient left-right; give patient_from_template explicitly")
    x /= np.linalg.norm(x)
    y = np.cross(axis, x)
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = x, y, axis, origin
    return m
