"""An ovoid (colpostat) of a tandem-and-ovoids applicator: a channel in the handle and cap, not from contours."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from reachplan.imaging.types import Roi
from reachplan.plugins.applicators.base import KindSpec


@dataclass(frozen=True)
class Ovoid(KindSpec):
    """An ovoid: an obstacle for needles; its channel comes from an RT Plan only."""

    def channels_from_roi(self, roi: Roi, axis: np.ndarray | None) -> tuple[tuple[np.ndarray, ...], tuple[str, ...]]:
        """Return no channel from contours, and say why.

        The source runs along the handle into the cap, off the cap's principal axis (shielded ovoids even put it
        off centre); the principal axis of the drawn cap would not be an honest channel.

        Parameters
        ----------
        roi : Roi
            The ovoid ROI.
        axis : (3,) float, LPS, or None
            Unused.

        Returns
        -------
        channels : empty tuple
        notes : tuple of str
            The reason.
        """
        return (), (f"ROI {roi.name!r}: an ovoid's channel is not derived from its contours (the source runs in "
                    "the handle, off the cap's axis); give an RT Plan with the ovoid channels",)


OVOID = Ovoid(
    name="ovoid",
    description="ovoid (colpostat): an obstacle for needles; channel from an RT Plan only",
    roi_names=("Ovoid", "Ovoids", "Applicator_Ovoid", "Ovoid_L", "Ovoid_R", "L_Ovoid", "R_Ovoid", "Ovoid_Lt",
               "Ovoid_Rt", "Lt_Ovoid", "Rt_Ovoid", "Left_Ovoid", "Right_Ovoid", "Ovoid_Left", "Ovoid_Right",
               "Colpostat", "Colpostat_L", "Colpostat_R"),
    obstacle=True,
    loadable=False,
)
