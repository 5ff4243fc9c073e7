"""Find the needles in a post-insertion image: which template holes hold one, and where each runs to its tip.

No hole is named by the user. Every needle hole of the template (placed as ``plan`` places it) is tested: along the
hole's axis from ``detect_from_mm`` to ``detect_to_mm`` (around the template plane, where a needle cannot yet have
left its hole's line by more than a millimetre), the image's cross-section is sampled in the plane across the axis;
a hole holds a needle when the median, over those depths, of the brightest excess within ``search_radius_mm`` above
the ring around it (``ring_mm``) is above ``detect_sigmas`` times the image noise (the rings' typical robust spread
over all holes) and above ``min_contrast``, and the bright part of its cross-section is thin (no wider than
``spread_mm``: a needle, not the edge of the skin, a bone or an organ). The background of a hole's test is the
ring's upper quartile: the ring must be darker than the needle nearly all round (a neighbouring needle or a streak
crossing it does not matter; an edge does). A dark needle (an MR signal void, an empty lumen in CT) is found the
same way on the negated image.

Each needle found is tracked from its hole in steps of ``step_mm``: the next point is predicted, then moved to the
intensity-weighted centre of the needle's cross-section there (voxels above half the cross-section's peak excess,
weighted by a Gaussian about the prediction); the prediction is a quadratic in arc length through the last
``direction_window_mm`` of measured track (tip following on a circle, as a needle moves). Where the cross-section
holds two needles (they cross), the track takes the bright blob nearest its prediction, or follows its prediction
while the two are merged (a section too wide, or with about twice a needle's summed excess) until they part. The
track stops where the peak excess and the summed excess both fall below half the needle's own medians for
``stop_steps`` steps. The tip is where the needle's integrated cross-section excess along the extrapolated axis
falls to half its value in the shaft (linear between samples: the half-way point of a slice's partial volume is
the tip for a needle crossing slices); for a dark needle, where the larger of that and the peak excess does. The
track is smoothed (a cubic smoothing spline per coordinate against arc length) and given from the template plane to
the tip.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from reachplan.imaging.types import Volume
from reachplan.plugins.templates import Template


@dataclass(frozen=True)
class FinderSettings:
    """How needles are found and tracked (module docstring).

    Parameters
    ----------
    polarity : str
        ``"bright"`` (a metal obturator or stylet in CT), ``"dark"`` (an MR void, an empty lumen) or ``"auto"``:
        bright for CT, dark for MR.
    detect_from_mm, detect_to_mm : float, mm
        Depths beyond the template plane (negative: outside it) over which a hole is tested.
    search_radius_mm : float, mm
        Radius of the cross-section searched for the needle around its predicted point.
    ring_mm : (float, float), mm
        Inner and outer radius of the ring whose median is the local background.
    detect_sigmas : float
        A needle's excess must be this many noise standard deviations.
    min_contrast : float
        And at least this (HU in CT, signal units in MR).
    step_mm : float, mm
        Tracking step.
    direction_window_mm : float, mm
        Length of track the direction is fitted over.
    stop_steps : int
        Steps below half the needle's contrast that end the track.
    max_depth_mm : float, mm
        Longest track beyond the template plane.
    smoothing_mm : float, mm
        Root-mean-square distance the smoothing spline may leave between the track points and the curve. 0.1 mm: at
        0.3 mm the spline cut the curvature of steered needles enough to bias the fitted in-tissue curvature
        (``reachplan calibrate``) by 3 % low on synthetic images; at 0.1 mm the bias was 0.4 %.
    min_length_mm : float, mm
        A track shorter than this beyond the template plane is not a needle (a stub of something else).
    prior_mm : float, mm
        Sigma of the Gaussian about the predicted point that weights the cross-section's centre.
    spread_mm : float, mm
        A cross-section whose bright voxels spread wider (largest standard deviation) holds two needles: the track
        follows its prediction there.
    merged_mass : float
        A cross-section whose excess summed over the disk is this many times the needle's own (its median over the
        last 20 measured steps) holds a second needle lying on it: the track follows its prediction there.
    detect_quantile : float
        The quantile of the ring taken as the background when a hole is tested (the median while tracking); a high
        one asks the ring to be darker than the needle all round (a thin tube, not the edge of a large region).

    Raises
    ------
    ValueError
        A bad polarity, a depth range or ring that is empty, or a non-positive step.
    """

    polarity: str = "auto"
    detect_from_mm: float = -15.0
    detect_to_mm: float = 15.0
    search_radius_mm: float = 2.5
    ring_mm: tuple[float, float] = (4.0, 7.0)
    detect_sigmas: float = 10.0
    min_contrast: float = 100.0
    step_mm: float = 1.0
    direction_window_mm: float = 16.0
    stop_steps: int = 3
    max_depth_mm: float = 250.0
    smoothing_mm: float = 0.1
    min_length_mm: float = 20.0
    prior_mm: float = 1.0
    spread_mm: float = 0.8
    detect_quantile: float = 0.75
    merged_mass: float = 1.5

    @staticmethod
    def for_image(volume: Volume, polarity: str = "auto") -> FinderSettings:
        """Return the settings for a needle look: the defaults for a bright needle, tighter for a dark one.

        A dark needle (an MR void about 3 mm across, an empty lumen) is tested inside the body only (5-35 mm
        beyond the template plane: outside, air is as dark as the needle) against a close ring (2.5-4.5 mm: MR
        holds large dark regions, muscle, bone and gas, that a wide ring would take for a needle).

        Parameters
        ----------
        volume : Volume
            The image (its modality decides ``"auto"``).
        polarity : str
            ``"auto"``, ``"bright"`` or ``"dark"``.

        Returns
        -------
        FinderSettings
            The settings.
        """
        base = FinderSettings(polarity=polarity)
        if _sign(volume, base) > 0:
            return base
        return FinderSettings(polarity=polarity, detect_from_mm=5.0, detect_to_mm=35.0, search_radius_mm=2.0,
                              ring_mm=(2.5, 4.5), min_contrast=50.0)

    def __post_init__(self) -> None:
        if self.polarity not in ("auto", "bright", "dark"):
            raise ValueError(f"polarity must be 'auto', 'bright' or 'dark', got {self.polarity!r}")
        if not (self.detect_from_mm < self.detect_to_mm and 0 < self.ring_mm[0] < self.ring_mm[1]):
            raise ValueError("the detection depths and the background ring must be non-empty ranges")
        if not (self.step_mm > 0 and self.search_radius_mm > 0 and self.stop_steps >= 1):
            raise ValueError("step, search radius and stop steps must be positive")


@dataclass(frozen=True)
class FoundNeedle:
    """A needle found in the image.

    Parameters
    ----------
    hole_id : str
        The template hole it came through.
    points_mm : (n, 3) float, mm, LPS
        Its smoothed centre line from the template plane to the tip, about 1 mm apart.
    tip_mm : (3,) float, mm, LPS
        The tip (the last point).
    contrast : float
        Median excess of its cross-section over the background along the track (HU, or MR units).
    confidence : float
        0-1: the share of the track well above the detection threshold, scaled down when its contrast is near it.
    seconds : float, s
        Time spent on it.
    note : str
        What to check by eye ("" when nothing): e.g. that its end runs along another needle's.
    """

    hole_id: str
    points_mm: np.ndarray
    tip_mm: np.ndarray
    contrast: float
    confidence: float
    seconds: float
    note: str = ""

    @property
    def length_mm(self) -> float:
        """Arc length from the template plane to the tip (mm)."""
        return float(np.sum(np.linalg.norm(np.diff(self.points_mm, axis=0), axis=1)))


class _Image:
    """The volume as a function of LPS points (trilinear), signed so that a needle is bright."""

    def __init__(self, volume: Volume, sign: float) -> None:
        self.array = np.asarray(volume.array, dtype=np.float32) * np.float32(sign)
        self.index_from_patient = np.linalg.inv(volume.grid.patient_from_index)

    def __call__(self, pts: np.ndarray) -> np.ndarray:
        from scipy.ndimage import map_coordinates

        p = np.asarray(pts, dtype=float).reshape(-1, 3)
        ijk = p @ self.index_from_patient[:3, :3].T + self.index_from_patient[:3, 3]
        lo = float(self.array.min())
        out = map_coordinates(self.array, [ijk[:, 2], ijk[:, 1], ijk[:, 0]], order=1, mode="constant", cval=lo)
        return np.asarray(out).reshape(np.shape(pts)[:-1])


def _frame(t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit vectors across unit direction ``t``."""
    a = np.array([1.0, 0.0, 0.0]) if abs(t[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    u = np.cross(t, a)
    u /= np.linalg.norm(u)
    return u, np.cross(t, u)


def _disk(radius_mm: float, step_mm: float) -> np.ndarray:
    """(m, 2) offsets (mm) of a square lattice within ``radius_mm``."""
    r = np.arange(-radius_mm, radius_mm + 1e-9, step_mm)
    g = np.stack(np.meshgrid(r, r, indexing="ij"), axis=-1).reshape(-1, 2)
    return g[np.hypot(g[:, 0], g[:, 1]) <= radius_mm + 1e-9]


def _ring(r0: float, r1: float, n: int = 48) -> np.ndarray:
    """(2n, 2) offsets (mm) on two circles between ``r0`` and ``r1``."""
    a = np.linspace(0.0, 2 * np.pi, n, endpoint=False)
    return np.concatenate([np.column_stack([r * np.cos(a), r * np.sin(a)]) for r in (r0, r1)])


@dataclass(frozen=True)
class _Section:
    """One cross-section: excess over the background per disk point, its peak, the ring's spread, the blob's width.

    The width is the largest standard deviation (mm) of the disk points above half the peak, weighted by their
    excess over it: about half a millimetre for a needle, several for the edge of an organ or the skin. The mass is
    the positive excess summed over the disk (mm² x image units): two needles lying on each other have about twice
    one's.
    """

    excess: np.ndarray
    peak: float
    spread: float
    width: float
    mass: float


class _Sampler:
    """Cross-sections of the image across a direction."""

    def __init__(self, image: _Image, settings: FinderSettings) -> None:
        self.image = image
        self.disk = _disk(settings.search_radius_mm, 0.25)
        self.ring = _ring(*settings.ring_mm)
        self.cells = np.round((self.disk + settings.search_radius_mm) / 0.25).astype(int)  # lattice (row, column)
        self.side = int(self.cells.max()) + 1

    def sections(self, centres: np.ndarray, t: np.ndarray, quantile: float = 0.5) -> list[_Section]:
        """Return the cross-sections at points across a direction; the background is the ring's quantile.

        Parameters
        ----------
        centres : (m, 3) float, mm, LPS
            The sections' centres.
        t : (3,) float, LPS
            The unit direction they lie across.
        quantile : float
            The ring's quantile taken as the background (0.5: its median).

        Returns
        -------
        list of _Section
            One per centre.
        """
        u, v = _frame(t)
        offs = np.concatenate([self.disk, self.ring])
        pts = centres[:, None, :] + offs[None, :, 0:1] * u + offs[None, :, 1:2] * v
        vals = self.image(pts)
        nd = len(self.disk)
        ring = vals[:, nd:]
        middle = np.median(ring, axis=1)
        spread = 1.4826 * np.median(np.abs(ring - middle[:, None]), axis=1)
        bg = middle if quantile == 0.5 else np.quantile(ring, quantile, axis=1)
        ex = vals[:, :nd] - bg[:, None]
        widths = self.widths(ex)
        mass = np.clip(ex, 0.0, None).sum(axis=1) * 0.0625
        return [_Section(ex[k], float(ex[k].max()), float(spread[k]), float(widths[k]), float(mass[k]))
                for k in range(len(ex))]

    def widths(self, excess: np.ndarray) -> np.ndarray:
        """Return the width of the bright part of each cross-section.

        Parameters
        ----------
        excess : (m, d) float
            Excess over the background at each disk point, one row per section.

        Returns
        -------
        (m,) float, mm
            Largest standard deviation of the disk points above half each row's peak (weighted by their excess over
            it); infinite for a row without any.
        """
        w = np.clip(excess - 0.5 * excess.max(axis=1, keepdims=True), 0.0, None)
        total = w.sum(axis=1)
        safe = np.where(total > 0, total, 1.0)
        mean = (w @ self.disk) / safe[:, None]
        xx = (w @ self.disk[:, 0] ** 2) / safe - mean[:, 0] ** 2
        yy = (w @ self.disk[:, 1] ** 2) / safe - mean[:, 1] ** 2
        xy = (w @ (self.disk[:, 0] * self.disk[:, 1])) / safe - mean[:, 0] * mean[:, 1]
        top = 0.5 * (xx + yy) + np.sqrt(0.25 * (xx - yy) ** 2 + xy ** 2)  # the 2 x 2 covariance's larger eigenvalue
        return np.where(total > 0, np.sqrt(np.clip(top, 0.0, None)), np.inf)

    def width(self, excess: np.ndarray) -> float:
        """Return the width of the bright part of one cross-section.

        Parameters
        ----------
        excess : (d,) float
            Excess over the background at each disk point.

        Returns
        -------
        float, mm
            :meth:`widths` of that one section.
        """
        return float(self.widths(np.asarray(excess)[None, :])[0])

    def centre(self, p: np.ndarray, t: np.ndarray, s: _Section, prior_mm: float, spread_mm: float,
               ) -> np.ndarray | None:
        """Return the needle's centre in a cross-section at the predicted point, or None when it is ambiguous.

        One needle in the section (its bright part, above half the peak, no wider than ``spread_mm``): the centre
        of that part, weighted by the excess and by a Gaussian of sigma ``prior_mm`` about the prediction. Two
        (they cross): the voxels above 80 % of the peak are split into connected blobs, and the blob nearest the
        prediction (within 1.5 mm, itself thin) gives the centre; when the blobs have merged, None (the track then
        follows its prediction).

        Parameters
        ----------
        p : (3,) float, mm, LPS
            The predicted point (the section's centre).
        t : (3,) float, LPS
            The unit direction the section lies across.
        s : _Section
            The section.
        prior_mm : float, mm
            Sigma of the Gaussian about ``p`` that weights the centre.
        spread_mm : float, mm
            A bright part wider than this holds two needles.

        Returns
        -------
        (3,) float, mm, LPS, or None
            The centre; None when two needles cannot be told apart here.
        """
        u, v = _frame(t)
        blob = np.clip(s.excess - 0.5 * s.peak, 0.0, None) if s.width <= spread_mm else self._nearest_blob(s, spread_mm)
        if blob is None:
            return None
        w = blob * np.exp(-0.5 * (self.disk ** 2).sum(axis=1) / prior_mm ** 2)
        if w.sum() <= 0:
            return None
        off = (w[:, None] * self.disk).sum(axis=0) / w.sum()
        return np.asarray(p + off[0] * u + off[1] * v)

    def _nearest_blob(self, s: _Section, spread_mm: float) -> np.ndarray | None:
        """Weights of the connected blob above 80 % of the peak nearest the centre (None: none thin and near)."""
        from scipy.ndimage import label

        bright = s.excess > 0.8 * s.peak
        grid = np.zeros((self.side, self.side), dtype=bool)
        grid[self.cells[:, 0], self.cells[:, 1]] = bright
        labels, n = label(grid, structure=np.ones((3, 3)))
        which = labels[self.cells[:, 0], self.cells[:, 1]]
        best, best_d = None, 1.5
        for k in range(1, n + 1):
            w = np.where(which == k, s.excess - 0.8 * s.peak, 0.0)
            if w.sum() <= 0 or self.width(np.where(which == k, s.excess, 0.0)) > spread_mm:
                continue
            d = float(np.linalg.norm((w[:, None] * self.disk).sum(axis=0) / w.sum()))
            if d < best_d:
                best, best_d = w, d
        return best

    def integrated(self, pts: np.ndarray, t: np.ndarray, radius_mm: float) -> np.ndarray:
        """Return the excess over the background summed over a disk across a direction at each point.

        Parameters
        ----------
        pts : (m, 3) float, mm, LPS
            The disks' centres.
        t : (3,) float, LPS
            The unit direction they lie across.
        radius_mm : float, mm
            The disks' radius.

        Returns
        -------
        (m,) float, mm² x image units
            The positive excess integrated over each disk.
        """
        sel = np.hypot(self.disk[:, 0], self.disk[:, 1]) <= radius_mm
        return np.array([np.clip(s.excess[sel], 0.0, None).sum() * 0.0625 for s in self.sections(pts, t)])


def detect_holes(volume: Volume, template: Template, patient_from_template: np.ndarray,
                 settings: FinderSettings = FinderSettings()) -> list[tuple[str, float, float]]:
    """Test every needle hole of the template for a needle (module docstring).

    Parameters
    ----------
    volume : Volume
        The post-insertion image.
    template : Template
        The template.
    patient_from_template : (4, 4) float
        Its pose, template frame (mm) to LPS mm.
    settings : FinderSettings
        Depths, radii and thresholds.

    Returns
    -------
    list of (str, float, float)
        Per hole with a needle: its id, the median excess over the depths and the detection threshold (image units).
    """
    sampler = _Sampler(_Image(volume, _sign(volume, settings)), settings)
    m = np.asarray(patient_from_template, dtype=float)
    t = m[:3, 2] / np.linalg.norm(m[:3, 2])
    depths = np.arange(settings.detect_from_mm, settings.detect_to_mm + 1e-9, 1.25)
    peaks, spreads = [], []
    for hole in template.needle_holes:
        entry = m[:3, :3] @ np.array([*hole.xy_mm, 0.0]) + m[:3, 3]
        secs = sampler.sections(entry + depths[:, None] * t, t, settings.detect_quantile)
        thin = float(np.median([s.width for s in secs])) <= settings.spread_mm  # a needle, not an edge
        peaks.append(float(np.median([s.peak for s in secs])) if thin else 0.0)
        spreads.append(float(np.median([s.spread for s in secs])))
    # the image's noise: the rings' typical spread over all holes (most hold no needle and lie in one tissue)
    threshold = max(settings.detect_sigmas * float(np.median(spreads)), settings.min_contrast)
    return [(hole.hole_id, peak, threshold) for hole, peak in zip(template.needle_holes, peaks, strict=True)
            if peak > threshold]


def _sign(volume: Volume, settings: FinderSettings) -> float:
    """+1 when needles are bright, -1 when dark."""
    if settings.polarity == "auto":
        return -1.0 if volume.modality.upper() == "MR" else 1.0
    return 1.0 if settings.polarity == "bright" else -1.0


def _predict(track: list[np.ndarray], measured: list[bool], window: int, previous: np.ndarray,
             h: float) -> tuple[np.ndarray, np.ndarray]:
    """Predict the next point and direction: a quadratic in arc length through the last ``window`` measured points.

    Tip following on a circle of constant curvature, as a needle moves; points followed by prediction (a crossing)
    do not feed it, so it does not drift on its own guesses. A straight step along ``previous`` until there are 6.
    """
    pts = np.asarray(track)
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(pts, axis=0), axis=1))])
    keep = np.flatnonzero(measured)[-window:]
    if len(keep) < 6:
        return np.asarray(track[-1] + h * previous), previous
    s_next = s[-1] + h
    coef = [np.polyfit(s[keep], pts[keep, j], 2) for j in range(3)]
    p = np.array([np.polyval(c, s_next) for c in coef])
    d = np.array([np.polyval(np.polyder(c), s_next) for c in coef])
    if not np.all(np.isfinite(d)) or np.linalg.norm(d) < 1e-9:
        return np.asarray(track[-1] + h * previous), previous
    d /= np.linalg.norm(d)
    if float(d @ previous) < 0.5:  # no turn this sharp in one step: keep the last direction
        return np.asarray(track[-1] + h * previous), previous
    return p, d


