"""The applicator exchange type, the Protocol of an applicator kind and the geometry kinds share.

An :class:`Applicator` is one intracavitary or vaginal part of an implant (a tandem, a ring, an ovoid, a vaginal
cylinder or obturator, or a third party's kind) as found in a structure set or a brachy RT Plan: its kind, where
it came from, its source channels as centre lines (mm, DICOM patient coordinates LPS, base to tip: the base is the
end nearer the template or introducer), whether needles must keep off it, and whether its channels are loaded for
dose. An :class:`ApplicatorKind` says which ROI names it claims and how its channels are found; the built-in kinds
live one per module beside this one and register through the ``reachplan.applicators`` entry-point group.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol, runtime_checkable

import numpy as np

from reachplan._arrays import frozen_floats
from reachplan.imaging.brachy_plan import Channel
from reachplan.imaging.names import name_key
from reachplan.imaging.types import Roi
from reachplan.plugins.applicators.centreline import CRANIAL, LINE_TYPES, roi_centreline


@dataclass(frozen=True, eq=False)
class Applicator:
    """One applicator of an implant and its source channels.

    Parameters
    ----------
    kind : str
        The name of its :class:`ApplicatorKind` (``"tandem"``, ``"ring"``, ``"ovoid"``, ``"cylinder"``,
        ``"obturator"`` or a plugin's).
    name : str
        What it is called: the ROI name for one from a structure set, the RT Plan's applicator ID (and channel ROI
        name) for one from a plan.
    roi_name : str or None
        The ROI it came from, as written in the structure set (None: no ROI).
    roi_number : int or None
        That ROI's ROI Number (None: no ROI).
    channels : tuple of (n, 3) float, mm, LPS
        Source channel centre lines, base (nearer the template / introducer) to tip, n >= 2 each. Empty when the
        kind finds no channel (``notes`` says why).
    obstacle : bool
        True: needles must not cross it.
    loadable : bool
        True: its channels are loaded for dose by the planner today. Never True without a channel.
    plan_channels : tuple of int
        The RT Plan Channel Number of each channel (empty for an applicator from a structure set).
    how : str
        One line saying how the channels were found (printed with a pose or a plan).
    notes : tuple of str
        Why a channel is missing, or what was assumed.

    Raises
    ------
    ValueError
        An empty kind or name, a channel that is not (n >= 2, 3) finite, ``loadable`` without a channel, or
        ``plan_channels`` not one per channel.
    """

    kind: str
    name: str
    roi_name: str | None
    roi_number: int | None
    channels: tuple[np.ndarray, ...]
    obstacle: bool
    loadable: bool
    plan_channels: tuple[int, ...] = ()
    how: str = ""
    notes: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        if not self.kind.strip() or not self.name.strip():
            raise ValueError(f"an applicator needs a kind and a name, got kind {self.kind!r}, name {self.name!r}")
        channels = tuple(frozen_floats(c, (3,), f"applicator {self.name!r}: channel") for c in self.channels)
        if any(len(c) < 2 for c in channels):
            raise ValueError(f"applicator {self.name!r}: a channel needs at least two points (base, tip)")
        object.__setattr__(self, "channels", channels)
        object.__setattr__(self, "notes", tuple(self.notes))
        object.__setattr__(self, "plan_channels", tuple(int(n) for n in self.plan_channels))
        if self.loadable and not channels:
            raise ValueError(f"applicator {self.name!r}: loadable without a channel")
        if self.plan_channels and len(self.plan_channels) != len(channels):
            raise ValueError(f"applicator {self.name!r}: one RT Plan channel number per channel, got "
                             f"{len(self.plan_channels)} for {len(channels)}")


@runtime_checkable
class ApplicatorKind(Protocol):
    """What an applicator kind provides (the ``reachplan.applicators`` entry-point group).

    Attributes
    ----------
    name : str
        The kind's name (``"tandem"``); the entry-point name.
    description : str
        One line for ``reachplan plugins``.
    roi_names : tuple of str
        The ROI names it claims: a TG-263-style standard name first, then synonyms. Matched as
        :func:`reachplan.imaging.names.name_key` does (case, spaces, ``_``, ``-`` and ``.`` ignored), whole names
        only.
    obstacle : bool
        True: needles must not cross an applicator of this kind.
    loadable : bool
        True: the planner loads its channels for dose.
    """

    @property
    def name(self) -> str:
        """The kind's name."""
        ...

    @property
    def description(self) -> str:
        """One line for ``reachplan plugins``."""
        ...

    @property
    def roi_names(self) -> tuple[str, ...]:
        """The ROI names it claims, standard name first."""
        ...

    @property
    def obstacle(self) -> bool:
        """True: needles must not cross it."""
        ...

    @property
    def loadable(self) -> bool:
        """True: its channels are loaded for dose."""
        ...

    def channels_from_roi(self, roi: Roi, axis: np.ndarray | None) -> tuple[tuple[np.ndarray, ...], tuple[str, ...]]:
        """Return the channel centre lines of an applicator drawn as ``roi``.

        Parameters
        ----------
        roi : Roi
            The applicator's ROI (contour points mm, LPS).
        axis : (3,) float, unit or any length, LPS, or None
            The template's insertion direction, to orient channels base to tip (None: patient cranial, +z).

        Returns
        -------
        channels : tuple of (n, 3) float, mm, LPS, base to tip
        notes : tuple of str
            Why no channel was found, or what was assumed.
        """
        ...

    def channels_from_plan(self, channel: Channel, path_mm: np.ndarray | None) -> tuple[np.ndarray, ...]:
        """Return the channel centre lines of a brachy RT Plan's applicator channel.

        Parameters
        ----------
        channel : reachplan.imaging.rtplan.Channel
            The plan's channel (dwell positions mm, LPS; relative positions from the tip).
        path_mm : (k, 3) float, mm, LPS, tip first, or None
            Its centre line as written (channel ROI or catheter sequence); None when the plan gives none.

        Returns
        -------
        tuple of (n, 3) float, mm, LPS, base to tip
        """
        ...


