"""Pick the cheapest rod model whose *measured* error fits a tolerance (models are looked up by the caller).

What the tolerance means: the largest tip error of a model against the *converged two-tube Cosserat model in
free space* (presets × tensions 0-15 N). It is a modelling and numerical error relative to the project's most
complete model, **not** an error against experiment: the calibrated two-tube model is itself off the published
measurements (by up to about 1 mm on the calibration rows, see :mod:`reachplan.rod_model.calibrate`), and a
model within 0.1 mm of it is no closer than that to a real needle.

Ties: measured costs are medians of wall times and move by tens of per cent between runs, so costs within a
factor :data:`COST_TIE_FACTOR` of the cheapest qualifying model count as equal and the stable
:data:`MODEL_RANK` (simplest model first) decides; only a model clearly cheaper wins on cost.

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

import numpy as np

from reachplan.rod_model.design import Loads, RodDesign
from reachplan.rod_model.errors import NoModelWithinToleranceError, RodModelError
from reachplan.rod_model.protocol import Capabilities

ERROR_TABLE = "model_errors.json"
#: Costs within this factor of the cheapest qualifying model are one cost class (timing medians are noisy).
COST_TIE_FACTOR = 1.5
#: Stable order that breaks ties within a cost class: the simplest model first (closed forms, then shooting
#: with fewer unknowns, then collocation); models not listed rank after these, by name.
MODEL_RANK: dict[str, int] = {"constant_curvature": 0, "planar_beam": 1, "cosserat_rod": 2, "two_tube_cosserat": 3,
                              "two_tube_collocation": 4}


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
    def of(cls, loads: Loads, design: RodDesign) -> Scene:
        """Return the scene of ``loads`` on ``design``.

        Tendons alone always bend the rod in one plane (their net moment keeps its direction); external loads
        need a Cosserat model, and a torque about the needle's axis (:func:`axial_torque_nm`, whatever the frame
        the load is given in) the two-tube one.

        Parameters
        ----------
        loads : Loads
            Tendon tensions, roll and external loads (needle base frame).
        design : RodDesign
            The rod (its tendons' positions and its length).

        Returns
        -------
        Scene
            What the solve has to represent.
        """
        return cls(planar=not loads.has_external, twist=axial_torque_nm(loads, design) > TWIST_TOL_NM,
                   external_load=loads.has_external)


#: Torque about the needle's axis, N·m, below which a load counts as untwisting (a numerical zero).
TWIST_TOL_NM = 1e-9


def axial_torque_nm(loads: Loads, design: RodDesign) -> float:
    """Return the largest torque (N·m) the external loads can exert about the needle's axis, anywhere along it.

    The tendons bend the needle in one plane, spanned by its unactuated axis ``e3`` and their net pull ``d``
    (the tension-weighted tendon offsets, rolled): the axis anywhere along the bent needle is
    ``t = cos θ e3 + sin θ d`` for some θ. A tip moment ``m`` has the axial part ``m·t``, at most the norm of its
    part in that plane (``|m − (m·n) n|``, ``n = e3 × d`` the plane's normal): a moment about the world ``x`` axis
    twists a needle bent toward ``x`` as surely as one about ``z`` twists a straight one, and one about ``n``
    only bends it. A tip force ``f`` at lever arm ``r`` (in the plane) gives ``(r × f)·t = f·(t × r)``, along
    ``n``: at most ``|f·n| L``; a distributed force ``q`` at most ``|q·n| L²/2``. With no net tendon pull the
    bending plane is not set and every component counts. The foundation (an elastic medium) is not counted: it
    pushes the needle back toward its own track, in the bending plane of a planar insertion.

    Parameters
    ----------
    loads : Loads
        The loads (N, N·m, N/m; needle base frame).
    design : RodDesign
        The rod: its tendons' angles and its length.

    Returns
    -------
    float, N·m
        The bound on the axial torque.
    """
    offsets = design.tendon_unit_offsets(loads.roll_deg)
    k = min(len(loads.tensions_n), len(offsets))
    pull = np.asarray(loads.tensions_n[:k], dtype=float) @ offsets[:k]
    length_m = design.length_mm * 1e-3
    m = np.asarray(loads.tip_moment_nm, dtype=float)
    f = np.asarray(loads.tip_force_n, dtype=float)
    q = np.asarray(loads.distributed_n_per_m, dtype=float)
    if np.linalg.norm(pull) < 1e-12:
        return float(np.linalg.norm(m) + np.linalg.norm(f) * length_m + np.linalg.norm(q) * length_m**2 / 2)
    n = np.cross((0.0, 0.0, 1.0), pull / np.linalg.norm(pull))
    return float(np.linalg.norm(m - (m @ n) * n) + abs(f @ n) * length_m + abs(q @ n) * length_m**2 / 2)


@dataclass(frozen=True)
class ErrorRow:
    """One row of the benchmark's error table.

    Read from the package data ``model_errors.json`` that ``reachplan bench models --install`` writes.

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
    (what a planner screening many candidates pays). Costs within :data:`COST_TIE_FACTOR` of the cheapest count
    as equal; among them the lowest :data:`MODEL_RANK` wins. ``tolerance_mm`` is the tip error against the
    converged two-tube Cosserat model in free space (see the module docstring), not against experiment.

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
    qualified: list[tuple[float, str]] = []
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
        qualified.append((cost, row.model))
    best = None
    if qualified:
        cheapest = min(c for c, _ in qualified)
        tied = [m for c, m in qualified if c <= COST_TIE_FACTOR * cheapest]
        best = min(tied, key=lambda m: (MODEL_RANK.get(m, len(MODEL_RANK)), m))
    if best is None:
        floor = min((r.max_tip_error_mm for r in rows), default=float("nan"))
        raise NoModelWithinToleranceError(f"no rod model is within {tolerance_mm} mm (best measured {floor:.3g} mm);"
                                          " raise --tolerance or use two_tube_cosserat")
    return best
