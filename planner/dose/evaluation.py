"""A plan's dose against its protocol, aim by aim: value, planning aim, hard limit, headroom, met or not.

Each aim of :class:`~reachplan.planner.dose.aims.Aims` becomes one :class:`AimResult`: the plan's value (Gy EQD2,
total with the external beam), the planning aim and the hard limit, the headroom (the value's distance from the
planning aim, positive on the safe side) and two verdicts, kept apart: the planning aim is met when the headroom is
at least the protocol's headroom for organs and points (``headroom_eqd2_gy``, e.g. 1 Gy below each D2cm³ aim) and
at least 0 for the targets (D90 inside its range, D98 above its aim); the hard limit is met when the value is
within it. A plan meets its aims (:attr:`AimsTable.aims_met`) only when every assessed planning aim is met.

Organs smaller than :data:`SMALL_ORGAN_CC` (2 cm³): D2cm³ is not applicable (the whole organ is less than the
volume; :func:`~reachplan.planner.dose.coverage.dose_to_volume` would return its minimum dose). Its D2cm³ is
reported as not applicable (None), its aim is neither met nor failed (not counted), and its D0.1cm³ is reported
instead, with no aim (protocols give none), and a :class:`~reachplan.planner.errors.SmallOrganWarning` names the
organ and its volume.
"""

from __future__ import annotations

import re
import warnings
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

from reachplan.planner.dose.aims import Aims
from reachplan.planner.dose.coverage import StructureMetrics
from reachplan.planner.errors import ProtocolSiteWarning, SmallOrganWarning

#: An organ smaller than this (cm³) has no D2cm³: :data:`SMALL_ORGAN_METRIC` is reported instead.
SMALL_ORGAN_CC = 2.0
#: What is reported for an organ smaller than :data:`SMALL_ORGAN_CC`: the minimum dose of its hottest 0.1 cm³.
SMALL_ORGAN_METRIC = "D0.1cm³"

#: How the dose-volume values are computed (plan.json ``protocol.dvh_method``, docs/commands.md).
DVH_METHOD = ("D90/D98: the minimum dose of the hottest 90 %/98 % of the structure's voxels, D2cm³/D0.1cm³ the "
              "minimum dose of its hottest 2/0.1 cm³: voxels sorted by dose, the dose of the voxel at which the "
              "accumulated volume first reaches the asked volume, no interpolation "
              "(reachplan.planner.dose.coverage). The HR-CTV and GTV on sub-voxels of the planning grid, each organ "
              "on its planning-grid voxels near the loaded dwells. TG-43 dose per fraction; EQD2 = n d (d + α/β) / "
              "(2 + α/β) of the brachytherapy fractions plus the external-beam course's EQD2.")

_TOL = 1e-6