def track_needle(volume: Volume, hole_id: str, entry_mm: np.ndarray, direction: np.ndarray,
                 settings: FinderSettings = FinderSettings(), image: Callable[..., np.ndarray] | None = None,
                 ) -> FoundNeedle:
    """Track one needle from its hole to its tip (module docstring).

    Parameters
    ----------
    volume : Volume
        The post-insertion image.
    hole_id : str
        The hole.
    entry_mm : (3,) float, mm, LPS
        The hole's centre on the template plane.
    direction : (3,) float, LPS
        The hole's insertion direction (unit).
    settings : FinderSettings
        Steps, radii, stopping rule.
    image : callable, optional
        The signed image (for reuse across needles); None: built from ``volume``.

    Returns
    -------
    FoundNeedle
        The smoothed centre line from the template plane to the tip.
    """
    import time

    start = time.perf_counter()
    img = image if isinstance(image, _Image) else _Image(volume, _sign(volume, settings))
    sampler = _Sampler(img, settings)
    t0 = np.asarray(direction, dtype=float) / np.linalg.norm(direction)
    h = settings.step_mm
    p = np.asarray(entry_mm, dtype=float) + settings.detect_from_mm * t0
    t = t0.copy()
    track: list[np.ndarray] = []
    measured: list[bool] = []
    mass: list[float] = []
    peaks: list[float] = []
    window = max(4, round(settings.direction_window_mm / h))
    low = 0
    while len(track) * h < settings.max_depth_mm - settings.detect_from_mm:
        s = sampler.sections(p[None, :], t)[0]
        # the needle ends where its peak and its summed excess both fall below half their own: the peak alone
        # dips wherever a thin lumen runs between voxel centres (partial volume), the sum does not
        if len(peaks) >= 5 and s.peak < 0.5 * float(np.median(peaks[-40:])) \
                and s.mass < 0.5 * float(np.median(mass[-40:])):
            low += 1
            if low >= settings.stop_steps:
                break
            p = p + h * t
            continue
        low = 0
        q = sampler.centre(p, t, s, settings.prior_mm, settings.spread_mm)
        masses = [m for m, ok in zip(mass, measured, strict=True) if ok][-20:]
        if q is not None and len(masses) >= 5 and s.mass > settings.merged_mass * float(np.median(masses)):
            q = None  # another needle lies on this one (their blobs merged): follow the prediction
        mass.append(s.mass)
        measured.append(q is not None)
        if q is None:  # two needles merged in the section (a crossing): follow the prediction
            q = p
        elif track:  # keep the step along the track: the centre moves across it only
            q = q - float((q - p) @ t) * t
        track.append(q)
        peaks.append(s.peak)
        p, t = _predict(track, measured, window, t, h)
    pts = np.asarray(track)
    contrast = float(np.median(peaks)) if peaks else 0.0
    tip = _tip(sampler, pts, t, _sign(volume, settings) < 0)
    line = _smoothed(pts, tip, settings.smoothing_mm)
    line = _from_plane(line, np.asarray(entry_mm, float), t0)
    strong = float(np.mean(np.asarray(peaks) > 0.5 * contrast)) if peaks else 0.0
    return FoundNeedle(hole_id, line, line[-1].copy(), contrast, round(strong, 3),
                       time.perf_counter() - start)


