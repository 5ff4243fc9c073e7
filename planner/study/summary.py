"""Summaries of studies.

A design study: reach rates and the best candidates' metrics per design, as a table and a figure. An implant cohort
(straight against steered): the paired statistics of :mod:`reachplan.planner.study.statistics`, the results by
stratum of anatomy (:data:`STRATA`) and a figure of each case's difference coloured by stratum.
"""

from __future__ import annotations

import csv
import dataclasses
import io
import json
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from reachplan.imaging.files import atomic_write_bytes
from reachplan.planner.study.statistics import (
    PairedSummary,
    bootstrap_ci,
    continuous_summary,
    count_summary,
    power_note,
)

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


# ------------------------------------------------------------------------------------------------ implant cohorts

#: The effect the power note is for: a mean saving of half a needle per case (the issue's question).
POWER_EFFECT_NEEDLES = 0.5
#: What the implant cohort's statistics assume (written to summary.json).
ASSUMPTIONS = (
    "cases are independent: one synthetic anatomy per seed, drawn from the distributions of "
    "reachplan.imaging.anatomy.VARIETY (published where a source exists, ASSUMED where it does not)",
    "each case is paired: both arms plan the same anatomy, template and aims; differences are steered against "
    "straight (needles saved = straight minus steered; dose gains = steered minus straight)",
    "needles saved are small integers with many ties and zeros: the Wilcoxon signed-rank test (zeros dropped; normal "
    "approximation with tie correction when ties or zeros occur) and the exact sign test, which assume no normality; "
    "their interval is a percentile bootstrap of the mean over cases",
    "D90 and organ D2cm3 differences are continuous: the paired t-test and t-interval assume roughly normal "
    "differences; the Wilcoxon signed-rank test beside them assumes only symmetry",
    "cases where an arm has no implant are left out of the paired statistics (listed under 'failed')",
    "strata are descriptive: with a few cases per group their intervals are wide and no test is made between groups",
)
#: Stratum variables of the strata figure and ``summary.json`` ``strata``: name -> (row column, how it is split).
STRATA = {
    "parametrial_extension": ("parametrial_extension", "none, proximal or distal (either side)"),
    "bladder_filling": ("bladder_cm3", "below or at least the cohort median volume"),
    "uterine_version": ("uterus_version_deg", "anteverted (>= 0 degrees) or retroverted"),
    "tumour_volume": ("hrctv_cm3", "HR-CTV below or at least the cohort median volume"),
}


@dataclass(frozen=True)
class ImplantCohortSummary:
    """Needles saved and doses gained by steering over a cohort of paired cases.

    Parameters
    ----------
    needles_saved : PairedSummary
        Straight-arm minus steered-arm needles of each case's chosen implant (cases with both arms planned).
    d90_gain_gy : PairedSummary
        Steered minus straight HR-CTV D90 (EQD2, Gy), same cases.
    oar_d2cc_change_gy : tuple of (str, PairedSummary)
        Per organ at risk, steered minus straight D2cm³ (EQD2, Gy; negative: steering spares it).
    aims_met_straight, aims_met_steered : int
        Cases whose chosen implant meets every aim, per arm (an arm without an implant does not).
    n_cases : int
        All cases.
    n_paired : int
        Cases with both arms planned.
    n_steered_used : int
        Paired cases whose steered arm's chosen implant holds at least one steered needle.
    """

    needles_saved: PairedSummary
    d90_gain_gy: PairedSummary
    oar_d2cc_change_gy: tuple[tuple[str, PairedSummary], ...]
    aims_met_straight: int
    aims_met_steered: int
    n_cases: int
    n_paired: int
    n_steered_used: int


def _paired(rows: Sequence[Mapping[str, Any]]) -> list[Mapping[str, Any]]:
    return [r for r in rows if r["straight_needles"] is not None and r["steered_needles"] is not None]