@dataclass(frozen=True)
class AimResult:
    """One aim of the protocol against the plan's value (Gy EQD2 totals).

    Parameters
    ----------
    label : str
        What it is (``"HR-CTV D90"``, ``"Bladder D2cm³"``, ``"ICRU recto-vaginal (ICRU rectum)"``).
    structure : str
        The structure or point.
    metric : str
        ``D90``, ``D98``, ``D2cm³``, ``D0.1cm³`` or ``point``.
    value_eqd2_gy : float or None, Gy EQD2
        The plan's value; None when not applicable (an organ under 2 cm³'s D2cm³) or not available.
    aim_min_eqd2_gy, aim_max_eqd2_gy : float or None, Gy EQD2
        Planning aim: at least / at most (None: no such side).
    limit_min_eqd2_gy, limit_max_eqd2_gy : float or None, Gy EQD2
        Hard limit: at least / at most.
    required_headroom_eqd2_gy : float, Gy
        Headroom the planning aim asks for (the protocol's for organs and points, 0 for targets).
    note : str
        Why a value is not applicable, or what it stands for.
    """

    label: str
    structure: str
    metric: str
    value_eqd2_gy: float | None
    aim_min_eqd2_gy: float | None = None
    aim_max_eqd2_gy: float | None = None
    limit_min_eqd2_gy: float | None = None
    limit_max_eqd2_gy: float | None = None
    required_headroom_eqd2_gy: float = 0.0
    note: str = ""

    @property
    def headroom_eqd2_gy(self) -> float | None:
        """Distance of the value from the planning aim, Gy (positive: on the safe side); None without either."""
        v = self.value_eqd2_gy
        if v is None:
            return None
        sides = [v - a for a in (self.aim_min_eqd2_gy,) if a is not None]
        sides += [a - v for a in (self.aim_max_eqd2_gy,) if a is not None]
        return min(sides) if sides else None

    @property
    def aim_met(self) -> bool | None:
        """Planning aim met with the required headroom; None when not assessed (no aim, or no value)."""
        h = self.headroom_eqd2_gy
        return None if h is None else bool(h >= self.required_headroom_eqd2_gy - _TOL)

    @property
    def limit_met(self) -> bool | None:
        """Hard limit kept; None when not assessed (no limit, or no value)."""
        v = self.value_eqd2_gy
        if v is None or (self.limit_min_eqd2_gy is None and self.limit_max_eqd2_gy is None):
            return None
        return bool((self.limit_min_eqd2_gy is None or v >= self.limit_min_eqd2_gy - _TOL)
                    and (self.limit_max_eqd2_gy is None or v <= self.limit_max_eqd2_gy + _TOL))

    def to_json(self) -> dict[str, object]:
        """Return the aim for plan.json.

        Returns
        -------
        dict
            The fields (Gy EQD2, 3 decimals), ``headroom_eqd2_gy``, ``planning_aim_met`` and ``hard_limit_met``
            (None: not assessed), the aim and limit in words.
        """
        def r(v: float | None) -> float | None:
            return None if v is None else round(v, 3)

        return {"aim": self.label, "structure": self.structure, "metric": self.metric,
                "value_eqd2_gy": r(self.value_eqd2_gy), "planning_aim": bounds_text(self.aim_min_eqd2_gy,
                                                                                   self.aim_max_eqd2_gy),
                "aim_min_eqd2_gy": r(self.aim_min_eqd2_gy), "aim_max_eqd2_gy": r(self.aim_max_eqd2_gy),
                "hard_limit": bounds_text(self.limit_min_eqd2_gy, self.limit_max_eqd2_gy),
                "limit_min_eqd2_gy": r(self.limit_min_eqd2_gy), "limit_max_eqd2_gy": r(self.limit_max_eqd2_gy),
                "headroom_eqd2_gy": r(self.headroom_eqd2_gy),
                "required_headroom_eqd2_gy": r(self.required_headroom_eqd2_gy),
                "planning_aim_met": self.aim_met, "hard_limit_met": self.limit_met, "note": self.note}


def bounds_text(low: float | None, high: float | None) -> str:
    """Return an aim or limit in words: ``"> 90, < 95"``, ``"< 80"``, ``"-"`` for none.

    Parameters
    ----------
    low : float or None, Gy
        At least (None: no lower side).
    high : float or None, Gy
        At most (None: no upper side).

    Returns
    -------
    str
    """
    parts = []
    if low is not None:
        parts.append(f"> {low:g}")
    if high is not None:
        parts.append(f"< {high:g}")
    return ", ".join(parts) or "-"


@dataclass(frozen=True)
class AimsTable:
    """A plan's dose against every aim of its protocol (what the terminal, the report and plan.json show).

    Parameters
    ----------
    protocol : str
        The protocol's name.
    results : tuple of AimResult
        One per aim (targets, organs, points), in the protocol's order.
    warnings : tuple of str
        ``"Category: message"`` of each named warning met (an organ under 2 cm³).
    """

    protocol: str
    results: tuple[AimResult, ...]
    warnings: tuple[str, ...] = ()

    @property
    def aims_met(self) -> bool:
        """Every assessed planning aim met with its headroom (and at least one assessed)."""
        verdicts = [r.aim_met for r in self.results if r.aim_met is not None]
        return bool(verdicts) and all(verdicts)

    @property
    def limits_met(self) -> bool:
        """Every assessed hard limit kept (and at least one assessed)."""
        verdicts = [r.limit_met for r in self.results if r.limit_met is not None]
        return bool(verdicts) and all(verdicts)

    @property
    def not_met(self) -> tuple[str, ...]:
        """Labels of the planning aims not met."""
        return tuple(r.label for r in self.results if r.aim_met is False)

    def to_json(self) -> dict[str, object]:
        """Return the table for plan.json.

        Returns
        -------
        dict
            ``protocol``, ``aims_met``, ``hard_limits_met``, ``aims_not_met`` (labels) and ``aims``: one record per
            aim (:meth:`AimResult.to_json`).
        """
        return {"protocol": self.protocol, "aims_met": self.aims_met, "hard_limits_met": self.limits_met,
                "aims_not_met": list(self.not_met), "aims": [r.to_json() for r in self.results]}


