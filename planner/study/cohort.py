"""Deterministic cohorts of case variants for design studies, tests and benchmarks.

``case="clinical"`` (the default): variant ``i`` of seed ``s`` is the built-in clinical case of seed ``s + i``
(:func:`reachplan.imaging.clinical.clinical_case`; its anatomy drawn from the distributions of
:data:`reachplan.imaging.anatomy.VARIETY`, each with its source: uterine version and flexion, uterine size, HR-CTV
size, parametrial and vaginal extension, bladder filling and position, rectum filling, sigmoid and small-bowel
position); its targets are the ``Target_*`` ROIs. :func:`case_anatomy` measures what ``cases.csv`` records of it.

``case="pilot"``: variant ``i`` of seed ``s`` perturbs the pilot phantom
(:func:`reachplan.imaging.phantom.phantom_spec`) with a random
generator seeded by ``(s, i)``: organs move in the axial plane and change size (bladder filling, rectum
calibre, HR-CTV extent), the pelvic side walls move laterally, and the target pattern rotates about the
obturator axis and scales radially. Variant 0 is the reference phantom itself. Every z bound stays where the
phantom puts it (on the CT slab boundaries), so the written contours represent each solid exactly.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from reachplan.imaging.case_spec import PhantomSpec, PhantomStructure
from reachplan.imaging.phantom import phantom_spec, write_phantom
from reachplan.imaging.solids import Box, Cylinder, Ellipsoid, EllipticCylinder, Shape, TorusSection

if TYPE_CHECKING:
    from reachplan.imaging.clinical import ClinicalCase


@dataclass(frozen=True)
class Perturbation:
    """How one cohort variant differs from the reference phantom (mm, degrees, dimensionless factors).

    Parameters
    ----------
    seed : int
        The cohort's seed, shared by all its variants.
    index : int
        The variant's index (0 = the reference phantom).
    shift_xy_mm : tuple of (str, float, float)
        Organ name -> its axial shift (x, y), mm, LPS.
    scale : tuple of (str, float)
        Organ name -> the factor on its axial size (radius or x/y semi-axes), > 0.
    bone_shift_mm : float, mm
        Each pelvic side wall moves outward (> 0) or inward.
    target_rotation_deg : float, degrees
        Rotation of the target pattern about the z axis.
    target_radius_scale : float
        Factor on the target pattern's radius (> 0).

    Raises
    ------
    ValueError
        A scale factor that is not positive.
    """

    seed: int
    index: int
    shift_xy_mm: tuple[tuple[str, float, float], ...]
    scale: tuple[tuple[str, float], ...]
    bone_shift_mm: float
    target_rotation_deg: float
    target_radius_scale: float

    def __post_init__(self) -> None:
        if any(not (np.isfinite(f) and f > 0) for _, f in self.scale) or not self.target_radius_scale > 0:
            raise ValueError("cohort scale factors must be positive")


#: Largest axial shift (mm) per organ; the cervix, obturator and body stay put (the applicator defines the frame).
_SHIFT_MM = {"Bladder": 6.0, "Rectum": 4.0, "Uterus": 5.0, "Bowel": 8.0, "HR-CTV": 3.0}
#: Range of the axial size factor per organ.
_SCALE = {"Bladder": (0.85, 1.2), "Rectum": (0.85, 1.15), "HR-CTV": (0.85, 1.15), "Uterus": (0.9, 1.1)}


def perturbation(seed: int, index: int) -> Perturbation:
    """Return the deterministic perturbation of variant ``index`` (0 = the reference phantom, unperturbed).

    Parameters
    ----------
    seed : int
        Seed of the cohort, shared by every variant.
    index : int
        The variant's index; its generator is seeded by ``(seed, index)``.

    Returns
    -------
    Perturbation
        Shifts, scales, wall shift and target rotation and scale, rounded.
    """
    if index == 0:
        return Perturbation(seed, 0, (), (), 0.0, 0.0, 1.0)
    rng = np.random.default_rng([seed, index])
    shifts = tuple((n, round(float(rng.uniform(-m, m)), 2), round(float(rng.uniform(-m, m)), 2))
                   for n, m in _SHIFT_MM.items())
    scale = tuple((n, round(float(rng.uniform(lo, hi)), 3)) for n, (lo, hi) in _SCALE.items())
    return Perturbation(seed, index, shifts, scale, round(float(rng.uniform(-3.0, 3.0)), 2),
                        round(float(rng.uniform(-10.0, 10.0)), 2), round(float(rng.uniform(0.94, 1.06)), 3))


def _move(shape: Shape, dx: float, dy: float, s: float) -> Shape:
    """``shape`` shifted by (dx, dy) mm in the axial plane, its axial size scaled by ``s`` about its centre."""
    if isinstance(shape, Cylinder):
        (cx, cy) = shape.center_xy_mm
        return dataclasses.replace(shape, center_xy_mm=(cx + dx, cy + dy), radius_mm=shape.radius_mm * s)
    if isinstance(shape, EllipticCylinder):
        (cx, cy), (a, b) = shape.center_xy_mm, shape.semi_axes_xy_mm
        return dataclasses.replace(shape, center_xy_mm=(cx + dx, cy + dy), semi_axes_xy_mm=(a * s, b * s))
    if isinstance(shape, Ellipsoid):
        (cx, cy, cz), (a, b, c) = shape.center_mm, shape.semi_axes_mm
        return dataclasses.replace(shape, center_mm=(cx + dx, cy + dy, cz), semi_axes_mm=(a * s, b * s, c))
    if isinstance(shape, TorusSection):
        cx, cy, cz = shape.center_mm
        return dataclasses.replace(shape, center_mm=(cx + dx, cy + dy, cz))
    if isinstance(shape, Box):
        (x0, y0, z0), (x1, y1, z1) = shape.lo_mm, shape.hi_mm
        return Box((x0 + dx, y0 + dy, z0), (x1 + dx, y1 + dy, z1))
    raise TypeError(f"unknown phantom shape {type(shape).__name__}")


def _structure(s: PhantomStructure, fn: Callable[[Shape], Shape]) -> PhantomStructure:
    return dataclasses.replace(s, shapes=tuple(fn(sh) for sh in s.shapes))


def perturbed_spec(p: Perturbation, base: PhantomSpec | None = None) -> PhantomSpec:
    """Return the phantom ``base`` (default: the built-in one) with perturbation ``p`` applied.

    Parameters
    ----------
    p : Perturbation
        The variant's perturbation.
    base : PhantomSpec or None
        The phantom to perturb; None: :func:`reachplan.imaging.phantom.phantom_spec`.

    Returns
    -------
    PhantomSpec
        Organs shifted and scaled in the axial plane, side walls moved, targets rotated and scaled; every z bound
        kept.
    """
    base = base or phantom_spec()
    shift = {n: (dx, dy) for n, dx, dy in p.shift_xy_mm}
    scale = dict(p.scale)
    rot = math.radians(p.target_rotation_deg)
    c, s = math.cos(rot), math.sin(rot)
    out = []
    for st in base.structures:
        dx, dy = shift.get("Rectum" if st.name == "Sigmoid" else st.name, (0.0, 0.0))  # the sigmoid follows the rectum
        if st.name == "Bone":
            def wall(b: Shape, d: float = p.bone_shift_mm) -> Shape:
                mid = 0.5 * (b.bounds()[0][0] + b.bounds()[1][0])
                return _move(b, math.copysign(d, mid) if abs(mid) > 30 else 0.0, 0.0, 1.0)
            out.append(_structure(st, wall))
        elif st.name.startswith("Target_"):
            def target(t: Shape) -> Shape:
                assert isinstance(t, Cylinder)
                x, y = t.center_xy_mm
                k = p.target_radius_scale
                nx, ny = k * (c * x - s * y), k * (s * x + c * y)
                return _move(t, round(nx - x, 6), round(ny - y, 6), 1.0)
            out.append(_structure(st, target))
        else:
            def organ(sh: Shape, dx: float = dx, dy: float = dy, k: float = scale.get(st.name, 1.0)) -> Shape:
                return _move(sh, dx, dy, k)
            out.append(_structure(st, organ))
    return dataclasses.replace(base, structures=tuple(out))


def make_cohort(out_dir: Path, n: int, seed: int = 0, case: str = "clinical") -> tuple[Path, ...]:
    """Write ``n`` case variants as ``out_dir/case_000``, ``case_001``, ... (image series + RT Structure Set).

    Deterministic in ``(seed, index)``. ``case="clinical"``: the clinical case of seed ``seed + index``;
    ``case="pilot"``: the pilot phantom perturbed (variant 0 is its reference geometry). Each variant carries
    its own Patient ID and DICOM UIDs (``PhantomSpec.case_id`` = the folder name). ``out_dir/cohort.json``
    records the variants.

    Parameters
    ----------
    out_dir : Path
        The cohort folder.
    n : int
        Number of variants (>= 1).
    seed : int
        The cohort's seed.
    case : {"clinical", "pilot"}
        Which case to vary.

    Returns
    -------
    tuple of Path
        The case folders, in index order.

    Raises
    ------
    ValueError
        ``n`` < 1 or an unknown ``case``.
    """
    if n < 1:
        raise ValueError(f"a cohort needs at least one case, got {n}")
    if case not in ("clinical", "pilot"):
        raise ValueError(f"case must be 'clinical' or 'pilot', got {case!r}")
    from reachplan.imaging.clinical import clinical_case, write_clinical
    from reachplan.imaging.files import atomic_write_json

    out_dir = Path(out_dir)
    cases = []
    doc: list[dict[str, object]] = []
    for i in range(n):
        folder = out_dir / f"case_{i:03d}"
        if case == "clinical":
            c = clinical_case(seed + i, case_id=folder.name)
            write_clinical(folder, c)
            doc.append({"case": folder.name, "seed": seed + i, **dataclasses.asdict(c.params)})
        else:
            p = perturbation(seed, i)
            write_phantom(folder, dataclasses.replace(perturbed_spec(p), case_id=folder.name))
            doc.append({"case": folder.name, **dataclasses.asdict(p)})
        cases.append(folder)
    atomic_write_json(out_dir / "cohort.json", {"seed": seed, "kind": case, "cases": doc})
    return tuple(cases)


@dataclass(frozen=True)
class CaseAnatomy:
    """What a clinical case's anatomy is, as ``cases.csv`` records it (measured on the built case).

    Parameters
    ----------
    hrctv_cm3 : float, cm³
        HR-CTV volume (its solid integrated on a 1 mm lattice).
    bladder_cm3 : float, cm³
        Bladder volume after it was placed clear of the HR-CTV and bones (it may hold less than drawn).
    rectum_cm3 : float, cm³
        Rectum volume.
    uterus_version_deg, uterus_flexion_deg : float, degrees
        Version and flexion as built (negative: retro-).
    parametrial_extension : str
        ``none`` or side(s) and extent, e.g. ``left proximal``, ``bilateral distal``.
    vaginal_extension_mm : float, mm
        Length of the vaginal extension (0: none).
    """

    hrctv_cm3: float
    bladder_cm3: float
    rectum_cm3: float
    uterus_version_deg: float
    uterus_flexion_deg: float
    parametrial_extension: str
    vaginal_extension_mm: float


def case_anatomy(case: ClinicalCase) -> CaseAnatomy:
    """Return the anatomy of a built clinical case (volumes measured on its solids).

    Parameters
    ----------
    case : ClinicalCase
        The case (:func:`reachplan.imaging.clinical.clinical_case`).

    Returns
    -------
    CaseAnatomy
        Volumes (cm³, rounded to 0.1) and the anatomy's descriptors.
    """
    def volume_cm3(name: str) -> float:
        (shape,) = case.spec.get(name).shapes
        return round(float(shape.analytic_volume_mm3) / 1000.0, 1)

    p = case.params
    return CaseAnatomy(volume_cm3("CTV_HR"), volume_cm3("Bladder"), volume_cm3("Rectum"), p.version_deg,
                       p.flexion_deg, p.parametrial_extension, p.vaginal_extension_mm)
