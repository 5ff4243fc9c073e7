"""The ring of a ring-tandem applicator: an obstacle for needles; its channel from an RT Plan or a drawn channel line.

The ring's source path is the curve through its tube's core, usually tilted to the axial slices; where along the loop
the source enters and how far it goes round is the applicator's, not the drawn solid's, so the ring's closed
contours give no channel (the note says so). A channel drawn as a line in its ROI, or the ring channel of an RT Plan,
is its channel as given, loaded for dose.
"""

from __future__ import annotations

from reachplan.plugins.applicators.base import PlanOnlyKind

RING = PlanOnlyKind(
    name="ring",
    description="ring of a ring-tandem applicator: an obstacle for needles; channel from an RT Plan or a drawn line, "
                "loaded for dose",
    roi_names=("Ring", "Applicator_Ring", "Ring_Applicator", "Ring_Vaginal", "Vaginal_Ring"),
    obstacle=True,
    loadable=True,
    why="a ring's channel is not derived from its solid contours (where the source enters the loop and how far it "
        "goes round is the applicator's, not the skeleton of the drawn tube's); give an RT Plan with the ring "
        "channel or draw the channel as a line",
)
