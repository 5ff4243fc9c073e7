"""Build :class:`Applicator` objects once, from a structure set or a brachy RT Plan, through the applicator kinds.

Recognition is by whole name: an ROI name (or an RT Plan channel's applicator ID or channel ROI name) is an
applicator of a kind when its :func:`reachplan.imaging.names.name_key` equals that of one of the kind's
``roi_names``; an ROI's standard name (``normalized_name``, after the synonym table and ``--oar``) is tried after its
name as written. A hand assignment (``--applicator KIND=ROI``) overrides recognition. This module is the one place
that decides whether a name is an applicator.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np

from reachplan.imaging.brachy_plan import Channel, RtPlan
from reachplan.imaging.names import SynonymTable
from reachplan.imaging.rtplan import channel_paths
from reachplan.imaging.types import Roi, StructureSet
from reachplan.plugins.applicators.base import Applicator, ApplicatorKind
from reachplan.plugins.errors import ApplicatorError


def name_table(kinds: Mapping[str, ApplicatorKind]) -> SynonymTable:
    """Return the synonym table of the kinds' ROI names: standard name = kind name.

    Parameters
    ----------
    kinds : mapping of str to ApplicatorKind
        Kind name -> kind.

    Returns
    -------
    SynonymTable
        Every claimed ROI name -> its kind's name.

    Raises
    ------
    ApplicatorError
        Two kinds claim the same ROI name.
    """
    try:
        return SynonymTable(tuple((k, tuple(kind.roi_names)) for k, kind in kinds.items()))
    except ValueError as exc:
        raise ApplicatorError(f"applicator kinds claim the same ROI name: {exc}") from None


def kind_of_name(name: str, kinds: Mapping[str, ApplicatorKind], table: SynonymTable | None = None) -> str | None:
    """Return the kind that claims ``name`` (whole name, :func:`reachplan.imaging.names.name_key`), or None.

    Parameters
    ----------
    name : str
        An ROI name, standard ROI name or RT Plan applicator ID.
    kinds : mapping of str to ApplicatorKind
        Kind name -> kind.
    table : SynonymTable, optional
        :func:`name_table` of ``kinds`` (built when not given).

    Returns
    -------
    str or None
        The kind's name; None when no kind claims ``name``.
    """
    standard = (name_table(kinds) if table is None else table).normalize(name)
    return standard if standard in kinds else None


def _assigned(assign: Mapping[str, str], kinds: Mapping[str, ApplicatorKind], names: Sequence[str]) -> dict[str, str]:
    """Check ``assign`` (name -> kind) against ``kinds`` and ``names``; return it keyed by casefolded name."""
    bad = sorted({k for k in assign.values() if k not in kinds})
    if bad:
        raise ApplicatorError(f"unknown applicator kind {', '.join(map(repr, bad))}; kinds: {', '.join(kinds)}")
    known = {n.strip().casefold() for n in names}
    unknown = [n for n in assign if n.strip().casefold() not in known]
    if unknown:
        raise ApplicatorError(f"no ROI named {', '.join(map(repr, unknown))} to assign an applicator kind to; "
                              f"available: {', '.join(map(repr, names)) or 'none'}")
    return {n.strip().casefold(): k for n, k in assign.items()}


def _kind_of(names: Sequence[str], kinds: Mapping[str, ApplicatorKind], table: SynonymTable,
             by_hand: Mapping[str, str]) -> str | None:
    """Return the kind of the first of ``names`` assigned by hand, else of the first recognised (or None)."""
    for n in names:
        if n.strip().casefold() in by_hand:
            return by_hand[n.strip().casefold()]
    return next((k for k in (kind_of_name(n, kinds, table) for n in names if n.strip()) if k is not None), None)


def applicator_from_roi(roi: Roi, kind: ApplicatorKind, axis: np.ndarray | None = None) -> Applicator:
    """Build the applicator of kind ``kind`` drawn as ``roi``.

    Parameters
    ----------
    roi : Roi
        The applicator's ROI (contours mm, LPS).
    kind : ApplicatorKind
        Its kind.
    axis : (3,) float, LPS, or None
        The template's insertion direction, to orient channels base to tip (None: patient cranial, +z).

    Returns
    -------
    Applicator
        Named as the ROI; ``loadable`` when the kind is and a channel was found.
    """
    channels, notes = kind.channels_from_roi(roi, axis)
    return Applicator(kind.name, roi.name, roi.name, roi.number, tuple(channels), kind.obstacle,
                      kind.loadable and bool(channels), how=f"from ROI {roi.name!r} ({kind.name})", notes=notes)


def applicators_from_structures(structures: StructureSet, kinds: Mapping[str, ApplicatorKind],
                                assign: Mapping[str, str] | None = None,
                                axis: np.ndarray | None = None) -> tuple[Applicator, ...]:
    """Recognise the applicator ROIs of a structure set and build their applicators.

    Parameters
    ----------
    structures : StructureSet
        The structure set (ROI contours mm, LPS).
    kinds : mapping of str to ApplicatorKind
        Kind name -> kind (the registry's ``applicators``, or :data:`BUILTIN_KINDS`).
    assign : mapping of str to str, optional
        ROI name (as written, case ignored) -> kind name, from ``--applicator KIND=ROI``; overrides recognition.
    axis : (3,) float, LPS, or None
        The template's insertion direction, to orient channels base to tip (None: patient cranial, +z).

    Returns
    -------
    tuple of Applicator
        In ROI order of the structure set.

    Raises
    ------
    ApplicatorError
        ``assign`` names an unknown kind or an ROI not in the structure set, or two kinds claim one name.
    """
    table = name_table(kinds)
    by_hand = _assigned(assign or {}, kinds, [r.name for r in structures.rois])
    out = []
    for roi in structures.rois:
        kind = _kind_of((roi.name, roi.normalized_name), kinds, table, by_hand)
        if kind is not None:
            out.append(applicator_from_roi(roi, kinds[kind], axis))
    return tuple(out)


def channel_label(channel: Channel, roi_names: Mapping[int, str]) -> str:
    """Return ``"<applicator ID> / <ROI name>"`` of a plan channel (one when they agree), else ``"channel <n>"``.

    Parameters
    ----------
    channel : reachplan.imaging.rtplan.Channel
        The plan's channel.
    roi_names : mapping of int to str
        ROI Number -> ROI name of the plan's structure set.

    Returns
    -------
    str
        The label.
    """
    roi = roi_names.get(channel.roi_number, "") if channel.roi_number is not None else ""
    parts = [channel.applicator_id.strip(), roi.strip()]
    return " / ".join(dict.fromkeys(x for x in parts if x)) or f"channel {channel.number}"


def applicators_from_rtplan(plan: RtPlan, kinds: Mapping[str, ApplicatorKind],
                            structures: StructureSet | None = None,
                            assign: Mapping[str, str] | None = None) -> tuple[Applicator, ...]:
    """Recognise the applicator channels of a brachy RT Plan and build one applicator per channel.

    A channel is recognised by its Source Applicator ID, else by the name of its channel ROI (Referenced ROI
    Number in ``structures``). Its centre line is the channel ROI's contour or the plan's catheter sequence
    (:func:`reachplan.imaging.rtplan.channel_paths`), else its dwell positions, base to tip.

    Parameters
    ----------
    plan : RtPlan
        The plan as :func:`reachplan.imaging.rtplan.read_rtplan` reads it.
    kinds : mapping of str to ApplicatorKind
        Kind name -> kind.
    structures : StructureSet, optional
        The structure set the plan refers to (channel ROI names and centre lines).
    assign : mapping of str to str, optional
        Applicator ID or channel ROI name (case ignored) -> kind name; overrides recognition.

    Returns
    -------
    tuple of Applicator
        In channel order; ``name`` is ``"<applicator ID> / <ROI name>"`` (one when they agree), ``plan_channels``
        the Channel Number.

    Raises
    ------
    ApplicatorError
        ``assign`` names an unknown kind or a name no channel has, or two kinds claim one name.
    """
    table = name_table(kinds)
    roi_names = {r.number: r.name for r in structures.rois} if structures is not None else {}
    names = [x for c in plan.channels for x in (c.applicator_id, roi_names.get(c.roi_number or -1, "")) if x.strip()]
    by_hand = _assigned(assign or {}, kinds, names)
    paths = channel_paths(plan, structures)
    out = []
    for c in plan.channels:
        roi = roi_names.get(c.roi_number) if c.roi_number is not None else None
        kind = _kind_of((c.applicator_id, roi or ""), kinds, table, by_hand)
        if kind is None:
            continue
        k = kinds[kind]
        channels = tuple(k.channels_from_plan(c, paths.get(c.number)))
        how = "its channel contour" if c.number in paths else "its dwell positions"
        out.append(Applicator(kind, channel_label(c, roi_names), roi, c.roi_number, channels, k.obstacle,
                              k.loadable and bool(channels), (c.number,) * len(channels), how,
                              () if channels else (f"channel {c.number}: no centre line and fewer than two dwells",)))
    return tuple(out)
