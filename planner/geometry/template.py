"""Template pose in the patient and the hole frames (layouts are :mod:`reachplan.plugins.templates`).

Template frame: origin at the template centre (the obturator axis on the template plane), ``x``/``y`` in
the template plane, ``+z`` the insertion direction. A template is placed with a rigid 4x4
``patient_from_template`` (LPS mm).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from reachplan.imaging.brachy_plan import RtPlan
from reachplan.imaging.types import Roi, StructureSet
from reachplan.planner.errors import PlanInputError
from reachplan.plugins.applicators import BUILTIN_KINDS, ApplicatorKind, applicators_from_rtplan, channel_label
from reachplan.plugins.errors import ApplicatorError
from reachplan.plugins.templates import Hole, Template


def hole_frames(
    template: Template, patient_from_template: np.ndarray, holes: tuple[Hole, ...] | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Entry points and insertion directions of holes in the patient.

    Parameters
    ----------
    template : Template
        The needle template.
    patient_from_template : (4, 4) float, template frame -> LPS mm
        The template's pose.
    holes : tuple of Hole or None
        The holes (``xy_mm`` in the template plane, mm); None: the template's needle holes.

    Returns
    -------
    entry_mm : (n, 3) float, mm, LPS
        Each hole's centre on the template plane.
    direction : (n, 3) float, unit vectors, LPS
        The template's +z, the same for every hole.
    """
    holes = template.needle_holes if holes is None else holes
    m = np.asarray(patient_from_template, dtype=float)
    xy = np.array([h.xy_mm for h in holes], dtype=float).reshape(-1, 2)
    local = np.column_stack([xy, np.zeros(len(xy)), np.ones(len(xy))])
    entry = (local @ m.T)[:, :3]
    direction = np.broadcast_to(m[:3, 2] / np.linalg.norm(m[:3, 2]), entry.shape).copy()
    return entry, direction


def check_rigid(patient_from_template: np.ndarray) -> np.ndarray:
    """Validate a rigid 4x4 transform (orthonormal rotation, det +1, last row 0 0 0 1).

    Parameters
    ----------
    patient_from_template : (4, 4) array-like
        The transform to check.

    Returns
    -------
    (4, 4) float
        The same transform as a float array.

    Raises
    ------
    PlanInputError
        Not a finite 4x4 matrix, or not rigid.
    """
    m = np.asarray(patient_from_template, dtype=float)
    if m.shape != (4, 4) or not np.all(np.isfinite(m)):
        raise PlanInputError("patient_from_template must be a finite 4x4 matrix")
    r = m[:3, :3]
    if not np.allclose(r.T @ r, np.eye(3), atol=1e-6) or np.linalg.det(r) < 0 or not np.allclose(m[3], [0, 0, 0, 1]):
        raise PlanInputError("patient_from_template must be rigid (orthonormal rotation, det +1, last row 0 0 0 1)")
    return m


@dataclass(frozen=True, eq=False)
class TemplatePose:
    """Where the template sits and how that was found.

    Parameters
    ----------
    patient_from_template : (4, 4) float, rigid, template frame -> LPS mm
    method : one line saying where the pose came from (printed and saved with the plan)
    """

    patient_from_template: np.ndarray
    method: str

    def __post_init__(self) -> None:
        m = check_rigid(self.patient_from_template).copy()
        m.setflags(write=False)
        object.__setattr__(self, "patient_from_template", m)

    def to_json(self) -> dict[str, object]:
        """Return the pose as JSON-ready values.

        Returns
        -------
        dict of str to object
            ``method`` and ``patient_from_template`` (4 x 4 nested lists, template frame -> LPS mm, 6 decimals).
        """
        return {"method": self.method,
                "patient_from_template": [[round(float(v), 6) for v in row] for row in self.patient_from_template]}


def pose_from_axis(origin_mm: np.ndarray | tuple[float, float, float],
                   axis: np.ndarray | tuple[float, float, float]) -> np.ndarray:
    """``patient_from_template`` from the template centre and the insertion direction.

    Template ``+z`` is ``axis`` (normalised); template ``+x`` is the patient's left (LPS ``+x``) made
    perpendicular to the axis, and ``+y = z × x`` (the patient's posterior for an axis along ``+z``). When the
    axis lies within 10 degrees of left-right, ``+y`` is taken from the patient's posterior (LPS ``+y``) instead
    and ``+x = y × z``, so every axis gives one deterministic pose.

    Parameters
    ----------
    origin_mm : (3,) float, mm, LPS: the template centre (the obturator axis on the template plane)
    axis : (3,) float, LPS: the insertion direction (any non-zero length)

    Returns
    -------
    patient_from_template : (4, 4) float
    """
    o = np.asarray(origin_mm, dtype=float).reshape(-1)
    a = np.asarray(axis, dtype=float).reshape(-1)
    if o.shape != (3,) or a.shape != (3,) or not (np.all(np.isfinite(o)) and np.all(np.isfinite(a))):
        raise PlanInputError("the template origin and axis must be three finite numbers each (mm, LPS)")
    norm = float(np.linalg.norm(a))
    if norm < 1e-9:
        raise PlanInputError("the template axis has zero length; give the insertion direction, e.g. 0,0,1")
    z = a / norm
    if abs(z[0]) < np.cos(np.radians(10.0)):
        x = np.array([1.0, 0.0, 0.0]) - z[0] * z
        x /= np.linalg.norm(x)
        y = np.cross(z, x)
    else:
        y = np.array([0.0, 1.0, 0.0]) - z[1] * z
        y /= np.linalg.norm(y)
        x = np.cross(y, z)
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = x, y, z, o
    return m