def _organ_changes(paired: Sequence[Mapping[str, Any]]) -> dict[str, list[float]]:
    """Organ -> steered minus straight D2cm³ (Gy) over the paired cases that report it in both arms."""
    out: dict[str, list[float]] = {}
    for r in paired:
        a, b = (json.loads(r.get(f"{arm}_oar_d2cc_eqd2_gy") or "{}") for arm in ("straight", "steered"))
        for organ in sorted(set(a) & set(b)):
            out.setdefault(organ, []).append(float(b[organ]) - float(a[organ]))
    return out


def summarise_cohort(rows: Sequence[Mapping[str, Any]]) -> ImplantCohortSummary:
    """Summarise an implant cohort from its rows (``ImplantRow`` fields as a mapping).

    Parameters
    ----------
    rows : sequence of mapping
        One per case: ``straight_needles``, ``steered_needles`` (None without an implant), the arms'
        ``*_hrctv_d90_eqd2_gy``, ``*_aims_met``, ``*_oar_d2cc_eqd2_gy`` (JSON object or "") and, optionally,
        ``steered_needles_used``.

    Returns
    -------
    ImplantCohortSummary
        Paired statistics (:mod:`reachplan.planner.study.statistics`), aims met and counts.
    """
    paired = _paired(rows)
    saved = [r["straight_needles"] - r["steered_needles"] for r in paired]
    gained = [r["steered_hrctv_d90_eqd2_gy"] - r["straight_hrctv_d90_eqd2_gy"] for r in paired]
    organs = tuple((o, continuous_summary(v)) for o, v in _organ_changes(paired).items())
    return ImplantCohortSummary(
        count_summary(saved), continuous_summary(gained), organs,
        sum(bool(r["straight_aims_met"]) for r in rows), sum(bool(r["steered_aims_met"]) for r in rows),
        len(rows), len(paired), sum(bool(r.get("steered_needles_used")) for r in paired))


def stratum_of(row: Mapping[str, Any], variable: str, medians: Mapping[str, float]) -> str | None:
    """Return the group of ``row`` for a stratum variable of :data:`STRATA` (None when the row lacks it).

    Parameters
    ----------
    row : mapping
        A case's row.
    variable : str
        A key of :data:`STRATA`.
    medians : mapping of str to float
        The cohort medians of the columns split at them (``bladder_cm3``, ``hrctv_cm3``).

    Returns
    -------
    str or None
        The group's label.
    """
    column, _ = STRATA[variable]
    v = row.get(column)
    if v is None or v == "":
        return None
    if variable == "parametrial_extension":
        return str(v).split()[-1]  # "left distal" -> "distal"; "none" stays
    if variable == "uterine_version":
        return "anteverted" if float(v) >= 0.0 else "retroverted"
    m = medians[column]
    return f"< {m:.0f} cm3" if float(v) < m else f">= {m:.0f} cm3"


def strata(rows: Sequence[Mapping[str, Any]]) -> dict[str, Any]:
    """Return the paired results by stratum (for ``summary.json`` ``strata``).

    Parameters
    ----------
    rows : sequence of mapping
        The cases' rows (paired ones are used).

    Returns
    -------
    dict
        Per variable of :data:`STRATA`: ``split`` (how) and ``groups``: per group ``n``, ``needles_saved_mean``
        and its bootstrap ``needles_saved_ci95``, ``d90_gain_gy_mean``, ``steered_needle_used`` (cases) and
        ``cases`` (their keys).
    """
    paired = _paired(rows)
    medians = {c: float(np.median([float(r[c]) for r in paired if r.get(c) is not None]))
               for c in ("bladder_cm3", "hrctv_cm3") if any(r.get(c) is not None for r in paired)}
    out: dict[str, Any] = {}
    for variable, (_, split) in STRATA.items():
        groups: dict[str, list[Mapping[str, Any]]] = {}
        for r in paired:
            g = stratum_of(r, variable, medians)
            if g is not None:
                groups.setdefault(g, []).append(r)
        doc = {}
        for g, members in sorted(groups.items()):
            saved = [float(r["straight_needles"] - r["steered_needles"]) for r in members]
            ci = bootstrap_ci(saved)
            doc[g] = {"n": len(members), "needles_saved_mean": round(float(np.mean(saved)), 4),
                      "needles_saved_ci95": None if ci is None else [round(ci[0], 4), round(ci[1], 4)],
                      "d90_gain_gy_mean": round(float(np.mean([r["steered_hrctv_d90_eqd2_gy"]
                                                                - r["straight_hrctv_d90_eqd2_gy"] for r in members])),
                                                4),
                      "steered_needle_used": sum(bool(r.get("steered_needles_used")) for r in members),
                      "cases": [r["case"] for r in members]}
        out[variable] = {"split": split, "groups": doc}
    return out


