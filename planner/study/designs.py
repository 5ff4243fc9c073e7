"""Stylet designs compared in one implant study: a straight + steered arm per design, one straight arm shared by all.

``reachplan study --implant N --designs A B ...`` plans on every case the straight arm once and, per stylet preset,
the arm of the straight candidates and that preset's steered ones (:func:`reachplan.planner.implant.case.
plan_design_arms`). The first design's arm is the case's ``steered`` arm (``cases.csv``); every design's result is a
row of ``designs.csv`` (case x design) and a block of ``summary.json`` ``designs``: needles saved against the shared
straight arm and HR-CTV D90 gained, each with its mean and paired t-interval (the study's, see
:mod:`reachplan.planner.study.implant`), the cases whose chosen implant uses a steered needle of the design, and the
tension reserve those needles keep (the stylet's limit less the schedule's peak, after the reference re-solve).
``best`` names the design with the most needles saved on average (ties: the larger D90 gain, then the larger
median reserve).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from reachplan.planner.study.summary import write_dataclass_csv

DESIGNS_CSV = "designs.csv"


@dataclass(frozen=True)
class DesignRow:
    """One case x stylet design of an implant study (a row of ``designs.csv``); doses EQD2 totals, Gy.

    Parameters
    ----------
    case : str
        The case's key.
    seed : int
        Its seed.
    design : str
        The stylet preset of the arm (straight candidates and this design's steered ones).
    status : str
        ``ok`` (the shared straight arm and this arm both have an implant) or ``failed``.
    needles, straight_needles : int or None
        Needles of this arm's and of the straight arm's chosen implant.
    needles_saved : int or None
        Straight minus this arm's needles.
    hrctv_d90_eqd2_gy, d90_gained_gy : float or None, Gy
        This arm's HR-CTV D90, and it less the straight arm's.
    aims_met : bool
        This arm's chosen implant meets every aim.
    steered_needles : int or None
        Steered needles of this design in the chosen implant.
    min_tension_reserve_n : float or None, N
        Smallest tension reserve (limit less peak tension) over them; None without one.
    max_peak_tension_n : float or None, N
        Largest peak tension over them.
    """

    case: str
    seed: int
    design: str
    status: str
    needles: int | None = None
    straight_needles: int | None = None
    needles_saved: int | None = None
    hrctv_d90_eqd2_gy: float | None = None
    d90_gained_gy: float | None = None
    aims_met: bool = False
    steered_needles: int | None = None
    min_tension_reserve_n: float | None = None
    max_peak_tension_n: float | None = None


def design_rows(case: str, seed: int, straight: Mapping[str, Any] | None,
                arms: Mapping[str, Mapping[str, Any] | None]) -> list[DesignRow]:
    """Return a case's rows: one per design, from the plan.json arm sections.

    Parameters
    ----------
    case : str
        The case's key.
    seed : int
        Its seed.
    straight : mapping or None
        The shared straight arm's plan.json section (None: the case failed).
    arms : mapping of str to mapping or None
        Design -> its arm's plan.json section (``n_needles``, ``hrctv_d90_eqd2_gy``, ``aims_met``, ``needles``).

    Returns
    -------
    list of DesignRow
        In the order of ``arms``.
    """
    rows = []
    base = None if straight is None or "n_needles" not in straight else straight
    for design, arm in arms.items():
        if arm is None or "n_needles" not in arm or base is None:
            rows.append(DesignRow(case, seed, design, "failed",
                                  straight_needles=None if base is None else int(base["n_needles"])))
            continue
        steered = [n for n in arm.get("needles", ()) if n.get("kind") == "steered" and n.get("design") == design]
        reserves = [float(n["tension_reserve_n"]) for n in steered if n.get("tension_reserve_n") is not None]
        peaks = [float(n["peak_tension_n"]) for n in steered if n.get("peak_tension_n") is not None]
        n, n0 = int(arm["n_needles"]), int(base["n_needles"])
        d90, d90_0 = float(arm["hrctv_d90_eqd2_gy"]), float(base["hrctv_d90_eqd2_gy"])
        rows.append(DesignRow(case, seed, design, "ok", n, n0, n0 - n, round(d90, 3), round(d90 - d90_0, 3),
                              bool(arm.get("aims_met")), len(steered), min(reserves) if reserves else None,
                              max(peaks) if peaks else None))
    return rows


def part_design_rows(case: str, seed: int, part: Mapping[str, Any], designs: Sequence[str]) -> list[DesignRow]:
    """Return the rows of one case's study part (its ``implant`` and ``designs`` sections), one per design.

    Parameters
    ----------
    case : str
        The case's key.
    seed : int
        Its seed.
    part : mapping
        The case's part file: ``implant`` (``straight`` and the first design's ``steered`` arm; None when the case
        failed) and ``designs`` (every further design's arm by name).
    designs : sequence of str
        The study's designs, in order.

    Returns
    -------
    list of DesignRow
        One per design.
    """
    implant = part.get("implant") or {}
    arms = {d: (implant.get("steered") if k == 0 else (part.get("designs") or {}).get(d))
            for k, d in enumerate(designs)}
    return design_rows(case, seed, implant.get("straight"), arms)


def designs_json(rows: Sequence[DesignRow], designs: Sequence[str], interval: Callable[[list[float], float], Any],
                 level: float = 0.95) -> dict[str, Any]:
    """Return ``summary.json``'s ``designs``: per design needles saved and D90 gained with their intervals.

    Parameters
    ----------
    rows : sequence of DesignRow
        Every case x design.
    designs : sequence of str
        The designs, in the study's order.
    interval : callable (differences, level) -> PairedStat
        The study's interval of a mean paired difference
        (:func:`reachplan.planner.study.implant.t_interval`: ``mean``, ``low``, ``high``, ``n``).
    level : float
        Confidence level of the intervals.

    Returns
    -------
    dict of str to JSON value
        ``by_design`` (per design: ``paired_cases``, ``needles_saved`` and ``d90_gained_gy`` each with ``mean``,
        ``ci95`` [low, high] and ``test``; ``aims_met``; ``cases_using_steered``; ``tension_reserve_n`` median and
        minimum over the chosen steered needles) and ``best``.
    """
    def stat(values: list[float]) -> dict[str, Any]:
        s = interval(values, level)

        def r(v: float | None) -> float | None:
            return None if v is None else round(v, 4)

        return {"mean": r(s.mean), "ci95": [r(s.low), r(s.high)], "n": s.n,
                "test": f"paired Student t-interval ({100 * level:g} %), straight arm shared by every design"}

    out: dict[str, Any] = {}
    for d in designs:
        ok = [r for r in rows if r.design == d and r.status == "ok"]
        reserves = [r.min_tension_reserve_n for r in ok if r.min_tension_reserve_n is not None]
        out[d] = {"paired_cases": len(ok),
                  "needles_saved": stat([float(r.needles_saved or 0) for r in ok]),
                  "d90_gained_gy": stat([float(r.d90_gained_gy or 0.0) for r in ok]),
                  "aims_met": sum(r.aims_met for r in rows if r.design == d),
                  "cases_using_steered": sum(bool(r.steered_needles) for r in ok),
                  "tension_reserve_n": {"median": round(float(np.median(reserves)), 3) if reserves else None,
                                        "min": round(min(reserves), 3) if reserves else None}}

    def rank(d: str) -> tuple[float, float, float]:
        b = out[d]
        return (b["needles_saved"]["mean"] if b["needles_saved"]["mean"] is not None else -np.inf,
                b["d90_gained_gy"]["mean"] if b["d90_gained_gy"]["mean"] is not None else -np.inf,
                b["tension_reserve_n"]["median"] if b["tension_reserve_n"]["median"] is not None else -np.inf)

    best = max(designs, key=rank) if any(out[d]["paired_cases"] for d in designs) else None
    return {"by_design": out, "best": best,
            "note": "each design's arm: the straight candidates and that design's steered ones; the straight arm is "
                    "planned once per case and shared"}


def write_designs(rows: Sequence[DesignRow], out: Path) -> Path:
    """Write ``designs.csv`` (one row per case x design) into the study folder ``out``, atomically.

    Parameters
    ----------
    rows : sequence of DesignRow
        The rows, case-major.
    out : Path
        The study's folder.

    Returns
    -------
    Path
        The file written.
    """
    path = Path(out) / DESIGNS_CSV
    write_dataclass_csv(DesignRow, rows, path)
    return path


def format_designs(doc: Mapping[str, Any]) -> str:
    """Return a plain-text table of :func:`designs_json`: one line per design.

    Parameters
    ----------
    doc : mapping
        :func:`designs_json`'s result.

    Returns
    -------
    str
        The table (needles saved and D90 gained: mean and interval; reserve in N).
    """
    def ci(s: Mapping[str, Any], fmt: str) -> str:
        lo, hi = s["ci95"]
        m = "-" if s["mean"] is None else format(s["mean"], fmt)
        return m if lo is None else f"{m} ({lo:{fmt}} .. {hi:{fmt}})"

    lines = [f"{'design':<16} {'cases':>5} {'needles saved (CI)':>26} {'D90 gained Gy (CI)':>26} {'steered':>7} "
             f"{'reserve N':>9}"]
    for d, b in doc["by_design"].items():
        res = b["tension_reserve_n"]["median"]
        lines.append(f"{d:<16} {b['paired_cases']:>5} {ci(b['needles_saved'], '+.2f'):>26} "
                     f"{ci(b['d90_gained_gy'], '+.2f'):>26} {b['cases_using_steered']:>7} "
                     f"{'-' if res is None else format(res, '.2f'):>9}")
    lines.append(f"most needles saved: {doc['best'] or '-'} (straight arm shared by every design)")
    return "\n".join(lines)
