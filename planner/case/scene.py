"""The scene of a case: the organs to avoid (meshed, with distance fields), the targets, the template and its pose."""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np
import trimesh
from tqdm import tqdm

from reachplan.imaging.types import Grid, StructureSet
from reachplan.planner.case.config import SCREEN_BAND_MM, PlanConfig
from reachplan.planner.errors import PlanInputError
from reachplan.planner.geometry.collision import Organ, make_organ, with_distance_field
from reachplan.planner.geometry.organs import check_unique, has_closed, roi_points, select_oars
from reachplan.planner.geometry.template import TemplatePose, pose_from_obturator
from reachplan.planner.lookup import load_template
from reachplan.planner.steering.candidates import Target
from reachplan.plugins.templates import Template

if TYPE_CHECKING:
    pass


@dataclass(frozen=True, eq=False)
class Scene:
    """What a plan needs: organs to avoid, targets, the template and its pose.

    ``meshes`` holds every meshed ROI by normalised name (for figures and exports);
    ``patient_from_template`` is (4, 4), LPS mm; ``pose`` says how it was found; ``notes`` are warnings about
    the input (organs at risk not found or skipped, targets planned to points).
    """

    organs: tuple[Organ, ...]
    targets: tuple[Target, ...]
    template: Template
    patient_from_template: np.ndarray
    meshes: dict[str, trimesh.Trimesh] = field(default_factory=dict)
    pose: TemplatePose | None = None
    notes: tuple[str, ...] = ()


def mesh_structures(
    structures: StructureSet, names: Iterable[str], grid: Grid | None = None, quiet: bool = True
) -> dict[str, trimesh.Trimesh]:
    """Watertight meshes (LPS mm) of the named ROIs that exist in ``structures``, by normalised name."""
    from reachplan.imaging.meshing import roi_mesh

    wanted = [n for n in names if n.casefold() in {s.casefold() for s in structures.names}]
    out: dict[str, trimesh.Trimesh] = {}
    for name in tqdm(wanted, desc="meshing organs", unit="roi", disable=quiet, leave=False):
        roi = structures.get(name)
        if has_closed(roi):
            out[roi.normalized_name] = roi_mesh(roi, grid)
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
) -> Scene:
    """Mesh the organs at risk and the target ROIs and place the template.

    Parameters
    ----------
    target_names : ROI names whose centroids are targets; None = every ROI named ``Target*``. A target ROI made
        only of POINT contours gives one target per point (named ``ROI`` or ``ROI_k``; a note says so).
    target_points : further targets given as points.
    grid : the CT grid to rasterise contours on (None: a grid derived from the contours).
    patient_from_template : (4, 4) float, a :class:`TemplatePose`, or None = placed on the ``Obturator`` ROI.
    allow_no_oars : plan even when no organ at risk is found (otherwise a :class:`PlanInputError`).
    standard_names : the synonym table's standard names (ROIs not mapped to one are listed in the notes).

    Organs at risk that are missing or have no closed contours are named in ``Scene.notes`` (see
    :func:`reachplan.planner.geometry.organs.select_oars`); ROIs of one name twice are an error.
    """
    config = config or PlanConfig()
    if target_names is None:
        target_names = [n for n in structures.names if n.casefold().startswith("target")]
    check_unique(structures, [*target_names, *(["Obturator"] if patient_from_template is None else [])])
    selection = select_oars(structures, config.oar_names, standard_names, exclude=target_names)
    oars = list(selection.found)
    notes = list(selection.notes)
    if not oars and not allow_no_oars:
        raise PlanInputError(
            f"no organ at risk to check needles against: none of {', '.join(config.oar_names)} is in the "
            f"structure set with closed contours (ROIs: {', '.join(repr(r.name) for r in structures.rois)}); map "
            "one with --oar ORGAN=ROI_NAME or --synonyms FILE, or plan anyway with --allow-no-oars"
        )
    rois = [structures.get(n) for n in target_names]
    context = [n for n in ("HR-CTV", "Uterus", "Cervix", "Obturator") if n in structures.names]
    meshes = mesh_structures(structures, [*oars, *[r.normalized_name for r in rois if has_closed(r)], *context],
                             grid, quiet)
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
    targets += list(target_points)
    if not targets:
        raise PlanInputError("no targets: name target ROIs or give target points")
    if patient_from_template is None:
        if "Obturator" not in structures.names:
            raise PlanInputError("no Obturator (or vaginal cylinder) ROI to place the template on; give the pose "
                                 "with --template-origin X,Y,Z --template-axis X,Y,Z, --template-pose FILE or "
                                 "--rtplan FILE")
        obturator = structures.get("Obturator")
        pose = TemplatePose(pose_from_obturator(obturator, config.obturator_depth_mm),
                            f"fitted to ROI {obturator.name!r} (principal axis of its contours; template "
                            f"{config.obturator_depth_mm:g} mm behind its cranial tip)")
    elif isinstance(patient_from_template, TemplatePose):
        pose = patient_from_template
    else:
        pose = TemplatePose(np.asarray(patient_from_template, dtype=float), "given")
    # distance-field screen (issue 19): FCL confirms clearances up to the ranking's cap + SCREEN_BAND_MM
    confirm = config.weights.clearance_cap_mm + SCREEN_BAND_MM
    organs = tuple(with_distance_field(make_organ(n, meshes[n]), confirm) for n in oars)
    return Scene(organs, tuple(targets), load_template(config.template), pose.patient_from_template,
                 meshes, pose=pose, notes=tuple(notes))