def _principal_axis(pts: np.ndarray) -> np.ndarray:
    """Return the unit principal direction of ``(n, 3)`` points (sign arbitrary)."""
    centre = pts.mean(axis=0)
    _, _, vt = np.linalg.svd(pts - centre, full_matrices=False)
    return np.asarray(vt[0], dtype=float)


def pose_from_obturator(obturator: Roi, depth_mm: float = 60.0) -> np.ndarray:
    """``patient_from_template`` for a template that sits on the obturator (or a vaginal cylinder ROI).

    The obturator axis is the principal axis of its contour points; its cranial end (larger patient z,
    the end inside the patient) is the tip, half a contour spacing beyond the last contour. The template
    plane is ``depth_mm`` behind the tip along the axis (how far the obturator is inserted beyond the
    template; 60 mm is our documented default, the
    vaginal length of the phantom); template ``+z`` points along the axis into the patient; the in-plane
    orientation is that of :func:`pose_from_axis`.

    Parameters
    ----------
    obturator : Roi
        The obturator (or vaginal cylinder) ROI, closed contours in LPS mm.
    depth_mm : float, mm
        How far the obturator tip lies beyond the template plane.

    Returns
    -------
    patient_from_template : (4, 4) float
    """
    closed = [c for c in obturator.contours if c.geometric_type == "CLOSED_PLANAR"]
    pts = np.concatenate([c.points_mm for c in closed]) if closed else np.zeros((0, 3))
    if len(pts) < 4:
        raise PlanInputError(f"ROI {obturator.name!r} has too few contour points to find the obturator axis; "
                             "give the pose with --template-origin/--template-axis or --template-pose")
    centre = pts.mean(axis=0)
    axis = _principal_axis(pts)
    axis = axis if axis[2] >= 0 else -axis
    proj = (pts - centre) @ axis
    # each planar contour stands for a slab one contour spacing thick: the tip is half a spacing beyond
    # the last contour's plane
    planes = np.unique(np.round([float(np.mean((c.points_mm - centre) @ axis)) for c in closed], 3))
    half = 0.5 * float(np.median(np.diff(planes))) if len(planes) > 1 else 0.0
    tip = centre + axis * (proj.max() + half)
    return pose_from_axis(tip - axis * depth_mm, axis)


#: Applicator kinds the template sits on, in order of preference: the vaginal obturator or cylinder (its tip), else
#: the tandem (its most proximal dwell).
SEAT_KINDS: tuple[tuple[str, ...], ...] = (("obturator", "cylinder"), ("tandem",))


