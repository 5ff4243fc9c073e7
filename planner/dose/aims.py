"""Planning aims as data: each aim with its planning value and its hard limit, the headroom and the fractionation.

Default aims are the EMBRACE II protocol's (Pötter et al., Clin. Transl. Radiat. Oncol. 9:48, 2018;
``reference/gyn_anatomy.md``, dose aims), totals of EBRT and brachytherapy in EQD2: HR-CTV D90 planning aim
> 90 and < 95 Gy, hard limit > 85 Gy; HR-CTV D98 > 75 Gy; GTV_res D98 > 95 Gy (limit > 90 Gy) (α/β 10); D2cm³
bladder < 80 (limit 90), rectum < 65 (limit 75), sigmoid < 70 (limit 75), bowel < 70 (limit 75) Gy (α/β 3);
45 Gy / 25 fractions external beam plus 4 brachytherapy fractions; the ICRU recto-vaginal point < 65 Gy (limit
75 Gy, α/β 3) and Point A reported (ICRU Report 89). The same numbers are the built-in protocol file
``reachplan/plugins/protocols/embrace_ii.toml``, which :func:`reachplan.planner.dose.protocol.load_protocol` reads
into these aims (a test checks that the two agree); other protocols are files in that format.

Two levels, as the protocol has them: the *planning aim* is what a plan is made for, the *hard limit* is what no
delivered plan may break. A plan meets its aims with ``headroom_eqd2_gy`` to spare on every organ (an independent
recomputation of the same plan lands within a fraction of a Gy on either side); robust planning holds the hard
limits when a needle is off its planned path.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from reachplan.planner.dose.coverage import Fractionation

#: EMBRACE II D2cm³ planning aims, EQD2 Gy (α/β 3), matched case-insensitively to organ names.
EMBRACE_II_OAR_D2CC: tuple[tuple[str, float], ...] = (
    ("bladder", 80.0),
    ("rectum", 65.0),
    ("sigmoid", 70.0),
    ("bowel", 70.0),
)
#: EMBRACE II D2cm³ hard limits, EQD2 Gy (α/β 3).
EMBRACE_II_OAR_D2CC_LIMIT: tuple[tuple[str, float], ...] = (
    ("bladder", 90.0),
    ("rectum", 75.0),
    ("sigmoid", 75.0),
    ("bowel", 75.0),
)


#: EMBRACE II's target ROI names: what a cervix HR-CTV is called (ICRU 89 ``CTV_HR``; clinical variants).
EMBRACE_II_TARGET_NAMES: tuple[str, ...] = ("HR-CTV", "CTV_HR", "CTV-HR", "HRCTV", "CTVHR")

#: Where EMBRACE II's numbers come from.
EMBRACE_II_SOURCE = ("Pötter R et al., The EMBRACE II study: the outcome and prospect of two decades of evolution "
                     "within the GEC-ESTRO GYN working group and the EMBRACE studies, Clin Transl Radiat Oncol "
                     "9:48-60, 2018, doi:10.1016/j.ctro.2018.01.001")


@dataclass(frozen=True)
class PointAim:
    """A dose point of the protocol (ICRU 89 reporting points): reported, with a planning aim and limit if any.

    Parameters
    ----------
    name : str
        The point's name in reports (``"ICRU recto-vaginal"``, ``"Point A"``).
    match : tuple of str
        Names of the plan's reference points it stands for, matched as a substring with case, spaces and
        punctuation ignored (``"Point A"`` matches ``"Point A left"`` and ``"POINT_A_RIGHT"``, each reported;
        ``"PtA"`` matches Eclipse's ``"PtA_left"`` and ``"PT A RIGHT"``).
    aim_max_eqd2_gy : float or None
        Planning aim, upper, Gy EQD2 (None: reported only).
    limit_max_eqd2_gy : float or None
        Hard limit, upper, Gy EQD2 (None: none); never below the aim.
    tissue : str
        ``"organ"`` or ``"target"``: which α/β gives its EQD2.

    Raises
    ------
    ValueError
        No match name, a non-positive aim or limit, a limit below the aim, or another tissue.
    """

    name: str
    match: tuple[str, ...]
    aim_max_eqd2_gy: float | None = None
    limit_max_eqd2_gy: float | None = None
    tissue: str = "organ"

    def __post_init__(self) -> None:
        object.__setattr__(self, "match", tuple(self.match))
        if not self.match or not all(m.strip() for m in self.match):
            raise ValueError(f"point {self.name!r}: give the reference point names it matches")
        if any(v is not None and not v > 0 for v in (self.aim_max_eqd2_gy, self.limit_max_eqd2_gy)):
            raise ValueError(f"point {self.name!r}: its aim and limit must be > 0 Gy")
        if (self.aim_max_eqd2_gy is not None and self.limit_max_eqd2_gy is not None
                and self.limit_max_eqd2_gy < self.aim_max_eqd2_gy):
            raise ValueError(f"point {self.name!r}: its hard limit must not be below its planning aim")
        if self.tissue not in ("organ", "target"):
            raise ValueError(f"point {self.name!r}: tissue must be 'organ' or 'target', got {self.tissue!r}")

    def matches(self, point_name: str) -> bool:
        """Return True when the plan's reference point ``point_name`` is this point.

        Parameters
        ----------
        point_name : str
            A reference point's name.

        Returns
        -------
        bool
            One of :attr:`match` is in ``point_name``, both with case, spaces and punctuation ignored.
        """
        def key(text: str) -> str:
            return "".join(ch for ch in text.casefold() if ch.isalnum())

        return any(key(m) in key(point_name) for m in self.match)


#: EMBRACE II's points: the ICRU recto-vaginal point (placed as the ICRU 38 rectum point) < 65 Gy, limit 75 Gy;
#: Point A (left and right) and the ICRU bladder point reported only.
EMBRACE_II_POINTS: tuple[PointAim, ...] = (
    PointAim("ICRU recto-vaginal", ("ICRU rectum", "recto-vaginal"), 65.0, 75.0),
    PointAim("ICRU bladder", ("ICRU bladder",)),
    PointAim("Point A", ("Point A", "PtA"), tissue="target"),
)


def _lookup(table: tuple[tuple[str, float], ...], name: str) -> float | None:
    """Return the value of the first organ of ``table`` that ``name`` matches (case-insensitively, or contains)."""
    key = name.casefold()
    for organ, value in table:
        if organ.casefold() == key or organ.casefold() in key:
            return value
    return None


@dataclass(frozen=True)
class Aims:
    """Coverage aims and organ limits of one protocol (EQD2, totals with the external-beam course).

    Defaults: EMBRACE II (see the module docstring). The prescription (V100) is the D90 planning aim. Organ
    aims and limits match organ names case-insensitively, also as a substring (``"Bladder_P"`` gets the bladder's);
    organs without an aim are reported only.

    Parameters
    ----------
    name : str
        The protocol's name, as reports show it.
    site : str
        The site it is for (``"cervix"``).
    target_names : tuple of str
        What the site's target volume is called (a dose target named otherwise gets a warning that these aims were
        used all the same).
    source : str
        Where the numbers come from (a citation).
    target_d90_eqd2_gy : float
        HR-CTV D90 planning aim (lower end), Gy EQD2 (α/β ``alpha_beta_target_gy``).
    target_d90_max_eqd2_gy : float or None
        HR-CTV D90 planning aim, upper end, Gy EQD2; None for none.
    target_d90_limit_eqd2_gy : float
        HR-CTV D90 hard limit (lower), Gy EQD2: kept in every robustness scenario.
    target_d98_eqd2_gy : float
        HR-CTV D98 planning aim, Gy EQD2.
    gtv_d98_eqd2_gy : float
        GTV_res D98 planning aim, Gy EQD2 (used when a GTV is given).
    gtv_d98_limit_eqd2_gy : float
        GTV_res D98 hard limit, Gy EQD2.
    oar_d2cc_eqd2_gy : tuple of (organ name, Gy EQD2)
        D2cm³ planning aim of each organ (α/β ``alpha_beta_oar_gy``).
    oar_d2cc_limit_eqd2_gy : tuple of (organ name, Gy EQD2)
        D2cm³ hard limit of each organ; an organ's limit is never below its aim (an organ with an aim and no limit
        here, or a lower one, has its aim as its limit).
    headroom_eqd2_gy : float
        Margin below each organ's planning aim that the nominal plan keeps, Gy EQD2 (>= 0).
    alpha_beta_target_gy, alpha_beta_oar_gy : float
        α/β of the tumour and of the organs, Gy.
    fractionation : Fractionation
        The external-beam course and the number of brachytherapy fractions.
    points : tuple of PointAim
        The dose points reported, with their aims and limits if any.
    origin : str
        Where the aims were read from (a built-in protocol's name or a file), for reports; not compared.

    Raises
    ------
    ValueError
        A non-positive aim, limit or α/β, a negative headroom, a target's hard limit above its planning aim, or a
        D90 upper aim below the lower one.
    """

    name: str = "EMBRACE II"
    target_d90_eqd2_gy: float = 90.0
    target_d90_max_eqd2_gy: float | None = 95.0
    target_d90_limit_eqd2_gy: float = 85.0
    target_d98_eqd2_gy: float = 75.0
    gtv_d98_eqd2_gy: float = 95.0
    gtv_d98_limit_eqd2_gy: float = 90.0
    oar_d2cc_eqd2_gy: tuple[tuple[str, float], ...] = EMBRACE_II_OAR_D2CC
    oar_d2cc_limit_eqd2_gy: tuple[tuple[str, float], ...] = EMBRACE_II_OAR_D2CC_LIMIT
    headroom_eqd2_gy: float = 1.0
    alpha_beta_target_gy: float = 10.0
    alpha_beta_oar_gy: float = 3.0
    fractionation: Fractionation = field(default_factory=Fractionation)
    site: str = "cervix"
    target_names: tuple[str, ...] = EMBRACE_II_TARGET_NAMES
    source: str = EMBRACE_II_SOURCE
    points: tuple[PointAim, ...] = EMBRACE_II_POINTS
    origin: str = field(default="built-in protocol embrace_ii", compare=False)

    def __post_init__(self) -> None:
        if not (self.target_d90_eqd2_gy > 0 and self.alpha_beta_target_gy > 0 and self.alpha_beta_oar_gy > 0):
            raise ValueError("aims: the D90 aim and both α/β must be > 0 Gy")
        if any(v <= 0 for _, v in self.oar_d2cc_eqd2_gy + self.oar_d2cc_limit_eqd2_gy):
            raise ValueError("aims: organ aims and limits must be > 0 Gy")
        if self.headroom_eqd2_gy < 0:
            raise ValueError("aims: the headroom must be >= 0 Gy")
        if self.target_d90_limit_eqd2_gy > self.target_d90_eqd2_gy or self.gtv_d98_limit_eqd2_gy > self.gtv_d98_eqd2_gy:
            raise ValueError("aims: a target's hard limit must not exceed its planning aim")
        if self.target_d90_max_eqd2_gy is not None and self.target_d90_max_eqd2_gy < self.target_d90_eqd2_gy:
            raise ValueError("aims: the D90 upper aim must be >= the lower aim")

    @property
    def prescription_gy(self) -> float:
        """Per-fraction physical dose whose D90 meets the planning aim, Gy."""
        return self.fractionation.per_fraction_for(self.target_d90_eqd2_gy, self.alpha_beta_target_gy)

    def per_fraction_target_gy(self, total_eqd2_gy: float) -> float:
        """Return the per-fraction dose that brings a target's total to ``total_eqd2_gy`` (α/β of the tumour).

        Parameters
        ----------
        total_eqd2_gy : float, Gy EQD2
            The target's total with the external beam.

        Returns
        -------
        float, Gy
            The brachytherapy dose of each fraction.
        """
        return self.fractionation.per_fraction_for(total_eqd2_gy, self.alpha_beta_target_gy)

    def oar_eqd2_gy(self, name: str, level: str = "aim") -> float | None:
        """Return organ ``name``'s D2cm³ aim or limit, Gy EQD2 (None when the organ has none).

        Parameters
        ----------
        name : str
            The organ's name (matched case-insensitively, also as a substring).
        level : {"aim", "planning", "limit"}
            The planning aim; the planning aim less the headroom (what a nominal plan may reach); the hard limit
            (never below the aim).

        Returns
        -------
        float or None
            Gy EQD2.

        Raises
        ------
        ValueError
            An unknown ``level``.
        """
        aim = _lookup(self.oar_d2cc_eqd2_gy, name)
        if level == "aim":
            return aim
        if level == "planning":
            return None if aim is None else max(aim - self.headroom_eqd2_gy, 1e-3)
        if level == "limit":
            limit = _lookup(self.oar_d2cc_limit_eqd2_gy, name)
            return aim if limit is None else limit if aim is None else max(aim, limit)
        raise ValueError(f"aims: level must be 'aim', 'planning' or 'limit', not {level!r}")

    def oar_gy(self, name: str, level: str = "aim") -> float | None:
        """Return :meth:`oar_eqd2_gy` as the per-fraction physical D2cm³ of the brachytherapy, Gy.

        Parameters
        ----------
        name : str
            The organ's name.
        level : {"aim", "planning", "limit"}
            As in :meth:`oar_eqd2_gy`.

        Returns
        -------
        float or None
            Gy per fraction (α/β of the organs, with the external beam).
        """
        total = self.oar_eqd2_gy(name, level)
        return None if total is None else self.fractionation.per_fraction_for(total, self.alpha_beta_oar_gy)
