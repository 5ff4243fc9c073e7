"""Planning aims as data: the HR-CTV coverage aim, the GTV aim and the organs' D2cm³ limits, with the fractionation.

Default aims are the EMBRACE II planning aims (Pötter et al., Clin. Transl. Radiat. Oncol. 9:48, 2018;
``reference/oncoreach.md``): HR-CTV D90 >= 85 Gy, D98 >= 75 Gy EQD2 (α/β 10); D2cm³ bladder < 80 Gy,
rectum < 65 Gy, sigmoid < 70 Gy, bowel < 70 Gy EQD2 (α/β 3); 45 Gy / 25 fractions external beam plus
4 brachytherapy fractions. The GTV D98 aim (> 90 Gy EQD2) is from the ESGO/ESTRO achievability table (reached in
90 % of patients).
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


@dataclass(frozen=True)
class Aims:
    """Coverage aim and organ limits (EQD2, totals with the external-beam course).

    Defaults: EMBRACE II (see the module docstring). The prescription (V100) and ``aim_met`` use the D90
    aim; the D98 aim is carried for reports. Organ limits match organ names case-insensitively, also as
    a substring (``"Bladder_P"`` gets the bladder limit); organs without a limit are reported only.

    Parameters
    ----------
    target_d90_eqd2_gy, target_d98_eqd2_gy : float
        HR-CTV D90 and D98 aims, Gy EQD2 (α/β ``alpha_beta_target_gy``), totals with the external beam.
    gtv_d98_eqd2_gy : float
        GTV_res D98 aim, Gy EQD2 (ESGO/ESTRO quality indicators 2023, reached in 90 % of patients); used by implant
        planning when a GTV is given.
    oar_d2cc_eqd2_gy : tuple of (organ name, Gy EQD2)
        D2cm³ limit of each organ (α/β ``alpha_beta_oar_gy``).
    alpha_beta_target_gy, alpha_beta_oar_gy : float
        α/β of the tumour and of the organs, Gy.
    fractionation : Fractionation
        The external-beam course and the number of brachytherapy fractions.

    Raises
    ------
    ValueError
        A non-positive aim, limit or α/β.
    """

    target_d90_eqd2_gy: float = 85.0
    target_d98_eqd2_gy: float = 75.0
    gtv_d98_eqd2_gy: float = 90.0
    oar_d2cc_eqd2_gy: tuple[tuple[str, float], ...] = EMBRACE_II_OAR_D2CC
    alpha_beta_target_gy: float = 10.0
    alpha_beta_oar_gy: float = 3.0
    fractionation: Fractionation = field(default_factory=Fractionation)

    def __post_init__(self) -> None:
        if not (self.target_d90_eqd2_gy > 0 and self.alpha_beta_target_gy > 0 and self.alpha_beta_oar_gy > 0):
            raise ValueError("aims: the D90 aim and both α/β must be > 0 Gy")
        if any(limit <= 0 for _, limit in self.oar_d2cc_eqd2_gy):
            raise ValueError("aims: organ limits must be > 0 Gy")

    @property
    def prescription_gy(self) -> float:
        """Per-fraction physical dose whose D90 meets the aim, Gy."""
        return self.fractionation.per_fraction_for(self.target_d90_eqd2_gy, self.alpha_beta_target_gy)

    def oar_limit_gy(self, name: str) -> float | None:
        """Return the per-fraction physical D2cm³ limit of organ ``name``.

        Parameters
        ----------
        name : str
            The organ's name (matched case-insensitively, also as a substring).

        Returns
        -------
        float or None
            Gy per fraction; None when the organ has no limit.
        """
        key = name.casefold()
        for organ, limit in self.oar_d2cc_eqd2_gy:
            if organ.casefold() == key or organ.casefold() in key:
                return self.fractionation.per_fraction_for(limit, self.alpha_beta_oar_gy)
        return None