def _span(rows: Sequence[Mapping[str, Any]], column: str) -> dict[str, float | None]:
    v = [float(r[column]) for r in rows if r.get(column) is not None]
    if not v:
        return {"min": None, "max": None, "ratio": None}
    return {"min": round(min(v), 2), "max": round(max(v), 2),
            "ratio": round(max(v) / min(v), 3) if min(v) > 0 else None}


def implant_summary_json(summary: ImplantCohortSummary, rows: Sequence[Mapping[str, Any]],
                         wall_s: float) -> dict[str, Any]:
    """Return ``summary.json`` of an implant cohort: tests, intervals, effect sizes, power, strata, anatomy span.

    Parameters
    ----------
    summary : ImplantCohortSummary
        The cohort's summary.
    rows : sequence of mapping
        The cases' rows.
    wall_s : float, s
        Wall time of the run.

    Returns
    -------
    dict of str to JSON value
        ``needles_saved`` and ``d90_gain_gy`` each with ``mean``, ``ci95``, ``test``, ``p_value`` (and more);
        ``needles_saved_both_meet_aims`` (the same, over the cases where both arms meet every aim: a count of an arm
        that misses an aim is no implant to compare with), ``only_steered_meets_aims`` and
        ``only_straight_meets_aims`` (cases), ``oar_d2cc_change_gy``, ``aims_met``, ``steered_needle_used``,
        ``power``, ``assumptions``, ``strata``,
        ``anatomy`` (span of the HR-CTV and bladder volumes, cases with parametrial extension), ``failed`` and the
        times (``median_case_cpu_s`` over the planned cases, both arms).
    """
    paired = _paired(rows)
    like = [r["straight_needles"] - r["steered_needles"] for r in paired
            if r["straight_aims_met"] and r["steered_aims_met"]]
    cpu = [float(r["cpu_seconds"]) for r in rows if r.get("cpu_seconds") is not None]
    secs = [float(r["seconds"]) for r in rows if r.get("seconds") is not None]
    ext = [r.get("parametrial_extension") for r in rows if r.get("parametrial_extension")]
    saved = [r["straight_needles"] - r["steered_needles"] for r in paired]
    return {
        "cases": summary.n_cases, "paired_cases": summary.n_paired,
        "needles_saved": summary.needles_saved.to_json(),
        # like for like: a needle count of an arm that misses an aim is no implant to compare with
        "needles_saved_both_meet_aims": count_summary(like).to_json() if len(like) > 1 else None,
        "only_steered_meets_aims": [r["case"] for r in paired if r["steered_aims_met"] and not r["straight_aims_met"]],
        "only_straight_meets_aims": [r["case"] for r in paired if r["straight_aims_met"] and not r["steered_aims_met"]],
        "d90_gain_gy": summary.d90_gain_gy.to_json(),
        "oar_d2cc_change_gy": {o: s.to_json() for o, s in summary.oar_d2cc_change_gy},
        "aims_met": {"straight": summary.aims_met_straight, "steered": summary.aims_met_steered},
        "steered_needle_used": {"cases": summary.n_steered_used, "of_paired": summary.n_paired},
        "power": power_note(saved, POWER_EFFECT_NEEDLES) if saved else None,
        "assumptions": list(ASSUMPTIONS),
        "strata": strata(rows),
        "anatomy": {"hrctv_cm3": _span(rows, "hrctv_cm3"), "bladder_cm3": _span(rows, "bladder_cm3"),
                    "parametrial_extension_cases": sum(e != "none" for e in ext), "with_anatomy": len(ext)},
        "failed": {r["case"]: r["reason"] for r in rows if r["status"] == "failed"},
        "mean_case_seconds": round(float(np.mean(secs)), 3) if secs else None,
        "median_case_cpu_s": round(float(np.median(cpu)), 3) if cpu else None,
        "wall_s": round(wall_s, 3),
    }


