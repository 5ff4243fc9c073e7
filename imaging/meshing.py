"""Contours -> masks, volumes and watertight meshes.

CLOSED_PLANAR contours of one ROI are filled slice by slice with the even-odd rule (nested contours and
holes as DICOM intends) by an exact scan-line rasteriser working in the voxel index frame of a grid, so
oblique grids work too. Each contour is taken to cover its slice's slab (half a slice spacing on each side).

* :func:`roi_mask` : boolean mask on a grid (a voxel is in when its centre is inside).
* :func:`roi_coverage` : fraction of each voxel inside (anti-aliased along rows, supersampled along columns).
* :func:`roi_mesh` : watertight triangle mesh (LPS mm) by marching cubes (scikit-image) on the coverage,
  optionally smoothed (Taubin) and decimated; works from the contours alone when no grid is given.
* :func:`structure_volume_cc` : volume in cm³ from the coverage.
"""

from __future__ import annotations

import importlib.util
import math
import warnings
from collections.abc import Sequence

import numpy as np
import trimesh

from reachplan.imaging.contour_checks import encloses_no_area
from reachplan.imaging.errors import MeshDecimationWarning, StructureError
from reachplan.imaging.types import Grid, Roi

#: largest in-plane pixel (mm) of the grid built from the contours when no grid is given
DEFAULT_PIXEL_MM = 1.0
#: without an explicit ``pixel_mm`` the in-plane pixel is refined until a ROI's smallest in-plane extent spans
#: this many pixels (small ROIs keep their volume through marching cubes), but not below MIN_AUTO_PIXEL_MM
PIXELS_ACROSS = 20
MIN_AUTO_PIXEL_MM = 0.2
#: largest grid (voxels) a single ROI is rasterised on (float32 coverage: 4 bytes per voxel)
MAX_VOXELS = 100_000_000


def _closed_contours(roi: Roi) -> list[np.ndarray]:
    polys = [c.points_mm for c in roi.contours if c.geometric_type == "CLOSED_PLANAR" and len(c.points_mm) >= 3
             and not encloses_no_area(c.points_mm)]  # the reader warned about those enclosing no area
    if not polys:
        raise StructureError(f"ROI {roi.name!r} has no closed planar contour of at least 3 points that encloses an "
                             "area; it cannot be filled or meshed")
    return polys


# --------------------------------------------------------------------------------------------------
# Scan-line rasteriser (index frame: u = column coordinate i, v = row coordinate j)
# --------------------------------------------------------------------------------------------------


def _crossings(polys_uv: Sequence[np.ndarray], v0: float, dv: float, n_rows: int) -> tuple[np.ndarray, np.ndarray]:
    """Where the rows ``v = v0 + r dv`` cross the polygons' edges (half-open rule, so counts are even).

    Returns
    -------
    rows : (m,) int
        Row index of each crossing.
    u : (m,) float
        Its column coordinate, index units.
    """
    a = np.concatenate(polys_uv)
    b = np.concatenate([np.roll(p, -1, axis=0) for p in polys_uv])
    vmin, vmax = np.minimum(a[:, 1], b[:, 1]), np.maximum(a[:, 1], b[:, 1])
    r0 = np.clip(np.ceil((vmin - v0) / dv), 0, n_rows).astype(np.int64)
    r1 = np.clip(np.ceil((vmax - v0) / dv), 0, n_rows).astype(np.int64)
    count = r1 - r0
    keep = count > 0
    a, b, r0, count = a[keep], b[keep], r0[keep], count[keep]
    edge = np.repeat(np.arange(len(a)), count)
    start = np.repeat(np.cumsum(count) - count, count)
    rows = r0[edge] + (np.arange(len(edge)) - start)
    v = v0 + rows * dv
    ea, eb = a[edge], b[edge]
    u = ea[:, 0] + (v - ea[:, 1]) * (eb[:, 0] - ea[:, 0]) / (eb[:, 1] - ea[:, 1])
    return rows, u


