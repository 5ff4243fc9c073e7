"""Per-design summary of a study: reach rates and the best candidates' metrics, as a table and a figure."""

from __future__ import annotations

import csv
import dataclasses
import io
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from reachplan.imaging.files import atomic_write_bytes

if TYPE_CHECKING:
    import pyarrow as pa


@dataclass(frozen=True)
class DesignSummary:
    """One design across the cohort.

    Rates are fractions of the planned (``ok``) case x target rows; ``median_*`` are over the targets the design
    reaches with a steered needle (None when it reaches none). Numbers are rounded to 1e-3 (rates 1e-4).

    Parameters
    ----------
    design : str
        Stylet preset, or ``straight``.
    n_cases : int
        Cases with a row of this design.
    n_targets : int
        Planned (``ok``) case x target rows.
    n_failed : int
        Failed rows.
    reach_rate_steered, reach_rate_straight : float or None
        Fraction reached with a feasible steered (straight) needle; None with no planned row.
    reach_rate_any : float or None
        Fraction reached with either.
    steered_only_rate : float or None
        Fraction reached only by steering.
    median_steered_reach_error_mm : float or None, mm
        Reach error of the best steered candidates.
    median_steered_clearance_mm : float or None, mm
        Their clearance to the nearest organ at risk.
    median_steered_peak_tension_n : float or None, N
        Their peak tendon tension.
    median_steered_insertion_depth_mm : float or None, mm
        Their insertion depth beyond the template.
    mean_task_plan_s : float or None, s
        Mean planning time of one case (all targets).
    median_hrctv_d90_gy : float or None, Gy
        With dose: median HR-CTV D90 over the cases with a dose.
    dose_aim_met_rate : float or None
        With dose: fraction of planned cases whose optimised dwell times meet the aims (a case without a feasible
        needle counts as not met).
    """

    design: str
    n_cases: int
    n_targets: int
    n_failed: int
    reach_rate_steered: float | None
    reach_rate_straight: float | None
    reach_rate_any: float | None
    steered_only_rate: float | None
    median_steered_reach_error_mm: float | None
    median_steered_clearance_mm: float | None
    median_steered_peak_tension_n: float | None
    median_steered_insertion_depth_mm: float | None
    mean_task_plan_s: float | None
    median_hrctv_d90_gy: float | None = None
    dose_aim_met_rate: float | None = None


def _col(table: pa.Table, name: str) -> np.ndarray:
    return np.array([np.nan if v is None else v for v in table[name].to_pylist()], dtype=float)


def _median(v: np.ndarray) -> float | None:
    v = v[np.isfinite(v)]
    return round(float(np.median(v)), 3) if len(v) else None


def summarise(table: pa.Table) -> tuple[DesignSummary, ...]:
    """One :class:`DesignSummary` per design (in name order) from a study table.

    Parameters
    ----------
    table : pyarrow.Table
        Study rows (:func:`reachplan.planner.study.store.schema`).

    Returns
    -------
    tuple of DesignSummary
        In design name order.
    """
    import pyarrow.compute as pc

    out = []
    for design in sorted(set(table["design"].to_pylist())):
        t = table.filter(pc.equal(table["design"], design))
        ok = t.filter(pc.equal(t["status"], "ok"))
        n = ok.num_rows
        st = np.array(ok["reached_steered"].to_pylist(), dtype=bool)
        sr = np.array(ok["reached_straight"].to_pylist(), dtype=bool)

        def rate(mask: np.ndarray, n: int = n) -> float | None:
            return round(float(mask.sum()) / n, 4) if n else None

        tasks = {r["task"]: r for r in ok.to_pylist()}
        per_task = {k: r["task_plan_s"] for k, r in tasks.items()}
        dosed = [r for r in tasks.values() if r["task_dose_reason"] is not None]
        d90 = np.array([np.nan if r["task_hrctv_d90_gy"] is None else r["task_hrctv_d90_gy"] for r in dosed])
        out.append(DesignSummary(
            design=design, n_cases=len(set(t["case"].to_pylist())), n_targets=n, n_failed=t.num_rows - n,
            reach_rate_steered=rate(st), reach_rate_straight=rate(sr), reach_rate_any=rate(st | sr),
            steered_only_rate=rate(st & ~sr),
            median_steered_reach_error_mm=_median(_col(ok, "steered_reach_error_mm")),
            median_steered_clearance_mm=_median(_col(ok, "steered_clearance_mm")),
            median_steered_peak_tension_n=_median(_col(ok, "steered_peak_tension_n")),
            median_steered_insertion_depth_mm=_median(_col(ok, "steered_insertion_depth_mm")),
            mean_task_plan_s=round(float(np.mean(list(per_task.values()))), 3) if per_task else None,
            median_hrctv_d90_gy=_median(d90),
            dose_aim_met_rate=round(sum(bool(r["task_dose_aim_met"]) for r in dosed) / len(dosed), 4)
            if dosed else None))
    return tuple(out)