def pose_from_channel(path_mm: np.ndarray, dwell_positions_mm: np.ndarray, tandem: bool,
                      depth_mm: float = 60.0) -> np.ndarray:
    """``patient_from_template`` from the centre line of a brachy plan's tandem or obturator channel.

    The path is written tip first (Eclipse, Oncentra: ``rtplan_conventions.md`` §7). The template sits on
    the vaginal obturator, whose axis continues the channel's part outside the uterus (Syed-Neblett: the
    tandem passes through the obturator's central bore). The reference point is the channel's tip for an
    obturator/cylinder channel, and for a tandem its most proximal dwell position, ASSUMED to lie at the
    external cervical os where the obturator tip rests. The axis is the principal axis of the path points at
    or proximal of the reference point (all points when fewer than two are), pointing toward the tip; the
    template plane is ``depth_mm`` (the obturator depth, 60 mm by default) behind the reference point; the
    in-plane orientation is that of :func:`pose_from_axis`.

    Parameters
    ----------
    path_mm : (k, 3) float, mm, LPS
        The channel's centre line, tip first.
    dwell_positions_mm : (n, 3) float, mm, LPS
        The channel's dwell positions (may be empty).
    tandem : bool
        Whether the channel is a tandem (else an obturator or cylinder).
    depth_mm : float, mm
        The obturator depth: the template plane lies this far behind the reference point.

    Returns
    -------
    (4, 4) float, template frame -> LPS mm
        ``patient_from_template``.

    Raises
    ------
    PlanInputError
        A centre line shorter than 1 mm.
    """
    path = np.asarray(path_mm, dtype=float).reshape(-1, 3)
    if len(path) < 2 or float(np.linalg.norm(path[-1] - path[0])) < 1.0:
        raise PlanInputError("the channel's centre line is shorter than 1 mm; give the pose with "
                             "--template-origin/--template-axis or --template-pose")
    tip = path[0]
    dwells = np.asarray(dwell_positions_mm, dtype=float).reshape(-1, 3)
    arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(path, axis=0), axis=1))])
    if tandem and len(dwells):
        # the dwell farthest from the tip along the path
        d = np.linalg.norm(path[None, :, :] - dwells[:, None, :], axis=2)
        depth_along = arc[np.argmin(d, axis=1)]
        ref = dwells[int(np.argmax(depth_along))]
        ref_arc = float(depth_along.max())
    else:
        ref, ref_arc = tip, 0.0
    part = path[arc >= ref_arc - 1e-9]
    part = part if len(part) >= 2 and float(np.ptp(part, axis=0).max()) > 1.0 else path
    axis = _principal_axis(part)
    if float(np.dot(axis, path[0] - path[-1])) < 0:
        axis = -axis
    return pose_from_axis(ref - axis * depth_mm, axis)


def pose_from_rtplan(rtplan: RtPlan, structures: StructureSet | None = None, depth_mm: float = 60.0,
                     kinds: Mapping[str, ApplicatorKind] = BUILTIN_KINDS,
                     assign: Mapping[str, str] | None = None) -> TemplatePose:
    """Find the template pose from the obturator or cylinder (preferred) or tandem channel of a brachy RT Plan.

    The plan's applicator channels are recognised by :func:`reachplan.plugins.applicators.applicators_from_rtplan`
    (applicator ID or channel ROI name, whole names of the ``kinds``; ``assign`` overrides); the first of
    :data:`SEAT_KINDS` found is used. Its centre line is the channel ROI's contour in ``structures`` or the plan's
    catheter sequence, else the dwell positions in order of relative position. See :func:`pose_from_channel`.

    Parameters
    ----------
    rtplan : RtPlan
        The brachy plan.
    structures : StructureSet, optional
        Its structure set (channel ROIs; must share the plan's Frame of Reference).
    depth_mm : float, mm
        How far the seat's reference point lies beyond the template plane.
    kinds : mapping of str to ApplicatorKind
        The applicator kinds (default: the built-in ones).
    assign : mapping of str to str, optional
        Applicator ID or channel ROI name -> kind name (``--applicator KIND=NAME``).

    Returns
    -------
    TemplatePose
        ``patient_from_template`` (4, 4) float, template frame -> LPS mm, and how it was found.

    Raises
    ------
    PlanInputError
        Another Frame of Reference than ``structures``, no brachy channel, no tandem, obturator or cylinder
        channel, no centre line, or a bad ``assign``.
    """
    where = f"RT Plan {Path(rtplan.path).name}"
    if structures is not None and rtplan.frame_of_reference_uid and structures.frame_of_reference_uid \
            and rtplan.frame_of_reference_uid != structures.frame_of_reference_uid:
        raise PlanInputError(f"{where} is in another Frame of Reference than the structure set; give the plan of "
                             "this case")
    if not rtplan.channels:
        raise PlanInputError(f"{where} has no brachy channels to place the template on")
    try:
        found = applicators_from_rtplan(rtplan, kinds, structures, assign)
    except ApplicatorError as exc:
        raise PlanInputError(f"{where}: {exc}") from None
    seats = [a for group in SEAT_KINDS for a in found if a.kind in group and a.channels]
    if not seats:
        roi_names = {r.number: r.name for r in structures.rois} if structures is not None else {}
        labels = [channel_label(c, roi_names) for c in rtplan.channels]
        raise PlanInputError(f"{where}: no channel is named as a tandem, obturator or cylinder (channels: "
                             f"{', '.join(map(repr, labels))}); name its kind with --applicator KIND=NAME or give "
                             "the pose with --template-origin/--template-axis or --template-pose")
    seat = seats[0]
    number = seat.plan_channels[0]
    channel = next(c for c in rtplan.channels if c.number == number)
    tandem = seat.kind == "tandem"
    m = pose_from_channel(seat.channels[0][::-1], channel.dwell_positions_mm, tandem, depth_mm)
    ref = "its most proximal dwell (the cervical os, assumed)" if tandem else "its tip"
    return TemplatePose(m, f"from {where}, channel {number} {seat.name!r} ({seat.how}; template {depth_mm:g} mm "
                           f"behind {ref})")