def _tip(sampler: _Sampler, pts: np.ndarray, t: np.ndarray, with_peak: bool) -> np.ndarray:
    """Return the tip: where the needle's signal along the track's extrapolated axis falls to half the shaft's.

    The signal is the excess integrated over the cross-section (a metal core saturates the scanner's scale, so its
    peak stays full well past the tip); for a dark needle (``with_peak``) the larger of that and the peak, each
    against its shaft value (a background that changes around a void dims the integral, not the peak).
    """
    end = pts[-1]
    back = pts[max(0, len(pts) - 8)]
    axis = end - back
    axis = axis / np.linalg.norm(axis) if np.linalg.norm(axis) > 0 else t
    s = np.arange(-8.0, 8.0 + 1e-9, 0.25)
    line = end + s[:, None] * axis
    prof = sampler.integrated(line, axis, 1.75)
    shaft = float(np.median(prof[s <= -4.0]))
    if shaft <= 0:
        return end
    ratio = prof / shaft
    if with_peak:
        peaks = np.array([sec.peak for sec in sampler.sections(line, axis)])
        ratio = np.maximum(ratio, peaks / max(float(np.median(peaks[s <= -4.0])), 1e-9))
    after = np.flatnonzero((ratio < 0.5) & (s > -4.0))
    if not len(after):
        return np.asarray(end + s[-1] * axis)
    k = int(after[0])
    if k == 0:
        return end
    f = float(np.clip((ratio[k - 1] - 0.5) / max(ratio[k - 1] - ratio[k], 1e-9), 0.0, 1.0))
    return np.asarray(end + (s[k - 1] + f * (s[k] - s[k - 1])) * axis)


