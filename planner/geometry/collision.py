"""Clearance and collision of needle paths against organ meshes, with FCL.

A needle path is a polyline; it is checked as a chain of capsules of the needle's outer radius (one per
segment). Organs are watertight triangle meshes held as FCL BVH models. FCL's mesh distance measures to
the *surface* only, so a path that never crosses an organ's surface is tested once for lying inside it
(a connected path that does not cross a closed surface is either wholly inside or wholly outside).

Clearance is the smallest surface-to-surface distance (mm) between the needle (capsules of radius
``radius_mm``) and an organ; it is ``0.0`` when they touch or the needle enters the organ.
"""

from __future__ import annotations

import dataclasses
import itertools
from dataclasses import dataclass
from functools import cached_property

import fcl
import numpy as np
import trimesh

from reachplan._arrays import arc_length_mm
from reachplan.planner.errors import PlanInputError
from reachplan.planner.geometry.distance_field import DistanceField, inside_by_parity


@dataclass(frozen=True, eq=False)
class Organ:
    """An organ at risk (or bone) as a watertight mesh in LPS mm; its FCL model is built on first use.

    Parameters
    ----------
    name : str
        The organ's normalised name.
    mesh : trimesh.Trimesh
        Watertight triangle mesh, vertices in mm, LPS.
    bounds_mm : (2, 3) float, mm, LPS
        Axis-aligned box of the mesh (min, max).
    field : DistanceField or None
        Screen: FCL only for paths that may come within its confirm band; None measures every path with FCL.
    """

    name: str
    mesh: trimesh.Trimesh
    bounds_mm: np.ndarray  # (2, 3) float, mm, LPS: axis-aligned box (min, max)
    field: DistanceField | None = None  # screen: FCL only for paths that may come within its confirm band

    @cached_property
    def fcl_object(self) -> fcl.CollisionObject:
        """The mesh as an FCL BVH model; built when first needed (an organ the screen always clears never is).

        Returns
        -------
        fcl.CollisionObject
            The mesh (LPS mm) at the identity transform.
        """
        bvh = fcl.BVHModel()
        bvh.beginModel(len(self.mesh.faces), len(self.mesh.vertices))  # (triangles, vertices): its arrays sized once
        bvh.addSubModel(np.asarray(self.mesh.vertices, dtype=float), np.asarray(self.mesh.faces, dtype=np.int64))
        bvh.endModel()
        return fcl.CollisionObject(bvh, fcl.Transform())

    @cached_property
    def _triangles(self) -> np.ndarray:
        return np.ascontiguousarray(self.mesh.triangles, dtype=float)

    @cached_property
    def _inside(self) -> dict[tuple[float, float, float], bool]:
        return {}  # containment by point: the candidates of one template hole all start there

    def contains(self, point_mm: np.ndarray) -> bool:
        """Tell whether a point lies inside the organ.

        By ray parity (compiled, :func:`reachplan.planner.geometry.distance_field.inside_by_parity`) when the
        point is within the bounding box.

        Parameters
        ----------
        point_mm : (3,) float, mm, LPS
            The point.

        Returns
        -------
        bool
            True inside the mesh (cached per point).
        """
        q = np.asarray(point_mm, dtype=float).reshape(3)
        lo, hi = self.bounds_mm
        if not (np.all(q >= lo) and np.all(q <= hi)):
            return False
        key = (float(q[0]), float(q[1]), float(q[2]))
        if key not in self._inside:
            self._inside[key] = inside_by_parity(self._triangles, q)
        return self._inside[key]


def make_organ(name: str, mesh: trimesh.Trimesh) -> Organ:
    """Wrap a mesh (LPS mm) for collision queries.

    Parameters
    ----------
    name : str
        Name the organ goes by (normalised).
    mesh : trimesh.Trimesh
        Its triangle mesh (vertices in mm, LPS); must be watertight.

    Returns
    -------
    Organ
        Without a distance field (see :func:`with_distance_field`).

    Raises
    ------
    PlanInputError
        If the mesh is empty or not watertight (containment would be undefined).
    """
    if len(mesh.faces) == 0:
        raise PlanInputError(f"organ {name!r} has an empty mesh")
    if not mesh.is_watertight:
        raise PlanInputError(f"organ {name!r}: mesh is not watertight; re-mesh it from its mask")
    return Organ(name, mesh, np.asarray(mesh.bounds, dtype=float))


def _rotation_to(direction: np.ndarray) -> np.ndarray:
    """Rotation matrix taking +z to the unit vector ``direction``."""
    z = direction
    v = np.array([-z[1], z[0], 0.0])  # e3 x z
    c = z[2]
    if np.dot(v, v) < 1e-24:
        return np.eye(3) if c > 0 else np.diag([1.0, -1.0, -1.0])
    vx = np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])
    return np.eye(3) + vx + vx @ vx / (1.0 + c)


