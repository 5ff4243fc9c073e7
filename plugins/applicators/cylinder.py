"""A vaginal cylinder: its principal axis (the central channel), as for the obturator."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from reachplan.imaging.types import Roi
from reachplan.plugins.applicators.base import KindSpec
from reachplan.plugins.applicators.obturator import axis_channel


@dataclass(frozen=True)
class Cylinder(KindSpec):
    """A vaginal cylinder: the template can sit on it; its central channel is not loaded yet."""

    def channels_from_roi(self, roi: Roi, axis: np.ndarray | None) -> tuple[tuple[np.ndarray, ...], tuple[str, ...]]:
        """Return its principal axis (:func:`reachplan.plugins.applicators.obturator.axis_channel`).

        Parameters
        ----------
        roi : Roi
            The cylinder ROI.
        axis : (3,) float, LPS, or None
            The template's insertion direction (None: patient cranial, +z).

        Returns
        -------
        channels : tuple of (2, 3) float, mm, LPS, base to tip
        notes : tuple of str
        """
        return axis_channel(roi, axis)


CYLINDER = Cylinder(
    name="cylinder",
    description="vaginal cylinder: its axis places the template; central channel not loaded yet",
    roi_names=("Cylinder", "Vaginal_Cylinder", "Cylinder_Vaginal", "Cyl_Vaginal", "Vaginal_Cyl",
               "Applicator_Cylinder", "Vaginal_Applicator"),
    obstacle=False,
    loadable=False,
)
