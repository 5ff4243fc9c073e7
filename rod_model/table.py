"""Tension → curvature tables: what an insertion model evaluates 10⁴-10⁵ times per second.

A table is built once per design (and model) from one :meth:`RodModel.solve_batch` call on a tension grid,
and checked: the model is solved again at every midpoint of the grid and the largest difference between
interpolated and solved curvature is stored with the table (``max_interp_error_per_m``), so the table
says how exact it is to the model it came from (for ``planar_beam`` curvature is linear in tension and the
error is at round-off).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from reachplan.rod_model.design import RodDesign
from reachplan.rod_model.errors import RodModelError
from reachplan.rod_model.protocol import RodModel


@dataclass(frozen=True, eq=False)
class CurvatureTable:
    """Mean curvature of each section of one design against the tension on tendon 0, in free space.

    Parameters
    ----------
    model : str
        Name of the model the table was built from.
    design_name : str
        Name of the design.
    tensions_n : (t,) float, N
        Strictly increasing, from 0 to the design's ``max_tension_n`` (or more).
    section_bounds_mm : (k + 1,) float, mm
        Arc length from the base.
    curvature_per_m : (t, k) float, 1/m
        Bending toward the pulled tendon.
    joint_section : int
        Index of the joint section.
    max_interp_error_per_m : float, 1/m
        Worst interpolation error found at the grid midpoints.

    Raises
    ------
    ValueError
        ``tensions_n`` not increasing, or ``curvature_per_m`` not (t, k).
    """

    model: str
    design_name: str
    tensions_n: np.ndarray
    section_bounds_mm: np.ndarray
    curvature_per_m: np.ndarray
    joint_section: int
    max_interp_error_per_m: float

    def __post_init__(self) -> None:
        for name in ("tensions_n", "section_bounds_mm", "curvature_per_m"):
            a = np.array(getattr(self, name), dtype=float)
            a.setflags(write=False)
            object.__setattr__(self, name, a)
        if np.any(np.diff(self.tensions_n) <= 0) or self.curvature_per_m.shape != (
                len(self.tensions_n), len(self.section_bounds_mm) - 1):
            raise ValueError("tensions_n must increase and curvature_per_m must be (t, k)")

    def curvature(self, tension_n: np.ndarray | float) -> np.ndarray:
        """Interpolate (linearly) the curvature of each section at ``tension_n``.

        Parameters
        ----------
        tension_n : (...) float, N
            Any shape, within the table.

        Returns
        -------
        (..., k) float, 1/m

        Raises
        ------
        ValueError
            For a tension outside the table.
        """
        t = np.asarray(tension_n, dtype=float)
        if np.any(t < self.tensions_n[0]) or np.any(t > self.tensions_n[-1]) or not np.all(np.isfinite(t)):
            raise ValueError(f"tension outside the table [{self.tensions_n[0]}, {self.tensions_n[-1]}] N")
        i = np.clip(np.searchsorted(self.tensions_n, t, side="right") - 1, 0, len(self.tensions_n) - 2)
        w = ((t - self.tensions_n[i]) / (self.tensions_n[i + 1] - self.tensions_n[i]))[..., None]
        return (1 - w) * self.curvature_per_m[i] + w * self.curvature_per_m[i + 1]

    def joint_curvature(self, tension_n: np.ndarray | float) -> np.ndarray:
        """Interpolate the curvature of the joint section at ``tension_n`` ((...) float, N): (...) float, 1/m."""
        return self.curvature(tension_n)[..., self.joint_section]


def curvature_table(model: RodModel, design: RodDesign, max_tension_n: float | None = None,
                    n: int = 61) -> CurvatureTable:
    """Build and check the table of ``model`` for ``design`` on ``n`` tensions from 0 to ``max_tension_n``.

    Parameters
    ----------
    model : RodModel
        The model solved on the grid and at its midpoints (one ``solve_batch`` call).
    design : RodDesign
        The design.
    max_tension_n : float, optional
        Top of the grid, N (default: the design's ``max_tension_n``).
    n : int
        Grid points, at least 2.

    Raises
    ------
    ValueError
        ``max_tension_n`` not positive or ``n < 2``.
    RodModelError
        When any solve of the grid fails.
    """
    top = design.max_tension_n if max_tension_n is None else max_tension_n
    if not (top > 0 and n >= 2):
        raise ValueError("max_tension_n must be positive and n at least 2")
    grid = np.linspace(0.0, top, n)
    mids = 0.5 * (grid[1:] + grid[:-1])
    both = model.solve_batch(design, np.concatenate([grid, mids]))
    if not both.converged.all():
        bad = np.concatenate([grid, mids])[~both.converged]
        raise RodModelError(f"{model.name} did not converge for {design.name} at {bad[:3].tolist()} N; "
                            "lower max_tension_n")
    curv = both.section_curvature_per_m[:n]
    table = CurvatureTable(model.name, design.name, grid, both.section_bounds_mm, curv, both.joint_section, 0.0)
    err = float(np.max(np.abs(table.curvature(mids) - both.section_curvature_per_m[n:])))
    return CurvatureTable(model.name, design.name, grid, both.section_bounds_mm, curv, both.joint_section, err)
