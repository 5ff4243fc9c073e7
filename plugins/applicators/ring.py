"""The ring of a ring-tandem applicator: an obstacle for needles; its channel comes from an RT Plan only.

The ring's source path is the curve through its tube's core, usually tilted to the axial slices; the contours of the
solid ring give it only through a skeleton fit that is not written yet.
"""

from __future__ import annotations

from reachplan.plugins.applicators.base import PlanOnlyKind

RING = PlanOnlyKind(
    name="ring",
    description="ring of a ring-tandem applicator: an obstacle for needles; channel from an RT Plan only",
    roi_names=("Ring", "Applicator_Ring", "Ring_Applicator", "Ring_Vaginal", "Vaginal_Ring"),
    obstacle=True,
    loadable=False,
    why="a ring's channel is not derived from its contours (the curve through the tube's core needs a skeleton "
        "fit); give an RT Plan with the ring channel",
)