def check_applicator_kind(obj: object) -> None:
    """Check that ``obj`` implements :class:`ApplicatorKind` (the registry's check of ``applicators``).

    Parameters
    ----------
    obj : object
        The loaded entry point.

    Raises
    ------
    TypeError
        A missing member, an empty or non-str name, or no ROI name claimed.
    """
    if not isinstance(obj, ApplicatorKind):
        raise TypeError(f"{obj!r} does not implement plugins.applicators.ApplicatorKind (name, description, "
                        "roi_names, obstacle, loadable, channels_from_roi, channels_from_plan)")
    if not isinstance(obj.name, str) or not obj.name.strip() or not isinstance(obj.description, str):
        raise TypeError(f"{obj!r}: name must be a non-empty str and description a str")
    if not isinstance(obj.roi_names, tuple) or not obj.roi_names \
            or not all(isinstance(n, str) and name_key(n) for n in obj.roi_names):
        raise TypeError(f"applicator kind {obj.name!r}: roi_names must be a non-empty tuple of non-empty str")


# --- geometry the kinds share -------------------------------------------------------------------------------


def roi_points(roi: Roi, closed_only: bool = False) -> np.ndarray:
    """Return every contour point of ``roi`` (only its CLOSED_PLANAR contours with ``closed_only``).

    Parameters
    ----------
    roi : Roi
        The ROI.
    closed_only : bool
        Keep only closed planar contours (a solid's wall, not a drawn line).

    Returns
    -------
    (n, 3) float, mm, LPS
        In file order; (0, 3) when there is none.
    """
    contours = [c.points_mm for c in roi.contours if not closed_only or c.geometric_type == "CLOSED_PLANAR"]
    return np.concatenate(contours) if contours else np.zeros((0, 3))


def principal_chord(points_mm: np.ndarray, axis: np.ndarray | None) -> np.ndarray | None:
    """Return the chord of ``points_mm`` along their principal axis, oriented along ``axis``.

    The line through the points' centroid along their first principal direction, from the smallest to the
    largest projection of a point on it; the direction is flipped so that it does not point against ``axis``.

    Parameters
    ----------
    points_mm : (n, 3) float, mm, LPS
        The points (contour points of a straight applicator).
    axis : (3,) float, LPS, or None
        The direction the chord runs along, base to tip (None: patient cranial, +z).

    Returns
    -------
    (2, 3) float, mm, LPS, or None
        Base and tip; None for fewer than two points or points that span no length.
    """
    pts = np.asarray(points_mm, dtype=float).reshape(-1, 3)
    if len(pts) < 2:
        return None
    toward = CRANIAL if axis is None else np.asarray(axis, dtype=float)
    centre = pts.mean(axis=0)
    u = np.linalg.svd(pts - centre, full_matrices=False)[2][0]
    u = u if u @ toward >= 0 else -u
    s = (pts - centre) @ u
    if not float(s.max() - s.min()) > 0.0:
        return None
    return np.asarray(centre + np.outer([s.min(), s.max()], u), dtype=float)


