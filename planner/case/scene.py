"""The scene of a case: the organs to avoid (meshed, with distance fields), the targets, the template and its pose."""

from __future__ import annotations

import functools
import hashlib
import threading
from collections import OrderedDict
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from typing import TypeVar, cast

import numpy as np
import trimesh
from tqdm import tqdm

from reachplan.imaging.errors import StructureError
from reachplan.imaging.types import Grid, Roi, StructureSet
from reachplan.planner.case.config import SCREEN_BAND_MM, PlanConfig
from reachplan.planner.errors import PlanInputError
from reachplan.planner.geometry.collision import Organ, make_organ, with_distance_field
from reachplan.planner.geometry.organs import check_unique, has_closed, roi_points, select_oars
from reachplan.planner.geometry.template import TemplatePose, pose_from_obturator
from reachplan.planner.lookup import applicator_kinds, load_template
from reachplan.planner.steering.candidates import Target
from reachplan.plugins.applicators import Applicator, applicators_from_structures
from reachplan.plugins.templates import Template

_T = TypeVar("_T")


@dataclass(frozen=True, eq=False)
class Scene:
    """What a plan needs: organs to avoid, targets, the template and its pose.

    Parameters
    ----------
    organs : tuple of Organ
        The organs at risk a needle must not touch (meshes, LPS mm).
    targets : tuple of Target
        The points to reach.
    template : Template
        The needle template.
    patient_from_template : (4, 4) float, template frame -> LPS mm
        The template's pose (rigid).
    meshes : dict of str to trimesh.Trimesh
        Every meshed ROI by normalised name, LPS mm (for figures and exports).
    pose : TemplatePose or None
        How the pose was found.
    notes : tuple of str
        Warnings about the input (organs at risk not found or skipped, targets planned to points).
    applicators : tuple of Applicator
        The applicators recognised in the structure set (or assigned with ``--applicator``), channels oriented
        along the template axis.
    """

    organs: tuple[Organ, ...]
    targets: tuple[Target, ...]
    template: Template
    patient_from_template: np.ndarray
    meshes: dict[str, trimesh.Trimesh] = field(default_factory=dict)
    pose: TemplatePose | None = None
    notes: tuple[str, ...] = ()
    applicators: tuple[Applicator, ...] = ()


#: Meshes and organs this process made with ``reuse=True``, by the ROI's content (most recently used last): cases of
#: a study share ROIs (the generated cases' pelvic bone, the largest mesh, is the same in each), so a worker meshes,
#: builds the collision model and distance field of such a ROI once. Read-only once made; at most
#: :data:`_REUSE_SIZE` are kept (more than a case makes, so the previous case's are all there).
_REUSED: OrderedDict[tuple[object, ...], object] = OrderedDict()
_REUSE_SIZE = 40
_REUSE_LOCK = threading.Lock()


def _roi_key(roi: Roi, grid: Grid | None) -> str:
    """Return a digest of what a ROI's mesh depends on: its name, contours (type and points) and the image grid."""
    h = hashlib.sha1(roi.normalized_name.encode())
    for c in roi.contours:
        h.update(c.geometric_type.encode())
        h.update(np.ascontiguousarray(c.points_mm, dtype=float).tobytes())
    if grid is not None:
        h.update(np.asarray(grid.shape, dtype=np.int64).tobytes())
        h.update(np.ascontiguousarray(grid.patient_from_index, dtype=float).tobytes())
    return h.hexdigest()


def _reused(key: tuple[object, ...], make: Callable[[], _T], reuse: bool) -> _T:
    """Return ``make()``, or with ``reuse`` the value this process made for ``key`` before (then kept for later)."""
    if not reuse:
        return make()
    with _REUSE_LOCK:
        if key in _REUSED:
            _REUSED.move_to_end(key)
            return cast(_T, _REUSED[key])
    value = make()
    with _REUSE_LOCK:
        _REUSED[key] = value
        while len(_REUSED) > _REUSE_SIZE:
            _REUSED.popitem(last=False)
    return value


