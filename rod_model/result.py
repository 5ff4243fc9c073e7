"""What a rod model returns: a solved shape, a failure with its reason, or a batch of solves.

Every position is in millimetres in the needle's own frame (base at the origin, unactuated axis ``+z``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from reachplan._arrays import frozen_floats


@dataclass(frozen=True, eq=False)
class RodPath:
    """A converged solve.

    Parameters
    ----------
    model : str
        Name of the model that produced it (``two_tube_cosserat``, ...).
    s_mm : (n,) float, mm
        Arc length from the base, increasing, ``s_mm[0] == 0``.
    positions_mm : (n, 3) float, mm, needle frame
        Centreline.
    frames : (n, 3, 3) float
        Orientation of the stylet's cross-section: columns are the directors ``d1, d2, d3`` in the needle
        frame (``d3`` the tangent).
    residual : float
        Boundary-condition residual of the solve, N (0 for closed forms).
    solve_ms : float
        Wall time of the solve, ms.
    iterations : int
        Solver iterations (0 for closed forms).
    tensions_n : tuple of float
        Tendon tensions solved for.
    roll_deg : float
        Roll solved for.
    twist_rad : (n,) float or None
        Relative twist of needle against stylet (two-tube model only).
    base_unknowns : (8,) float or None
        The shooting models' converged base values ``N(0), M(0), n2z(0), m2z(0)`` (SI), a warm start for a
        neighbouring solve.

    Attributes
    ----------
    converged : bool
        Always True (a :class:`FailedSolve` has False); a RodPath is truthy.

    Raises
    ------
    ValueError
        Arrays of the wrong shape or length (n < 2), non-finite values, or ``s_mm`` not strictly increasing.
    """

    model: str
    s_mm: np.ndarray
    positions_mm: np.ndarray
    frames: np.ndarray
    residual: float
    solve_ms: float
    iterations: int
    tensions_n: tuple[float, ...]
    roll_deg: float
    twist_rad: np.ndarray | None = None
    base_unknowns: np.ndarray | None = None

    def __post_init__(self) -> None:
        s = frozen_floats(self.s_mm, (), "s_mm")
        object.__setattr__(self, "s_mm", s)
        object.__setattr__(self, "positions_mm", frozen_floats(self.positions_mm, (3,), "positions_mm"))
        object.__setattr__(self, "frames", frozen_floats(self.frames, (3, 3), "frames"))
        if len(s) < 2 or len(self.positions_mm) != len(s) or len(self.frames) != len(s):
            raise ValueError("s_mm, positions_mm and frames must have the same length n >= 2")
        if np.any(np.diff(s) <= 0):
            raise ValueError("s_mm must be strictly increasing")
        if self.twist_rad is not None:
            tw = frozen_floats(self.twist_rad, (), "twist_rad")
            if len(tw) != len(s):
                raise ValueError("twist_rad must have the same length as s_mm")
            object.__setattr__(self, "twist_rad", tw)

    converged = True

    def __bool__(self) -> bool:
        return True

    @property
    def tip_position_mm(self) -> np.ndarray:
        """(3,) float, mm, needle frame: the tip."""
        return self.positions_mm[-1]

    @property
    def tip_deflection_mm(self) -> float:
        """Lateral distance of the tip from the unactuated tip (perpendicular to the base axis ``z``), mm."""
        return float(np.hypot(self.positions_mm[-1, 0], self.positions_mm[-1, 1]))

    def to_json(self) -> dict[str, object]:
        """Return a plain JSON-able summary (positions in mm rounded to 1 nm, needle frame)."""
        return {
            "model": self.model,
            "converged": True,
            "tensions_n": list(self.tensions_n),
            "roll_deg": self.roll_deg,
            "tip_deflection_mm": round(self.tip_deflection_mm, 6),
            "tip_position_mm": [round(float(x), 6) for x in self.tip_position_mm],
            "residual": self.residual,
            "solve_ms": round(self.solve_ms, 4),
            "iterations": self.iterations,
            "s_mm": [round(float(x), 6) for x in self.s_mm],
            "positions_mm": np.round(self.positions_mm, 6).tolist(),
        }


@dataclass(frozen=True)
class FailedSolve:
    """A solve that did not converge: falsy, with the reason (never a plausible wrong shape).

    Returned, never raised: a batch or an insertion goes on and reports which solve failed.

    Parameters
    ----------
    model : str
        The rod model that did not converge (its name).
    reason : str
        One line: what failed (e.g. ``"shooting residual 3.1e-02 N after 30 iterations"``).
    residual : float
        Best boundary-condition residual reached, N (``inf`` if none).
    solve_ms : float
        Wall time spent, ms.
    tensions_n : tuple of float
        Tendon tensions asked for, N.
    roll_deg : float
        Roll asked for, degrees.

    Attributes
    ----------
    converged : bool
        Always False; a FailedSolve is falsy.
    """

    model: str
    reason: str
    residual: float
    solve_ms: float
    tensions_n: tuple[float, ...]
    roll_deg: float

    converged = False

    def __bool__(self) -> bool:
        return False

    def to_json(self) -> dict[str, object]:
        """Return a plain JSON-able summary (a residual of ``inf`` becomes None)."""
        return {"model": self.model, "converged": False, "reason": self.reason,
                "residual": self.residual if np.isfinite(self.residual) else None,
                "solve_ms": round(self.solve_ms, 4), "tensions_n": list(self.tensions_n), "roll_deg": self.roll_deg}


@dataclass(frozen=True, eq=False)
class RodBatch:
    """Many free-space solves of one design at once (what an insertion model integrates).

    Parameters
    ----------
    model : str
        Name of the model that produced it.
    tensions_n : (b,) float, N
        Tension on tendon 0 for each solve.
    roll_deg : float
        Roll of every solve, degrees.
    tip_positions_mm : (b, 3) float, mm, needle frame
        Rows of failed solves are NaN.
    section_bounds_mm : (k + 1,) float, mm
        Arc-length boundaries of the design's sections (see :meth:`RodDesign.sections`).
    section_curvature_per_m : (b, k) float, 1/m
        Mean curvature of each section: angle between the tangents at its ends over its length (exact for
        a section of constant curvature, as every section is in free space).
    joint_section : int
        Index of the joint section among the ``k`` sections.
    converged : (b,) bool
        Which solves converged.
    residual : (b,) float, N
        Boundary-condition residual of each solve (0 for closed forms).

    Raises
    ------
    ValueError
        Arrays whose lengths disagree with ``tensions_n`` or with the sections.
    """

    model: str
    tensions_n: np.ndarray
    roll_deg: float
    tip_positions_mm: np.ndarray
    section_bounds_mm: np.ndarray
    section_curvature_per_m: np.ndarray
    joint_section: int
    converged: np.ndarray
    residual: np.ndarray

    def __post_init__(self) -> None:
        for name in ("tensions_n", "tip_positions_mm", "section_bounds_mm", "section_curvature_per_m",
                     "converged", "residual"):
            a = np.array(getattr(self, name))
            a.setflags(write=False)
            object.__setattr__(self, name, a)
        b = len(self.tensions_n)
        k = len(self.section_bounds_mm) - 1
        if (self.tip_positions_mm.shape != (b, 3) or self.section_curvature_per_m.shape != (b, k)
                or self.converged.shape != (b,) or self.residual.shape != (b,)):
            raise ValueError("RodBatch arrays must have b rows matching tensions_n and k matching the sections")

    @property
    def tip_deflection_mm(self) -> np.ndarray:
        """(b,) float, mm: lateral tip distance from the unactuated tip."""
        return np.hypot(self.tip_positions_mm[:, 0], self.tip_positions_mm[:, 1])

    @property
    def joint_curvature_per_m(self) -> np.ndarray:
        """(b,) float, 1/m: mean curvature of the joint section."""
        return self.section_curvature_per_m[:, self.joint_section]


def section_curvatures(frames: np.ndarray, s_mm: np.ndarray, bounds_mm: np.ndarray) -> np.ndarray:
    """Compute the mean curvature of each section from the tangents at its ends.

    The angle between the end tangents over the section's length: exact for a section of constant curvature.

    Parameters
    ----------
    frames : (..., n, 3, 3) float, needle frame
        Directors ``d1, d2, d3`` as columns at each ``s_mm`` (``d3`` the tangent), as in :attr:`RodPath.frames`.
    s_mm : (n,) float, mm
        Arc length of the frames, increasing.
    bounds_mm : (k + 1,) float, mm
        Section boundaries; each must be one of ``s_mm``.

    Returns
    -------
    (..., k) float, 1/m
    """
    idx = np.searchsorted(s_mm, bounds_mm - 1e-9)
    return turn_per_length(frames[..., idx, :, 2], np.diff(bounds_mm) * 1e-3)


def turn_per_length(tangents: np.ndarray, lengths: np.ndarray) -> np.ndarray:
    """Mean curvature of consecutive pieces: the angle between the unit tangents at a piece's ends over its length.

    Parameters
    ----------
    tangents : (..., k + 1, 3) float
        Unit tangents at the piece boundaries.
    lengths : (k,) float
        Piece lengths (the unit of the result is rad per this unit).

    Returns
    -------
    (..., k) float, rad per unit of ``lengths``
    """
    cos = np.clip(np.sum(tangents[..., :-1, :] * tangents[..., 1:, :], axis=-1), -1.0, 1.0)
    sin = np.linalg.norm(np.cross(tangents[..., :-1, :], tangents[..., 1:, :]), axis=-1)
    return np.arctan2(sin, cos) / lengths
