"""The intrauterine tandem: one channel, the centre line of its ROI, curved as drawn.

The tube's closed contours (or a drawn channel line) give the channel through
:func:`reachplan.plugins.applicators.centreline.roi_centreline`; an RT Plan's tandem channel gives its own path
(:func:`reachplan.plugins.applicators.base.plan_centreline`).
"""

from __future__ import annotations

from reachplan.plugins.applicators.base import CentrelineKind

TANDEM = CentrelineKind(
    name="tandem",
    description="intrauterine tandem: one channel (the centre line of its ROI, curved as drawn), loaded for dose; "
                "needles keep off it",
    roi_names=("Tandem", "Applicator_Tandem", "Tandem_Applicator", "Uterine_Tandem", "Tandem_Uterine",
               "Intrauterine_Tube", "Intrauterine_Tandem", "Intrauterine", "IU_Tube", "IU_Tandem", "IU", "UT"),
    obstacle=True,
    loadable=True,
)
