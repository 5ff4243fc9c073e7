"""A recomputed plan's dose against a protocol (``reachplan dose --protocol``): target, organs and points.

The recomputed dose (:func:`reachplan.planner.run.dose_check.check_plan_dose`, all fractions and pulses) divided by
the plan's Number of Fractions Planned is the dose of one fraction; the EQD2 totals assume the protocol's
fractionation (its number of brachytherapy fractions of that dose, plus its external beam), as the planner does.
Pulses of a PDR fraction are summed as one fraction (no repair between pulses: an upper bound of the EQD2).

The target volume is the first ROI named as the protocol's site names it (``target_names``); the organs are the
ROIs the protocol has a D2cm³ aim for (matched as :class:`~reachplan.planner.dose.aims.Aims` matches them); the
points are the plan's dose references. Each ROI is rasterised on its own grid (its contours' planes, 1 mm in
plane: the dose grid's slices may not match the contours') and the dose at its voxel centres is interpolated
linearly from the dose grid (0 outside the dose grid, which holds the dwells with a margin: far from the dwells,
where neither D2cm³ nor the target's D90 lies); its volume (for the 2 cm³ rule) is its voxels'.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from reachplan.imaging.brachy_plan import RtPlan
from reachplan.imaging.types import Grid, Roi, StructureSet
from reachplan.planner.dose.aims import Aims
from reachplan.planner.dose.coverage import StructureMetrics, structure_metrics, voxel_volume_cc
from reachplan.planner.dose.evaluation import AimsTable, evaluate_aims, is_site_target
from reachplan.planner.dose.plan_check import PointCheck
from reachplan.planner.errors import ProtocolSiteWarning
from reachplan.planner.geometry.organs import has_closed

#: How a recomputed plan's dose-volume values are computed (the module docstring), in words for its outputs.
DVH_METHOD = ("each ROI rasterised on its own grid (its contours' planes, 1 mm in plane) and the recomputed TG-43 "
              "dose interpolated linearly at its voxel centres; D90/D98 the minimum dose of the hottest 90 %/98 % of "
              "those voxels, D2cm³/D0.1cm³ the minimum dose of the hottest 2/0.1 cm³, no interpolation between "
              "voxels (reachplan dose --protocol)")


def _metrics(roi: Roi, grid: Grid, dose: np.ndarray, aims: Aims, alpha_beta_gy: float) -> StructureMetrics | None:
    """Return a ROI's metrics on its own grid, the dose interpolated from ``grid`` (None: no voxel inside)."""
    from scipy.ndimage import map_coordinates

    from reachplan.imaging.meshing import fit_grid, roi_mask

    own = fit_grid(roi, None, 1.0)
    kji = np.argwhere(roi_mask(roi, own))
    if not len(kji):
        return None
    ijk = grid.to_index(own.to_patient(kji[:, ::-1].astype(float)))
    values = map_coordinates(dose, ijk[:, ::-1].T, order=1, mode="constant", cval=0.0)
    return structure_metrics(roi.name, values, voxel_volume_cc(own), aims.prescription_gy, alpha_beta_gy,
                             aims.fractionation)


def plan_dose_aims(plan: RtPlan, structures: StructureSet, grid: Grid, dose_gy: np.ndarray,
                   checks: Sequence[PointCheck], aims: Aims) -> tuple[AimsTable, tuple[str, ...]]:
    """Return a recomputed plan's dose against every aim of ``aims``, and the protocol's warnings.

    Parameters
    ----------
    plan : RtPlan
        The plan (its Number of Fractions Planned).
    structures : StructureSet
        Its RT Structure Set (target volume and organs, contours mm, LPS).
    grid : Grid
        The dose grid (LPS mm).
    dose_gy : (nk, nj, ni) float, Gy
        The dose of all fractions and pulses on ``grid``.
    checks : sequence of PointCheck
        The dose at the plan's reference points (all fractions and pulses).
    aims : Aims
        The protocol.

    Returns
    -------
    table : AimsTable
        Each aim against the plan.
    warnings : tuple of str
        ``"Category: message"``: no target volume of the protocol's site, an organ under 2 cm³.
    """
    per_fraction = np.asarray(dose_gy, dtype=float) / max(plan.n_fractions, 1)
    closed = [r for r in structures.rois if has_closed(r)]
    target_roi = next((r for r in closed if is_site_target(aims, r.name)), None)
    notes = []
    target = None
    if target_roi is None:
        notes.append(f"{ProtocolSiteWarning.__name__}: the structure set has no {aims.site} target of {aims.name} "
                     f"(named {', '.join(aims.target_names)}): only its organ and point aims are reported; give the "
                     "site's protocol with --protocol FILE_OR_NAME")
    else:
        target = _metrics(target_roi, grid, per_fraction, aims, aims.alpha_beta_target_gy)
    organs = []
    for roi in closed:
        if roi is target_roi or aims.oar_eqd2_gy(roi.name) is None:
            continue
        m = _metrics(roi, grid, per_fraction, aims, aims.alpha_beta_oar_gy)
        if m is not None:
            organs.append(m)
    points = [(c.name, c.dose_gy / max(plan.n_fractions, 1)) for c in checks]
    table = evaluate_aims(aims, target, organs, points=points)
    return table, (*notes, *table.warnings)
