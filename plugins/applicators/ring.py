"""The ring of a ring-tandem applicator: a curved channel in the vaginal fornices, not derived from contours."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from reachplan.imaging.types import Roi
from reachplan.plugins.applicators.base import KindSpec


@dataclass(frozen=True)
class Ring(KindSpec):
    """A ring applicator: an obstacle for needles; its channel comes from an RT Plan only."""

    def channels_from_roi(self, roi: Roi, axis: np.ndarray | None) -> tuple[tuple[np.ndarray, ...], tuple[str, ...]]:
        """Return no channel from contours, and say why.

        The ring's source path is the curve through its tube's core, usually tilted to the axial slices; the
        contours of the solid ring give it only through a skeleton fit that is not written yet.

        Parameters
        ----------
        roi : Roi
            The ring ROI.
        axis : (3,) float, LPS, or None
            Unused.

        Returns
        -------
        channels : empty tuple
        notes : tuple of str
            The reason.
        """
        return (), (f"ROI {roi.name!r}: a ring's channel is not derived from its contours (the curve through the "
                    "tube's core needs a skeleton fit); give an RT Plan with the ring channel",)


RING = Ring(
    name="ring",
    description="ring of a ring-tandem applicator: an obstacle for needles; channel from an RT Plan only",
    roi_names=("Ring", "Applicator_Ring", "Ring_Applicator", "Ring_Vaginal", "Vaginal_Ring"),
    obstacle=True,
    loadable=False,
)
