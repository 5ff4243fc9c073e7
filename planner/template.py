"""Needle templates: hole layouts in template coordinates, and their pose in the patient.

Template frame: origin at the template centre (the obturator axis on the template plane), ``x``/``y`` in
the template plane, ``+z`` the insertion direction. A template is placed with a rigid 4x4
``patient_from_template`` (LPS mm).
"""

from __future__ import annotations

import csv
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from imaging.types import Roi
from planner.errors import PlanInputError


@dataclass(frozen=True)
class Hole:
    """One template hole.

    Parameters
    ----------
    hole_id : str
        Label as printed on the template.
    xy_mm : (2,) float, mm, template frame
    kind : str
        ``"needle"`` or ``"tandem"`` (the central channel the tandem/obturator occupies).
    """

    hole_id: str
    xy_mm: tuple[float, float]
    kind: str = "needle"

    def __post_init__(self) -> None:
        if not self.hole_id:
            raise ValueError("a hole needs a non-empty hole_id")
        if not all(np.isfinite(self.xy_mm)):
            raise ValueError(f"hole {self.hole_id}: position must be finite, got {self.xy_mm}")
        if self.kind not in ("needle", "tandem"):
            raise ValueError(f"hole {self.hole_id}: kind must be 'needle' or 'tandem', got {self.kind!r}")

    @property
    def distance_mm(self) -> float:
        """Distance from the template centre (mm); smaller is more medial."""
        return float(np.hypot(*self.xy_mm))


@dataclass(frozen=True)
class Template:
    """A hole layout (from a template plugin)."""

    name: str
    holes: tuple[Hole, ...]
    source: str = ""

    def __post_init__(self) -> None:
        ids = [h.hole_id for h in self.holes]
        if len(set(ids)) != len(ids):
            raise ValueError(f"template {self.name}: hole ids must be unique")
        if not self.holes:
            raise ValueError(f"template {self.name}: no holes")

    @property
    def needle_holes(self) -> tuple[Hole, ...]:
        """The holes a needle may use (the tandem channel excluded)."""
        return tuple(h for h in self.holes if h.kind == "needle")


def load_template_csv(path: Path, name: str | None = None) -> Template:
    """Read a template layout: CSV with ``hole_id,x_mm,y_mm[,kind]``; lines starting with ``#`` are comments.

    The comment lines are kept as the template's ``source`` (its citation).
    """
    text = Path(path).read_text(encoding="utf-8").splitlines()
    comments = [line[1:].strip() for line in text if line.startswith("#")]
    reader = csv.DictReader(line for line in text if line.strip() and not line.startswith("#"))
    missing = {"hole_id", "x_mm", "y_mm"} - set(reader.fieldnames or ())
    if missing:
        raise PlanInputError(f"template {path}: missing column(s) {sorted(missing)}; need hole_id,x_mm,y_mm")
    try:
        holes = tuple(
            Hole(r["hole_id"], (float(r["x_mm"]), float(r["y_mm"])), r.get("kind") or "needle") for r in reader
        )
    except ValueError as exc:
        raise PlanInputError(f"template {path}: {exc}") from None
    return Template(name or Path(path).stem, holes, " ".join(comments))


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
