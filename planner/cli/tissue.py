"""The tissue options of ``plan`` and ``demo``: the tissue's Young's modulus, per organ, and the band around it."""

from __future__ import annotations

import argparse
from typing import Any

from reachplan.planner.cli.edges import finite_float

#: The moduli the screening model's curvature factor is fitted over, MPa (the packaged table's range:
#: ``reachplan bench factors``); below the lower end tip following does not describe the needle.
MODULUS_RANGE_MPA = (0.1, 10.0)
#: The widest modulus band: x/÷ this.
MAX_BAND_FACTOR = 10.0


def add_tissue_arguments(parser: argparse.ArgumentParser) -> None:
    """Add ``--tissue-modulus``, ``--organ-modulus`` and ``--modulus-band`` (``plan`` and ``demo``).

    Parameters
    ----------
    parser : argparse.ArgumentParser
        The command's parser.
    """
    lo, hi = MODULUS_RANGE_MPA
    group = parser.add_argument_group(
        "tissue", "the tissue the steered needles are predicted in (default: the phantom gel's 0.19 MPa, SimuGel #3, "
        "the only tissue modulus the reference material gives)")
    group.add_argument("--tissue-modulus", type=modulus_mpa, default=None, metavar="MPA",
                       help=f"Young's modulus of the tissue, MPa, in [{lo:g}, {hi:g}] (default 0.19)")
    group.add_argument("--organ-modulus", type=organ_modulus, action="append", default=[], metavar="ORGAN=MPA",
                       help="Young's modulus of the tissue inside ROI ORGAN (e.g. Uterus=0.4), MPa; repeatable; "
                            "the first ORGAN that holds a point sets it there")
    group.add_argument("--modulus-band", type=band_factor, default=None, metavar="FACTOR",
                       help="each shown steered needle is re-inserted in tissue of every modulus divided and "
                            "multiplied by FACTOR, and its worst reach and clearance over that band reported "
                            f"(default 3, ASSUMED: no cited range for uterus, cervix or parametrium; 1: no band; at "
                            f"most {MAX_BAND_FACTOR:g})")
    group.add_argument("--calibration", type=site_calibration, default=None, metavar="FILE",
                       help="a site calibration file (written by 'reachplan calibrate' from the steered needles found "
                            "in post-insertion images): each design's in-tissue curvature is scaled by the ratio "
                            "its needles showed")


def modulus_mpa(text: str) -> float:
    """Argparse ``type=`` of a Young's modulus in MPa, within :data:`MODULUS_RANGE_MPA`.

    Parameters
    ----------
    text : str
        The argument as given (MPa).

    Returns
    -------
    float
        The modulus, MPa.
    """
    value = finite_float(text)
    lo, hi = MODULUS_RANGE_MPA
    if not lo <= value <= hi:
        raise argparse.ArgumentTypeError(
            f"{text} MPa is outside [{lo:g}, {hi:g}] MPa, where the screening model's curvature factor is fitted to "
            "the in-tissue rod (softer tissue does not hold the needle on its track); give a modulus in that range")
    return value


def organ_modulus(text: str) -> tuple[str, float]:
    """Argparse ``type=`` of ``--organ-modulus ORGAN=MPA``.

    Parameters
    ----------
    text : str
        ``ORGAN=MPA`` (the ROI name may itself hold ``=``: the last one splits).

    Returns
    -------
    tuple of (str, float)
        The ROI name and the modulus, MPa.
    """
    name, sep, value = text.rpartition("=")
    if not sep or not name.strip():
        raise argparse.ArgumentTypeError(f"--organ-modulus needs ORGAN=MPA (e.g. Uterus=0.4), not {text!r}")
    return name.strip(), modulus_mpa(value)


def band_factor(text: str) -> float:
    """Argparse ``type=`` of ``--modulus-band FACTOR``: a number in [1, :data:`MAX_BAND_FACTOR`].

    Parameters
    ----------
    text : str
        The argument as given.

    Returns
    -------
    float
        The factor.
    """
    value = finite_float(text)
    if not 1.0 <= value <= MAX_BAND_FACTOR:
        raise argparse.ArgumentTypeError(f"--modulus-band needs a factor in [1, {MAX_BAND_FACTOR:g}] (3: the moduli "
                                         f"÷ 3 to x 3; 1: no band), not {text}")
    return value


def site_calibration(text: str) -> tuple[tuple[str, float], ...]:
    """Argparse ``type=`` of ``--calibration FILE``: the file's per-design curvature ratios.

    Parameters
    ----------
    text : str
        The file's path.

    Returns
    -------
    tuple of (str, float)
        Design name and ratio (``PlanConfig.curvature_scale``).
    """
    import json
    from pathlib import Path

    from reachplan.planner.errors import PlanInputError
    from reachplan.planner.steering.calibration import RATIO_RANGE, site_scales

    try:
        doc = json.loads(Path(text).read_text(encoding="utf-8"))
    except (OSError, ValueError) as exc:
        raise argparse.ArgumentTypeError(f"cannot read the site calibration {text}: {exc}") from None
    try:
        scales = site_scales(doc)
    except PlanInputError as exc:
        raise argparse.ArgumentTypeError(f"{text}: {exc}") from None
    lo, hi = RATIO_RANGE
    for design, ratio in scales:
        if not lo <= ratio <= hi:
            raise argparse.ArgumentTypeError(f"{text}: the curvature ratio of {design} is {ratio:g}, outside "
                                             f"[{lo:g}, {hi:g}]: check the needles it was fitted to")
    return scales


def tissue_options(args: argparse.Namespace) -> dict[str, Any]:
    """Return the :class:`~reachplan.planner.case.config.PlanConfig` fields the tissue options set (Pa).

    Parameters
    ----------
    args : argparse.Namespace
        Parsed options (``tissue_modulus``, ``organ_modulus``, ``modulus_band``; MPa; ``calibration``).

    Returns
    -------
    dict of str to object
        ``tissue_modulus_pa``, ``tissue_moduli_pa``, ``modulus_band`` and ``curvature_scale`` for the options given
        (none for the others).
    """
    out: dict[str, Any] = {}
    if args.tissue_modulus is not None:
        out["tissue_modulus_pa"] = args.tissue_modulus * 1e6
    if args.organ_modulus:
        out["tissue_moduli_pa"] = tuple((name, mpa * 1e6) for name, mpa in args.organ_modulus)
    if args.modulus_band is not None:
        from reachplan.planner.steering.tissue_band import ModulusBand

        source = None if args.modulus_band == 3.0 else f"given: --modulus-band {args.modulus_band:g}"
        out["modulus_band"] = ModulusBand(args.modulus_band, source=source) if source else ModulusBand()
    if getattr(args, "calibration", None):
        out["curvature_scale"] = args.calibration
    return out
