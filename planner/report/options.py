"""What the report computes and draws: its options and the straight-versus-steered comparison's LP settings."""

from __future__ import annotations

from dataclasses import dataclass

from reachplan.planner.implant.dwells import OptimizerSettings
from reachplan.planner.report import figures

#: Faster LP settings for the straight-versus-steered comparison in the report (the delivered plan keeps the
#: full :class:`~reachplan.planner.implant.dwells.OptimizerSettings`); about 5 s for 4 + 12 needles on the demo phantom.
COMPARISON_SETTINGS = OptimizerSettings(max_target_points=1000, max_oar_points=500, relax_iterations=1)


@dataclass(frozen=True)
class ReportOptions:
    """What the report computes and draws.

    Parameters
    ----------
    max_slice_targets : int
        Targets that get slice overlays (in ranking order), >= 0.
    comparison : bool
        Run the straight-versus-steered dose comparison.
    comparison_settings : OptimizerSettings
        Its LP settings.
    mesh_faces : int
        Faces per organ in the 3-D view (quadric decimation), >= 4.

    Raises
    ------
    ValueError
        ``max_slice_targets`` < 0 or ``mesh_faces`` < 4.
    """

    max_slice_targets: int = 12
    comparison: bool = True
    comparison_settings: OptimizerSettings = COMPARISON_SETTINGS
    mesh_faces: int = figures.VIEW_FACES

    def __post_init__(self) -> None:
        if self.max_slice_targets < 0:
            raise ValueError("max_slice_targets must be >= 0")
        if self.mesh_faces < 4:
            raise ValueError("mesh_faces must be at least 4 (a tetrahedron)")