def mesh_structures(
    structures: StructureSet, names: Iterable[str], grid: Grid | None = None, quiet: bool = True,
    reuse: bool = False,
) -> dict[str, trimesh.Trimesh]:
    """Watertight meshes of the named ROIs that exist in ``structures``, by normalised name.

    Parameters
    ----------
    structures : StructureSet
        The structure set.
    names : iterable of str
        ROI names to mesh (case-insensitive); absent ones and ROIs without closed contours are skipped.
    grid : Grid or None
        The image grid the contours were drawn on (meshing resolution); None: chosen from the contours.
    quiet : bool
        No progress bar.
    reuse : bool
        Take the mesh of a ROI this process meshed before with the same contours and grid (a study's later cases;
        the meshes are shared: do not modify them).

    Returns
    -------
    dict of str to trimesh.Trimesh
        Normalised ROI name -> mesh, LPS mm.
    """
    from reachplan.imaging.meshing import roi_mesh

    wanted = [n for n in names if n.casefold() in {s.casefold() for s in structures.names}]
    out: dict[str, trimesh.Trimesh] = {}
    for name in tqdm(wanted, desc="meshing organs", unit="roi", disable=quiet, leave=False):
        roi = structures.get(name)
        if has_closed(roi):
            key = ("mesh", _roi_key(roi, grid) if reuse else roi.normalized_name)
            out[roi.normalized_name] = _reused(key, functools.partial(roi_mesh, roi, grid), reuse)
    return out


def build_scene(
    structures: StructureSet,
    target_names: Sequence[str] | None = None,
    target_points: Sequence[Target] = (),
    grid: Grid | None = None,
    patient_from_template: np.ndarray | TemplatePose | None = None,
    config: PlanConfig | None = None,
    quiet: bool = True,
    *,
    allow_no_oars: bool = False,
    standard_names: Sequence[str] | None = None,
    reuse: bool = False,
) -> Scene:
    """Recognise the applicators, mesh the organs at risk and the target ROIs, and place the template.

    Parameters
    ----------
    structures : StructureSet
        The case's ROIs (contours mm, LPS).
    target_names : sequence of str or None
        ROI names whose centroids are targets; None = every ROI named ``Target*``. A target ROI made only of POINT
        contours gives one target per point (named ``ROI`` or ``ROI_k``; a note says so).
    target_points : sequence of Target
        Further targets given as points (mm, LPS).
    grid : Grid or None
        The CT grid to rasterise contours on (None: a grid derived from the contours).
    patient_from_template : (4, 4) float array, TemplatePose or None
        The template pose (mm, LPS); None = placed on the obturator (or vaginal cylinder) applicator's ROI.
    config : PlanConfig or None
        Organs at risk, template, obturator depth, ranking cap and the ``--applicator`` assignments.
    quiet : bool
        No progress bars.
    allow_no_oars : bool
        Plan even when no organ at risk is found (otherwise a :class:`PlanInputError`).
    standard_names : sequence of str or None
        The synonym table's standard names (ROIs not mapped to one are listed in the notes).
    reuse : bool
        Take the mesh and organ (collision model, distance field) of a ROI this process made before from the same
        contours and grid (:func:`mesh_structures`; for studies, whose cases share ROIs).

    Returns
    -------
    Scene
        Organs (those of ``config.oar_names`` and every applicator that is an obstacle), targets, template, pose
        and applicators.

    Raises
    ------
    PlanInputError
        No organ at risk (unless allowed), no target, no ROI to place the template on, or a duplicate ROI name.

    Notes
    -----
    Organs at risk that are missing or have no closed contours are named in ``Scene.notes`` (see
    :func:`reachplan.planner.geometry.organs.select_oars`).
    """
    config = config or PlanConfig()
    if target_names is None:
        target_names = [n for n in structures.names if n.casefold().startswith("target")]
    kinds = applicator_kinds()
    found = applicators_from_structures(structures, kinds, dict(config.applicators))
    check_unique(structures, [*target_names, *([] if patient_from_template is not None or _cylinder(found)
                                                else ["Obturator"])])
    parts = {structures.get(a.roi_name).normalized_name: a for a in found if a.roi_name}
    obstacles = [n for n, a in parts.items() if a.obstacle]
    oar_names = (*config.oar_names, *[n for n in obstacles if n not in config.oar_names])
    selection = select_oars(structures, oar_names, standard_names, exclude=target_names)
    oars = list(selection.found)
    notes = list(selection.notes)
    if not oars and not allow_no_oars:
        raise PlanInputError(
            f"no organ at risk to check needles against: none of {', '.join(config.oar_names)} is in the "
            f"structure set with closed contours (ROIs: {', '.join(repr(r.name) for r in structures.rois)}); map "
            "one with --oar ORGAN=ROI_NAME or --synonyms FILE, or plan anyway with --allow-no-oars"
        )
    rois = [structures.get(n) for n in target_names]
    context = [*[n for n in ("HR-CTV", "Uterus", "Cervix") if n in structures.names],
               *[n for n in parts if n not in oars],  # for the figures: the target volume and the applicators
               *_modulus_organs(structures, config)]  # the organs given a tissue modulus
    meshes = mesh_structures(structures, [*oars, *[r.normalized_name for r in rois if has_closed(r)], *context],
                             grid, quiet, reuse)
    targets = [*_targets(rois, meshes, notes), *target_points]
    if not targets:
        raise PlanInputError("no targets: name target ROIs or give target points")
    pose = _pose(structures, patient_from_template, config, _cylinder(found))
    applicators = applicators_from_structures(structures, kinds, dict(config.applicators),
                                              axis=pose.patient_from_template[:3, 2])
    notes += [note for a in applicators for note in a.notes]  # e.g. a tandem that gives no channel, and why
    # distance-field screen (issue 19): FCL confirms clearances up to the ranking's cap + SCREEN_BAND_MM
    confirm = config.weights.clearance_cap_mm + SCREEN_BAND_MM
    organs = tuple(_reused(("organ", _roi_key(structures.get(n), grid) if reuse else n, confirm),
                           functools.partial(_organ, n, meshes[n], confirm), reuse) for n in oars)
    return Scene(organs, tuple(targets), load_template(config.template), pose.patient_from_template,
                 meshes, pose=pose, notes=tuple(notes), applicators=applicators)