def _organ_results(aims: Aims, o: StructureMetrics, volume_cc: float) -> tuple[list[AimResult], str]:
    """Return the D2cm³ row of one organ (not applicable under 2 cm³, D0.1cm³ then) and its warning ("" without)."""
    aim, limit = aims.oar_eqd2_gy(o.name), aims.oar_eqd2_gy(o.name, "limit")
    h = aims.headroom_eqd2_gy
    if volume_cc >= SMALL_ORGAN_CC:
        return [AimResult(f"{o.name} D2cm³", o.name, "D2cm³", o.d2cc_eqd2_gy, None, aim, None,
                          limit, h)], ""
    note = (f"not applicable: {o.name} is {volume_cc:.2f} cm³, smaller than {SMALL_ORGAN_CC:g} cm³; its "
            f"{SMALL_ORGAN_METRIC} is reported instead and its D2cm³ aim is not counted")
    warning = (f"{SmallOrganWarning.__name__}: organ {o.name} is {volume_cc:.2f} cm³ (< {SMALL_ORGAN_CC:g} cm³): its "
               f"D2cm³ is not applicable (not counted against the {aims.name} aim); {SMALL_ORGAN_METRIC} "
               f"{o.d0_1cc_eqd2_gy:.1f} Gy EQD2 is reported instead")
    return [AimResult(f"{o.name} D2cm³", o.name, "D2cm³", None, None, aim, None, limit, h, note),
            AimResult(f"{o.name} {SMALL_ORGAN_METRIC}", o.name, SMALL_ORGAN_METRIC, o.d0_1cc_eqd2_gy,
                      note=f"reported instead of D2cm³ (organ < {SMALL_ORGAN_CC:g} cm³); no protocol aim")], warning


def _point_results(aims: Aims, points: Sequence[tuple[str, float]]) -> list[AimResult]:
    """One row per plan reference point each protocol point matches (a row saying none when none does)."""
    out = []
    fr = aims.fractionation
    for pa in aims.points:
        ab = aims.alpha_beta_target_gy if pa.tissue == "target" else aims.alpha_beta_oar_gy
        h = aims.headroom_eqd2_gy if pa.aim_max_eqd2_gy is not None else 0.0
        found = [(n, d) for n, d in points if pa.matches(n)]
        for n, d in found:
            label = pa.name if n.casefold() == pa.name.casefold() else f"{pa.name} ({n})"
            out.append(AimResult(label, n, "point", fr.total_eqd2(d, ab), None, pa.aim_max_eqd2_gy, None,
                                 pa.limit_max_eqd2_gy, h))
        if not found:
            out.append(AimResult(pa.name, pa.name, "point", None, None, pa.aim_max_eqd2_gy, None,
                                 pa.limit_max_eqd2_gy, h, "not placed: the plan has no such reference point "
                                                         "(not counted)"))
    return out


def evaluate_aims(aims: Aims, target: StructureMetrics | None, oars: Sequence[StructureMetrics], *,
                  organ_volumes_cc: Mapping[str, float] | None = None, gtv: StructureMetrics | None = None,
                  points: Sequence[tuple[str, float]] = ()) -> AimsTable:
    """Return a plan's dose against every aim of ``aims`` (module docstring).

    Parameters
    ----------
    aims : Aims
        The protocol.
    target : StructureMetrics or None
        The target volume's metrics (EQD2 totals with ``aims``' fractionation); None: no target rows (a plan
        checked without its target volume).
    oars : sequence of StructureMetrics
        Each organ's metrics.
    organ_volumes_cc : mapping of str to float, cm³, or None
        Each organ's whole volume by name (the metrics may cover only the voxels near the implant); an organ not
        in it: its metrics' volume.
    gtv : StructureMetrics or None
        The GTV's metrics when there is a GTV (its D98 aim is then assessed).
    points : sequence of (str, float)
        The plan's reference points: name and dose, Gy per fraction.

    Returns
    -------
    AimsTable
        One result per aim, the verdicts and the warnings met.
    """
    volumes = organ_volumes_cc or {}
    rows = [] if target is None else [
        AimResult(f"{target.name} D90", target.name, "D90", target.d90_eqd2_gy, aims.target_d90_eqd2_gy,
                  aims.target_d90_max_eqd2_gy, aims.target_d90_limit_eqd2_gy),
        AimResult(f"{target.name} D98", target.name, "D98", target.d98_eqd2_gy, aims.target_d98_eqd2_gy)]
    if gtv is not None:
        rows.append(AimResult(f"{gtv.name} D98", gtv.name, "D98", gtv.d98_eqd2_gy, aims.gtv_d98_eqd2_gy,
                              limit_min_eqd2_gy=aims.gtv_d98_limit_eqd2_gy))
    warnings = []
    for o in oars:
        organ_rows, warning = _organ_results(aims, o, volumes.get(o.name, o.volume_cc))
        rows += organ_rows
        if warning:
            warnings.append(warning)
    rows += _point_results(aims, points)
    return AimsTable(aims.name, tuple(rows), tuple(warnings))


