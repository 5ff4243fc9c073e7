"""Array helpers every floor shares (below the floors: imports nothing of reachplan).

:func:`frozen_floats` makes the read-only float arrays the frozen dataclasses hold; :func:`arc_length_mm` is the
cumulative length of a polyline (needle paths, contours).
"""

from __future__ import annotations

import numpy as np


def frozen_floats(a: object, shape_tail: tuple[int, ...] | None = None, name: str = "array") -> np.ndarray:
    """Copy ``a`` as a read-only float array.

    Parameters
    ----------
    a : array-like
        The values.
    shape_tail : tuple of int, optional
        When given, ``a`` must have shape ``(n, *shape_tail)`` and finite values.
    name : str
        What ``a`` is, for the error message.

    Returns
    -------
    ndarray of float, not writeable, the shape of ``a``.

    Raises
    ------
    ValueError
        ``a`` has the wrong shape or non-finite values (only checked with ``shape_tail``).
    """
    arr = np.array(a, dtype=float)
    if shape_tail is not None:
        if arr.ndim != 1 + len(shape_tail) or arr.shape[1:] != shape_tail:
            want = ", ".join(["n", *map(str, shape_tail)])
            raise ValueError(f"{name} must have shape ({want}), got {arr.shape}")
        if not np.all(np.isfinite(arr)):
            raise ValueError(f"{name} must be finite")
    arr.setflags(write=False)
    return arr


def arc_length_mm(path_mm: np.ndarray) -> np.ndarray:
    """Cumulative arc length along a polyline.

    Parameters
    ----------
    path_mm : (n, d) float, mm
        The polyline's points, in order (any frame; ``d`` is usually 3).

    Returns
    -------
    (n,) float, mm
        Length from ``path_mm[0]`` to each point; starts at 0.
    """
    seg = np.linalg.norm(np.diff(np.asarray(path_mm, dtype=float), axis=0), axis=1)
    return np.concatenate([[0.0], np.cumsum(seg)])
