"""Pick the cheapest rod model whose *measured* error fits a tolerance (models are looked up by the caller).

The error table is package data (``rod_model/model_errors.json``) written by ``reachplan bench models``
(``benchmarks/rod_models.py``): for every model and resolution, the largest tip error against a converged
two-tube reference over the benchmark grid of presets × tensions (0-15 N), and the measured time per solve.
Nothing in it is guessed; re-run the benchmark to refresh it.
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from dataclasses import dataclass
from functools import cache
from importlib import resources

from reachplan.rod_model.design import Loads
from reachplan.rod_model.errors import NoModelWithinToleranceError, RodModelError
from reachplan.rod_model.protocol import Capabilities

ERROR_TABLE = "model_errors.json"


@dataclass(frozen=True)
class Scene:
    """What a solve has to represent.

    Parameters
    ----------
    planar : bool
        One pulled tendon direction, no out-of-plane load.
    twist : bool
        Relative twist of stylet and needle matters (torsional loads).
    external_load : bool
        Tip force/moment or distributed load.
    """

    planar: bool = True
    twist: bool = False
    external_load: bool = False

    @classmethod
    def of(cls, loads: Loads) -> Scene:
        """Return the scene of ``loads``.

        Tendons alone always bend the rod in one plane (their net moment keeps its direction); external loads
        need a Cosserat model, a torque about the axis the two-tube one.
        """
        return cls(planar=not loads.has_external, twist=loads.tip_moment_nm[2] != 0.0,
                   external_load=loads.has_external)


@dataclass(frozen=True)
class ErrorRow:
    """One row of the benchmark's error table.

    Parameters
    ----------
    model : str
        Plugin name of the model.
    resolution : str
        ``"default"`` for the configuration registered as the plugin (the one the selector can return); other
        rows (coarser or finer steps) are there for the chart.
    max_tip_error_mm : float, mm
        Worst tip error against the reference over the grid.
    median_ms : float, ms
        Median wall time of one ``solve``.
    batched_solves_per_s : float or None, 1/s
        Throughput of ``solve_batch``; None when not measured.
    success_rate : float
        Fraction of the grid's solves that converged (0..1); the selector takes only 1.
    """

    model: str
    resolution: str
    max_tip_error_mm: float
    median_ms: float
    batched_solves_per_s: float | None
    success_rate: float


@cache
def error_table() -> tuple[ErrorRow, ...]:
    """Read the rows of the packaged error table (once; cached).

    Raises
    ------
    RodModelError
        The table is missing or unreadable.
    """
    try:
        text = resources.files("reachplan.rod_model").joinpath(ERROR_TABLE).read_text(encoding="utf-8")
        doc = json.loads(text)
        return tuple(ErrorRow(**row) for row in doc["rows"])
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise RodModelError(f"rod-model error table {ERROR_TABLE} is missing or unreadable ({exc}); "
                            "run `reachplan bench models --out DIR --install` from a source checkout") from None


def select_model(tolerance_mm: float, scene: Scene, capabilities: Mapping[str, Capabilities],
                 rows: tuple[ErrorRow, ...] | None = None, *, batched: bool = False) -> str:
    """Name the cheapest model able to represent ``scene`` whose measured tip error is within ``tolerance_mm``.

    Cheapest by the median time of one ``solve``, or with ``batched`` by the throughput of ``solve_batch``
    (what a planner screening many candidates pays).

    The errors are measured in free space over the benchmark grid; for a scene with external loads or twist
    only the Cosserat models qualify by their capabilities, and their tabulated error is then their numerical
    error against the converged reference.

    Parameters
    ----------
    tolerance_mm : float, mm
        Largest tip error accepted; positive.
    scene : Scene
        What the solve has to represent.
    capabilities : mapping of str to Capabilities
        The installed models (name -> what it can represent); the caller looks them up.
    rows : tuple of ErrorRow, optional
        The error table (default :func:`error_table`).
    batched : bool
        Rank by ``solve_batch`` throughput instead of single-solve time.

    Returns
    -------
    str
        The model's plugin name.

    Raises
    ------
    ValueError
        ``tolerance_mm`` not positive.
    NoModelWithinToleranceError
        When no model qualifies (the message gives the best error available).
    RodModelError
        The packaged table is missing or unreadable.
    """
    if not tolerance_mm > 0:
        raise ValueError(f"tolerance_mm must be positive, got {tolerance_mm}")
    rows = error_table() if rows is None else rows
    best: tuple[float, str] | None = None
    for row in rows:
        if row.resolution != "default" or row.success_rate < 1.0 or row.max_tip_error_mm > tolerance_mm:
            continue
        caps = capabilities.get(row.model)
        if caps is None:  # not installed (or not loadable)
            continue
        if (not scene.planar and caps.planar_only) or (scene.twist and not caps.twist) or (
                scene.external_load and not caps.external_load):
            continue
        cost = row.median_ms
        if batched:
            cost = 1e3 / row.batched_solves_per_s if row.batched_solves_per_s else float("inf")
        if best is None or cost < best[0]:
            best = (cost, row.model)
    if best is None:
        floor = min((r.max_tip_error_mm for r in rows), default=float("nan"))
        raise NoModelWithinToleranceError(f"no rod model is within {tolerance_mm} mm (best measured {floor:.3g} mm);"
                                          " raise --tolerance or use two_tube_cosserat")
    return best[1]