def _modulus_organs(structures: StructureSet, config: PlanConfig) -> list[str]:
    """Return the normalised names of the ROIs ``config.tissue_moduli_pa`` names (typed error for one not there)."""
    names = []
    for name, _ in config.tissue_moduli_pa:
        try:
            names.append(structures.get(name).normalized_name)
        except StructureError:
            raise PlanInputError(f"--organ-modulus names {name!r}, which is not a ROI of the structure set (ROIs: "
                                 f"{', '.join(repr(r.name) for r in structures.rois)})") from None
    return names


def _organ(name: str, mesh: trimesh.Trimesh, confirm_mm: float) -> Organ:
    """Return an organ to keep needles off: its mesh (LPS mm) and distance-field screen (FCL within ``confirm_mm``)."""
    return with_distance_field(make_organ(name, mesh), confirm_mm)


def _cylinder(applicators: Sequence[Applicator]) -> str | None:
    """Return the ROI name of the first obturator or vaginal cylinder among ``applicators`` (None: none)."""
    return next((a.roi_name for a in applicators if a.kind in ("obturator", "cylinder") and a.roi_name), None)


def _targets(rois: Sequence[Roi], meshes: dict[str, trimesh.Trimesh], notes: list[str]) -> list[Target]:
    """Return the targets of target ROIs: a closed ROI's centroid, or each point of a POINT ROI (noted in ``notes``)."""
    targets = []
    for roi in rois:
        if has_closed(roi):
            x, y, z = (float(v) for v in meshes[roi.normalized_name].center_mass)
            targets.append(Target(roi.normalized_name, (x, y, z)))
            continue
        pts = roi_points(roi)
        notes.append(f"target ROI {roi.name!r} is made of POINT contours: planned to its {len(pts)} point(s)")
        for k, p in enumerate(pts, start=1):
            name = roi.normalized_name if len(pts) == 1 else f"{roi.normalized_name}_{k}"
            targets.append(Target(name, (float(p[0]), float(p[1]), float(p[2]))))
    return targets


def _pose(structures: StructureSet, given: np.ndarray | TemplatePose | None, config: PlanConfig,
          cylinder: str | None) -> TemplatePose:
    """Return the template pose: ``given``, else fitted to the obturator/cylinder ROI ``cylinder`` or ``Obturator``."""
    if isinstance(given, TemplatePose):
        return given
    if given is not None:
        return TemplatePose(np.asarray(given, dtype=float), "given")
    name = cylinder or "Obturator"
    if name not in structures.names:
        raise PlanInputError("no Obturator (or vaginal cylinder) ROI to place the template on; give the pose "
                             "with --template-origin X,Y,Z --template-axis X,Y,Z, --template-pose FILE or "
                             "--rtplan FILE")
    obturator = structures.get(name)
    return TemplatePose(pose_from_obturator(obturator, config.obturator_depth_mm),
                        f"fitted to ROI {obturator.name!r} (principal axis of its contours; template "
                        f"{config.obturator_depth_mm:g} mm behind its cranial tip)")