def _joints(path_mm: np.ndarray, radius_mm: float) -> np.ndarray:
    """Return the points a needle path's capsules join ((m, 3) float, mm), zero-length segments dropped.

    Raises :class:`PlanInputError` for a path that is not a finite (n, 3) array or a radius that is not positive.
    """
    p = np.asarray(path_mm, dtype=float)
    if p.ndim != 2 or p.shape[1] != 3 or len(p) == 0 or not np.all(np.isfinite(p)):
        raise PlanInputError("a needle path must be a finite (n, 3) array of points in mm")
    if radius_mm <= 0:
        raise PlanInputError(f"needle radius must be positive, got {radius_mm} mm")
    keep = np.concatenate([[True], np.linalg.norm(np.diff(p, axis=0), axis=1) >= 1e-9])
    return p[keep]


def capsule_chain(path_mm: np.ndarray, radius_mm: float) -> list[fcl.CollisionObject]:
    """FCL capsules of radius ``radius_mm`` along a needle path, one per segment.

    Zero-length segments are skipped; a single point becomes a sphere.

    Parameters
    ----------
    path_mm : (n, 3) float, mm, LPS
        Needle centreline.
    radius_mm : float, mm
        Needle radius (> 0).

    Returns
    -------
    list of fcl.CollisionObject
        One capsule per non-zero segment, in path order (one sphere for a single point).

    Raises
    ------
    PlanInputError
        A path that is not a finite (n, 3) array, or a radius that is not positive.
    """
    pts = _joints(path_mm, radius_mm)
    if len(pts) == 1:
        return [fcl.CollisionObject(fcl.Sphere(radius_mm), fcl.Transform(np.eye(3), pts[0]))]
    return [_capsule(a, b, radius_mm) for a, b in itertools.pairwise(pts)]


def _capsule(a: np.ndarray, b: np.ndarray, radius_mm: float) -> fcl.CollisionObject:
    """FCL capsule of radius ``radius_mm`` from ``a`` to ``b`` ((3,) float, mm, LPS; distinct points)."""
    seg = b - a
    length = float(np.linalg.norm(seg))
    return fcl.CollisionObject(fcl.Capsule(radius_mm, length), fcl.Transform(_rotation_to(seg / length), a + seg / 2))


@dataclass(frozen=True)
class Clearance:
    """Result of checking one path against one organ.

    Parameters
    ----------
    organ : str
        The name of the organ checked against.
    clearance_mm : float, mm
        Surface-to-surface distance from the needle to the organ (0.0 when touching or inside).
    collides : bool
        True when the needle touches, crosses or lies inside the organ.
    contact_s_mm : float or None, mm
        Arc length along the path (from its first point) where the needle first touches the organ, to within
        the check's resolution; None when clear.
    """

    organ: str
    clearance_mm: float
    collides: bool
    contact_s_mm: float | None = None


def _first_contact_s(a: np.ndarray, b: np.ndarray, radius_mm: float, organ: Organ, resolution_mm: float) -> float:
    """Arc length from ``a`` at which the capsule ``a``-``b`` first touches ``organ``."""
    length = float(np.linalg.norm(b - a))
    n = max(1, int(np.ceil(length / resolution_mm)))
    pts = a + np.outer(np.linspace(0.0, 1.0, n + 1), b - a)
    creq = fcl.CollisionRequest()
    for i, obj in enumerate(capsule_chain(pts, radius_mm)):
        if fcl.collide(obj, organ.fcl_object, creq, fcl.CollisionResult()):
            return length * i / n
    return length  # touching within numerical tolerance only at the far end


def path_clearance(
    path_mm: np.ndarray, radius_mm: float, organ: Organ, resolution_mm: float = 1.0
) -> Clearance:
    """Clearance of a needle path to one organ.

    Exact (FCL, one capsule per segment). With the organ's distance field, only the segments whose lower bound
    is at most the smallest upper bound are measured
    (:meth:`reachplan.planner.geometry.distance_field.DistanceField.segment_bounds`): any other is farther than
    some segment and clear of the organ, so the clearance, the collision and its first contact are unchanged.

    Parameters
    ----------
    path_mm : (n, 3) float, mm, LPS
        Needle centreline, checked as capsules of ``radius_mm``.
    radius_mm : float, mm
        Needle radius (> 0).
    organ : Organ
        The organ.
    resolution_mm : float, mm
        Arc-length resolution of the first contact.

    Returns
    -------
    Clearance
        Clearance (mm), whether it collides and where it first touches.

    Raises
    ------
    PlanInputError
        A path that is not a finite (n, 3) array, or a radius that is not positive.
    """
    pts = _joints(path_mm, radius_mm)
    measure: list[int] = list(range(max(len(pts) - 1, 1)))
    if organ.field is not None and len(pts) > 2:
        lower, upper = organ.field.segment_bounds(pts, radius_mm)
        measure = np.flatnonzero(lower <= upper.min()).tolist()  # path order: the first collision is the first
    caps = capsule_chain(pts, radius_mm) if len(pts) <= 2 else [_capsule(pts[i], pts[i + 1], radius_mm)
                                                                 for i in measure]
    s0 = arc_length_mm(pts)
    req, creq = fcl.DistanceRequest(), fcl.CollisionRequest()
    best = np.inf
    for obj, i in zip(caps, measure, strict=True):
        d = fcl.distance(obj, organ.fcl_object, req, fcl.DistanceResult())
        if d <= 0.0 and fcl.collide(obj, organ.fcl_object, creq, fcl.CollisionResult()):
            if len(pts) < 2:
                return Clearance(organ.name, 0.0, True, 0.0)
            s = s0[i] + _first_contact_s(pts[i], pts[i + 1], radius_mm, organ, resolution_mm)
            return Clearance(organ.name, 0.0, True, float(s))
        best = min(best, max(d, 0.0))
    if organ.contains(pts[0]):
        return Clearance(organ.name, 0.0, True, 0.0)
    return Clearance(organ.name, float(best), False, None)