def _smoothed(pts: np.ndarray, tip: np.ndarray, smoothing_mm: float) -> np.ndarray:
    """Return the track cut at (or extended to) the tip, smoothed by a cubic spline per coordinate, every ~1 mm.

    The tip counts as one point of the spline like the others (weighted up, it pulled the last centimetres of a
    curving needle toward its chord, the line along which the tip is sought) and ends the line as measured.
    """
    from scipy.interpolate import make_splrep

    axis_end = pts[-1] - pts[max(0, len(pts) - 6)]
    keep = pts[(pts - tip) @ axis_end < 0] if np.linalg.norm(axis_end) > 0 else pts
    pts = np.vstack([keep, tip]) if len(keep) >= 1 else np.vstack([pts[:1], tip])
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(pts, axis=0), axis=1))])
    ok = np.concatenate([[True], np.diff(s) > 1e-6])
    pts, s = pts[ok], s[ok]
    if len(pts) < 6:
        return pts
    fine = np.linspace(0.0, s[-1], max(2, int(np.ceil(s[-1])) + 1))
    cols = []
    for j in range(3):
        spline = make_splrep(s, pts[:, j], k=3, s=len(s) * smoothing_mm ** 2 / 3.0)
        cols.append(spline(fine))
    out = np.column_stack(cols)
    out[-1] = tip
    return out