def write_dataclass_csv(cls: type, rows: Sequence[object], path: Path) -> None:
    """Write ``rows`` (instances of the dataclass ``cls``) as CSV, one column per field, atomically.

    Empty cells for None.

    Parameters
    ----------
    cls : type
        The dataclass; its fields name the columns, in order.
    rows : sequence of object
        Instances of ``cls``.
    path : Path
        The CSV file to write.
    """
    buf = io.StringIO()
    names = [f.name for f in dataclasses.fields(cls)]
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(names)
    for r in rows:
        w.writerow(["" if getattr(r, n) is None else getattr(r, n) for n in names])
    atomic_write_bytes(path, buf.getvalue().encode("utf-8"))


def format_summary(summaries: Sequence[DesignSummary]) -> str:
    """Return a plain-text table: one line per design.

    Parameters
    ----------
    summaries : sequence of DesignSummary
        The designs' summaries.

    Returns
    -------
    str
        Header and one line per design (rates in %, mm, N; dose columns when a design has a dose).
    """
    def pct(v: float | None) -> str:
        return "   -" if v is None else f"{100 * v:3.0f}%"

    def num(v: float | None) -> str:
        return "    -" if v is None else f"{v:5.1f}"

    lines = [f"{'design':<16} {'cases':>5} {'rows':>5} {'fail':>4}  {'steer':>5} {'strt':>5} {'any':>5} "
             f"{'only':>5}  {'err mm':>6} {'clr mm':>6} {'ten N':>6}"
             + (f" {'D90 Gy':>6} {'aims':>5}" if any(s.dose_aim_met_rate is not None for s in summaries) else "")]
    for s in summaries:
        lines.append(f"{s.design:<16} {s.n_cases:>5} {s.n_targets:>5} {s.n_failed:>4}  {pct(s.reach_rate_steered):>5} "
                     f"{pct(s.reach_rate_straight):>5} {pct(s.reach_rate_any):>5} {pct(s.steered_only_rate):>5}  "
                     f"{num(s.median_steered_reach_error_mm):>6} {num(s.median_steered_clearance_mm):>6} "
                     f"{num(s.median_steered_peak_tension_n):>6}"
                     + (f" {num(s.median_hrctv_d90_gy):>6} {pct(s.dose_aim_met_rate):>5}"
                        if s.dose_aim_met_rate is not None else ""))
    return "\n".join(lines)


def summary_figure(table: pa.Table, summaries: Sequence[DesignSummary], path: Path) -> None:
    """Reach rates per design (bars) and the best steered candidates' clearance and peak tension (boxes).

    Parameters
    ----------
    table : pyarrow.Table
        Study rows.
    summaries : sequence of DesignSummary
        The designs' summaries, in the figure's order.
    path : Path
        The PNG file to write (atomically); with dose a third panel shows the HR-CTV D90 (Gy).
    """
    import pyarrow.compute as pc
    from matplotlib.figure import Figure

    designs = [s.design for s in summaries]
    x = np.arange(len(designs))
    panels: tuple[tuple[str, str, str], ...] = (
        ("steered_clearance_mm", "clearance to nearest OAR (mm)", "best steered candidate"),
        ("steered_peak_tension_n", "peak tendon tension (N)", "best steered candidate"))
    if any(s.dose_aim_met_rate is not None for s in summaries):
        panels += (("task_hrctv_d90_gy", "HR-CTV D90 (Gy)", "optimised dwell times"),)
    fig = Figure(figsize=(2 + (1 + len(panels)) * (0.8 + 0.6 * len(designs)), 4.2), layout="constrained")
    axes = fig.subplots(1, 1 + len(panels))
    ax = axes[0]
    for i, (label, attr) in enumerate((("steered", "reach_rate_steered"), ("straight", "reach_rate_straight"),
                                       ("either", "reach_rate_any"))):
        vals = [100 * (getattr(s, attr) or 0.0) for s in summaries]
        ax.bar(x + (i - 1) * 0.27, vals, 0.27, label=label)
    ax.set_ylabel("targets reached (%)")
    ax.set_ylim(0, 105)
    ax.set_title("reach rate")
    ax.legend(fontsize=8, loc="lower right")
    for ax, (col, label, title) in zip(axes[1:], panels, strict=True):
        data = []
        for d in designs:
            t = table.filter(pc.equal(table["design"], d))
            if col.startswith("task_"):  # one value per task
                t = t.take([t["task"].to_pylist().index(k) for k in dict.fromkeys(t["task"].to_pylist())])
            v = _col(t, col)
            data.append(v[np.isfinite(v)])
        ax.boxplot([v if len(v) else [np.nan] for v in data], positions=x, widths=0.5)
        ax.set_ylabel(label)
        ax.set_title(title)
    for ax in axes:
        ax.set_xticks(x, designs, rotation=30, ha="right", fontsize=8)
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110)
    atomic_write_bytes(path, buf.getvalue())
