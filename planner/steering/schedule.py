"""Tension schedules: what the user does while inserting a steered needle.

A plan's instruction for the handheld stylet is, along the insertion depth, the tendon tension (the
handheld only pulls: tension >= 0, at most the design's limit) and the roll angle of the bending plane
(the user rolls the wrist to steer in another direction). Reference: ``oncoreach.md``, Actuation.

A schedule is piecewise linear in insertion depth (mm beyond the template plane) and constant beyond its
last breakpoint.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True, eq=False)
class TensionSchedule:
    """Piecewise-linear tendon tension and roll along insertion depth.

    Parameters
    ----------
    depth_mm : (k,) float, mm, strictly increasing, first value >= 0
    tension_n : (k,) float, N, >= 0
    roll_deg : (k,) float, degrees; the bending direction in the template frame, 0 = template +x,
        90 = template +y (rolling the wrist).
    """

    depth_mm: np.ndarray
    tension_n: np.ndarray
    roll_deg: np.ndarray

    def __post_init__(self) -> None:
        d, t, r = (np.atleast_1d(np.asarray(a, dtype=float)).copy() for a in
                   (self.depth_mm, self.tension_n, self.roll_deg))
        if not (d.ndim == t.ndim == r.ndim == 1 and len(d) == len(t) == len(r) and len(d) >= 1):
            raise ValueError("depth_mm, tension_n and roll_deg must be 1-D arrays of the same non-zero length")
        if not (np.all(np.isfinite(d)) and np.all(np.isfinite(t)) and np.all(np.isfinite(r))):
            raise ValueError("a schedule must hold finite numbers only")
        if d[0] < 0 or np.any(np.diff(d) <= 0):
            raise ValueError("schedule depths must start at >= 0 mm and increase strictly")
        if np.any(t < 0):
            raise ValueError("tendon tension cannot be negative: the handheld only pulls")
        for a in (d, t, r):
            a.setflags(write=False)
        object.__setattr__(self, "depth_mm", d)
        object.__setattr__(self, "tension_n", t)
        object.__setattr__(self, "roll_deg", r)

    @property
    def peak_tension_n(self) -> float:
        """Largest tendon tension of the schedule, N."""
        return float(self.tension_n.max())

    def at(self, depth_mm: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Tension (N) and roll (deg) at the given depths (mm); constant outside the breakpoints.

        Parameters
        ----------
        depth_mm : (m,) float, mm
            Insertion depths beyond the template plane (any shape; the results take it).

        Returns
        -------
        tension_n : (m,) float, N
            Tendon tension, linearly interpolated between breakpoints.
        roll_deg : (m,) float, degrees
            Roll of the bending plane in the template frame (0 = template +x).
        """
        q = np.asarray(depth_mm, dtype=float)
        return np.interp(q, self.depth_mm, self.tension_n), np.interp(q, self.depth_mm, self.roll_deg)

    def rows(self, step_mm: float, end_mm: float) -> np.ndarray:
        """Return the device instructions resampled every ``step_mm`` to ``end_mm``.

        Parameters
        ----------
        step_mm : float, mm
            Depth step of the rows (> 0).
        end_mm : float, mm
            Last depth (>= 0), usually the insertion depth.

        Returns
        -------
        (n, 3) float
            Rows of (depth mm, tension N, roll deg), the breakpoints included.

        Raises
        ------
        ValueError
            ``step_mm`` <= 0 or ``end_mm`` < 0.
        """
        if step_mm <= 0 or end_mm < 0:
            raise ValueError("step_mm must be > 0 and end_mm >= 0")
        q = np.union1d(np.arange(0.0, end_mm + 1e-9, step_mm), self.depth_mm[self.depth_mm <= end_mm])
        t, r = self.at(q)
        return np.column_stack([q, t, r])

    @classmethod
    def constant(cls, tension_n: float = 0.0, roll_deg: float = 0.0) -> TensionSchedule:
        """Return the same tension and roll from the template on (``tension_n = 0``: a straight needle).

        Parameters
        ----------
        tension_n : float, N
            Tendon tension held along the whole insertion.
        roll_deg : float, degrees
            Roll of the bending plane in the template frame.

        Returns
        -------
        TensionSchedule
            One breakpoint at depth 0.
        """
        return cls(np.array([0.0]), np.array([tension_n]), np.array([roll_deg]))

    @classmethod
    def ramp(cls, onset_mm: float, ramp_mm: float, plateau_n: float, roll_deg: float = 0.0) -> TensionSchedule:
        """No tension until ``onset_mm``, a linear ramp over ``ramp_mm`` to ``plateau_n``, then held.

        Parameters
        ----------
        onset_mm : float, mm
            Depth beyond the template plane where the ramp starts (>= 0).
        ramp_mm : float, mm
            Depth over which the tension rises (> 0).
        plateau_n : float, N
            Tension held after the ramp.
        roll_deg : float, degrees
            Roll of the bending plane in the template frame, constant.

        Returns
        -------
        TensionSchedule
            Two or three breakpoints (two when ``onset_mm`` is 0).

        Raises
        ------
        ValueError
            ``onset_mm`` < 0 or ``ramp_mm`` <= 0.
        """
        if onset_mm < 0 or ramp_mm <= 0:
            raise ValueError("onset_mm must be >= 0 and ramp_mm > 0")
        d = np.array([0.0, onset_mm, onset_mm + ramp_mm]) if onset_mm > 0 else np.array([0.0, ramp_mm])
        t = np.array([0.0, 0.0, plateau_n]) if onset_mm > 0 else np.array([0.0, plateau_n])
        return cls(d, t, np.full(len(d), roll_deg))
