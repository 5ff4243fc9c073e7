"""The one place the stages are chained: structures -> scene -> candidates -> ranking.

Stages are plain functions on plain data; the command line (``planner/commands``) only parses
arguments, calls these and writes files.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field

import numpy as np
import trimesh
from tqdm import tqdm

from imaging.types import Grid, StructureSet
from planner.candidates import straight_candidates
from planner.collision import Organ, make_organ
from planner.errors import PlanInputError
from planner.ranking import Candidate, Target, rank
from planner.template import Template, check_rigid, hole_frames, pose_from_obturator
from plugins import registry

#: Organs at risk (and bone) a needle must not touch, by normalised ROI name.
DEFAULT_OARS: tuple[str, ...] = ("Bladder", "Rectum", "Sigmoid", "Bowel", "Bone")

#: 15-gauge plastic ISBT needle, outer diameter 1.83 mm (reference: oncoreach.md, ASSUMED dimensions).
NEEDLE_RADIUS_15GA_MM = 1.83 / 2


@dataclass(frozen=True)
class PlanConfig:
    """Settings of a plan (all lengths in mm).

    ``reach_tolerance_mm``: a candidate reaches its target when its tip is within this distance of the
    target point. ``max_depth_mm``: free length of the needle beyond the template (reference: about 200 mm).
    ``obturator_depth_mm``: how far the obturator tip lies beyond the template plane, used to place the
    template from an ``Obturator`` ROI when no pose is given.
    """

    template: str = "needlefinder_syed_63"
    needle_radius_mm: float = NEEDLE_RADIUS_15GA_MM
    reach_tolerance_mm: float = 2.0
    max_depth_mm: float = 200.0
    oar_names: tuple[str, ...] = DEFAULT_OARS
    obturator_depth_mm: float = 60.0

    def __post_init__(self) -> None:
        for name in ("needle_radius_mm", "reach_tolerance_mm", "max_depth_mm", "obturator_depth_mm"):
            v = getattr(self, name)
            if not (np.isfinite(v) and v > 0):
                raise ValueError(f"{name} must be a positive number of mm, got {v}")


@dataclass(frozen=True, eq=False)
class Scene:
    """What a plan needs: organs to avoid, targets, the template and its pose.

    ``meshes`` holds every meshed ROI by normalised name (for figures and exports);
    ``patient_from_template`` is (4, 4), LPS mm.
    """

    organs: tuple[Organ, ...]
    targets: tuple[Target, ...]
    template: Template
    patient_from_template: np.ndarray
    meshes: dict[str, trimesh.Trimesh] = field(default_factory=dict)


@dataclass(frozen=True, eq=False)
class PlanResult:
    """All scored candidates and their ranking per target."""

    candidates: tuple[Candidate, ...]
    ranking: dict[str, tuple[Candidate, ...]]
    config: PlanConfig

    def to_json(self) -> dict[str, object]:
        return {
            "config": {k: getattr(self.config, k) for k in self.config.__dataclass_fields__},
            "targets": {t: [c.to_json() for c in cs] for t, cs in self.ranking.items()},
        }


def load_template(name: str) -> Template:
    """A template layout from the plugin registry."""
    factory = registry.get("templates", name)
    template = factory()
    if not isinstance(template, Template):
        raise PlanInputError(f"template plugin {name!r} did not return a Template")
    return template


def mesh_structures(
    structures: StructureSet, names: Iterable[str], grid: Grid | None = None, quiet: bool = True
) -> dict[str, trimesh.Trimesh]:
    """Watertight meshes (LPS mm) of the named ROIs that exist in ``structures``, by normalised name."""
    from imaging.meshing import roi_mesh

    wanted = [n for n in names if n.casefold() in {s.casefold() for s in structures.names}]
    out: dict[str, trimesh.Trimesh] = {}
    for name in tqdm(wanted, desc="meshing organs", unit="roi", disable=quiet, leave=False):
        roi = structures.get(name)
        if any(c.geometric_type == "CLOSED_PLANAR" for c in roi.contours):
            out[roi.normalized_name] = roi_mesh(roi, grid)
    return out


def build_scene(
    structures: StructureSet,
    target_names: Sequence[str] | None = None,
    target_points: Sequence[Target] = (),
    grid: Grid | None = None,
    patient_from_template: np.ndarray | None = None,
    config: PlanConfig | None = None,
    quiet: bool = True,
) -> Scene:
    """Mesh the organs at risk and the target ROIs and place the template.

    Parameters
    ----------
    target_names : ROI names whose centroids are targets; None = every ROI named ``Target*``.
    target_points : further targets given as points.
    grid : the CT grid to rasterise contours on (None: a grid derived from the contours).
    patient_from_template : (4, 4) float or None; None = placed on the ``Obturator`` ROI.
    """
    config = config or PlanConfig()
    if target_names is None:
        target_names = [n for n in structures.names if n.casefold().startswith("target")]
    oars = [n for n in config.oar_names if n.casefold() in {s.casefold() for s in structures.names}]
    if not oars:
        raise PlanInputError(
            f"none of the organs at risk {', '.join(config.oar_names)} is in the structure set "
            f"(it has: {', '.join(structures.names)}); add a synonym or name them with --oars"
        )
    context = [n for n in ("HR-CTV", "Uterus", "Cervix", "Obturator") if n in structures.names]
    meshes = mesh_structures(structures, [*oars, *target_names, *context], grid, quiet)
    targets = []
    for n in target_names:
        x, y, z = (float(v) for v in meshes[structures.get(n).normalized_name].center_mass)
        targets.append(Target(structures.get(n).normalized_name, (x, y, z)))
    targets += list(target_points)
    if not targets:
        raise PlanInputError("no targets: name target ROIs or give target points")
    if patient_from_template is None:
        if "Obturator" not in structures.names:
            raise PlanInputError("no Obturator ROI to place the template on; give patient_from_template")
        patient_from_template = pose_from_obturator(structures.get("Obturator"), config.obturator_depth_mm)
    organs = tuple(make_organ(structures.get(n).normalized_name, meshes[structures.get(n).normalized_name])
                   for n in oars)
    return Scene(organs, tuple(targets), load_template(config.template), check_rigid(patient_from_template),
                 meshes)


def plan(scene: Scene, config: PlanConfig | None = None, quiet: bool = True) -> PlanResult:
    """Score every hole x target candidate and rank them (straight needles)."""
    config = config or PlanConfig()
    holes = scene.template.needle_holes
    entry, direction = hole_frames(scene.template, scene.patient_from_template, holes)
    cands: list[Candidate] = []
    for target in tqdm(scene.targets, desc="planning targets", unit="target", disable=quiet, leave=False):
        cands += straight_candidates(
            [target], [h.hole_id for h in holes], np.array([h.distance_mm for h in holes]), entry, direction,
            scene.organs, config.needle_radius_mm, config.reach_tolerance_mm, config.max_depth_mm,
        )
    return PlanResult(tuple(cands), rank(cands), config)