def _from_plane(line: np.ndarray, entry: np.ndarray, normal: np.ndarray) -> np.ndarray:
    """Return the line from where it crosses the template plane (through ``entry``, across ``normal``) on."""
    h = (line - entry) @ normal
    after = np.flatnonzero(h >= 0)
    if not len(after):
        return line
    if after[0] == 0:  # the track starts beyond the plane: extended back to it along its first direction
        d = line[min(5, len(line) - 1)] - line[0]
        if float(d @ normal) <= 1e-9 or h[0] <= 1e-9:
            return line
        return np.vstack([line[0] - d * h[0] / float(d @ normal), line])
    k = int(after[0])
    f = -h[k - 1] / (h[k] - h[k - 1])
    start = line[k - 1] + f * (line[k] - line[k - 1])
    return np.vstack([start, line[k:]])


def find_needles(volume: Volume, template: Template, patient_from_template: np.ndarray,
                 settings: FinderSettings = FinderSettings(), progress: Callable[[str], None] | None = None,
                 detected: Sequence[tuple[str, float, float]] | None = None) -> list[FoundNeedle]:
    """Find every needle that entered through a hole of the template, each tracked to its tip.

    Parameters
    ----------
    volume : Volume
        The post-insertion image.
    template : Template
        The template.
    patient_from_template : (4, 4) float
        Its pose, template frame (mm) to LPS mm.
    settings : FinderSettings
        How needles are detected and tracked.
    progress : callable, optional
        Called with each hole id after its needle is tracked (a progress bar).
    detected : sequence of (str, float, float), optional
        The holes holding a needle (:func:`detect_holes`); None: detected here.

    Returns
    -------
    list of FoundNeedle
        In the template's hole order; tracks shorter than ``min_length_mm`` left out.
    """
    m = np.asarray(patient_from_template, dtype=float)
    t = m[:3, 2] / np.linalg.norm(m[:3, 2])
    image = _Image(volume, _sign(volume, settings))
    holes = {h.hole_id: h for h in template.needle_holes}
    out = []
    for hole_id, _, _ in detect_holes(volume, template, m, settings) if detected is None else detected:
        entry = m[:3, :3] @ np.array([*holes[hole_id].xy_mm, 0.0]) + m[:3, 3]
        needle = track_needle(volume, hole_id, entry, t, settings, image)
        if needle.length_mm >= settings.min_length_mm:
            out.append(needle)
        if progress is not None:
            progress(hole_id)
    return _flag_shared_ends(out)


