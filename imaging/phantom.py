"""A deterministic synthetic pelvis for gynecologic interstitial brachytherapy, written as DICOM.

The phantom follows the OncoReach pilot phantom (reference ``oncoreach.md``, "Tissue and phantom": SimuGel
tissue, a uterus, 10 mm target cylinders, 15 mm tall every 60 degrees on a 65 mm circle and 5 mm tall on
an 80 mm circle) and the clinical case it stands for: an anteverted uterus tilted toward the bladder, a
cervix with a vaginal obturator, an HR-CTV reaching laterally into the parametria, bladder, rectum,
sigmoid colon, a bowel loop and pelvic bones.

Every structure is a union of disjoint analytic solids (:mod:`reachplan.imaging.solids`: cylinders, elliptic
cylinders, boxes, ellipsoids, torus sections) with a closed-form volume, so the DICOM round trip (write -> read
-> mask -> mesh) can be checked against exact numbers; :mod:`reachplan.imaging.case_dicom` encodes the files
:func:`write_phantom` writes. Geometry in DICOM patient
coordinates (LPS, mm): patient supine, +x patient left, +y posterior, +z superior; the perineal template
plane is ``z = 0`` with its centre on the obturator axis ``(0, 0, 0)`` and needles go in along +z.

CT slices are 2.5 mm thick with centres at ``z = -28.75 + 2.5 k``, so slab boundaries fall on multiples of
2.5 mm, where every flat end of a solid is placed (a contour stack then represents them exactly).

Geometry (LPS mm; exact values in :func:`phantom_spec`)
--------------------------------------------------------
* CT: 84 slices z -30..180, 256 x 256 pixels of 1 mm centred on the z axis; air -1000 HU, an 8 mm
  subcutaneous fat layer -90 HU, SimuGel +30 HU.
* Body: elliptic cylinder semi-axes (95, 90), z -30..180 (EXTERNAL).
* Obturator: cylinder r 15 on the z axis, z -30..60, +100 HU (BRACHY_ACCESSORY).
* Cervix: cylinder r 15, z 60..85, +50 HU. Uterus: ellipsoid semi (25, 18, 38) centred (0, -25, 115), long
  axis tilted 45 degrees from +z toward anterior (anteverted, toward the bladder), +45 HU.
* HR-CTV: ellipsoid semi (45, 20, 18) centred (0, 0, 75), +55 HU (CTV).
* Bladder: ellipsoid semi (40, 18, 25) centred (0, -65, 100), +10 HU.
* Rectum: cylinder r 12 at (0, 60), z -20..100, +40 HU. Sigmoid: tube r 10 on a quarter circle of radius 35
  from the rectum top (0, 60, 100) toward patient left and up to (35, 60, 135), +40 HU.
* Bowel: torus R 25, r 10 centred (0, -10, 160), axis along z, +35 HU.
* Bone (AVOIDANCE, +700 HU): side walls |x| 62..75, y -40..30, z -10..120; pubic symphysis x -15..15,
  y -75..-60, z -10..30.
* Targets (PTV, +80 HU): cylinders r 5, axes along z: ``Target_65_aaa`` 15 mm tall (z 67.5..82.5) on a 65 mm
  circle at angles 0, 60, ..., 300; ``Target_80_aaa`` 5 mm tall (z 77.5..82.5) on an 80 mm circle at
  30, 90, ..., 330; angle 0 = patient left (+x), 90 = anterior (-y).
* ``patient_from_template`` is the identity: template plane z = 0, centre on the obturator axis.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from reachplan.imaging.case_dicom import encode, image_files, is_case_file, rtstruct_dataset
from reachplan.imaging.case_spec import PhantomSpec, PhantomStructure
from reachplan.imaging.errors import OutputExistsError
from reachplan.imaging.files import atomic_write_files, digest, manifest_file, written_by_reachplan
from reachplan.imaging.solids import Box, Cylinder, Ellipsoid, EllipticCylinder, TorusSection, rotation_x
from reachplan.imaging.sweep import Sweep, Union


def _targets() -> list[PhantomStructure]:
    """Build the reference target cylinders (10 mm diameter, axes along z); angle 0 = patient left, 90 = anterior."""
    out = []
    for diameter, height, z_centre, angles in ((65.0, 15.0, 75.0, range(0, 360, 60)),
                                               (80.0, 5.0, 80.0, range(30, 360, 60))):
        r = diameter / 2
        for a in angles:
            x, y = r * math.cos(math.radians(a)), -r * math.sin(math.radians(a))
            out.append(PhantomStructure(
                f"Target_{diameter:.0f}_{a:03d}", "PTV",
                (Cylinder((round(x, 6), round(y, 6)), 5.0, z_centre - height / 2, z_centre + height / 2),),
                hu=80.0, color=(255, 0, 0)))
    return out


def phantom_spec() -> PhantomSpec:
    """Describe the built-in phantom analytically (see the module docstring for frames and values).

    Returns
    -------
    PhantomSpec
        The pilot phantom: its ROIs (the reference target cylinders included), tissues and CT geometry.
    """
    tilt = rotation_x(45.0)  # uterus long axis: +z tilted 45 degrees toward anterior (-y)
    structures = [
        PhantomStructure("Body", "EXTERNAL", (EllipticCylinder((0.0, 0.0), (95.0, 90.0), -30.0, 180.0),),
                         hu=30.0, color=(200, 180, 140)),
        PhantomStructure("Bone", "AVOIDANCE", (
            Box((-75.0, -40.0, -10.0), (-62.0, 30.0, 120.0)),  # right pelvic side wall
            Box((62.0, -40.0, -10.0), (75.0, 30.0, 120.0)),  # left pelvic side wall
            Box((-15.0, -75.0, -10.0), (15.0, -60.0, 30.0)),  # pubic symphysis
        ), hu=700.0, color=(240, 240, 220), is_oar=True),
        PhantomStructure("Rectum", "ORGAN", (Cylinder((0.0, 60.0), 12.0, -20.0, 100.0),),
                         hu=40.0, color=(150, 90, 40), is_oar=True),
        PhantomStructure("Sigmoid", "ORGAN", (TorusSection(
            (35.0, 60.0, 100.0), 35.0, 10.0, u=(-1.0, 0.0, 0.0), v=(0.0, 0.0, 1.0), phi0_deg=0.0, phi1_deg=90.0),),
            hu=40.0, color=(200, 120, 60), is_oar=True),
        PhantomStructure("Bowel", "ORGAN", (TorusSection(
            (0.0, -10.0, 160.0), 25.0, 10.0, u=(1.0, 0.0, 0.0), v=(0.0, 1.0, 0.0)),),
            hu=35.0, color=(230, 180, 60), is_oar=True),
        PhantomStructure("Bladder", "ORGAN", (Ellipsoid((0.0, -65.0, 100.0), (40.0, 18.0, 25.0)),),
                         hu=10.0, color=(250, 230, 50), is_oar=True),
        PhantomStructure("Uterus", "ORGAN", (Ellipsoid(
            (0.0, -25.0, 115.0), (25.0, 18.0, 38.0), tuple(tuple(float(v) for v in row) for row in tilt)),),
            hu=45.0, color=(230, 130, 170)),
        PhantomStructure("Cervix", "ORGAN", (Cylinder((0.0, 0.0), 15.0, 60.0, 85.0),),
                         hu=50.0, color=(200, 90, 140)),
        PhantomStructure("HR-CTV", "CTV", (Ellipsoid((0.0, 0.0, 75.0), (45.0, 20.0, 18.0)),),
                         hu=55.0, color=(255, 60, 60)),
        PhantomStructure("Obturator", "BRACHY_ACCESSORY", (Cylinder((0.0, 0.0), 15.0, -30.0, 60.0),),
                         hu=100.0, color=(120, 120, 255)),
        *_targets(),
    ]
    return PhantomSpec(tuple(structures))


# Paint order of the CT (later wins): tissue first, then organs, target complex, applicator, bone.
_PAINT_ORDER = ("Body", "Rectum", "Sigmoid", "Bowel", "Bladder", "Uterus", "Cervix", "HR-CTV")


def phantom_ct_hu(spec: PhantomSpec) -> np.ndarray:
    """Paint the CT of the phantom in HU, sampled at the voxel centres (later structures in the paint order win).

    Parameters
    ----------
    spec : PhantomSpec
        The phantom (structures, CT geometry and CT numbers).

    Returns
    -------
    hu : (n_slices, matrix, matrix) int16, HU
        Indexed ``[k, j, i]`` (slice, row = y, column = x); voxel centres at LPS ``z = spec.slice_z_mm[k]``,
        ``y = x0 + j * pixel_mm``, ``x = x0 + i * pixel_mm`` with ``x0 = spec.first_pixel_xy_mm``.
    """
    n, z = spec.matrix, spec.slice_z_mm
    xy = spec.first_pixel_xy_mm + np.arange(n) * spec.pixel_mm
    hu = np.full((len(z), n, n), spec.air_hu, dtype=np.float32)
    if spec.paint_order:
        for name in spec.paint_order:
            _paint(hu, spec.get(name), z, xy)
        return np.round(hu).astype(np.int16)
    order = [*_PAINT_ORDER, *(s.name for s in spec.targets), "Obturator", "Bone"]
    painted = {s.name for s in spec.structures if s.name in order}
    order += [s.name for s in spec.structures if s.name not in painted]
    body = spec.get("Body") if "Body" in {s.name for s in spec.structures} else None
    fat_inner = None
    if body is not None and isinstance(body.shapes[0], EllipticCylinder) and spec.fat_thickness_mm > 0:
        outer = body.shapes[0]
        (a, b), t = outer.semi_axes_xy_mm, spec.fat_thickness_mm
        fat_inner = PhantomStructure("gel", "", (EllipticCylinder(outer.center_xy_mm, (a - t, b - t), outer.z0_mm,
                                                                  outer.z1_mm),), hu=body.hu, color=body.color)
        body = PhantomStructure("fat", "", body.shapes, hu=spec.fat_hu, color=body.color)
    for name in order:
        if name == "Body" and body is not None and fat_inner is not None:
            shapes = [body, fat_inner]
        else:
            shapes = [spec.get(name)]
        for s in shapes:
            _paint(hu, s, z, xy)
    return np.round(hu).astype(np.int16)


def _paint(hu: np.ndarray, s: PhantomStructure, z: np.ndarray, xy: np.ndarray) -> None:
    """Set ``hu`` to ``s.hu`` at the voxel centres inside ``s`` (in place)."""
    lo, hi = s.bounds()
    ks = np.flatnonzero((z >= lo[2]) & (z <= hi[2]))
    js = np.flatnonzero((xy >= lo[1]) & (xy <= hi[1]))
    is_ = np.flatnonzero((xy >= lo[0]) & (xy <= hi[0]))
    if not (len(ks) and len(js) and len(is_)):
        return
    parts = [sh for sh in s.shapes if isinstance(sh, Sweep | Union)]
    if len(parts) == len(s.shapes):  # slice by slice, in each part's window
        for sh in parts:
            for k in ks:
                win = sh.slice_window(float(z[k]))
                if win is None:
                    continue
                j = np.flatnonzero((xy >= win[0][1]) & (xy <= win[1][1]))
                i = np.flatnonzero((xy >= win[0][0]) & (xy <= win[1][0]))
                if not (len(j) and len(i)):
                    continue
                gy, gx = np.meshgrid(xy[j], xy[i], indexing="ij")
                inside = sh.contains(np.stack([gx, gy, np.full_like(gx, z[k])], axis=-1))
                hu[k, j[0]:j[-1] + 1, i[0]:i[-1] + 1][inside] = s.hu
        return
    gz, gy, gx = np.meshgrid(z[ks], xy[js], xy[is_], indexing="ij")
    inside = s.contains(np.stack([gx, gy, gz], axis=-1))
    sub = hu[ks[0]:ks[-1] + 1, js[0]:js[-1] + 1, is_[0]:is_[-1] + 1]
    sub[inside] = s.hu


@dataclass(frozen=True)
class PhantomFiles:
    """Where :func:`write_phantom` put the phantom.

    Parameters
    ----------
    ct_dir : Path
        The image series folder (CT or MR).
    rtstruct_path : Path
        The RT Structure Set file.
    """

    ct_dir: Path
    rtstruct_path: Path


def write_phantom(out_dir: Path, spec: PhantomSpec | None = None, beside: Mapping[str, bytes] | None = None,
                  values: np.ndarray | None = None) -> PhantomFiles:
    """Write the phantom as a DICOM CT series and an RT Structure Set.

    Files: ``out_dir/CT/CT.0001.dcm ...`` (``out_dir/MR/MR.0001.dcm ...`` for an MR spec) and
    ``out_dir/RS.phantom.dcm``. The output is deterministic
    (fixed UIDs derived from the phantom version). Existing phantom files are replaced (atomically,
    file by file); any other file in the way is left untouched and :class:`OutputExistsError` is raised
    before anything is written. The files are recorded in ``out_dir``'s record of what reachplan wrote
    (:func:`~reachplan.imaging.files.manifest_file`, renamed in with them); on a failure (a full disk) nothing new is
    left, not even a folder.

    Parameters
    ----------
    out_dir : Path
        Folder to create or reuse.
    spec : PhantomSpec, optional
        The phantom to write (default :func:`phantom_spec`).
    beside : mapping of str to bytes, optional
        More files for ``out_dir`` (name -> content, e.g. the clinical case's ``case.json``), written with the
        series; one that exists is replaced only when reachplan wrote it.
    values : (n_slices, matrix, matrix) int16, optional
        The image to write (HU, or MR signal), e.g. with needles painted in
        (:func:`reachplan.imaging.implanted.implanted_image`); None: :func:`phantom_ct_hu` of ``spec``.

    Returns
    -------
    PhantomFiles

    Raises
    ------
    OutputExistsError
        ``out_dir`` is a file, or a file that is not a reachplan phantom file is in the way.
    """
    spec = spec or phantom_spec()
    out_dir = Path(out_dir)
    ct_dir, rs_path = out_dir / spec.modality, out_dir / "RS.phantom.dcm"
    if out_dir.exists() and not out_dir.is_dir():
        raise OutputExistsError(f"{out_dir} is a file; give a folder for the phantom")
    names = [f"{spec.modality}.{k + 1:04d}.dcm" for k in range(spec.n_slices)]
    in_the_way = [p for p in [rs_path, *(ct_dir / n for n in names)] if p.exists() and not is_case_file(p)]
    in_the_way += [p for p in (out_dir / n for n in beside or {}) if p.exists() and not written_by_reachplan(p)]
    stale = []
    if ct_dir.is_dir():
        extra = [p for p in sorted(ct_dir.iterdir()) if p.name not in names and not p.name.startswith(".")]
        in_the_way += [p for p in extra if not is_case_file(p)]
        stale = [p for p in extra if p not in in_the_way]
    if in_the_way:
        raise OutputExistsError(
            f"{in_the_way[0]} (and {len(in_the_way) - 1} more) is not a reachplan phantom file; "
            "refusing to overwrite: choose an empty or new --out folder"
        )
    ct, encoded = [], []
    for name, data, ref in image_files(spec, phantom_ct_hu(spec) if values is None else values):
        encoded.append((ct_dir / name, data))
        ct.append(ref)
    encoded.append((rs_path, encode(rtstruct_dataset(spec, ct))))
    encoded += [(out_dir / name, data) for name, data in (beside or {}).items()]
    encoded.append(manifest_file(out_dir, {path: digest(data) for path, data in encoded}))  # renamed in with them
    atomic_write_files(encoded)  # each file atomic, one batch of disk flushes for the series
    for p in stale:  # slices of an older phantom version would form a second series
        p.unlink()
    return PhantomFiles(ct_dir=ct_dir, rtstruct_path=rs_path)