def format_implant_summary(summary: ImplantCohortSummary, rows: Sequence[Mapping[str, Any]]) -> str:
    """Return a plain-text table: one line per case, then the paired statistics.

    Parameters
    ----------
    summary : ImplantCohortSummary
        Paired statistics and aims met, printed last.
    rows : sequence of mapping
        One line each (``ImplantRow`` fields).

    Returns
    -------
    str
        The table (D90 in Gy EQD2; ``st`` marks a steered arm whose implant holds a steered needle).
    """
    def v(x: object, fmt: str = "") -> str:
        return "-" if x is None else format(x, fmt)

    lines = [f"{'case':<12} {'HR-CTV':>6} {'bladder':>7} {'param.':<18} {'needles':>11} {'D90 Gy (EQD2)':>15} "
             f"{'aims met':>11}  note",
             f"{'':<12} {'cm3':>6} {'cm3':>7} {'':<18} {'strt':>5} {'steer':>5} {'strt':>7} {'steer':>7} "
             f"{'strt':>5} {'steer':>5}"]
    for r in rows:
        lines.append(
            f"{r['case']:<12} {v(r.get('hrctv_cm3'), '.0f'):>6} {v(r.get('bladder_cm3'), '.0f'):>7} "
            f"{r.get('parametrial_extension') or '-'!s:<18} {v(r['straight_needles']):>5} "
            f"{v(r['steered_needles']):>4}{'s' if r.get('steered_needles_used') else ' '} "
            f"{v(r['straight_hrctv_d90_eqd2_gy'], '.1f'):>7} {v(r['steered_hrctv_d90_eqd2_gy'], '.1f'):>7} "
            f"{'yes' if r['straight_aims_met'] else 'no':>5} {'yes' if r['steered_aims_met'] else 'no':>5}  "
            f"{r['reason'][:50]}")

    def stat(name: str, s: PairedSummary, unit: str) -> str:
        if s.mean is None:
            return f"{name}: no case with both arms planned"
        ci = "CI needs 2 cases" if s.ci95 is None else f"95 % CI {s.ci95[0]:+.2f} .. {s.ci95[1]:+.2f}"
        p = "no p-value" if s.primary.p_value is None else f"p = {s.primary.p_value:.3g}"
        return f"{name}: mean {s.mean:+.2f}{unit} ({ci}; {s.primary.test} {p}; {s.n} cases)"

    lines += ["", stat("needles saved by steering", summary.needles_saved, ""),
              stat("D90 gained by steering", summary.d90_gain_gy, " Gy"),
              f"steered arm uses a steered needle in {summary.n_steered_used} of {summary.n_paired} paired cases "
              "(s after the count)",
              f"aims met: straight {summary.aims_met_straight}/{summary.n_cases}, "
              f"steered {summary.aims_met_steered}/{summary.n_cases}"]
    return "\n".join(lines)


#: Colours of the parametrial-extension groups in the implant cohort figure.
_GROUP_COLOURS = {"none": "#7f7f7f", "proximal": "#1f77b4", "distal": "#d62728"}


