"""The built-in clinical case: a cervix-cancer pelvis where organs stand in the way of straight needles.

Modelled on the reference case of the OncoReach paper (Fig. 1; ``oncoreach.md``, Clinical setting): an
anteverted, anteflexed uterus tilted toward the bladder with a tandem in the uterine canal, an HR-CTV covering
cervix and uterus with parametrial extension, the bladder anterior-inferior under the uterus, the rectum and
rectosigmoid posterior, the sigmoid colon looping beside and over the uterus (down into the vesico-uterine
pouch on the left), small-bowel loops above, the vagina around the obturator, the pelvic bones (iliac walls,
pubic rami and symphysis, ischial tuberosities, sacrum), fat and muscle. Every solid is smooth
(:mod:`reachplan.imaging.sweep`: tubes along curves, bent ellipsoids); no boxes.

Frame (LPS mm, as the pilot phantom): +x patient left, +y posterior, +z superior along the vaginal axis; the
perineal template plane is ``z = 0`` with its centre on the obturator axis (``patient_from_template`` is the
identity, found again from the ``Obturator`` ROI by the planner).

Published numbers (``gyn_anatomy.md``; anything marked ASSUMED is ours, a field of :class:`ClinicalParams`):

* uterus 79 ± 11.5 mm long, 43 ± 7.7 wide, 35 ± 6.6 thick in multiparous women (Nayab et al. 2022); cervix
  25-40 mm long on MRI (Eur J Obstet Gynecol Reprod Biol 2020); anteverted in 84.8 % (Appelbaum et al.,
  Diagnostics 12:1428, 2022), anteflexed in 83.9 % (Gynecol Surg 2009); version and flexion angles: NOT FOUND,
  ASSUMED 15-45 and 20-50 degrees (together roughly the right angle of the normal position).
* bladder 138 ± 41 cm³ at CT-based brachytherapy (Jamema et al., J Med Phys 33:3, 2008), wall 2.8 mm
  (Zafar et al. 2022); rectum 60 ± 28 cm³ (Jamema 2008), length 12-15 cm; colonic wall < 3 mm; sigmoid about
  25 mm across when collapsed (secondary sources; ASSUMED radius 12 mm); small bowel ASSUMED radius 12 mm.
* vagina 62.7 mm long, 26-33 mm wide (Barnhart et al., Hum Reprod 2006): obturator 30 mm across, 60 mm inside.
* CT numbers (:data:`CT_RANGES`): fat -120..-90 and -100..-50, soft tissue +25..+60, muscle +40..+80, fluid
  +5..+15, cancellous bone +300..+400, cortical bone 700-3000, air -1000 (Hounsfield-scale tables cited in
  ``gyn_anatomy.md`` section 3). Plastic applicator: NOT FOUND, ASSUMED +150 HU.
* MR (``modality="MR"``): T2-weighted-like signal, arbitrary units, ASSUMED relative values (GEC-ESTRO
  recommends MR-based planning; the relative T2 intensities were NOT FOUND): urine and bowel fluid bright,
  fat bright, tumour intermediate-high, myometrium intermediate, cervical stroma and muscle dark, cortical
  bone, gas and the plastic applicator void.

Targets: named points inside the HR-CTV (:attr:`ClinicalCase.targets`), each on the line of one hole of the
built-in 63-hole template (hole coordinates from ``needlefinder_syed_63.csv``) so a straight needle can reach
it and be compared with a steered one: ``corpus_ant`` (anterior uterine body, over the bladder),
``corpus_L``/``corpus_R`` (lateral uterine body), ``param_L``/``param_R`` (parametrial extension).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from reachplan.imaging.anatomy import draw_params
from reachplan.imaging.case_spec import PhantomSpec, PhantomStructure
from reachplan.imaging.phantom import PhantomFiles, write_phantom
from reachplan.imaging.sweep import SAMPLE_MM, Sweep, Union, arc_curve, resample_curve
from reachplan.imaging.types import Contour, Grid, Roi, StructureSet

#: CT number ranges (HU) of each painted tissue class, with the source of the range (gyn_anatomy.md §3).
CT_RANGES: dict[str, tuple[float, float, str]] = {
    "air": (-1000.0, -1000.0, "Hounsfield scale definition"),
    "fat": (-120.0, -50.0, "fat -120..-90 (Wikipedia HU table); -100..-50 (radclass.mudr.org)"),
    "soft tissue": (25.0, 60.0, "soft tissue +25..+60 (uvm.edu CT tutorial)"),
    "muscle": (40.0, 80.0, "muscle +40..+80 (Grainger & Allison via stethoprep)"),
    "fluid": (5.0, 15.0, "fluid +5..+15 (thecommonvein.net)"),
    "cancellous bone": (300.0, 400.0, "cancellous bone +300..+400 (Wikipedia HU table)"),
    "cortical bone": (700.0, 3000.0, "cortical bone 700-3000 (radclass.mudr.org); ~+1000 (uvm.edu)"),
    "plastic": (150.0, 150.0, "ASSUMED (NOT FOUND)"),
}

#: Painted CT number (HU) and T2-like MR signal (a.u., ASSUMED) per tissue class.
TISSUES: dict[str, tuple[float, float]] = {
    "air": (-1000.0, 0.0),
    "fat": (-100.0, 700.0),
    "muscle": (50.0, 150.0),
    "soft tissue": (40.0, 350.0),  # organ walls, vagina
    "myometrium": (45.0, 500.0),
    "cervical stroma": (40.0, 200.0),
    "tumour": (55.0, 650.0),
    "fluid": (10.0, 1500.0),  # urine, bowel fluid
    "cortical bone": (1000.0, 20.0),
    "cancellous bone": (350.0, 600.0),
    "plastic": (150.0, 0.0),
}
#: the CT range class of each tissue (for the HU test)
TISSUE_CLASS = {"air": "air", "fat": "fat", "muscle": "muscle", "soft tissue": "soft tissue",
                "myometrium": "soft tissue", "cervical stroma": "soft tissue", "tumour": "soft tissue",
                "fluid": "fluid", "cortical bone": "cortical bone", "cancellous bone": "cancellous bone",
                "plastic": "plastic"}

#: A parametrial extension reaching this far (mm) from the cervix axis is distal, a shorter one proximal (ASSUMED:
#: about half way to the obturator internus on the side wall, 55 mm from the axis in this case).
DISTAL_REACH_MM = 36.0

#: Target lines (x, y) in LPS mm: holes Ce, Cg, Cc, Df, Da of the built-in template (identity pose). When a line
#: misses (a retroverted uterus, a proximal extension), the fallback of :data:`TARGET_FALLBACK` is taken.
TARGET_COLUMNS: dict[str, tuple[float, float]] = {
    "corpus_ant": (0.0, -30.0),
    "corpus_L": (19.284, -22.981),
    "corpus_R": (-19.284, -22.981),
    "param_L": (40.0, 0.0),
    "param_R": (-40.0, 0.0),
}
#: Further lines, tried in order, for targets whose first misses (holes Cn, Ab, Cl, Ch, Bg, Ba: posterior, inner
#: ring, 20 mm ring).
TARGET_FALLBACK: dict[str, tuple[tuple[float, float], ...]] = {
    "corpus_ant": ((0.0, 30.0), (0.0, -10.6)),
    "corpus_L": ((19.284, 22.981),),
    "corpus_R": ((-19.284, 22.981),),
    "param_L": ((20.0, 0.0),),
    "param_R": ((-20.0, 0.0),),
}


@dataclass(frozen=True)
class ClinicalParams:
    """The anatomy of one clinical case (mm, degrees, cm³); defaults are the reference case.

    Fields marked ASSUMED are ours where the literature gave no number (see the module docstring).

    Parameters
    ----------
    version_deg : float, degrees
        Cervix axis tilted anteriorly from the vaginal axis (ASSUMED), -80..80; negative: retroverted (posteriorly).
    flexion_deg : float, degrees
        Uterine body axis from the cervix axis (ASSUMED), -80..80; negative: retroflexed (bent posteriorly).
    cervix_length_mm, corpus_length_mm : float, mm
        Lengths of the cervix and of the uterine body along their axes.
    uterus_width_mm, uterus_thickness_mm : float, mm
        The uterine body's lateral and antero-posterior size.
    bladder_volume_cc : float, cm³
        Bladder filling.
    rectum_radius_mm, sigmoid_radius_mm : float, mm
        Radii of the rectum and sigmoid tubes.
    sigmoid_shift_mm : (float, float, float), mm, LPS
        Displacement of the sigmoid loop (x, y, z).
    parametria : str
        ``"L"``, ``"R"`` or ``"LR"``: the sides of parametrial extension; ``""``: none.
    param_reach_mm : float, mm
        The extension's lateral reach from the cervix axis (ASSUMED); below :data:`DISTAL_REACH_MM` it is proximal
        (the medial parametrium), else distal (toward the pelvic side wall).
    hrctv_margin_mm : float, mm
        The HR-CTV's margin grown around the uterus.
    hrctv_corpus_fraction : float
        The fraction of the uterine body's length (from the cervix up) the HR-CTV covers, in (0, 1]; 1: the whole
        uterus (a tumour confined to the cervix and lower body is smaller).
    vaginal_extension_mm : float, mm
        Length of the tumour's extension down the vaginal wall from the fornix (0: none).
    vaginal_extension_azimuth_deg : float, degrees
        Where around the vagina it lies, in the axial plane from patient left (+x) toward posterior (+y); any value
        (taken modulo 360).
    bowel_shift_mm : (float, float, float), mm, LPS
        Displacement of the small-bowel loops (x, y, z) before they are moved clear of the other organs.
    bladder_wall_y_mm : float, mm, LPS
        The bladder's posterior wall (y) in the mid-sagittal plane; its base rests on the anterior vaginal wall
        and the cervix (ASSUMED, as the distances cervix-to-bladder-wall were NOT FOUND).

    Raises
    ------
    ValueError
        ``parametria`` not one of the three, angles out of 0-80 degrees, or a size that is not positive.
    """

    version_deg: float = 30.0
    flexion_deg: float = 35.0
    cervix_length_mm: float = 30.0
    corpus_length_mm: float = 48.0
    uterus_width_mm: float = 46.0
    uterus_thickness_mm: float = 35.0
    bladder_volume_cc: float = 138.0
    rectum_radius_mm: float = 12.5
    sigmoid_radius_mm: float = 12.0
    sigmoid_shift_mm: tuple[float, float, float] = (0.0, 0.0, 0.0)
    parametria: str = "L"
    param_reach_mm: float = 45.0
    hrctv_margin_mm: float = 2.0
    bladder_wall_y_mm: float = -28.0
    hrctv_corpus_fraction: float = 1.0
    vaginal_extension_mm: float = 0.0
    vaginal_extension_azimuth_deg: float = 0.0
    bowel_shift_mm: tuple[float, float, float] = (0.0, 0.0, 0.0)

    def __post_init__(self) -> None:
        if self.parametria not in ("", "L", "R", "LR"):
            raise ValueError(f"parametria must be '', 'L', 'R' or 'LR', got {self.parametria!r}")
        if not -80.0 <= self.version_deg <= 80.0 or not -80.0 <= self.flexion_deg <= 80.0:
            raise ValueError("version_deg and flexion_deg must be in -80..80 degrees (negative: retro-)")
        if not 0.0 < self.hrctv_corpus_fraction <= 1.0 or not 0.0 <= self.vaginal_extension_mm <= 40.0:
            raise ValueError("hrctv_corpus_fraction must be in (0, 1] and vaginal_extension_mm in 0..40 mm")
        for name in ("cervix_length_mm", "corpus_length_mm", "uterus_width_mm", "uterus_thickness_mm",
                     "bladder_volume_cc", "rectum_radius_mm", "sigmoid_radius_mm", "param_reach_mm"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"ClinicalParams.{name} must be positive, got {v}")

    @property
    def parametrial_extension(self) -> str:
        """Return the parametrial extension in words: ``none``, or the side(s) and proximal or distal.

        Returns
        -------
        str
            ``none``, ``left proximal``, ``right distal``, ``bilateral distal``, ...
        """
        if not self.parametria:
            return "none"
        side = {"L": "left", "R": "right", "LR": "bilateral"}[self.parametria]
        return f"{side} {'distal' if self.param_reach_mm >= DISTAL_REACH_MM else 'proximal'}"


def sample_params(seed: int) -> ClinicalParams:
    """Deterministic anatomical variation for ``seed`` (0 = the reference case).

    Every parameter is drawn from the distribution :data:`reachplan.imaging.anatomy.VARIETY` documents, with its
    source (:func:`reachplan.imaging.anatomy.draw_params`).

    Parameters
    ----------
    seed : int
        The case number; 0 gives the reference case.

    Returns
    -------
    ClinicalParams
        The anatomy, each varied value rounded to 0.01.
    """
    if seed == 0:
        return ClinicalParams()
    rectum_mm = tube(_RECTUM_POINTS, 10.0, rounded=False).length_mm
    return ClinicalParams(**draw_params(np.random.default_rng([1013, seed]), rectum_mm))


@dataclass(frozen=True, eq=False)
class ClinicalCase:
    """A clinical case: the phantom description (ROIs, painted tissues, CT geometry) and named target points.

    Parameters
    ----------
    params : ClinicalParams
        The anatomy.
    seed : int
        The seed it was sampled with (0: the reference case).
    spec : PhantomSpec
        The phantom built from ``params``.
    targets : tuple of (str, (float, float, float))
        Named points, mm, LPS, inside the HR-CTV.
    """

    params: ClinicalParams
    seed: int
    spec: PhantomSpec
    targets: tuple[tuple[str, tuple[float, float, float]], ...]

    def to_json(self) -> dict[str, object]:
        """Return the case as JSON-ready values (seed, parameters, named target points in mm LPS).

        Returns
        -------
        dict
            ``case``, ``seed``, ``params``, ``modality``, ``targets`` (name to ``[x, y, z]``, mm, LPS, rounded to
            0.001) and ``patient_from_template`` (4 x 4 nested lists).
        """
        return {
            "case": "clinical", "seed": self.seed, "params": dataclasses.asdict(self.params),
            "modality": self.spec.modality,
            "targets": {n: [round(v, 3) for v in p] for n, p in self.targets},
            "patient_from_template": np.asarray(self.spec.patient_from_template).tolist(),
        }


def _profile(s: np.ndarray, pieces: list[tuple[float, float, float]]) -> np.ndarray:
    """Piecewise-smooth profile: ``pieces`` of (s, a_before, a_after) blended by smoothsteps 15 mm wide."""
    out = np.full_like(s, pieces[0][1])
    for s0, a0, a1 in pieces:
        t = np.clip((s - (s0 - 7.5)) / 15.0, 0.0, 1.0)
        out += (a1 - a0) * t * t * (3 - 2 * t)
    return out


def _round_ends(s: np.ndarray, length: float, start_mm: float, end_mm: float) -> np.ndarray:
    """Factor (0..1) that rounds a profile over ``start_mm`` at s = 0 and ``end_mm`` at s = length."""
    f = np.ones_like(s)
    if start_mm > 0:
        x = np.clip((start_mm - s) / start_mm, 0.0, 1.0)
        f *= np.sqrt(np.clip(1 - x * x, 0.0, 1.0))
    if end_mm > 0:
        x = np.clip((s - (length - end_mm)) / end_mm, 0.0, 1.0)
        f *= np.sqrt(np.clip(1 - x * x, 0.0, 1.0))
    return f


def tube(points_mm: Sequence[tuple[float, float, float]], radius_mm: float, rounded: bool = True) -> Sweep:
    """Return a round tube along a smooth curve through ``points_mm``; hemispherical ends when ``rounded``.

    Parameters
    ----------
    points_mm : sequence of (float, float, float), mm, LPS
        Points the centre line passes through (resampled to a smooth curve).
    radius_mm : float, mm
        The tube's radius.
    rounded : bool
        Close each end with a hemisphere.

    Returns
    -------
    Sweep
        The tube.
    """
    c = resample_curve(np.array(points_mm, float))
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(c, axis=0), axis=1))])
    r = radius_mm * (_round_ends(s, s[-1], radius_mm, radius_mm) if rounded else np.ones_like(s))
    return Sweep(c, r, r, (0.0, 0.0, 1.0) if abs(c[-1, 2] - c[0, 2]) < 0.5 * s[-1] else (1.0, 0.0, 0.0))


def _uterus(p: ClinicalParams) -> tuple[Sweep, Sweep, np.ndarray]:
    """(uterus, cervix, centreline) sweeps: cervix straight along the version angle, corpus arc by flexion."""
    v = math.radians(p.version_deg)
    d0 = np.array([0.0, -math.sin(v), math.cos(v)])
    c = arc_curve(np.array([0.0, 0.0, 61.0]), d0, np.array([0.0, -1.0, 0.0]), p.corpus_length_mm,
                  p.flexion_deg, straight_mm=p.cervix_length_mm)
    s = np.arange(len(c)) * SAMPLE_MM
    length = s[-1]
    ends = _round_ends(s, length, 6.0, 0.45 * p.corpus_length_mm)
    lat = _profile(s, [(p.cervix_length_mm + 4.0, 15.0, p.uterus_width_mm / 2)]) * ends
    ap = _profile(s, [(p.cervix_length_mm + 4.0, 13.0, p.uterus_thickness_mm / 2)]) * ends
    uterus = Sweep(c, lat, ap, (1.0, 0.0, 0.0))
    k = round(p.cervix_length_mm / SAMPLE_MM) + 1
    cervix = Sweep(c[:k], lat[:k], ap[:k], (1.0, 0.0, 0.0))
    return uterus, cervix, c


def _parametrium(p: ClinicalParams, centre: np.ndarray, side: float) -> Sweep:
    """Return a lobe of parametrial extension from the cervix toward one pelvic side wall (ellipsoidal profile)."""
    start = centre + np.array([0.0, 0.0, 0.0])
    end = centre + np.array([side * p.param_reach_mm, 6.0, 8.0])
    c = resample_curve(np.array([start, 0.5 * (start + end) + [0.0, 2.0, 2.0], end]))
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(c, axis=0), axis=1))])
    f = _round_ends(s, s[-1], 0.0, 14.0)
    return Sweep(c, 13.0 * f, 14.0 * f, (0.0, 1.0, 0.0))


def _bladder(p: ClinicalParams, fill: float = 1.0) -> Sweep:
    """Return the bladder holding ``fill`` x its nominal volume.

    An ellipsoid bent anteriorly under the uterus, its base at z = 32 mm. Semi-axes scale with the cube root of the
    volume (reference 36 x 25 x 25 mm, 94 cm³; ASSUMED shape).
    """
    k = (fill * p.bladder_volume_cc * 1000.0 / (4 / 3 * math.pi * 36 * 25 * 25)) ** (1 / 3)
    lat, ap, half = 36 * k, 25 * k, 25 * k
    start = np.array([0.0, -ap, 32.0])
    c = arc_curve(start, np.array([0.0, -0.35, 1.0]), np.array([0.0, -1.0, 0.0]), 2 * half, 45.0)
    s = np.arange(len(c)) * SAMPLE_MM
    u = (s - s[-1] / 2) / (s[-1] / 2)
    f = np.sqrt(np.clip(1 - u * u, 0.0, 1.0))
    return Sweep(c, lat * f, ap * f, (1.0, 0.0, 0.0))


def _shifted(sw: Sweep, by: tuple[float, float, float]) -> Sweep:
    return Sweep(sw.samples_mm + np.asarray(by, float), sw.semi_a_mm, sw.semi_b_mm, sw.reference)


def _midline_extent(shape: Sweep | Union, z0: float, z1: float) -> tuple[float, float]:
    """(most anterior, most posterior) y (mm) of the solid in the mid-sagittal plane x = 0, z0 <= z < z1."""
    y, z = np.meshgrid(np.arange(-120.0, 60.0, 0.5), np.arange(z0, z1, 1.0), indexing="ij")
    inside = shape.contains(np.stack([np.zeros_like(y), y, z], axis=-1))
    ys = y[inside]
    return float(ys.min()), float(ys.max())


def _back_y(shape: Sweep | Union) -> float:
    """Posterior wall of the bladder (z 35-75 mm)."""
    return _midline_extent(shape, 35.0, 75.0)[1]


#: points of the lattice :func:`_overlap` tests at a time (it stops at the first block with a point of contact)
_OVERLAP_BLOCK = 4096


def _overlap(a: Sweep | Union, b: Sweep | Union, gap_mm: float = 0.0, step: float = 1.5) -> bool:
    """Tell whether a point of a ``step`` lattice inside ``a`` lies within ``gap_mm`` of ``b`` (their boxes' overlap).

    The lattice is tested a block at a time, stopping at the first point of contact (the answer the whole lattice
    gives, at a fraction of the cost when the solids touch, which is when a placement loop tries again).
    """
    lo = np.maximum(a.bounds()[0], b.bounds()[0] - gap_mm)
    hi = np.minimum(a.bounds()[1], b.bounds()[1] + gap_mm)
    if np.any(hi <= lo):
        return False
    axes = [np.arange(x0, x1 + step, step) for x0, x1 in zip(lo, hi, strict=True)]
    pts = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    for start in range(0, len(pts), _OVERLAP_BLOCK):
        block = pts[start:start + _OVERLAP_BLOCK]
        inside = block[a.contains(block)]
        if len(inside) and bool(np.any(b.field(inside) <= gap_mm)):
            return True
    return False


def _bowel(dx: float, dy: float = 0.0, dz: float = 0.0) -> tuple[Sweep, Sweep]:
    """Two small-bowel loops above the uterus, on the right (ASSUMED course), shifted by (dx, dy, dz) mm."""
    a = [(-48, -25, 150), (-38, -58, 154), (-12, -52, 170), (-36, -28, 180), (-50, -45, 190), (-25, -70, 194),
         (-12, -76, 190)]
    b = [(-45, 15, 165), (-25, 5, 184), (-5, -18, 197)]
    return (tube([(x + dx, y + dy, z + dz) for x, y, z in a], 12.0), tube([(x + dx, y + dy, z + dz) for x, y, z in b],
                                                                          12.0))


def _hip(side: float) -> Sweep:
    """One hip bone.

    Iliac wall (flattened), down the side wall, superior ramus to the symphysis, back along the inferior
    (ischiopubic) ramus to the ischial tuberosity. Radii ASSUMED.
    """
    pts = [(75, 45, 198), (69, 25, 160), (64, 8, 115), (61, -10, 75), (56, -48, 44), (30, -80, 36),
           (10, -87, 32), (9.5, -87, 21), (22, -74, 12), (44, -40, 6), (56, -5, 6), (62, 22, 8)]
    c = resample_curve(np.array([(side * x, y, z) for x, y, z in pts], float))
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(c, axis=0), axis=1))])
    ends = _round_ends(s, s[-1], 6.0, 9.0)
    wide = np.clip((c[:, 2] - 60.0) / 60.0, 0.0, 1.0)  # the iliac wall widens upward
    return Sweep(c, 7.0 * ends, (7.0 + 15.0 * wide) * ends, (1.0, 0.0, 1.0))


def clinical_case(seed: int = 0, params: ClinicalParams | None = None, modality: str = "CT",
                  case_id: str = "") -> ClinicalCase:
    """Return the clinical case of ``seed`` (or of explicit ``params``), deterministic.

    Parameters
    ----------
    seed : int
        0 = the reference case; others vary the anatomy (:func:`sample_params`).
    params : ClinicalParams or None
        Explicit anatomy instead of the seed's.
    modality : str
        ``"CT"`` or ``"MR"`` (T2-like contrast).
    case_id : str
        Gives the written files their own Patient ID and UIDs (default ``clinical_<seed>``).

    Returns
    -------
    ClinicalCase
        The phantom description and the named target points (LPS mm).
    """
    p = params or sample_params(seed)
    mr = modality.upper() == "MR"
    rectum = tube(_RECTUM_POINTS, p.rectum_radius_mm, rounded=False)
    p, uterus, cervix, axis, hrctv = _fitted_uterus(p, rectum)
    hips = (_hip(1.0), _hip(-1.0))
    bladder = _placed_bladder(p, hrctv, hips)
    sigmoid = _placed_sigmoid(p, hrctv, bladder, hips)
    bowel = _placed_bowel(sigmoid, p.bowel_shift_mm, (hrctv, bladder, sigmoid), hips)
    bones = (*hips, _sacrum())
    body = _z_rod(np.linspace(0.0, 210.0, 841), 150.0, 108.0, y_mm=5.0)
    structures = (
        _roi("Body", "EXTERNAL", (body,), "fat", (200, 180, 140), mr),
        _roi("Bone_Pelvic", "AVOIDANCE", bones, "cortical bone", (240, 240, 220), mr, oar=True),
        _roi("Rectum", "ORGAN", (rectum,), "soft tissue", (150, 90, 40), mr, oar=True),
        _roi("Colon_Sigmoid", "ORGAN", (sigmoid,), "soft tissue", (200, 120, 60), mr, oar=True),
        _roi("Bowel_Small", "ORGAN", bowel, "soft tissue", (230, 180, 60), mr, oar=True),
        _roi("Bladder", "ORGAN", (bladder,), "soft tissue", (250, 230, 50), mr, oar=True),
        _roi("Uterus", "ORGAN", (uterus,), "myometrium", (230, 130, 170), mr),
        _roi("Cervix", "ORGAN", (cervix,), "cervical stroma", (200, 90, 140), mr),
        _roi("Vagina", "ORGAN", (_z_rod(np.linspace(0.0, 60.0, 241), 18.0, 18.0),), "soft tissue", (210, 150, 150),
             mr),
        _roi("CTV_HR", "CTV", (hrctv,), "tumour", (255, 60, 60), mr),
        _roi("Obturator", "BRACHY_ACCESSORY", (_z_rod(np.linspace(-20.0, 60.0, 321), 15.0, 15.0),), "plastic",
             (120, 120, 255), mr),
        _roi("Tandem", "BRACHY_ACCESSORY", (_tandem(uterus, axis),), "plastic", (90, 90, 255), mr),
    )
    tissues = _tissues(body, bladder, rectum, sigmoid, bowel, bones, cervix, mr)
    spec = PhantomSpec(structures, slice_thickness_mm=2.5, z_range_mm=(-20.0, 210.0), matrix=320,
                       air_hu=0.0 if mr else TISSUES["air"][0], fat_thickness_mm=0.0,
                       case_id=case_id or f"clinical_{seed}", tissues=tissues, paint_order=_CLINICAL_PAINT_ORDER,
                       modality="MR" if mr else "CT", description="reachplan clinical case (cervix ISBT)")
    points = _target_points(p, uterus, hrctv)
    target_rois = tuple(_roi(f"Target_{n}", "PTV", (_target_cylinder(xyz),), "tumour", (255, 0, 0), mr)
                        for n, xyz in points)
    spec = dataclasses.replace(spec, structures=(*spec.structures, *target_rois))
    return ClinicalCase(p, seed, spec, tuple(points))


#: The rectum's centre line (LPS mm), from the anal canal up to the recto-sigmoid junction.
_RECTUM_POINTS = ((0, 36, 4), (0, 37, 30), (0, 42, 65), (0, 50, 95), (3, 56, 112), (14, 56, 124))
#: The sigmoid loop's course (LPS mm) before the case's shift, between its fixed ends.
_SIGMOID_LOOP = ((33, 44, 130), (35, 18, 124), (36, -16, 112), (36, -46, 104), (20, -72, 118), (0, -66, 140),
                 (25, -35, 152), (50, -24, 170))
#: Paint order of the clinical case's structures and tissues (later wins).
_CLINICAL_PAINT_ORDER = (
    "Body", "muscle", "pelvic fat", "obturator internus 0", "obturator internus 1", "psoas 0", "psoas 1",
    "Vagina", "Rectum", "rectal gas", "Colon_Sigmoid", "sigmoid gas", "Bowel_Small", "bowel fluid 0",
    "bowel fluid 1", "Bladder", "urine", "CTV_HR", "Uterus", "Cervix", "cervical tumour", "Obturator",
    "Tandem", "Bone_Pelvic", "marrow 0", "marrow 1", "marrow 2")


def _roi(name: str, kind: str, parts: tuple[Sweep | Union, ...], tissue: str, color: tuple[int, int, int], mr: bool,
         oar: bool = False) -> PhantomStructure:
    """Return a written ROI of the case, painted with ``tissue``'s CT number (or MR signal when ``mr``)."""
    return PhantomStructure(name, kind, parts, hu=TISSUES[tissue][1 if mr else 0], color=color, is_oar=oar)


def _paint(name: str, shape: Sweep | Union, tissue: str, mr: bool) -> PhantomStructure:
    """Return a painted tissue of the case (not written as a ROI)."""
    return PhantomStructure(name, "", (shape,), hu=TISSUES[tissue][1 if mr else 0], color=(0, 0, 0))


def _hrctv(p: ClinicalParams, uterus: Sweep, axis: np.ndarray) -> Union:
    """Return the HR-CTV: the uterus grown by the case's margin, with the parametrial and vaginal extensions.

    With ``hrctv_corpus_fraction`` < 1 only the cervix and that fraction of the body are covered (the cut end
    rounded over 10 mm); a vaginal extension is a tube 7 mm in radius in the vaginal wall (its axis 22.5 mm from the
    obturator's) from the fornix down (ASSUMED shape).

    Parameters
    ----------
    p : ClinicalParams
        The case's anatomy (margin, which parametria, reach).
    uterus : Sweep
        The uterus (corpus and cervix).
    axis : (n, 3) float, mm, LPS
        The uterus' centre line, sampled every ``SAMPLE_MM`` from the external os.
    """
    cervix_mid = axis[round(0.55 * p.cervix_length_mm / SAMPLE_MM)]
    sides = {"": [], "L": [1.0], "R": [-1.0], "LR": [1.0, -1.0]}[p.parametria]
    body = uterus
    if p.hrctv_corpus_fraction < 1.0:
        k = round((p.cervix_length_mm + p.hrctv_corpus_fraction * p.corpus_length_mm) / SAMPLE_MM) + 1
        s = np.arange(k) * SAMPLE_MM
        f = _round_ends(s, s[-1], 0.0, min(10.0, 0.5 * s[-1]))
        body = Sweep(uterus.samples_mm[:k], uterus.semi_a_mm[:k] * f, uterus.semi_b_mm[:k] * f, uterus.reference)
    parts = [body.grown(p.hrctv_margin_mm), *(_parametrium(p, cervix_mid, s) for s in sides)]
    if p.vaginal_extension_mm > 0.0:
        a = math.radians(p.vaginal_extension_azimuth_deg)
        x, y = 22.5 * math.cos(a), 22.5 * math.sin(a)
        parts.append(tube([(x, y, 66.0), (x, y, 61.0 - p.vaginal_extension_mm)], 7.0))
    return Union(tuple(parts))


def _fitted_uterus(p: ClinicalParams, rectum: Sweep) -> tuple[ClinicalParams, Sweep, Sweep, np.ndarray, Union]:
    """Return the anatomy, uterus, cervix, centre line and HR-CTV, a retro-tilted uterus lifted off the rectum.

    A retroverted or retroflexed uterus rests on the rectum: its negative angles are brought 5 degrees at a time
    toward 0 until 3 mm of tissue separate the HR-CTV from the rectum (ASSUMED; at most 16 steps). The anatomy
    returned holds the angles used.
    """
    for _ in range(16):
        uterus, cervix, axis = _uterus(p)
        hrctv = _hrctv(p, uterus, axis)
        if min(p.version_deg, p.flexion_deg) >= 0.0 or not _overlap(hrctv, rectum, gap_mm=3.0, step=2.0):
            break
        p = dataclasses.replace(p, version_deg=min(p.version_deg + 5.0, 0.0) if p.version_deg < 0 else p.version_deg,
                                flexion_deg=min(p.flexion_deg + 5.0, 0.0) if p.flexion_deg < 0 else p.flexion_deg)
    return p, uterus, cervix, axis, hrctv


def _placed_bladder(p: ClinicalParams, hrctv: Union, hips: tuple[Sweep, Sweep]) -> Sweep:
    """Return the bladder, anchored at its posterior wall and emptied in 5 % steps until it is clear.

    Clear: 3 mm of tissue from the HR-CTV and 2 mm from the bones (at most 30 steps; a fuller bladder would lift
    the uterus: not modelled).
    """
    fill = 1.0
    for _ in range(30):
        bladder = _bladder(p, fill)
        bladder = _shifted(bladder, (0.0, p.bladder_wall_y_mm - _back_y(bladder), 0.0))
        if not _overlap(bladder, hrctv, gap_mm=3.0, step=2.0) and not any(
                _overlap(bladder, h, gap_mm=2.0, step=2.0) for h in hips):
            break
        fill *= 0.95
    return bladder


def _placed_sigmoid(p: ClinicalParams, hrctv: Union, bladder: Sweep, hips: tuple[Sweep, Sweep]) -> Sweep:
    """Return the sigmoid colon clear of its neighbours (at most 20 steps of 2 mm).

    Moved toward the midline while it touches a hip bone (2 mm of gap), then lifted until 3 mm of fat separate it
    from the HR-CTV and bladder.
    """
    dx, dy, dz = p.sigmoid_shift_mm

    def course(dx: float, dz: float) -> Sweep:
        loop = ((x + dx, y + dy, z + dz) for x, y, z in _SIGMOID_LOOP)
        return tube([(26, 56, 127), *loop, (56, -10, 205)], p.sigmoid_radius_mm, rounded=False)

    sigmoid = course(dx, dz)
    for _ in range(20):
        if any(_overlap(sigmoid, h, 2.0, step=2.0) for h in hips):
            dx -= 2.0
        elif _overlap(sigmoid, hrctv, 3.0, step=2.0) or _overlap(sigmoid, bladder, 3.0, step=2.0):
            dz += 2.0
        else:
            break
        sigmoid = course(dx, dz)
    return sigmoid


def _placed_bowel(sigmoid: Sweep, shift_mm: tuple[float, float, float] = (0.0, 0.0, 0.0),
                  avoid: tuple[Sweep | Union, ...] = (), hips: tuple[Sweep, ...] = ()) -> tuple[Sweep, Sweep]:
    """Return the small-bowel loops on the right, shifted by ``shift_mm``, then clear of the other organs.

    They move further right (up to 12 mm) until clear of the sigmoid; then (at most 30 steps of 2 mm) up while
    they touch a hip bone (2 mm gap), further right while they touch the sigmoid (up to 16 mm in all), else up
    until 3 mm separate them from each of ``avoid`` (the HR-CTV, the bladder, the sigmoid).
    """
    dx, dy, dz = shift_mm
    bowel_shift = 0.0
    while True:
        bowel = _bowel(bowel_shift + dx, dy, dz)
        if bowel_shift <= -12.0 or not any(_overlap(b, sigmoid, 4.0, step=2.0) for b in bowel):
            break
        bowel_shift -= 2.0
    for _ in range(30):
        if any(_overlap(b, h, 2.0, step=2.0) for b in bowel for h in hips):
            dz += 2.0  # the iliac wing flares outward above: up is away from it
        elif bowel_shift > -16.0 and any(_overlap(b, sigmoid, 4.0, step=2.0) for b in bowel):
            bowel_shift -= 2.0
        elif any(_overlap(b, a, 3.0, step=2.0) for b in bowel for a in avoid):
            dz += 2.0
        else:
            break
        bowel = _bowel(bowel_shift + dx, dy, dz)
    return bowel


def _z_rod(z_mm: np.ndarray, semi_x_mm: float, semi_y_mm: float, y_mm: float = 0.0) -> Sweep:
    """Return a straight elliptic rod along z at ``x = 0, y = y_mm`` through the samples ``z_mm`` (mm, LPS)."""
    n = len(z_mm)
    return Sweep(np.column_stack([np.zeros(n), np.full(n, y_mm), z_mm]), np.full(n, semi_x_mm), np.full(n, semi_y_mm),
                 (1.0, 0.0, 0.0))


def _tandem(uterus: Sweep, axis: np.ndarray) -> Sweep:
    """Return the tandem: straight through the obturator, then bent into the uterine canal.

    It ends 12 mm short of the fundus and is 6 mm across (ASSUMED), with rounded ends.
    """
    canal = axis[: int((uterus.length_mm - 12.0) / SAMPLE_MM)]
    tandem_line = resample_curve(np.vstack([[0.0, 0.0, -20.0], [0.0, 0.0, 40.0], canal[:-1:24], canal[-1:]]))
    r_t = np.full(len(tandem_line), 3.0) * _round_ends(np.arange(len(tandem_line)) * SAMPLE_MM,
                                                       (len(tandem_line) - 1) * SAMPLE_MM, 0.0, 3.0)
    return Sweep(tandem_line, r_t, r_t, (1.0, 0.0, 0.0))


def _sacrum() -> Sweep:
    """Return the sacrum: a flat band along the posterior pelvic wall (ASSUMED course and size)."""
    sacrum_c = resample_curve(np.array([(0, 74, 62), (0, 86, 110), (0, 92, 160), (0, 92, 205)], float))
    return Sweep(sacrum_c, np.full(len(sacrum_c), 42.0), np.full(len(sacrum_c), 11.0), (1.0, 0.0, 0.0))


def _tissues(body: Sweep, bladder: Sweep, rectum: Sweep, sigmoid: Sweep, bowel: tuple[Sweep, Sweep],
             bones: tuple[Sweep, ...], cervix: Sweep, mr: bool) -> tuple[PhantomStructure, ...]:
    """Return the tissues painted into the image but not written as ROIs.

    Muscle and pelvic fat inside the body, the obturator internus and psoas muscles, urine, gas, bowel fluid,
    marrow and the cervical tumour inside a rim of cervical stroma (T2: dark).
    """
    n = len(body.samples_mm)
    return (
        _paint("muscle", body.shrunk(15.0), "muscle", mr),
        _paint("pelvic fat", Sweep(body.samples_mm - [0.0, 5.0, 0.0], np.full(n, 100.0), np.full(n, 85.0),
                                   (1.0, 0.0, 0.0)), "fat", mr),
        *(_paint(f"obturator internus {i}", tube([(s * 55, 5, 10), (s * 56, 0, 60), (s * 54, 5, 110)], 8.0),
                 "muscle", mr) for i, s in enumerate((1.0, -1.0))),
        *(_paint(f"psoas {i}", tube([(s * 45, 55, 120), (s * 50, 50, 160), (s * 50, 45, 215)], 16.0), "muscle", mr)
          for i, s in enumerate((1.0, -1.0))),
        _paint("urine", bladder.shrunk(2.8), "fluid", mr),
        _paint("rectal gas", rectum.shrunk(3.0), "air", mr),
        _paint("sigmoid gas", sigmoid.shrunk(3.0), "air", mr),
        *(_paint(f"bowel fluid {i}", b.shrunk(3.0), "fluid", mr) for i, b in enumerate(bowel)),
        *(_paint(f"marrow {i}", b.shrunk(2.5), "cancellous bone", mr) for i, b in enumerate(bones)),
        _paint("cervical tumour", cervix.shrunk(3.0), "tumour", mr),
    )


def _target_points(p: ClinicalParams, uterus: Sweep, hrctv: Union) -> list[tuple[str, tuple[float, float, float]]]:
    """Return the named target points (LPS mm), each on a slice boundary.

    Corpus targets in the anterior-inferior part of the body (a fifth of the chord up: about 10 mm from the canal
    and its tandem); parametrial targets in the middle of the extension, on the involved side(s) only. Each is
    written as a small target ROI (``Target_<name>``: a cylinder 8 mm across and 5 mm tall centred on the point,
    its flat ends on slice boundaries, so the ROI's centroid is the point exactly). A line that misses, or whose
    point falls outside the HR-CTV, gives way to the next of :data:`TARGET_FALLBACK` (with an HR-CTV that covers
    only part of the body the corpus targets are taken on the HR-CTV); a target with no line left is not made.
    """
    points = []
    for name, xy in TARGET_COLUMNS.items():
        if name.startswith("param") and name[-1] not in p.parametria:
            continue
        for column in (xy, *TARGET_FALLBACK[name]):
            try:
                x, y, z = (_column_target(uterus if p.hrctv_corpus_fraction == 1.0 else hrctv, column, 0.2)
                           if name.startswith("corpus") else _column_target(hrctv, column))
            except ValueError:  # the line misses: try the fallback, else no such target in this case
                continue
            z = -20.0 + 2.5 * round((z + 20.0) / 2.5)  # on a slice boundary
            if float(hrctv.field(np.array([x, y, z]))) < 0.0:
                points.append((name, (x, y, z)))
                break
    return points


def _target_cylinder(xyz: tuple[float, float, float], radius_mm: float = 4.0) -> Sweep:
    """Return a cylinder along z, ``radius_mm`` across, from 2.5 mm below to 2.5 mm above ``xyz``."""
    n = 21
    c = np.column_stack([np.full(n, xyz[0]), np.full(n, xyz[1]), np.linspace(xyz[2] - 2.5, xyz[2] + 2.5, n)])
    return Sweep(c, np.full(n, radius_mm), np.full(n, radius_mm), (1.0, 0.0, 0.0))


def _column_target(shape: Sweep | Union, xy: tuple[float, float], at: float = 0.5) -> tuple[float, float, float]:
    """Return the point a fraction ``at`` up the highest chord of the line ``(x, y)`` (along z) through ``shape``.

    The chord is taken 2 mm inside the surface.
    """
    z = np.arange(0.0, 210.0, 0.25)
    f = shape.field(np.column_stack([np.full(len(z), xy[0]), np.full(len(z), xy[1]), z]))
    inside = f <= -2.0
    if not inside.any():
        inside = f <= 0.0
    if not inside.any():
        raise ValueError(f"the target line {xy} misses the structure; adjust TARGET_COLUMNS or the anatomy")
    runs = np.flatnonzero(np.diff(np.r_[0, inside.astype(int), 0]))
    starts, stops = runs[::2], runs[1::2]
    k = len(starts) - 1
    return (float(xy[0]), float(xy[1]), round(float(z[starts[k]] + at * (z[stops[k] - 1] - z[starts[k]])), 3))


def write_clinical(out_dir: Path, case: ClinicalCase) -> PhantomFiles:
    """Write the case as an image series (CT or MR) + RT Structure Set.

    Also ``case.json`` (parameters and named target points) beside them, written with them (a ``case.json`` that
    reachplan did not write is not replaced: :class:`~reachplan.imaging.errors.OutputExistsError`).

    Parameters
    ----------
    out_dir : Path
        The folder to write into.
    case : ClinicalCase
        The case.

    Returns
    -------
    PhantomFiles
        The image series folder and the structure set file.
    """
    from reachplan.imaging.files import json_bytes

    return write_phantom(out_dir, case.spec, beside={"case.json": json_bytes(case.to_json())})


def structure_set(spec: PhantomSpec, names: tuple[str, ...] | None = None) -> StructureSet:
    """Return the ROIs of ``spec`` as an in-memory structure set, without writing DICOM (for studies and tests).

    The contours are those :func:`write_phantom` would write, names normalised by the default synonym table.

    Parameters
    ----------
    spec : PhantomSpec
        The phantom.
    names : tuple of str, optional
        The ROIs to take (by name); None takes all.

    Returns
    -------
    StructureSet
        One ROI per structure, its contours at the slice centres (mm, LPS), Frame of Reference ``"in-memory"``.
    """
    from reachplan.imaging.names import DEFAULT_SYNONYMS

    rois = []
    for number, s in enumerate(spec.structures, start=1):
        if names is not None and s.name not in names:
            continue
        contours = tuple(Contour(np.column_stack([poly, np.full(len(poly), z)]))
                         for z in spec.slice_z_mm for poly in s.cross_section(float(z)))
        rois.append(Roi(number, s.name, contours, DEFAULT_SYNONYMS.normalize(s.name), s.interpreted_type, s.color))
    return StructureSet(tuple(rois), frame_of_reference_uid="in-memory")


def image_grid(spec: PhantomSpec) -> Grid:
    """Return the grid of the image series :func:`write_phantom` writes for ``spec``.

    Parameters
    ----------
    spec : PhantomSpec
        The phantom the series is written for.

    Returns
    -------
    Grid
        Shape ``(n_slices, matrix, matrix)``, ``pixel_mm`` in-plane and ``slice_thickness_mm`` between slices.
    """
    m = np.diag([spec.pixel_mm, spec.pixel_mm, spec.slice_thickness_mm, 1.0])
    m[:3, 3] = [spec.first_pixel_xy_mm, spec.first_pixel_xy_mm, float(spec.slice_z_mm[0])]
    return Grid((spec.n_slices, spec.matrix, spec.matrix), m)
