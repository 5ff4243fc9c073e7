"""An ovoid (colpostat) of a tandem-and-ovoids applicator: an obstacle; its channel from an RT Plan or a drawn line.

The source runs along the handle into the cap, off the cap's principal axis (shielded ovoids even put it off
centre); the drawn cap's centre line would not be an honest channel. A channel drawn as a line in its ROI (as
Eclipse writes the "left ovoid" channel ROI), or the ovoid channel of an RT Plan, is its channel as given, loaded
for dose.
"""

from __future__ import annotations

from reachplan.plugins.applicators.base import PlanOnlyKind

OVOID = PlanOnlyKind(
    name="ovoid",
    description="ovoid (colpostat): an obstacle for needles; channel from an RT Plan or a drawn line, loaded for dose",
    roi_names=("Ovoid", "Ovoids", "Applicator_Ovoid", "Ovoid_L", "Ovoid_R", "L_Ovoid", "R_Ovoid", "Ovoid_Lt",
               "Ovoid_Rt", "Lt_Ovoid", "Rt_Ovoid", "Left_Ovoid", "Right_Ovoid", "Ovoid_Left", "Ovoid_Right",
               "Colpostat", "Colpostat_L", "Colpostat_R"),
    obstacle=True,
    loadable=True,
    why="an ovoid's channel is not derived from its cap's contours (the source runs in the handle, off the cap's "
        "axis); give an RT Plan with the ovoid channels or draw the channel as a line",
)
