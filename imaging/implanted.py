"""Post-insertion images: thin plastic tubes (with or without a metal core) painted into a case's CT or MR.

The image a scanner gives after the implant is in: the case as painted (:func:`reachplan.imaging.phantom.phantom_ct_hu`)
with each inserted tube added as a partial volume over the voxel (every voxel is sampled on a sub-grid of
0.25 x 0.25 x 0.3 mm, so a 1.8 mm tube in a 1 x 1 x 2.5 mm voxel adds the fraction it fills), then the scanner's
blur, metal streaks (CT) and noise. This module knows no plan and no template: it takes centre lines (LPS mm) and
how they look (:class:`TubeLook`). What a needle is, which hole it came through and where the plan wanted it are the
planner's (:mod:`reachplan.planner.verify.implant`).

Appearance (every number ASSUMED where no source is named; the reference material gives none for needles,
``gyn_anatomy.md`` section 3 marks plastic applicators NOT FOUND):

* plastic needle 1.83 mm outer diameter (the planner's ``needle_radius_mm``, 0.915 mm), acetal-like wall
  +340 HU (ASSUMED: the CT number usually quoted for acetal/POM);
* ``content="metal"``: a steel obturator (or the steerable stylet) 1.1 mm across (ASSUMED) inside it, far above the
  CT scale: painted at +12000 HU before the scanner's clip to +3071 HU, the top of the usual 12-bit CT range;
  beam hardening draws a dark streak along the line through every two metal cross-sections of a slice
  (amplitude ``streak_hu`` for two full cores) and photon starvation random bright and dark rays through each
  (``ray_hu``) (the classic metal-artefact pattern; amplitudes ASSUMED);
* ``content="air"`` or ``"fluid"``: the obturator removed, a lumen 1.3 mm across (ASSUMED) of air (-1000 HU) or
  water (0 HU);
* in-plane blur: a Gaussian of ``blur_mm`` (0.45 mm sigma, about 1 mm full width at half maximum, ASSUMED for a
  standard pelvic kernel); the slice profile is the 2.5 mm slab the sub-grid integrates;
* noise: white, ``noise_hu`` (12 HU, ASSUMED for a pelvis at a routine dose);
* MR (T2-weighted-like, arbitrary units): plastic and metal give no signal; a metal core's susceptibility widens
  the void to ``mr_void_radius_mm`` (1.5 mm, ASSUMED; titanium and nitinol give small artefacts); Rician noise of
  ``mr_noise`` (ASSUMED). Simplified: a lumen's content is not drawn in MR (a water-filled lumen 1.3 mm across would
  show a faint bright core), nor are susceptibility distortion, flow or motion.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from reachplan.imaging.case_spec import PhantomSpec

#: Sub-samples per voxel: in-plane per axis, and across the slice.
_SUB_XY = 4
_SUB_Z = 8
#: Spacing of the dense centre-line samples the distances are taken to (mm).
_LINE_STEP_MM = 0.1


@dataclass(frozen=True)
class TubeLook:
    """How an inserted needle looks in the image (see the module docstring for where each number comes from).

    Parameters
    ----------
    outer_radius_mm : float, mm
        The plastic tube's outer radius.
    core_radius_mm : float, mm
        The metal core's (obturator, stylet) radius, ``content="metal"``.
    lumen_radius_mm : float, mm
        The empty lumen's radius, ``content`` ``"air"`` or ``"fluid"``.
    content : str
        ``"metal"`` (obturator or stylet in), ``"air"`` or ``"fluid"`` (lumen empty or filled).
    plastic_hu, metal_hu : float, HU
        CT number of the wall, and of the metal before the scanner's clip.
    ct_max_hu, ct_min_hu : float, HU
        The scanner's range (the image is clipped to it).
    blur_mm : float, mm
        Sigma of the in-plane Gaussian blur.
    noise_hu : float, HU
        Standard deviation of the CT noise.
    streak_hu : float, HU
        Depth of the dark streak between two full metal cross-sections of a slice.
    ray_hu : float, HU
        Standard deviation of the bright and dark rays through each metal cross-section.
    mr_void_radius_mm : float, mm
        MR: radius of the signal void of a tube with a metal core (a plain tube: ``outer_radius_mm``).
    mr_noise : float, a.u.
        MR: the noise's sigma (Rician magnitude).

    Raises
    ------
    ValueError
        Radii not ``0 < core, lumen < outer``, an unknown content or a negative amplitude.
    """

    outer_radius_mm: float = 0.915
    core_radius_mm: float = 0.55
    lumen_radius_mm: float = 0.65
    content: str = "metal"
    plastic_hu: float = 340.0
    metal_hu: float = 12000.0
    ct_max_hu: float = 3071.0
    ct_min_hu: float = -1024.0
    blur_mm: float = 0.45
    noise_hu: float = 12.0
    streak_hu: float = 150.0
    ray_hu: float = 40.0
    mr_void_radius_mm: float = 1.5
    mr_noise: float = 15.0

    def __post_init__(self) -> None:
        if not (0 < self.core_radius_mm < self.outer_radius_mm and 0 < self.lumen_radius_mm < self.outer_radius_mm):
            raise ValueError("tube radii must satisfy 0 < core, lumen < outer")
        if self.content not in ("metal", "air", "fluid"):
            raise ValueError(f"content must be 'metal', 'air' or 'fluid', got {self.content!r}")
        if min(self.blur_mm, self.noise_hu, self.streak_hu, self.ray_hu, self.mr_noise) < 0:
            raise ValueError("blur, noise and streak amplitudes must be >= 0")

    @property
    def inner_radius_mm(self) -> float:
        """Radius of what fills the tube (mm): the metal core, or the lumen."""
        return self.core_radius_mm if self.content == "metal" else self.lumen_radius_mm

    @property
    def inner_hu(self) -> float:
        """CT number of what fills the tube (HU): metal, air or water."""
        return {"metal": self.metal_hu, "air": -1000.0, "fluid": 0.0}[self.content]


def _voxel_axes(spec: PhantomSpec) -> tuple[np.ndarray, np.ndarray]:
    """In-plane voxel centres (matrix,) and slice centres (n_slices,), mm, LPS."""
    return spec.first_pixel_xy_mm + np.arange(spec.matrix) * spec.pixel_mm, spec.slice_z_mm


def _dense(path_mm: np.ndarray) -> np.ndarray:
    """Return the centre line resampled every :data:`_LINE_STEP_MM` (mm, LPS), its points kept."""
    seg = np.diff(path_mm, axis=0)
    out = [path_mm[:1]]
    for a, d in zip(path_mm[:-1], seg, strict=True):
        n = max(1, int(np.ceil(np.linalg.norm(d) / _LINE_STEP_MM)))
        out.append(a + d * (np.arange(1, n + 1) / n)[:, None])
    return np.concatenate(out)


def tube_fractions(spec: PhantomSpec, path_mm: np.ndarray, radii_mm: Sequence[float],
                   ) -> tuple[np.ndarray, list[np.ndarray]]:
    """Fraction of each voxel near a tube that lies within each radius of its centre line.

    The tube ends flat at the line's last point (the tip) and at its first point.

    Parameters
    ----------
    spec : PhantomSpec
        The image geometry.
    path_mm : (n, 3) float, mm, LPS
        The centre line, first point to tip.
    radii_mm : sequence of float, mm
        Increasing radii (e.g. core, outer).

    Returns
    -------
    index : (m, 3) int
        The voxels touched, ``[k, j, i]``.
    fractions : list of (m,) float
        Per radius, the fraction of each voxel within it (0-1).
    """
    from scipy.spatial import cKDTree

    xy, z = _voxel_axes(spec)
    line = _dense(np.asarray(path_mm, dtype=float))
    reach = max(radii_mm) + spec.pixel_mm
    ks = np.searchsorted(z, line[:, 2])
    cand = set()
    span = int(np.ceil(reach / spec.pixel_mm))
    for p, k0 in zip(line[:: max(1, int(0.5 / _LINE_STEP_MM))], ks[:: max(1, int(0.5 / _LINE_STEP_MM))],
                     strict=True):
        i0 = round((p[0] - xy[0]) / spec.pixel_mm)
        j0 = round((p[1] - xy[0]) / spec.pixel_mm)
        for k in (k0 - 1, k0):
            if 0 <= k < len(z):
                for j in range(j0 - span, j0 + span + 1):
                    for i in range(i0 - span, i0 + span + 1):
                        if 0 <= j < spec.matrix and 0 <= i < spec.matrix:
                            cand.add((k, j, i))
    index = np.array(sorted(cand), dtype=int).reshape(-1, 3)
    if not len(index):
        return index, [np.zeros(0) for _ in radii_mm]
    sub_xy = (np.arange(_SUB_XY) + 0.5) / _SUB_XY - 0.5
    sub_z = (np.arange(_SUB_Z) + 0.5) / _SUB_Z - 0.5
    off = np.stack(np.meshgrid(sub_xy * spec.pixel_mm, sub_xy * spec.pixel_mm, sub_z * spec.slice_thickness_mm,
                               indexing="ij"), axis=-1).reshape(-1, 3)
    centres = np.column_stack([xy[index[:, 2]], xy[index[:, 1]], z[index[:, 0]]])
    pts = (centres[:, None, :] + off[None, :, :]).reshape(-1, 3)
    dist, _ = cKDTree(line).query(pts, distance_upper_bound=reach + 1.0)
    tip_t = line[-1] - line[-2]
    base_t = line[1] - line[0]
    inside_ends = ((pts - line[-1]) @ tip_t <= 0) & ((pts - line[0]) @ base_t >= 0)
    fr = [((dist <= r) & inside_ends).reshape(len(index), -1).mean(axis=1) for r in radii_mm]
    return index, fr


def implanted_image(spec: PhantomSpec, base: np.ndarray, paths_mm: Sequence[np.ndarray], look: TubeLook,
                    seed: int = 0) -> np.ndarray:
    """Paint the tubes into the case's image as the scanner would show them.

    Parameters
    ----------
    spec : PhantomSpec
        The case (image geometry and modality).
    base : (n_slices, matrix, matrix) int16
        The case's image without the tubes (HU, or MR signal).
    paths_mm : sequence of (n, 3) float, mm, LPS
        Each tube's centre line, its outer end (outside the patient) first, the tip last.
    look : TubeLook
        The tubes' appearance.
    seed : int
        Seed of the noise and the photon-starvation rays.

    Returns
    -------
    (n_slices, matrix, matrix) int16
        The post-insertion image (HU clipped to the scanner's range, or MR signal >= 0).
    """
    from scipy.ndimage import gaussian_filter

    rng = np.random.default_rng(seed)
    img = base.astype(np.float64)
    mr = spec.modality == "MR"
    inner_r = look.mr_void_radius_mm if (mr and look.content == "metal") else look.inner_radius_mm
    metal = np.zeros(img.shape)
    for path in paths_mm:
        radii = (inner_r, max(look.outer_radius_mm, inner_r))
        index, (f_in, f_out) = tube_fractions(spec, path, radii)
        if not len(index):
            continue
        k, j, i = index.T
        if mr:  # plastic and metal alike give no signal
            img[k, j, i] *= 1.0 - f_out
        else:
            wall = f_out - f_in
            img[k, j, i] = img[k, j, i] * (1.0 - f_out) + wall * look.plastic_hu + f_in * look.inner_hu
            if look.content == "metal":
                metal[k, j, i] += f_in
    sigma_px = look.blur_mm / spec.pixel_mm
    if sigma_px > 0:
        img = gaussian_filter(img, sigma=(0.0, sigma_px, sigma_px))
    if mr:
        noisy = np.hypot(img + rng.normal(0.0, look.mr_noise, img.shape), rng.normal(0.0, look.mr_noise, img.shape))
        return np.round(np.clip(noisy, 0, 32767)).astype(np.int16)
    if look.content == "metal":
        full = np.pi * look.core_radius_mm ** 2 / spec.pixel_mm ** 2  # one full core's cross-section, in pixels
        for k in np.flatnonzero(metal.reshape(len(metal), -1).max(axis=1) > 0.02):
            img[k] += _streaks(metal[k] / full, spec, look, rng)
    img += rng.normal(0.0, look.noise_hu, img.shape)
    return np.round(np.clip(img, look.ct_min_hu, look.ct_max_hu)).astype(np.int16)


def _streaks(amount: np.ndarray, spec: PhantomSpec, look: TubeLook, rng: np.random.Generator) -> np.ndarray:
    """Return the metal artefacts of one slice (HU): dark lines between metal spots, random rays through each.

    ``amount``: (matrix, matrix) metal per pixel in full core cross-sections.
    """
    from scipy.ndimage import center_of_mass, label

    labels, n = label(amount > 0.02)
    if n == 0:
        return np.zeros_like(amount)
    idx = list(range(1, n + 1))
    centres = np.array(center_of_mass(amount, labels, idx)).reshape(-1, 2)  # (row j, column i)
    sizes = np.array([amount[labels == q].sum() for q in idx])
    jj, ii = np.mgrid[0:amount.shape[0], 0:amount.shape[1]].astype(float)
    px = spec.pixel_mm
    out = np.zeros_like(amount)

    def line(c: np.ndarray, angle: float, width_mm: float) -> np.ndarray:
        # distance (mm) of every pixel from the line through c at angle: a Gaussian profile across it
        d = ((ii - c[1]) * np.sin(angle) - (jj - c[0]) * np.cos(angle)) * px
        return np.asarray(np.exp(-0.5 * (d / width_mm) ** 2))

    for a in range(n):
        for b in range(a + 1, n):
            d = centres[b] - centres[a]
            if np.hypot(*d) * px < 2.0:
                continue
            out -= look.streak_hu * min(sizes[a], 1.0) * min(sizes[b], 1.0) * line(
                centres[a], float(np.arctan2(d[0], d[1])), 0.7)
        for angle in rng.uniform(0, np.pi, 4):
            r = np.hypot(ii - centres[a][1], jj - centres[a][0]) * px
            out += rng.normal(0.0, look.ray_hu) * min(sizes[a], 1.0) * line(centres[a], float(angle), 0.5) \
                * 20.0 / (20.0 + r)
    return out