def plan_centreline(channel: Channel, path_mm: np.ndarray | None) -> np.ndarray | None:
    """Return a plan channel's centre line base to tip: its path reversed, else its dwells from the base.

    Parameters
    ----------
    channel : reachplan.imaging.rtplan.Channel
        The plan's channel.
    path_mm : (k, 3) float, mm, LPS, tip first, or None
        Its centre line as written (Eclipse, Oncentra: tip first).

    Returns
    -------
    (n, 3) float, mm, LPS, base to tip, or None
        None when there is no path and fewer than two dwell positions.
    """
    if path_mm is not None and len(path_mm) >= 2:
        return np.asarray(path_mm, dtype=float)[::-1].copy()
    order = np.argsort(channel.dwell_relative_mm, kind="stable")  # relative position: from the tip
    tip_first = channel.dwell_positions_mm[order]
    return tip_first[::-1].copy() if len(tip_first) >= 2 else None


@dataclass(frozen=True)
class KindSpec:
    """The data part of an applicator kind; a kind module subclasses it and adds ``channels_from_roi``.

    Parameters
    ----------
    name, description : str
        See :class:`ApplicatorKind`.
    roi_names : tuple of str
        The ROI names it claims, TG-263-style standard name first.
    obstacle, loadable : bool
        See :class:`ApplicatorKind`.
    """

    name: str
    description: str
    roi_names: tuple[str, ...]
    obstacle: bool
    loadable: bool

    def channels_from_plan(self, channel: Channel, path_mm: np.ndarray | None) -> tuple[np.ndarray, ...]:
        """Return the channel's centre line, base to tip (see :func:`plan_centreline`).

        Parameters
        ----------
        channel : reachplan.imaging.rtplan.Channel
            The plan's channel.
        path_mm : (k, 3) float, mm, LPS, tip first, or None
            Its centre line as written.

        Returns
        -------
        tuple of (n, 3) float, mm, LPS, base to tip
            One centre line, or none when the plan gives neither a path nor two dwells.
        """
        line = plan_centreline(channel, path_mm)
        return () if line is None else (line,)


@dataclass(frozen=True)
class CentrelineKind(KindSpec):
    """A kind whose one channel is the centre line of its ROI, curved as drawn (a tube's contours or a drawn line).

    Parameters
    ----------
    name, description, roi_names, obstacle, loadable
        See :class:`KindSpec`.
    """

    def channels_from_roi(self, roi: Roi, axis: np.ndarray | None) -> tuple[tuple[np.ndarray, ...], tuple[str, ...]]:
        """Return the ROI's centre line (:func:`reachplan.plugins.applicators.centreline.roi_centreline`).

        Parameters
        ----------
        roi : Roi
            The applicator ROI: closed contours of the tube, or an open centre line.
        axis : (3,) float, LPS, or None
            The template's insertion direction, to orient the channel base to tip (None: patient cranial, +z).

        Returns
        -------
        channels : tuple of (n, 3) float, mm, LPS, base to tip
            One centre line, or none when the ROI gives no honest one.
        notes : tuple of str
            Why there is no channel, or what was left out.
        """
        line, notes = roi_centreline(roi, axis)
        return ((), notes) if line is None else ((line,), notes)


@dataclass(frozen=True)
class PlanOnlyKind(CentrelineKind):
    """A kind whose channel is not derived from the drawn solid: from an RT Plan, or from a drawn channel line.

    Its closed contours (the solid: a ring's tube, an ovoid's cap) give no channel, and the note says why; a
    channel drawn as a line in its ROI (open contours, as a treatment planning system writes a channel ROI) is taken
    as drawn, unless the ROI is a MARKER (a marker line beside the applicator, not its channel).

    Parameters
    ----------
    name, description, roi_names, obstacle, loadable
        See :class:`KindSpec`.
    why : str
        Why the contours give no honest channel (the note, after the ROI name).
    """

    why: str = "its channel is not derived from its contours"

    def channels_from_roi(self, roi: Roi, axis: np.ndarray | None) -> tuple[tuple[np.ndarray, ...], tuple[str, ...]]:
        """Return the channel drawn as a line in ``roi``, else no channel and the reason.

        Parameters
        ----------
        roi : Roi
            The applicator ROI.
        axis : (3,) float, LPS, or None
            The template's insertion direction, to orient a drawn channel base to tip (None: patient cranial, +z).

        Returns
        -------
        channels : tuple of (n, 3) float, mm, LPS, base to tip
            The drawn channel line, or none.
        notes : tuple of str
            ``"ROI '<name>': <why>"`` when there is no drawn line, or why the line gives no channel.
        """
        if roi.interpreted_type.strip().upper() == "MARKER":
            return (), (f"ROI {roi.name!r} is a MARKER, not a channel: {self.why}",)
        if any(c.geometric_type in LINE_TYPES for c in roi.contours):
            return super().channels_from_roi(roi, axis)
        return (), (f"ROI {roi.name!r}: {self.why}",)