def is_site_target(aims: Aims, name: str) -> bool:
    """Return True when ROI ``name`` is one of the protocol's target names (case and punctuation ignored).

    Parameters
    ----------
    aims : Aims
        The protocol (its ``target_names``).
    name : str
        A ROI's name.

    Returns
    -------
    bool
    """
    def key(text: str) -> str:
        return re.sub(r"[^0-9a-z]", "", text.casefold())

    return key(name) in {key(n) for n in aims.target_names}


def site_warning(aims: Aims, target_name: str) -> str:
    """Return the warning when the dose target is not the protocol's site's target volume ("" when it is).

    Parameters
    ----------
    aims : Aims
        The protocol (its ``target_names`` and ``site``).
    target_name : str
        The ROI the dose is optimised on.

    Returns
    -------
    str
        ``"ProtocolSiteWarning: ..."`` saying which protocol's aims were used, or "".
    """
    if is_site_target(aims, target_name):
        return ""
    return (f"{ProtocolSiteWarning.__name__}: the dose target {target_name!r} is not a {aims.site} target of "
            f"{aims.name} (its targets are named {', '.join(aims.target_names)}); the {aims.name} ({aims.site}) "
            f"aims were used all the same: give the site's protocol with --protocol FILE_OR_NAME")


def emit(lines: Sequence[str]) -> None:
    """Issue each ``"Category: message"`` line of :meth:`AimsTable.warnings` or :func:`site_warning` once, named.

    Parameters
    ----------
    lines : sequence of str
        The lines; repeated ones are issued once, lines of another category are ignored.
    """
    categories = {c.__name__: c for c in (SmallOrganWarning, ProtocolSiteWarning)}
    for line in dict.fromkeys(lines):
        name, _, message = line.partition(": ")
        if name in categories:
            warnings.warn(message, categories[name], stacklevel=2)


def protocol_json(aims: Aims) -> dict[str, object]:
    """Return plan.json's ``protocol``: which aims were used, their numbers and how the values are computed.

    Parameters
    ----------
    aims : Aims
        The protocol.

    Returns
    -------
    dict
        ``name``, ``site``, ``origin`` (built-in name or file), ``source`` (citation), ``target_names``,
        ``headroom_eqd2_gy``, ``fractionation``, ``alpha_beta_gy``, ``aims`` (each planning aim and hard limit,
        Gy EQD2), ``points``, ``small_organ_rule`` and ``dvh_method``.
    """
    fr = aims.fractionation
    organs = [{"structure": n, "metric": "D2cm³", "planning_aim": bounds_text(None, v),
               "hard_limit": bounds_text(None, aims.oar_eqd2_gy(n, "limit"))} for n, v in aims.oar_d2cc_eqd2_gy]
    return {
        "name": aims.name, "site": aims.site, "origin": aims.origin, "source": aims.source,
        "target_names": list(aims.target_names), "headroom_eqd2_gy": aims.headroom_eqd2_gy,
        "fractionation": {"brachytherapy_fractions": fr.n_fractions, "ebrt_dose_gy": fr.ebrt_dose_gy,
                          "ebrt_fractions": fr.ebrt_fractions},
        "alpha_beta_gy": {"target": aims.alpha_beta_target_gy, "organ": aims.alpha_beta_oar_gy},
        "aims": [{"structure": "target", "metric": "D90",
                  "planning_aim": bounds_text(aims.target_d90_eqd2_gy, aims.target_d90_max_eqd2_gy),
                  "hard_limit": bounds_text(aims.target_d90_limit_eqd2_gy, None)},
                 {"structure": "target", "metric": "D98", "planning_aim": bounds_text(aims.target_d98_eqd2_gy, None),
                  "hard_limit": "-"},
                 {"structure": "GTV (when given)", "metric": "D98",
                  "planning_aim": bounds_text(aims.gtv_d98_eqd2_gy, None),
                  "hard_limit": bounds_text(aims.gtv_d98_limit_eqd2_gy, None)}, *organs],
        "points": [{"point": p.name, "matches": list(p.match), "planning_aim": bounds_text(None, p.aim_max_eqd2_gy),
                    "hard_limit": bounds_text(None, p.limit_max_eqd2_gy), "tissue": p.tissue} for p in aims.points],
        "small_organ_rule": (f"an organ under {SMALL_ORGAN_CC:g} cm³ has no D2cm³ (null, its aim not counted); its "
                             f"{SMALL_ORGAN_METRIC} is reported instead"),
        "dvh_method": DVH_METHOD,
    }