def _box_gap_mm(lo_a: np.ndarray, hi_a: np.ndarray, lo_b: np.ndarray, hi_b: np.ndarray) -> float:
    """Return the distance (mm) between two axis-aligned boxes, 0 when they overlap.

    A lower bound on any distance between what they contain.
    """
    gap = np.maximum(0.0, np.maximum(lo_a - hi_b, lo_b - hi_a))
    return float(np.linalg.norm(gap))


def with_distance_field(organ: Organ, confirm_within_mm: float = np.inf, pitch_mm: float = 1.0,
                        reach_mm: float | None = None) -> Organ:
    """Return the organ with a :class:`DistanceField` screen (see :func:`check_path`).

    With a finite ``confirm_within_mm`` clearances proven beyond it are the field's
    estimates instead of FCL's.

    Parameters
    ----------
    organ : Organ
        The organ to screen.
    confirm_within_mm : float, mm
        Clearances whose lower bound is at most this are confirmed by FCL (infinite: all).
    pitch_mm : float, mm
        Grid pitch of the field.
    reach_mm : float or None, mm
        How far the field reaches beyond the mesh's box; None: the default (see
        :meth:`DistanceField.from_mesh`).

    Returns
    -------
    Organ
        A copy with ``field`` set.
    """
    f = DistanceField.from_mesh(organ.mesh, pitch_mm=pitch_mm, reach_mm=reach_mm, confirm_within_mm=confirm_within_mm)
    return dataclasses.replace(organ, field=f)


def check_path(path_mm: np.ndarray, radius_mm: float, organs: tuple[Organ, ...]) -> tuple[Clearance, ...]:
    """Clearance of one needle path against the organs that can matter.

    Broad phase first: organs are measured in order of the gap between their bounding box and the
    path's (inflated by ``radius_mm``); an organ whose gap exceeds the smallest clearance found so far is
    skipped, as it can neither touch the needle nor be the nearest organ. Organs with distance fields are
    screened first: one whose lower bound exceeds another's upper bound is skipped for the same reason, and one
    whose lower bound exceeds its field's ``confirm_within_mm`` (infinite unless set) gets the field's estimate.
    The rest is measured exactly with FCL, so the minimum clearance, the nearest organ and every collision are
    exact (with an infinite band); skipped organs are absent from the result.

    Parameters
    ----------
    path_mm : (n, 3) float, mm, LPS
        The needle's centreline, hole first.
    radius_mm : float, mm
        Outer radius of the needle.
    organs : tuple of Organ
        Organs at risk and bone.

    Returns
    -------
    tuple of Clearance
        One per organ measured, nearest boxes first; organs that cannot matter are absent.

    Raises
    ------
    PlanInputError
        A path that is not an (n, 3) array.
    """
    p = np.asarray(path_mm, dtype=float)
    if p.ndim != 2 or p.shape[1] != 3 or len(p) == 0:
        raise PlanInputError("a needle path must be a finite (n, 3) array of points in mm")
    lo, hi = p.min(axis=0) - radius_mm, p.max(axis=0) + radius_mm
    gaps = [_box_gap_mm(lo, hi, *o.bounds_mm) for o in organs]
    bounds = [o.field.path_clearance(p, radius_mm) if o.field is not None else None for o in organs]
    best_upper = min((b[2] for b in bounds if b is not None), default=np.inf)
    out: list[Clearance] = []
    best = np.inf
    for gap, organ, b in sorted(zip(gaps, organs, bounds, strict=True), key=lambda g: g[0]):
        if gap > best:
            break
        if b is not None and organ.field is not None and (b[1] > best_upper or b[1] > organ.field.confirm_within_mm):
            # the field proves the needle clear of this organ's surface; only a path wholly inside is left
            if organ.contains(p[0]):
                c = Clearance(organ.name, 0.0, True, 0.0)
            elif b[1] > best_upper:
                continue  # neither touched nor the nearest: absent, like the organs the box gap skips
            else:
                c = Clearance(organ.name, b[0], False, None)  # beyond the confirm band: the estimate
        else:
            c = path_clearance(p, radius_mm, organ)
        out.append(c)
        best = min(best, c.clearance_mm)
    return tuple(out)
