"""The report's tissue band: each shown steered needle over the plan's range of tissue moduli.

The bands come with the plan (:mod:`reachplan.planner.steering.tissue_band`): each target's chosen steered needle
(:func:`~reachplan.planner.case.search.band_shortlist`) and each implant arm's steered needles
(:mod:`reachplan.planner.implant.tissue`). Here they are collected for the 3-D view and tabulated.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from reachplan.planner.case.config import PlanConfig
from reachplan.planner.delivery import Delivery
from reachplan.planner.report.html import Paragraph, Section, Table
from reachplan.planner.steering.candidates import Candidate, TissueBand


def tissue_bands(steered: Sequence[Candidate], delivery: Delivery | None) -> list[tuple[str, TissueBand]]:
    """Return every computed band with its needle's label: the chosen steered needles, then the implants' ones.

    Parameters
    ----------
    steered : sequence of Candidate
        The chosen steered needle of each target.
    delivery : Delivery or None
        Its implant arms' chosen plans (when planned).

    Returns
    -------
    list of (str, TissueBand)
        ``"<hole> → <target>"`` or ``"implant <arm> <hole>"`` and the band (paths mm, LPS).
    """
    out = [(f"{c.hole_id} → {c.target}", c.tissue_band) for c in steered if c.tissue_band is not None]
    implant = None if delivery is None else delivery.implant
    for arm in implant.arms if implant is not None else ():
        for ch in arm.plan.channels if arm.plan is not None else ():
            if ch.tissue_band is not None:
                out.append((f"implant {arm.name} {ch.name}", ch.tissue_band))
    return out


def _mm(v: float) -> str:
    return f"{v:.1f}" if np.isfinite(v) else "-"


def band_section(config: PlanConfig, bands: Sequence[tuple[str, TissueBand]]) -> Section | None:
    """Return the report's tissue-band section: the moduli, where their range comes from, and each needle's band.

    Parameters
    ----------
    config : PlanConfig
        The plan's moduli (``tissue_modulus_pa``, ``tissue_moduli_pa``, Pa) and ``modulus_band``.
    bands : sequence of (str, TissueBand)
        :func:`tissue_bands`.

    Returns
    -------
    Section or None
        None when the plan has no band (``--modulus-band 1``) and no band was computed.
    """
    band = config.modulus_band
    if not bands and not band.enabled:
        return None
    organs = "; ".join(f"{n} {e / 1e6:g} MPa" for n, e in config.tissue_moduli_pa)
    rows = []
    for label, b in bands:
        per = " / ".join(_mm(r) for r in b.reach_mm) or "-"
        span = f"{b.moduli_pa[0] / 1e6:.3g}-{b.moduli_pa[-1] / 1e6:.3g}" if b.moduli_pa else "-"
        rows.append((label, span, per, _mm(b.worst_reach_mm), _mm(b.worst_clearance_mm), b.worst_case))
    calibrated = "; ".join(f"{d} x {r:g}" for d, r in config.curvature_scale)
    return Section("Tissue: the band of moduli", "tissue-band", (
        Paragraph(f"Tissue modulus: {config.tissue_modulus_pa / 1e6:g} MPa"
                  + (f" ({organs} inside those organs)" if organs else "")
                  + (f"; the site's calibration scales each design's in-tissue curvature ({calibrated}: the ratio "
                     "its steered needles found after insertion showed, 'reachplan calibrate')" if calibrated else "")
                  + f". Each steered needle is re-inserted with its planned schedule in tissue of every modulus "
                  f"divided and multiplied by {band.factor:g} ({band.source}); drawn as a ribbon in the 3-D view. Its "
                  "reach is measured from the target (an implant needle's: from its own planned tip, where the "
                  "dwells lie), its clearance from the organs at risk; the worst over the band is what the tissue "
                  "could do to the needle. Model: the in-tissue rod's change of shape added to the planned path."),
        Table(("needle", "modulus at the tip (MPa)", "reach soft / planned / stiff (mm)", "worst reach (mm)",
               "worst clearance (mm)", "worst case"), tuple(rows),
              "Worst reach and clearance of each steered needle over the band of tissue moduli", numeric=(2, 3, 4)),
    ))
