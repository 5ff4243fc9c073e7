"""Rod-model benchmark, robustness: the stability map and the honesty cases.

The stability map runs each solver on tension x placement x initial guess (with its chart); the honesty cases are
the load cases a reviewer found wrong.

Part of ``reachplan bench models`` (:mod:`reachplan.planner.bench.models`).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
from matplotlib.figure import Figure

from reachplan.planner.bench.models_speed import ModelSettings
from reachplan.rod_model.collocation import NS, CollocationCosserat
from reachplan.rod_model.cosserat import TWO_TUBE_COSSERAT
from reachplan.rod_model.design import Loads, RodDesign, preset
from reachplan.rod_model.result import FailedSolve, RodPath


@dataclass(frozen=True)
class StabilityCase:
    """One case of the stability map.

    Parameters
    ----------
    solver, placement : str
        Solver and joint placement.
    tension_n : float, N
        Tendon tension.
    guess : str
        Initial guess (``zero``, ``small``, ``large``).
    success : bool
        The solve converged.
    residual : float, N
        Boundary residual.
    ms : float, ms
        Solve time.
    reason : str
        Why it failed ("" when it did not).
    """

    solver: str
    placement: str
    tension_n: float
    guess: str
    success: bool
    residual: float
    ms: float
    reason: str


def stability(s: ModelSettings, log: Callable[[str], None]) -> list[StabilityCase]:
    """Every solver on placement × tension × initial guess, with an out-of-plane tip force.

    Parameters
    ----------
    s : ModelSettings
        Tensions and placements of the map.
    log : callable (str) -> None
        Where the progress goes, line by line.

    Returns
    -------
    list of StabilityCase
        One per solver, placement, tension and guess.
    """
    rng = np.random.default_rng(7)
    out: list[StabilityCase] = []
    collocation = CollocationCosserat(tol=1e-6, nodes_per_section=11, max_nodes=300, max_ramp=2)
    solvers: dict[str, tuple[Any, bool]] = {"shooting": (TWO_TUBE_COSSERAT, False),
                                            "shooting+continuation": (TWO_TUBE_COSSERAT, True),
                                            "collocation": (collocation, True)}
    for placement in s.stability_placements:
        d = preset(f"15ga-20j-{placement}")
        for t in s.stability_tensions_n:
            loads = Loads((t, 0.0, 0.0, 0.0), tip_force_n=(0.0, 0.2, -0.2))
            scale = 1.0 + t + 0.4
            for guess, mag in (("zero", 0.0), ("small", 0.1), ("large", 10.0)):
                noise = rng.standard_normal(8)
                x0 = mag * scale * noise * np.r_[1, 1, 1, 0.01, 0.01, 0.01, 1, 0.01]  # N and N·(1 cm)
                for label, (solver, cont) in solvers.items():
                    if isinstance(solver, CollocationCosserat):
                        k = len(d.sections())
                        y0 = np.zeros((NS * k, solver.nodes_per_section))
                        tau = np.linspace(0, 1, solver.nodes_per_section)
                        for i, sec in enumerate(d.sections()):
                            b = y0[NS * i:NS * (i + 1)]
                            b[2] = (sec.start_m + tau * sec.length_m) * 1e3
                            b[3] = b[7] = b[11] = 1.0
                            b[12:15] = x0[0:3, None]
                            b[15:18] = x0[3:6, None] * 1e3
                        r = solver.solve(d, loads, initial_guess=y0, continuation=cont)
                    else:
                        r = solver.solve(d, loads, initial_guess=x0, continuation=cont)
                    ok = isinstance(r, RodPath)
                    reason = r.reason if isinstance(r, FailedSolve) else ""
                    out.append(StabilityCase(label, placement, t, guess, ok, float(r.residual),
                                             float(r.solve_ms), reason))
    for label in solvers:
        cases = [c for c in out if c.solver == label]
        log(f"stability {label:22s}: {sum(c.success for c in cases)}/{len(cases)} converged")
    return out


@dataclass(frozen=True)
class HonestyCase:
    """One load case of the honesty table and what the solver returned for it.

    A row of ``rod_models_honesty.csv``.

    Parameters
    ----------
    case : str
        The load case in words.
    converged : bool
        The solver reports convergence.
    tip_mm : (3,) float or None, mm, rod frame
        Tip position; None when the solve failed.
    ms : float, ms
        Solve time.
    reason : str
        Why it failed.
    """

    case: str
    converged: bool
    tip_mm: tuple[float, float, float] | None
    ms: float
    reason: str


def honesty(log: Callable[[str], None]) -> list[HonestyCase]:
    """Run the reviewer's wrong-branch and blow-up cases through the checked two-tube solver.

    The Euler load is that of the tube-plus-needle column clamped at the template, free at the tip:
    ``P = π² EI / (4 L²)`` (Timoshenko & Gere, Theory of Elastic Stability, 2nd ed., 1961, §2.1).

    Parameters
    ----------
    log : callable (str) -> None
        One line per case.

    Returns
    -------
    list of HonestyCase
        One per load case.
    """
    base, tip = preset("15ga-20j-base"), preset("15ga-20j-tip")
    sec = tip.sections()[0]
    p_cr = math.pi**2 * (sec.ei1 + sec.ei2) / (4 * (tip.length_mm * 1e-3) ** 2)  # tube + needle column, N
    lateral = (0.0, 2.0, 0.0)
    cases: list[tuple[str, RodDesign, Loads, bool]] = [
        ("15ga-20j-base, 2 N lateral tip force (+y)", base, Loads((0.0,) * 4, tip_force_n=lateral), True),
        ("same, direct solve (no continuation)", base, Loads((0.0,) * 4, tip_force_n=lateral), False),
        ("15ga-20j-base, 9.9 N + 2 N lateral (+y)", base, Loads((9.9, 0, 0, 0), tip_force_n=lateral), True),
        ("same, direct solve (no continuation)", base, Loads((9.9, 0, 0, 0), tip_force_n=lateral), False),
        ("15ga-20j-tip, axial 0.9 P_euler(tube)", tip, Loads((0.0,) * 4, tip_force_n=(0.0, 0.0, -0.9 * p_cr)), True),
        ("15ga-20j-tip, axial 1.1 P_euler(tube)", tip, Loads((0.0,) * 4, tip_force_n=(0.0, 0.0, -1.1 * p_cr)), True),
        ("15ga-20j-tip, 1.5 P_euler + 1 % lateral", tip,
         Loads((0.0,) * 4, tip_force_n=(0.015 * p_cr, 0.0, -1.5 * p_cr)), True),
        ("15ga-20j-tip, 5000 N tension", tip, tip.loads(5000.0), True),
    ]
    out = []
    for label, d, loads, cont in cases:
        r = TWO_TUBE_COSSERAT.solve(d, loads, continuation=cont)
        if isinstance(r, RodPath):
            x, y, z = (float(v) for v in r.tip_position_mm)
            out.append(HonestyCase(label, True, (x, y, z), r.solve_ms, ""))
        else:
            out.append(HonestyCase(label, False, None, r.solve_ms, r.reason))
        c = out[-1]
        log(f"honesty: {label:44s} " + (f"tip {np.round(c.tip_mm, 2)} mm" if c.tip_mm else f"FAILED: {c.reason}"))
    return out


def stability_figure(cases: list[StabilityCase]) -> Figure:
    """Converged / failed map of each solver over placement × initial guess (rows) and tension (columns).

    Parameters
    ----------
    cases : list of StabilityCase
        The map's cases.

    Returns
    -------
    matplotlib.figure.Figure
    """
    solvers = list(dict.fromkeys(c.solver for c in cases))
    tensions = sorted({c.tension_n for c in cases})
    rows = list(dict.fromkeys((c.placement, c.guess) for c in cases))
    fig = Figure(figsize=(4.2 * len(solvers), 4.8))
    axes = fig.subplots(1, len(solvers), sharey=True)
    for ax, s in zip(np.atleast_1d(axes), solvers, strict=True):
        img = np.zeros((len(rows), len(tensions)))
        for c in cases:
            if c.solver == s:
                img[rows.index((c.placement, c.guess)), tensions.index(c.tension_n)] = 1.0 if c.success else 0.0
        ax.imshow(img, cmap="RdYlGn", vmin=0, vmax=1, aspect="auto")
        for c in cases:
            if c.solver == s and not c.success:
                code = "NC" if "did not converge" in c.reason else ("SJ" if "singular" in c.reason else "NF")
                ax.text(tensions.index(c.tension_n), rows.index((c.placement, c.guess)), code, ha="center",
                        va="center", fontsize=7)
        ok = [c.success for c in cases if c.solver == s]
        ax.set_title(f"{s}\n{sum(ok)}/{len(ok)} converged", fontsize=9)
        ax.set_xticks(range(len(tensions)), [f"{t:g} N" for t in tensions])
        ax.set_yticks(range(len(rows)), [f"{p} / {g} guess" for p, g in rows], fontsize=7)
    fig.suptitle("Two-tube solver stability (tip force (0, 0.2, -0.2) N; NC: not converged, SJ: singular, "
                 "NF: non-finite)", fontsize=9)
    fig.tight_layout()
    return fig
