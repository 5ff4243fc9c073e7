"""Quasi-static tension sweeps with friction: the loading/unloading hysteresis of the stylet.

With friction (the design's ``tendon_friction_coefficient``, capstan law, and ``joint_friction_coefficient``,
Coulomb friction in the ball joints; see :class:`reachplan.rod_model.design.StyletDesign`) the shape at a given
load-cell tension depends on where the sweep comes from: pulling, the tendon's tension decays distally by
``exp(−μ φ)`` and the joints' friction holds back the bending; releasing, the distal tension and the joints
stick until the load-cell tension has dropped far enough, then slide the other way. :func:`solve_sweep` tracks
the reversals of a sweep and passes them to the model as a :class:`~reachplan.rod_model.design.TensionHistory`.
Without friction every point of a sweep equals an independent solve.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from reachplan.rod_model.design import RodDesign, TensionHistory
from reachplan.rod_model.kinematic import joint_section_index, section_bounds_mm
from reachplan.rod_model.protocol import RodModel
from reachplan.rod_model.result import FailedSolve, RodPath, section_curvatures


def joint_curvature_per_m(design: RodDesign, path: RodPath) -> float:
    """Mean curvature of the joint section of a solved shape, 1/m."""
    curv = section_curvatures(path.frames, path.s_mm, section_bounds_mm(design))
    return float(curv[joint_section_index(design)])


def solve_sweep(model: RodModel, design: RodDesign, tensions_n: Sequence[float],
                roll_deg: float = 0.0) -> list[RodPath | FailedSolve]:
    """Solve a quasi-static sweep of load-cell tensions on tendon 0, starting from rest.

    Parameters
    ----------
    tensions_n : (b,) float, N, in the order applied (e.g. ``0, 2, ..., 10, ..., 2, 0`` for a loop).

    Returns
    -------
    One result per tension. A failed solve ends the memory of the sweep: the next points are solved as if
    pulled from rest (their results are still honest solves of that history, not of the sweep's).
    """
    history = TensionHistory()
    previous_t = 0.0
    previous: RodPath | FailedSolve | None = None
    out: list[RodPath | FailedSolve] = []
    for t in (float(x) for x in tensions_n):
        if t != previous_t and (t > previous_t) != history.increasing:
            kappa = joint_curvature_per_m(design, previous) if isinstance(previous, RodPath) else 0.0
            history = TensionHistory(t > previous_t, previous_t, kappa)
        result = model.solve(design, design.loads(t, roll_deg, history))
        out.append(result)
        previous_t, previous = t, result
    return out


def loop_width_mm(tensions_n: Sequence[float], tip_deflection_mm: Sequence[float]) -> float:
    """Return the largest difference in tip deflection (mm) between the unloading and the loading branch.

    The sweep goes up then down; the branches are compared at the tensions both visit.
    """
    t = np.asarray(tensions_n, dtype=float)
    d = np.asarray(tip_deflection_mm, dtype=float)
    peak = int(np.argmax(t))
    up = dict(zip(t[: peak + 1], d[: peak + 1], strict=True))
    width = 0.0
    for ti, di in zip(t[peak + 1:], d[peak + 1:], strict=True):
        if ti in up:
            width = max(width, abs(di - up[ti]))
    return width
