"""An ovoid (colpostat) of a tandem-and-ovoids applicator: an obstacle; its channel comes from an RT Plan only.

The source runs along the handle into the cap, off the cap's principal axis (shielded ovoids even put it off
centre); the principal axis of the drawn cap would not be an honest channel.
"""

from __future__ import annotations

from reachplan.plugins.applicators.base import PlanOnlyKind

OVOID = PlanOnlyKind(
    name="ovoid",
    description="ovoid (colpostat): an obstacle for needles; channel from an RT Plan only",
    roi_names=("Ovoid", "Ovoids", "Applicator_Ovoid", "Ovoid_L", "Ovoid_R", "L_Ovoid", "R_Ovoid", "Ovoid_Lt",
               "Ovoid_Rt", "Lt_Ovoid", "Rt_Ovoid", "Left_Ovoid", "Right_Ovoid", "Ovoid_Left", "Ovoid_Right",
               "Colpostat", "Colpostat_L", "Colpostat_R"),
    obstacle=True,
    loadable=False,
    why="an ovoid's channel is not derived from its contours (the source runs in the handle, off the cap's axis); "
        "give an RT Plan with the ovoid channels",
)
