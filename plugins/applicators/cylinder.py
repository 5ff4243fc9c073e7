"""A vaginal cylinder: one channel, its principal axis, as for the obturator (the template can sit on it)."""

from __future__ import annotations

from reachplan.plugins.applicators.obturator import AxisKind

CYLINDER = AxisKind(
    name="cylinder",
    description="vaginal cylinder: its axis places the template; central channel not loaded yet",
    roi_names=("Cylinder", "Vaginal_Cylinder", "Cylinder_Vaginal", "Cyl_Vaginal", "Vaginal_Cyl",
               "Applicator_Cylinder", "Vaginal_Applicator"),
    obstacle=False,
    loadable=False,
)
