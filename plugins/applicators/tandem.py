"""The intrauterine tandem: one channel, the chord of its ROI along the ROI's principal axis."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from reachplan.imaging.types import Roi
from reachplan.plugins.applicators.base import KindSpec, principal_chord, roi_points


def tandem_channel(roi: Roi, axis: np.ndarray | None) -> np.ndarray | None:
    """Return the tandem's channel: the chord of all its contour points along their principal axis.

    ASSUMED straight: a curved tandem is approximated by its chord (a later version follows the drawn curve;
    replace this function). Oriented along the template axis, from the end nearer the template.

    Parameters
    ----------
    roi : Roi
        The tandem ROI (closed contours of the tube or an open centre line; every point counts).
    axis : (3,) float, LPS, or None
        The template's insertion direction (None: patient cranial, +z).

    Returns
    -------
    (2, 3) float, mm, LPS, base to tip, or None
        None for fewer than two points.
    """
    return principal_chord(roi_points(roi), axis)


@dataclass(frozen=True)
class Tandem(KindSpec):
    """An intrauterine tandem (tube): in the uterine canal, needles keep off it; its channel is loaded."""

    def channels_from_roi(self, roi: Roi, axis: np.ndarray | None) -> tuple[tuple[np.ndarray, ...], tuple[str, ...]]:
        """Return the channel of :func:`tandem_channel` and the assumption made.

        The tandem is assumed straight: its channel is the chord of the ROI along its principal axis.

        Parameters
        ----------
        roi : Roi
            The tandem ROI.
        axis : (3,) float, LPS, or None
            The template's insertion direction (None: patient cranial, +z).

        Returns
        -------
        channels : tuple of (2, 3) float, mm, LPS, base to tip
            One chord, or none for fewer than two points.
        notes : tuple of str
            The straightness assumption, or why there is no channel.
        """
        chord = tandem_channel(roi, axis)
        if chord is None:
            return (), (f"ROI {roi.name!r} has fewer than two distinct contour points: no tandem channel",)
        return (chord,), ("channel ASSUMED straight: the chord of the ROI along its principal axis",)


TANDEM = Tandem(
    name="tandem",
    description="intrauterine tandem: one channel (the chord of its ROI), loaded for dose; needles keep off it",
    roi_names=("Tandem", "Applicator_Tandem", "Tandem_Applicator", "Uterine_Tandem", "Tandem_Uterine",
               "Intrauterine_Tube", "Intrauterine_Tandem", "Intrauterine", "IU_Tube", "IU_Tandem", "IU", "UT"),
    obstacle=True,
    loadable=True,
)
