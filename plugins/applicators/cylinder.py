"""A vaginal cylinder: one central channel, the centre line of its ROI (the template can sit on its axis).

The channel is the centre line of the cylinder's contours, curved as drawn (straight for a straight cylinder), or a
channel drawn as a line in its ROI (:func:`reachplan.plugins.applicators.centreline.roi_centreline`); the template
pose is fitted to the cylinder's principal axis separately. The central channel is loaded for dose where it lies in
the target.
"""

from __future__ import annotations

from reachplan.plugins.applicators.base import CentrelineKind

CYLINDER = CentrelineKind(
    name="cylinder",
    description="vaginal cylinder: its axis places the template; its central channel (the ROI's centre line) is "
                "loaded for dose",
    roi_names=("Cylinder", "Vaginal_Cylinder", "Cylinder_Vaginal", "Cyl_Vaginal", "Vaginal_Cyl",
               "Applicator_Cylinder", "Vaginal_Applicator"),
    obstacle=False,
    loadable=True,
)
