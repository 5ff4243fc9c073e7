"""The vaginal obturator of an interstitial template (Syed-Neblett): its principal axis, where the template sits."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from reachplan.imaging.types import Roi
from reachplan.plugins.applicators.base import KindSpec, principal_chord, roi_points


def axis_channel(roi: Roi, axis: np.ndarray | None) -> tuple[tuple[np.ndarray, ...], tuple[str, ...]]:
    """Return the principal axis of a vaginal cylinder's or obturator's closed contours as its one channel.

    The axis the template pose is fitted to; the channel runs between the extreme contour points along it.

    Parameters
    ----------
    roi : Roi
        The ROI (closed planar contours of the solid).
    axis : (3,) float, LPS, or None
        The template's insertion direction (None: patient cranial, +z).

    Returns
    -------
    channels : tuple of (2, 3) float, mm, LPS, base to tip
        One chord, or none for fewer than two closed-contour points.
    notes : tuple of str
        Why there is no channel (empty otherwise).
    """
    chord = principal_chord(roi_points(roi, closed_only=True), axis)
    if chord is None:
        return (), (f"ROI {roi.name!r} has fewer than two distinct closed-contour points: no axis",)
    return (chord,), ()


@dataclass(frozen=True)
class AxisKind(KindSpec):
    """A vaginal obturator or cylinder: one channel, its principal axis (where the template sits)."""

    def channels_from_roi(self, roi: Roi, axis: np.ndarray | None) -> tuple[tuple[np.ndarray, ...], tuple[str, ...]]:
        """Return its principal axis (:func:`axis_channel`).

        Parameters
        ----------
        roi : Roi
            The obturator's or cylinder's ROI.
        axis : (3,) float, LPS, or None
            The template's insertion direction (None: patient cranial, +z).

        Returns
        -------
        channels : tuple of (2, 3) float, mm, LPS, base to tip
        notes : tuple of str
        """
        return axis_channel(roi, axis)


#: The template sits on the obturator and its needles run through it, so it is no obstacle.
OBTURATOR = AxisKind(
    name="obturator",
    description="vaginal obturator of an interstitial template: its axis places the template; not loaded",
    roi_names=("Obturator", "Vaginal_Obturator", "Obturator_Vaginal", "Applicator_Obturator"),
    obstacle=False,
    loadable=False,
)