#: Two needles' centre lines lie at least one outer diameter apart: the 15-gauge plastic needle's 1.83 mm (the
#: thinner of the needles the stylet fits; ASSUMED in ``reference/oncoreach.md``), less 0.3 mm for the tracks'
#: own error.
APART_MM = 1.83 - 0.3


def _flag_shared_ends(found: list[FoundNeedle], length_mm: float = 15.0,
                      within_mm: float = APART_MM) -> list[FoundNeedle]:
    """Flag pairs of needles whose last ``length_mm`` run along each other (one may have taken the other's track).

    Two needles do not end on one line: where two tracks end within 2 mm and the last ``length_mm`` of one lies
    closer to the other than two needles' centre lines can (:data:`APART_MM`, median), one of them most likely
    followed the other past a crossing. Both keep their tracks, at a confidence of at most 0.3, with a note saying
    so.
    """
    import dataclasses

    shared: dict[str, list[str]] = {}
    for a, fa in enumerate(found):
        for fb in found[a + 1:]:
            tail = fa.points_mm[np.cumsum(np.r_[0.0, np.linalg.norm(np.diff(fa.points_mm[::-1], axis=0), axis=1)])
                                [::-1] <= length_mm]
            if np.linalg.norm(fa.tip_mm - fb.tip_mm) < 2.0 and float(np.median(
                    distances_to_line(tail, fb.points_mm))) < within_mm:
                shared.setdefault(fa.hole_id, []).append(fb.hole_id)
                shared.setdefault(fb.hole_id, []).append(fa.hole_id)
    return [f if f.hole_id not in shared else dataclasses.replace(
        f, confidence=min(f.confidence, 0.3),
        note=f"its last {length_mm:g} mm run along needle {', '.join(shared[f.hole_id])}: one of them may have "
             "taken the other's track where they cross; check both by eye") for f in found]


def distances_to_line(points_mm: np.ndarray, line_mm: np.ndarray) -> np.ndarray:
    """Distance of each point from a polyline (exact: to its nearest segment).

    Parameters
    ----------
    points_mm : (n, 3) float, mm
        The points.
    line_mm : (m, 3) float, mm
        The polyline, m >= 2.

    Returns
    -------
    (n,) float, mm
        Each point's distance to the nearest point of the line's segments.
    """
    pts = np.asarray(points_mm, dtype=float).reshape(-1, 3)
    a = np.asarray(line_mm, dtype=float)[:-1]
    d = np.diff(np.asarray(line_mm, dtype=float), axis=0)
    dd = np.maximum((d * d).sum(axis=1), 1e-24)
    out = np.empty(len(pts))
    for lo in range(0, len(pts), 256):  # (256, m, 3) at a time
        rel = pts[lo:lo + 256, None, :] - a[None, :, :]
        u = np.clip((rel * d[None]).sum(axis=2) / dd[None], 0.0, 1.0)
        out[lo:lo + 256] = np.linalg.norm(rel - u[..., None] * d[None], axis=2).min(axis=1)
    return out