def _row_parity(rows: np.ndarray, u: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Crossings sorted along each row with +1 for leaving the inside (odd rank) and -1 for entering."""
    order = np.lexsort((u, rows))
    rows, u = rows[order], u[order]
    first = np.flatnonzero(np.r_[True, rows[1:] != rows[:-1]])
    run = np.diff(np.r_[first, len(rows)])
    rank = np.arange(len(rows)) - np.repeat(first, run)
    sign = np.where(rank % 2 == 1, 1.0, -1.0)
    return rows, u, sign


def _coverage_slice(polys_uv: Sequence[np.ndarray], nj: int, ni: int, supersample: int) -> np.ndarray:
    """Fraction of each pixel inside the even-odd union of ``polys_uv`` (each (n, 2) in index units).

    Exact along rows (u), ``supersample`` sub-rows per pixel along columns (v). Returns (nj, ni) float32.
    """
    s = supersample
    n_rows = nj * s
    rows, u = _crossings(polys_uv, -0.5 + 0.5 / s, 1.0 / s, n_rows)
    if len(rows) == 0:
        return np.zeros((nj, ni), dtype=np.float32)
    rows, u, sign = _row_parity(rows, u)
    p = u + 0.5  # pixel i covers p in [i, i + 1]
    fl = np.floor(p)
    frac = np.where((fl >= 0) & (fl < ni), p - fl, 0.0)
    col = np.clip(fl, 0, ni).astype(np.int64)
    width = ni + 1
    size = n_rows * width
    diff = np.bincount(rows * width, weights=sign, minlength=size)
    diff -= np.bincount(rows * width + col, weights=sign, minlength=size)
    part = np.bincount(rows * width + np.minimum(col, ni), weights=sign * frac, minlength=size)
    cov = np.cumsum(diff.reshape(n_rows, width), axis=1) + part.reshape(n_rows, width)
    return cov[:, :ni].reshape(nj, s, ni).mean(axis=1).astype(np.float32)


def _inside_slice(polys_uv: Sequence[np.ndarray], nj: int, ni: int) -> np.ndarray:
    """Even-odd test of the pixel centres ``(i, j)``. Returns (nj, ni) bool."""
    rows, u = _crossings(polys_uv, 0.0, 1.0, nj)
    if len(rows) == 0:
        return np.zeros((nj, ni), dtype=bool)
    col = np.clip(np.floor(u) + 1, 0, ni).astype(np.int64)  # first pixel centre right of the crossing
    counts = np.bincount(rows * (ni + 1) + col, minlength=nj * (ni + 1)).reshape(nj, ni + 1)
    return (np.cumsum(counts, axis=1)[:, :ni] % 2).astype(bool)


# --------------------------------------------------------------------------------------------------
# Contours in a grid's index frame
# --------------------------------------------------------------------------------------------------


def _slices_in_grid(roi: Roi, grid: Grid) -> dict[int, list[np.ndarray]]:
    """Return the closed contours of ``roi`` in the index frame of ``grid``: ``{k: [(n, 2) (i, j) ...]}``.

    Raises
    ------
    StructureError
        A contour does not lie in one plane of the grid, or contours on different planes fall onto the same
        slice of the grid.
    """
    out: dict[int, list[np.ndarray]] = {}
    plane_of: dict[int, float] = {}
    normal = np.cross(grid.patient_from_index[:3, 0], grid.patient_from_index[:3, 1])
    normal /= np.linalg.norm(normal)
    for pts in _closed_contours(roi):
        ijk = grid.to_index(pts)
        k = ijk[:, 2]
        if k.max() - k.min() > 0.2:
            raise StructureError(
                f"ROI {roi.name!r} has a contour that is not in one slice plane of the grid "
                f"(spans {k.max() - k.min():.2f} slices); mesh it without a grid or use the images it was drawn on"
            )
        kk = round(float(k.mean()))
        d = float(np.mean(pts @ normal))
        if kk in plane_of and abs(plane_of[kk] - d) > 1e-3 * max(1.0, abs(d)) + 1e-2:
            raise StructureError(
                f"ROI {roi.name!r} has contours on planes {plane_of[kk]:.2f} and {d:.2f} mm that fall onto the "
                "same slice of the grid; mesh it without a grid or use the images it was drawn on"
            )
        plane_of[kk] = d
        out.setdefault(kk, []).append(ijk[:, :2])
    return out


def roi_mask(roi: Roi, grid: Grid) -> np.ndarray:
    """Rasterise a ROI's closed planar contours on ``grid`` into a boolean mask (even-odd filling).

    A voxel is inside when its centre is inside the contours of its slice; each contour is assigned to the
    nearest slice; contours outside the grid are left out.

    Parameters
    ----------
    roi : Roi
        Its CLOSED_PLANAR contours are used (LPS mm).
    grid : Grid
        The voxel grid, usually that of the images the contours were drawn on.

    Returns
    -------
    mask : (nk, nj, ni) bool
        ``grid.shape``, indexed ``[k, j, i]``.

    Raises
    ------
    StructureError
        No closed contour, a contour that does not lie in one slice plane of ``grid``, or contours on two
        planes that fall onto one slice.
    """
    nk, nj, ni = grid.shape
    mask = np.zeros(grid.shape, dtype=bool)
    for k, polys in _slices_in_grid(roi, grid).items():
        if 0 <= k < nk:
            mask[k] = _inside_slice(polys, nj, ni)
    return mask


def roi_coverage(roi: Roi, grid: Grid, supersample: int = 4) -> np.ndarray:
    """Compute the fraction (0..1) of each voxel of ``grid`` inside the ROI (contours cover their whole slab).

    Parameters
    ----------
    roi : Roi
        As for :func:`roi_mask`.
    grid : Grid
        As for :func:`roi_mask`.
    supersample : int
        Sub-rows per pixel (exact along rows); at least 1.

    Returns
    -------
    coverage : (nk, nj, ni) float32
        Voxel fractions on ``grid``, indexed ``[k, j, i]``.

    Raises
    ------
    ValueError
        ``supersample < 1``.
    StructureError
        As for :func:`roi_mask`.
    """
    if supersample < 1:
        raise ValueError(f"supersample must be >= 1, got {supersample}")
    nk, nj, ni = grid.shape
    cov = np.zeros(grid.shape, dtype=np.float32)
    for k, polys in _slices_in_grid(roi, grid).items():
        if 0 <= k < nk:
            cov[k] = _coverage_slice(polys, nj, ni, supersample)
    return np.clip(cov, 0.0, 1.0, out=cov)


# --------------------------------------------------------------------------------------------------
# A grid that fits a ROI
# --------------------------------------------------------------------------------------------------


def _newell_normal(pts: np.ndarray) -> np.ndarray:
    """Area vector (mm², (3,)) of a closed polygon by Newell's method."""
    a, b = pts, np.roll(pts, -1, axis=0)
    return 0.5 * np.cross(a, b).sum(axis=0)


def contour_plane_frame(roi: Roi, slice_spacing_mm: float | None = None) -> tuple[np.ndarray, np.ndarray, float]:
    """Find the common plane of a ROI's closed contours and the positions of its slices.

    Parameters
    ----------
    roi : Roi
        Its CLOSED_PLANAR contours are used (LPS mm).
    slice_spacing_mm : float, optional
        The slice spacing, mm; needed when all contours lie on one plane.

    Returns
    -------
    axes : (3, 3) float, LPS
        Columns u, v, n: orthonormal, right-handed; n is the contour normal (+z for axial contours).
    positions_mm : (m,) float, mm
        Sorted distinct plane positions along n (``n · x`` with x in LPS).
    spacing_mm : float, mm
        The slice spacing: the smallest gap between planes, or ``slice_spacing_mm`` when given.

    Raises
    ------
    StructureError
        Contours not planar or not parallel, plane positions not on a regular grid, a single plane
        without ``slice_spacing_mm``.
    """
    polys = _closed_contours(roi)
    areas = [_newell_normal(p) for p in polys]
    n = areas[int(np.argmax([np.linalg.norm(a) for a in areas]))]
    if np.linalg.norm(n) < 1e-9:
        raise StructureError(f"ROI {roi.name!r}: contours enclose no area; cannot find their plane")
    n = n / np.linalg.norm(n)
    axis = int(np.argmax(np.abs(n)))
    if n[axis] < 0:
        n = -n
    if abs(abs(n[axis]) - 1) < 1e-6:
        n = np.eye(3)[axis]
    d = [p @ n for p in polys]
    extent = max(float(np.ptp(np.concatenate(polys), axis=0).max()), 1.0)
    if max(float(np.ptp(x)) for x in d) > 1e-3 * extent + 0.05:
        raise StructureError(f"ROI {roi.name!r}: closed contours are not planar or not parallel; it cannot be "
                             "stacked into slices")
    pos = np.sort(np.array([float(np.mean(x)) for x in d]))
    distinct = pos[np.r_[True, np.diff(pos) > 1e-3]]
    if slice_spacing_mm is not None:
        h = float(slice_spacing_mm)
    elif len(distinct) > 1:
        h = float(np.diff(distinct).min())
    else:
        raise StructureError(f"ROI {roi.name!r} has contours on a single plane; its thickness is unknown: give a "
                             "grid or slice_spacing_mm")
    k = (distinct - distinct[0]) / h
    if np.abs(k - np.round(k)).max() > 0.1:
        raise StructureError(f"ROI {roi.name!r}: contour planes are not evenly spaced (smallest gap {h:.3g} mm); "
                             "give the image grid to mesh it on")
    ref = np.eye(3)[0] if axis != 0 else np.eye(3)[1]
    u = ref - (ref @ n) * n
    u /= np.linalg.norm(u)
    v = np.cross(n, u)
    return np.column_stack([u, v, n]), distinct, h


def roi_contains(roi: Roi, points_mm: np.ndarray, slice_spacing_mm: float | None = None) -> np.ndarray:
    """Tell which points lie inside a ROI's closed contours (even-odd rule; each contour covers its slice's slab).

    Parameters
    ----------
    roi : Roi
        Its CLOSED_PLANAR contours are used (LPS mm).
    points_mm : (n, 3) float, mm, LPS
        The points.
    slice_spacing_mm : float, optional
        The slice spacing, mm (the image grid's); needed when all contours lie on one plane.

    Returns
    -------
    (n,) bool
        Inside: within half a slice of a contour plane and inside that plane's contours.

    Raises
    ------
    StructureError
        Contours that do not stack into slices (see :func:`contour_plane_frame`).
    """
    axes, planes, h = contour_plane_frame(roi, slice_spacing_mm)
    local = np.atleast_2d(np.asarray(points_mm, dtype=float)) @ axes
    polys = [p @ axes for p in _closed_contours(roi)]
    plane_of = [int(np.abs(planes - float(np.mean(p[:, 2]))).argmin()) for p in polys]
    out = np.zeros(len(local), dtype=bool)
    for n, (u, v, d) in enumerate(local):
        k = int(np.abs(planes - d).argmin())
        if abs(planes[k] - d) > 0.5 * h + 1e-6:
            continue
        crossings = 0
        for poly, plane in zip(polys, plane_of, strict=True):
            if plane != k:
                continue
            a, b = poly[:, :2], np.roll(poly[:, :2], -1, axis=0)
            spans = (a[:, 1] > v) != (b[:, 1] > v)  # the half-open rule: a vertex on the ray counts once
            with np.errstate(divide="ignore", invalid="ignore"):
                x = a[:, 0] + (v - a[:, 1]) * (b[:, 0] - a[:, 0]) / (b[:, 1] - a[:, 1])
            crossings += int(np.count_nonzero(spans & (x > u)))
        out[n] = crossings % 2 == 1
    return out


def fit_grid(
    roi: Roi, grid: Grid | None = None, pixel_mm: float | None = None, pad_pixels: int = 2
) -> Grid:
    """Build a grid that holds ``roi`` with empty voxels all around (for marching cubes and volumes).

    With ``grid``: the grid's slices and orientation, cropped to the ROI, padded by one slice below and
    above, in-plane pixels refined to about ``pixel_mm``. Without: a grid built from the contours (their
    plane, their slice spacing, ``pixel_mm`` in-plane).

    Parameters
    ----------
    roi : Roi
        Its CLOSED_PLANAR contours are used (LPS mm).
    grid : Grid, optional
        The image grid the contours were drawn on.
    pixel_mm : float, optional
        In-plane pixel size, mm. None picks the grid's pixel (or :data:`DEFAULT_PIXEL_MM`), refined so that
        the ROI spans at least :data:`PIXELS_ACROSS` pixels (not below :data:`MIN_AUTO_PIXEL_MM`).
    pad_pixels : int
        Empty pixels added on each in-plane side.

    Returns
    -------
    Grid
        ``patient_from_index`` maps to LPS mm.

    Raises
    ------
    ValueError
        ``pixel_mm`` not a positive number.
    StructureError
        Contours that do not stack into slices, or a grid of more than :data:`MAX_VOXELS` voxels.
    """
    if pixel_mm is not None and not (np.isfinite(pixel_mm) and pixel_mm > 0):
        raise ValueError(f"pixel_mm must be a positive number of mm, got {pixel_mm}")
    pts = np.concatenate(_closed_contours(roi))
    frame = contour_plane_frame(roi) if grid is None else None
    if pixel_mm is None:
        base = float(min(grid.spacing_mm[:2])) if grid is not None else DEFAULT_PIXEL_MM
        axes = frame[0] if frame is not None else grid.patient_from_index[:3, :3]  # type: ignore[union-attr]
        axes = axes[:, :2] / np.linalg.norm(axes[:, :2], axis=0)
        extent = float(np.ptp(pts @ axes, axis=0).min())
        pixel_mm = min(base, max(MIN_AUTO_PIXEL_MM, extent / PIXELS_ACROSS))
    if grid is not None:
        ijk = grid.to_index(pts)
        spacing = grid.spacing_mm
        f = max(1, round(float(min(spacing[:2]) / pixel_mm)))
        lo = np.floor(ijk.min(axis=0)) - np.array([pad_pixels, pad_pixels, 0])
        hi = np.ceil(ijk.max(axis=0)) + np.array([pad_pixels, pad_pixels, 0])
        k0, k1 = round(float(ijk[:, 2].min())) - 1, round(float(ijk[:, 2].max())) + 1
        index_from_new = np.diag([1.0 / f, 1.0 / f, 1.0, 1.0])
        index_from_new[:3, 3] = [lo[0], lo[1], k0]
        shape = (k1 - k0 + 1, int((hi[1] - lo[1]) * f) + 1, int((hi[0] - lo[0]) * f) + 1)
        return _checked_grid(roi, shape, grid.patient_from_index @ index_from_new)
    assert frame is not None
    axes, planes, h = frame
    px = pixel_mm
    local = pts @ axes  # (u, v, n) coordinates
    lo = local.min(axis=0)[:2] - pad_pixels * px
    hi = local.max(axis=0)[:2] + pad_pixels * px
    n_k = round(float((planes[-1] - planes[0]) / h)) + 3
    m = np.eye(4)
    m[:3, :3] = axes * [px, px, h]
    m[:3, 3] = axes @ np.array([lo[0], lo[1], planes[0] - h])
    shape = (n_k, math.ceil((hi[1] - lo[1]) / px) + 1, math.ceil((hi[0] - lo[0]) / px) + 1)
    return _checked_grid(roi, shape, m)


def _checked_grid(roi: Roi, shape: tuple[int, int, int], m: np.ndarray) -> Grid:
    n = float(np.prod(np.asarray(shape, dtype=float)))
    if n > MAX_VOXELS:
        extent = np.asarray(shape) * np.linalg.norm(m[:3, :3], axis=0)[::-1]
        raise StructureError(f"ROI {roi.name!r} spans {extent[2]:.0f} x {extent[1]:.0f} x {extent[0]:.0f} mm, "
                             f"{n:.2g} voxels to rasterise; check its coordinates or pass a larger pixel_mm")
    return Grid(shape, m)


# --------------------------------------------------------------------------------------------------
# Meshes and volumes
# --------------------------------------------------------------------------------------------------


def roi_mesh(
    roi: Roi,
    grid: Grid | None = None,
    *,
    pixel_mm: float | None = None,
    supersample: int = 4,
    step_size: int = 1,
    z_supersample: int | None = None,
    smooth_iterations: int = 0,
    max_faces: int | None = None,
) -> trimesh.Trimesh:
    """Mesh a ROI's closed planar contours into a watertight triangle mesh in LPS mm.

    Parameters
    ----------
    roi : Roi
        Its CLOSED_PLANAR contours are used (LPS mm).
    grid : Grid, optional
        The image grid the contours were drawn on (its slices and orientation are used); None builds a grid
        from the contours themselves (works from an RT Structure Set alone).
    pixel_mm : float, optional
        In-plane pixel size of the meshing grid, mm (level of detail); default: the grid's own pixels
        (:data:`DEFAULT_PIXEL_MM` without a grid), refined for small ROIs (see :func:`fit_grid`).
    supersample : int
        Sub-rows per pixel of the anti-aliased coverage.
    step_size : int
        Marching cubes step (coarser mesh for larger values).
    z_supersample : int, optional
        Sub-slices per slice (each a copy of its slab's coverage) so that marching cubes cuts the slab
        corners less; default ``ceil(slice spacing / pixel size)``.
    smooth_iterations : int
        Taubin smoothing passes (volume-preserving to first order), 0 = none.
    max_faces : int, optional
        Decimate to at most this many faces (needs the optional ``fast-simplification`` package); when that
        breaks watertightness, twice as many are tried, and so on (the result may then exceed it, with a
        :class:`~reachplan.imaging.errors.MeshDecimationWarning`).

    Returns
    -------
    trimesh.Trimesh
        Watertight, outward normals, vertices (n, 3) float LPS mm. Each contour covers its slab of one slice
        spacing, so the mesh volume equals the contour areas times the slice spacing.

    Raises
    ------
    StructureError
        No closed contours, contours that do not stack, a mesh that is not watertight, or ``max_faces``
        without the ``fast-simplification`` package.
    """
    from skimage.measure import marching_cubes

    fit = fit_grid(roi, grid, pixel_mm)
    cov = roi_coverage(roi, fit, supersample)
    if not cov.any():
        raise StructureError(f"ROI {roi.name!r}: contours enclose no voxel; cannot mesh it")
    spacing = fit.spacing_mm
    m = z_supersample or max(1, math.ceil(spacing[2] / min(spacing[:2]) - 1e-6))
    if m > 1:  # sub-slice centres at k + (t + 0.5) / m - 0.5; the zero padding slices stay zero
        cov = np.repeat(cov, m, axis=0)
    # A sample exactly at the iso-level puts marching-cubes vertices of neighbouring cells on one grid point;
    # merged, they make non-manifold edges (seen on the clinical case, seed 5). Nudge such samples off the level
    # by far less than any coverage step (the surface moves by 1e-4 voxel at most).
    cov = np.where(cov == np.float32(0.5), np.float32(0.5 + 1e-4), cov)
    verts, faces, _, _ = marching_cubes(cov, level=0.5, step_size=step_size, allow_degenerate=False)
    ijk = verts[:, ::-1].copy()
    ijk[:, 2] = (ijk[:, 2] + 0.5) / m - 0.5
    mesh = trimesh.Trimesh(fit.to_patient(ijk), faces, process=True)
    if _signed_volume_mm3(mesh) < 0:
        mesh.invert()
    if smooth_iterations:
        trimesh.smoothing.filter_taubin(mesh, iterations=smooth_iterations)
    if not mesh.is_watertight:
        raise StructureError(f"ROI {roi.name!r}: the mesh is not watertight; try another pixel_mm")
    if max_faces is not None and len(mesh.faces) > max_faces:
        mesh = _decimate(mesh, max_faces, roi.name)
    return mesh


def _signed_volume_mm3(mesh: trimesh.Trimesh) -> float:
    """Return a closed mesh's signed volume (mm³; negative when its normals point inward).

    The divergence theorem over its triangles, the sign of ``mesh.volume`` without the rest of the mass properties
    (centre of mass, inertia) that trimesh computes with it.
    """
    v = np.asarray(mesh.vertices, dtype=float)[np.asarray(mesh.faces)]
    return float(np.einsum("ij,ij->", v[:, 0], np.cross(v[:, 1], v[:, 2]))) / 6.0


def _decimate(mesh: trimesh.Trimesh, max_faces: int, name: str) -> trimesh.Trimesh:
    """Quadric decimation to at most ``max_faces`` faces that keeps the mesh watertight.

    Tries ``max_faces``, then twice as many, ...; when no decimated mesh is watertight the full mesh is kept
    with a :class:`~reachplan.imaging.errors.MeshDecimationWarning`.
    """
    if importlib.util.find_spec("fast_simplification") is None:  # optional dependency of trimesh's decimation
        raise StructureError("decimating meshes needs the optional package fast-simplification; "
                             "install it or leave max_faces unset")
    target = max_faces
    while target < len(mesh.faces):
        small = mesh.simplify_quadric_decimation(face_count=target)
        small = trimesh.Trimesh(small.vertices, small.faces, process=True, validate=True)  # drop degenerate faces
        if small.is_watertight and small.volume > 0:
            return small
        target *= 2
    warnings.warn(MeshDecimationWarning(
        f"ROI {name!r}: no watertight mesh with at most {max_faces} faces; kept all {len(mesh.faces)}"), stacklevel=3)
    return mesh


def structure_volume_cc(roi: Roi, grid: Grid | None = None, pixel_mm: float | None = None) -> float:
    """Compute the volume (cm³) of a ROI's closed planar contours: coverage of a fitted grid times voxel volume.

    Each contour covers its slice's slab; with ``grid`` the grid's slices are used, otherwise the contours'.

    Parameters
    ----------
    roi : Roi
        As for :func:`fit_grid`.
    grid : Grid or None
        As for :func:`fit_grid`.
    pixel_mm : float or None
        As for :func:`fit_grid`, mm.

    Returns
    -------
    float
        Volume in cm³.

    Raises
    ------
    StructureError
        As for :func:`fit_grid`.
    """
    fit = fit_grid(roi, grid, pixel_mm)
    cov = roi_coverage(roi, fit)
    voxel_mm3 = abs(float(np.linalg.det(fit.patient_from_index[:3, :3])))
    return float(cov.sum(dtype=np.float64)) * voxel_mm3 / 1000.0