def implant_summary_figure(summary: ImplantCohortSummary, rows: Sequence[Mapping[str, Any]], path: Path) -> None:
    """Waterfalls of each case's needles saved and D90 gained (coloured by parametrial extension), and the strata.

    Bars of cases whose steered arm uses a steered needle are hatched. The third panel shows each stratum group's
    mean needles saved with its bootstrap 95 % interval.

    Parameters
    ----------
    summary : ImplantCohortSummary
        The cohort's summary (its overall mean and interval are drawn as the first row of the strata panel).
    rows : sequence of mapping
        The cases' rows.
    path : Path
        The PNG file to write (atomically).
    """
    from matplotlib.figure import Figure
    from matplotlib.patches import Patch

    paired = _paired(rows)
    saved = np.array([r["straight_needles"] - r["steered_needles"] for r in paired], dtype=float)
    gain = np.array([r["steered_hrctv_d90_eqd2_gy"] - r["straight_hrctv_d90_eqd2_gy"] for r in paired], dtype=float)
    group = [stratum_of(r, "parametrial_extension", {}) or "unknown" for r in paired]
    used = [bool(r.get("steered_needles_used")) for r in paired]
    fig = Figure(figsize=(13.0, 4.6), layout="constrained")
    ax_n, ax_d, ax_s = fig.subplots(1, 3, width_ratios=(1.0, 1.0, 1.1))
    order = np.lexsort((-gain, -saved)) if len(saved) else np.array([], dtype=int)
    for ax, values, label in ((ax_n, saved, "needles saved by steering (per case)"),
                              (ax_d, gain, "HR-CTV D90 gained by steering (Gy EQD2)")):
        for x, k in enumerate(order):
            colour = _GROUP_COLOURS.get(group[k], "#bcbd22")
            ax.bar(x, values[k], 0.8, color=colour, edgecolor="black", lw=0.5, hatch="///" if used[k] else None)
            ax.plot([x], [values[k]], "o", color=colour, mec="black", mew=0.5, ms=5)  # a zero difference shows too
        ax.axhline(0.0, color="black", lw=0.8)
        ax.set_xticks(range(len(order)), [paired[k]["case"].rsplit("_", 1)[-1] for k in order], fontsize=7,
                      rotation=90)
        ax.set_xlabel("case (seed); sorted by needles, then D90", fontsize=9)
        ax.set_ylabel(label, fontsize=9)
    ax_n.yaxis.get_major_locator().set_params(integer=True)
    handles = [Patch(color=c, label=f"parametrium: {g}") for g, c in _GROUP_COLOURS.items()]
    handles.append(Patch(facecolor="white", edgecolor="black", hatch="///", label="steered needle used"))
    ax_n.legend(handles=handles, fontsize=8, loc="upper right")
    s = summary.needles_saved
    p = "" if s.primary.p_value is None else f", Wilcoxon p = {s.primary.p_value:.2g}"
    ax_n.set_title(f"{summary.n_paired} paired cases{p}", fontsize=9)
    _strata_panel(ax_s, summary, strata(rows))
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110)
    atomic_write_bytes(path, buf.getvalue())


def _strata_panel(ax: Any, summary: ImplantCohortSummary, by_stratum: Mapping[str, Any]) -> None:
    """Mean needles saved with its bootstrap 95 % interval: the whole cohort, then each stratum group."""
    labels: list[str] = []
    s = summary.needles_saved
    entries: list[tuple[str, float | None, list[float] | None, int]] = [
        ("all cases", s.mean, None if s.ci95 is None else list(s.ci95), s.n)]
    for variable, doc in by_stratum.items():
        for g, d in doc["groups"].items():
            entries.append((f"{variable.replace('_', ' ')}: {g}", d["needles_saved_mean"], d["needles_saved_ci95"],
                            d["n"]))
    for y, (label, mean, ci, n) in enumerate(entries):
        labels.append(f"{label} (n={n})")
        if mean is None:
            continue
        err = None if ci is None else [[mean - ci[0]], [ci[1] - mean]]
        ax.errorbar([mean], [y], xerr=err, fmt="o", color="C0" if y else "black", capsize=3, ms=4)
    ax.axvline(0.0, color="grey", lw=0.8)
    ax.set_yticks(range(len(entries)), labels, fontsize=8)
    ax.invert_yaxis()
    ax.set_xlabel("mean needles saved (bootstrap 95 % CI)", fontsize=9)
    ax.set_title("where steering pays: by stratum", fontsize=9)
