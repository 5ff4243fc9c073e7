"""The anatomical variety of the clinical cohort: each parameter's distribution and where it comes from.

:func:`draw_params` draws the fields of one case's ``ClinicalParams`` (:mod:`reachplan.imaging.clinical`) from the
distributions of :data:`VARIETY` (seed 0, the reference case of ``reachplan demo``, is not drawn: it keeps the
defaults). Each :class:`Draw` names its source in ``gyn_anatomy.md`` (the project's reference notes on published
pelvic anatomy), or says ASSUMED and why (no citable number was found there). :func:`variety_table` prints them.

Sampling order is fixed (one generator per case, every draw made whether or not it is used), so a case's anatomy
depends on its seed only.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, cast

import numpy as np


@dataclass(frozen=True)
class Draw:
    """One parameter's distribution and its source.

    Parameters
    ----------
    kind : {"normal", "uniform", "choice"}
        ``normal``: ``args = (mean, sd)``, truncated to ``clip`` by redrawing; ``uniform``: ``args = (low, high)``;
        ``choice``: ``args = (values, probabilities)``.
    args : tuple
        The distribution's parameters (in ``unit``).
    source : str
        Where the numbers come from, or ``ASSUMED: <reason>``.
    unit : str
        The unit of the values (``mm``, ``cm3``, ``deg``, or empty).
    clip : (float, float) or None
        Range a normal draw is truncated to (redrawn until inside, at most 100 times, then clipped).

    Raises
    ------
    ValueError
        An unknown kind, choice probabilities that do not sum to 1, or an empty uniform range.
    """

    kind: str
    args: tuple[Any, ...]
    source: str
    unit: str = ""
    clip: tuple[float, float] | None = None

    def __post_init__(self) -> None:
        if self.kind not in ("normal", "uniform", "choice"):
            raise ValueError(f"Draw.kind must be normal, uniform or choice, got {self.kind!r}")
        if self.kind == "choice":
            values, probs = self.args
            if len(values) != len(probs) or not math.isclose(sum(probs), 1.0):
                raise ValueError("a choice needs one probability per value, summing to 1")
        elif self.kind == "uniform" and not float(self.args[0]) < float(self.args[1]):
            raise ValueError("a uniform draw needs low < high")

    def sample(self, rng: np.random.Generator) -> object:
        """Return one value (a float rounded to 0.01, or one of the choice's values).

        Parameters
        ----------
        rng : numpy.random.Generator
            The case's generator.

        Returns
        -------
        float or object
            The value, in ``unit``.
        """
        if self.kind == "choice":
            values, probs = self.args
            return values[int(rng.choice(len(values), p=probs))]
        a, b = float(self.args[0]), float(self.args[1])
        if self.kind == "uniform":
            return round(float(rng.uniform(a, b)), 2)
        lo, hi = self.clip or (-math.inf, math.inf)
        for _ in range(100):
            v = float(rng.normal(a, b))
            if lo <= v <= hi:
                break
        return round(float(np.clip(v, lo, hi)), 2)

    def describe(self) -> str:
        """Return the distribution in words, e.g. ``normal 138 ± 41 cm3, truncated to 50..260``.

        Returns
        -------
        str
            Kind, parameters, unit and truncation.
        """
        if self.kind == "choice":
            values, probs = self.args
            return "one of " + ", ".join(f"{v!r} {100 * p:.1f} %" for v, p in zip(values, probs, strict=True))
        a, b = self.args[0], self.args[1]
        if self.kind == "uniform":
            return f"uniform {a}..{b} {self.unit}".rstrip()
        clip = "" if self.clip is None else f", truncated to {self.clip[0]:g}..{self.clip[1]:g}"
        return f"normal {a} ± {b} {self.unit}{clip}".replace("  ", " ")


_NOT_FOUND = "ASSUMED: gyn_anatomy.md found no citable number"
#: Every parameter the cohort varies, by name (see :func:`draw_params` for how they map to ClinicalParams).
VARIETY: dict[str, Draw] = {
    "anteverted": Draw("choice", ((True, False), (0.848, 0.152)),
                       "274 of 323 uteri anteverted on CT/MRI (Appelbaum et al., Diagnostics 12:1428, 2022)"),
    "version_anteverted_deg": Draw("uniform", (15.0, 45.0), f"{_NOT_FOUND} for version angles; with the flexion "
                                   "roughly the right angle of the normal position", "deg"),
    "version_retroverted_deg": Draw("uniform", (-20.0, 0.0), "ASSUMED: 89.8 % of retroverted uteri insert at the "
                                    "vaginal apex, the cervix nearly in line with the vagina (Appelbaum 2022)", "deg"),
    "anteflexed": Draw("choice", ((True, False), (0.839, 0.161)),
                       "767 of 914 uteri anteflexed on transvaginal US (Gynecol Surg, 2009)"),
    "flexion_anteflexed_deg": Draw("uniform", (20.0, 50.0), f"{_NOT_FOUND} for flexion angles", "deg"),
    "flexion_retroflexed_deg": Draw("uniform", (-40.0, -10.0), f"{_NOT_FOUND} for flexion angles", "deg"),
    "uterus_length_mm": Draw("normal", (79.0, 11.5), "79 ± 11.5 mm, multiparous women, US (Nayab et al. 2022)",
                             "mm", (60.0, 100.0)),
    "cervix_length_mm": Draw("normal", (32.0, 4.0), "ASSUMED spread: 25-40 mm on MRI, mean 39.7 mm at 36-40 y "
                             "(Eur J Obstet Gynecol Reprod Biol 2020)", "mm", (25.0, 40.0)),
    "uterus_width_mm": Draw("normal", (43.0, 7.7), "43 ± 7.7 mm (Nayab et al. 2022)", "mm", (30.0, 58.0)),
    "uterus_thickness_mm": Draw("normal", (35.0, 6.6), "35 ± 6.6 mm (Nayab et al. 2022)", "mm", (24.0, 48.0)),
    "tumour_size": Draw("choice", (("small", "typical", "bulky"), (0.3, 0.4, 0.3)),
                        f"{_NOT_FOUND} for HR-CTV volumes at brachytherapy (EMBRACE volumes not retrieved); bulky "
                        "tumours (> 4 cm wide at brachytherapy) are the trigger for needles (PMC4987974)"),
    "small_corpus_fraction": Draw("uniform", (0.25, 0.5), "ASSUMED: a small tumour's HR-CTV covers the cervix and "
                                  "the lower quarter to half of the body"),
    "small_margin_mm": Draw("uniform", (1.0, 3.0), "ASSUMED", "mm"),
    "typical_corpus_fraction": Draw("uniform", (0.6, 1.0), "ASSUMED"),
    "typical_margin_mm": Draw("uniform", (1.5, 4.0), "ASSUMED", "mm"),
    "bulky_margin_mm": Draw("uniform", (4.0, 8.0), "ASSUMED: a bulky tumour grows beyond the uterine outline",
                            "mm"),
    "parametria": Draw("choice", (("", "L", "R", "LR"), (0.4, 0.2, 0.2, 0.2)),
                       f"{_NOT_FOUND} for the frequency of parametrial extension at brachytherapy; ASSUMED common "
                       "in cases planned for interstitial needles, either side equally"),
    "parametrium_distal": Draw("choice", ((False, True), (0.5, 0.5)), "ASSUMED (frequency NOT FOUND)"),
    "proximal_reach_mm": Draw("uniform", (24.0, 32.0), "ASSUMED: the medial parametrium, the cervix's edge "
                              "being 15-17 mm from its axis", "mm"),
    "distal_reach_mm": Draw("uniform", (40.0, 48.0), "ASSUMED: toward the pelvic side wall (obturator internus "
                            "55 mm from the axis in this case)", "mm"),
    "vaginal_extension": Draw("choice", ((False, True), (0.75, 0.25)), f"{_NOT_FOUND} for the frequency of "
                              "vaginal extension"),
    "vaginal_extension_mm": Draw("uniform", (10.0, 25.0), "ASSUMED: within the upper third to half of the vagina, "
                                 "62.7 mm long (Barnhart et al., Hum Reprod 2006)", "mm"),
    "vaginal_extension_left": Draw("choice", ((True, False), (0.5, 0.5)), "ASSUMED: either lateral wall"),
    "vaginal_extension_azimuth_deg": Draw("uniform", (-30.0, 30.0), "ASSUMED: within 30 degrees of the lateral "
                                          "wall (the model keeps the bladder and rectum, in front of and behind "
                                          "the vagina, clear of the HR-CTV)", "deg"),
    "bladder_volume_cm3": Draw("normal", (138.0, 41.0), "138 ± 41 cm3 at CT-based brachytherapy (Jamema et al., "
                               "J Med Phys 33:3, 2008)", "cm3", (50.0, 260.0)),
    "bladder_wall_y_mm": Draw("uniform", (-34.0, -24.0), f"{_NOT_FOUND} for the cervix-to-bladder distance; "
                              "5 mm either side of the reference case", "mm"),
    "rectum_volume_cm3": Draw("normal", (60.0, 28.0), "60 ± 28 cm3 at intracavitary brachytherapy (Jamema 2008)",
                              "cm3", (25.0, 130.0)),
    "sigmoid_shift_mm": Draw("uniform", (-8.0, 8.0), f"{_NOT_FOUND} for the sigmoid's position at "
                             "brachytherapy; each axis (then moved clear of bones, HR-CTV and bladder)", "mm"),
    "sigmoid_radius_mm": Draw("uniform", (10.0, 13.0), "ASSUMED: about 25 mm across collapsed (secondary sources in "
                              "gyn_anatomy.md); kept below 13 mm so the recto-sigmoid junction stays one tube",
                              "mm"),
    "bowel_shift_xy_mm": Draw("uniform", (-5.0, 8.0), f"{_NOT_FOUND} for small-bowel distances to the uterus; "
                              "x (the loops lie on the right, near the side wall: more room medially) and y", "mm"),
    "bowel_shift_z_mm": Draw("uniform", (-30.0, 5.0), "ASSUMED: loops may hang down onto the fundus (then moved "
                             "clear of it)", "mm"),
}


def rectum_radius_mm(volume_cm3: float, length_mm: float) -> float:
    """Return the radius (mm) of a rectum tube ``length_mm`` long holding ``volume_cm3``, clipped to 8..16 mm.

    The clip keeps the rectum off the vagina.

    Parameters
    ----------
    volume_cm3 : float, cm³
        The rectum's volume.
    length_mm : float, mm
        The length of its centre line.

    Returns
    -------
    float, mm
        ``sqrt(V / (π L))``, rounded to 0.01.
    """
    return round(float(np.clip(math.sqrt(volume_cm3 * 1000.0 / (math.pi * length_mm)), 8.0, 16.0)), 2)


def draw_params(rng: np.random.Generator, rectum_length_mm: float) -> dict[str, Any]:
    """Draw one case's anatomy from :data:`VARIETY` (every draw made, in a fixed order).

    Parameters
    ----------
    rng : numpy.random.Generator
        The case's generator.
    rectum_length_mm : float, mm
        Length of the case's rectum centre line (its drawn volume becomes a radius).

    Returns
    -------
    dict of str to object
        The fields of :class:`reachplan.imaging.clinical.ClinicalParams` (the uterine body's length is the uterus'
        less the cervix', at least 30 mm).
    """
    d = {name: draw.sample(rng) for name, draw in VARIETY.items()}

    def f(name: str) -> float:
        return float(cast(float, d[name]))

    size = str(d["tumour_size"])
    cervix = f("cervix_length_mm")
    return dict(
        version_deg=f("version_anteverted_deg" if d["anteverted"] else "version_retroverted_deg"),
        flexion_deg=f("flexion_anteflexed_deg" if d["anteflexed"] else "flexion_retroflexed_deg"),
        cervix_length_mm=cervix, corpus_length_mm=round(max(f("uterus_length_mm") - cervix, 30.0), 2),
        uterus_width_mm=f("uterus_width_mm"), uterus_thickness_mm=f("uterus_thickness_mm"),
        bladder_volume_cc=f("bladder_volume_cm3"), bladder_wall_y_mm=f("bladder_wall_y_mm"),
        rectum_radius_mm=rectum_radius_mm(f("rectum_volume_cm3"), rectum_length_mm),
        sigmoid_radius_mm=f("sigmoid_radius_mm"),
        sigmoid_shift_mm=(f("sigmoid_shift_mm"), _float(VARIETY["sigmoid_shift_mm"].sample(rng)),
                          _float(VARIETY["sigmoid_shift_mm"].sample(rng))),
        bowel_shift_mm=(f("bowel_shift_xy_mm"), _float(VARIETY["bowel_shift_xy_mm"].sample(rng)),
                        f("bowel_shift_z_mm")),
        parametria=str(d["parametria"]),
        param_reach_mm=f("distal_reach_mm" if d["parametrium_distal"] else "proximal_reach_mm"),
        hrctv_margin_mm=f(f"{size}_margin_mm"),
        hrctv_corpus_fraction=1.0 if size == "bulky" else f(f"{size}_corpus_fraction"),
        vaginal_extension_mm=f("vaginal_extension_mm") if d["vaginal_extension"] else 0.0,
        vaginal_extension_azimuth_deg=f("vaginal_extension_azimuth_deg") + (0.0 if d["vaginal_extension_left"]
                                                                             else 180.0),
    )


def _float(v: object) -> float:
    return float(cast(float, v))


def variety_table() -> str:
    """Return :data:`VARIETY` as a Markdown table (parameter, distribution, source), for the docs.

    Returns
    -------
    str
        One row per parameter.
    """
    rows = ["| parameter | distribution | source |", "|---|---|---|"]
    rows += [f"| `{n}` | {d.describe()} | {d.source} |" for n, d in VARIETY.items()]
    return "\n".join(rows)
