"""The plan's summary as text, for the terminal.

The first screen is the research-use statement and the delivered implant's insert list (the hand-off, the same rows
the report and the device page print); below it, to explain it, the best needles per target with robustness margins,
the models in plain words and the implant arms side by side; the HTML report reuses the margins, the model words and
the rows.
"""

from __future__ import annotations

import textwrap
from collections.abc import Callable, Collection, Mapping, Sequence
from typing import TYPE_CHECKING

import numpy as np

from reachplan.planner.case.result import PlanResult
from reachplan.planner.delivery import Delivery
from reachplan.planner.dose.evaluation import AimsTable, bounds_text
from reachplan.planner.implant.compare import Comparison
from reachplan.planner.steering.candidates import Candidate
from reachplan.plugins.exporters.handoff import NUMERIC_COLUMNS as INSERT_NUMERIC
from reachplan.plugins.exporters.handoff import RESEARCH_USE, InsertList

if TYPE_CHECKING:
    from reachplan.planner.delivery import ImplantComparison
    from reachplan.planner.implant.arms import ImplantArm, ImplantPlan


def top_candidates(result: PlanResult, n_per_target: int = 1) -> list[Candidate]:
    """Return the best ``n_per_target`` feasible candidates of every target.

    Parameters
    ----------
    result : PlanResult
        The ranked plan.
    n_per_target : int
        Feasible candidates kept per target.

    Returns
    -------
    list of Candidate
        Target by target in ranking order, best first.
    """
    return [c for cs in result.ranking.values() for c in [c for c in cs if c.feasible][:n_per_target]]


def _cell(v: float, digits: int = 1) -> str:
    return f"{v:.{digits}f}" if np.isfinite(v) else "-"


def reach_margin_mm(c: Candidate, tolerance_mm: float) -> float:
    """Return how far a needle's worst-case reach error stays under (+) or goes over (-) the reach tolerance.

    Parameters
    ----------
    c : Candidate
        The needle (not assessed: NaN).
    tolerance_mm : float, mm
        The plan's reach tolerance.

    Returns
    -------
    float, mm
        ``tolerance - worst_reach``; NaN when the needle was not assessed.
    """
    return float(tolerance_mm - c.worst_reach_mm) if np.isfinite(c.worst_reach_mm) else float("nan")


def tension_reserve_n(c: Candidate) -> float:
    """Return the tension a needle's schedule leaves below its stylet's design limit.

    Parameters
    ----------
    c : Candidate
        The needle.

    Returns
    -------
    float, N
        Limit less peak; NaN for a straight needle (no stylet design).
    """
    return float(c.design.max_tension_n - c.peak_tension_n) if c.design is not None else float("nan")


#: Rod and insertion models in plain words.
PLAIN_MODELS = {
    "straight": "a straight line from the hole (exact geometry)",
    "kinematic": "fast screening: the shaft follows the tip (kinematic insertion)",
    "tissue_rod": "reference: the needle as an exact rod pushed into the tissue, held on the track its tip cut",
    "planar_beam": "a planar beam model of the stylet",
    "two_tube_cosserat": "the two-tube Cosserat model of stylet inside needle",
    "cosserat_rod": "a single-rod Cosserat model",
    "constant_curvature": "a constant-curvature arc",
}


#: The models in a few words, for the terminal.
SHORT_MODELS = {"straight": "exact straight line", "kinematic": "fast screening model",
                "tissue_rod": "reference model (rod in tissue)"}


def plain_model(c: Candidate) -> str:
    """Return the model behind a candidate's numbers in plain words.

    E.g. ``fast screening: ... bending from a planar beam model of the stylet``.

    Parameters
    ----------
    c : Candidate
        The candidate.

    Returns
    -------
    str
        Its insertion model, and rod model when there is one, in words.
    """
    words = PLAIN_MODELS.get(c.model.insertion, c.model.insertion)
    if c.model.rod_model:
        words += f", bending from {PLAIN_MODELS.get(c.model.rod_model, c.model.rod_model)}"
    return words


def _verdict(table: AimsTable | None, met: bool, over: str) -> tuple[bool, str]:
    """Return the protocol table's verdict and the aims it misses, else the optimiser's (``met``, ``over``)."""
    if table is None:
        return met, over
    return table.aims_met, f"; not met: {', '.join(table.not_met)}" if table.not_met else ""


def _arm_lines(delivery: Delivery | None, comparison: Comparison | None) -> list[str]:
    """Return the protocol used, its warnings, one line per arm (needles, HR-CTV D90, aims met), then the aims table."""
    from reachplan.planner.dose.aims import Aims

    aims = delivery.aims if delivery is not None else comparison.aims if comparison is not None else Aims()
    limits = ", ".join(f"{o} < {v:g} Gy" for o, v in aims.oar_d2cc_eqd2_gy)
    lines = [f"dose aims: {aims.name} ({aims.site}; {aims.origin}), EQD2: {aims.target_names[0]} D90 >= "
             f"{aims.target_d90_eqd2_gy:g} Gy; D2cm³ {limits}; {aims.headroom_eqd2_gy:g} Gy headroom below each "
             "organ and point aim"]
    lines += [f"  warning: {w}" for w in (delivery.warnings if delivery is not None else ())]
    limit = {k.casefold(): v for k, v in aims.oar_d2cc_eqd2_gy}
    tables = delivery.aims_tables if delivery is not None else {}

    def over(organs: Sequence[tuple[str, float]]) -> str:
        bad = [f"{o} {v:.1f} Gy" for o, v in organs if o.casefold() in limit and v > limit[o.casefold()]]
        return f"; over the limit: {', '.join(bad)}" if bad else ""

    arms: list[tuple[str, int, float, bool, str]] = []
    if delivery is not None and delivery.implant is not None:  # the whole HR-CTV: what the aims are about
        for arm, label in zip(delivery.implant.arms, ("implant, straight", "implant, straight + steered"), strict=True):
            pl = arm.plan
            if pl is None:
                arms.append((label, 0, np.nan, False, f"; no implant: {arm.reason}"))
                continue
            met, why = _verdict(tables.get(arm.name), pl.aims_met, over([(o.name, o.d2cc_eqd2_gy) for o in pl.oars]))
            arms.append((label, pl.n_needles, pl.target.d90_eqd2_gy, met, why))
    per_target = " (one needle per target)" if arms else ""
    if comparison is not None:
        arms += [(f"{r.arm} arm{per_target}", r.n_needles, r.d90_eqd2_gy, r.aim_met, over(r.oar_d2cc_eqd2_gy))
                 for r in comparison.rows()]
    if delivery is not None:
        opt = delivery.optimisation
        met, why = (_verdict(tables.get("delivered"), opt.aim_met, over([(o.name, o.d2cc_eqd2_gy) for o in opt.oars]))
                    if opt.success else (False, f"; not solved: {opt.reason}"))
        arms.append((f"exported plan ({delivery.kind})", delivery.n_needles,
                     opt.target.d90_eqd2_gy if opt.success else np.nan, met, why))
    if not arms:
        return ["dose: not computed (--no-export)"]
    width = max(len(a[0]) for a in arms)
    for name, n, d90, met, why in arms:
        low = "" if met or not d90 < aims.target_d90_eqd2_gy else f"; D90 below {aims.target_d90_eqd2_gy:g} Gy"
        why = f"{low}{why}".removeprefix("; ")
        lines.append(f"  {name:<{width}}  {n:>3} needle{'s' if n != 1 else ' '}  HR-CTV D90 {_cell(d90):>5} Gy EQD2  "
                     f"{'aims met' if met else 'aims NOT met'}{f' ({why})' if why else ''}")
    if delivery is not None and delivery.aims_tables:
        rows = aims_rows(delivery.aims_tables)
        lines += ["", *_aligned(rows), AIMS_LEGEND.format(headroom=aims.headroom_eqd2_gy)]
    return lines


#: What an aims-table cell says (the terminal and the report).
AIMS_LEGEND = ("value (headroom: distance from the planning aim, + on the safe side) planning aim met / hard limit "
               "kept; organs and points need {headroom:g} Gy headroom, targets 0; n/a: not applicable (organ < 2 cm³, "
               "not counted); -: no aim or limit")


def _flag(v: bool | None) -> str:
    return "-" if v is None else "yes" if v else "NO"


def aims_rows(tables: Mapping[str, AimsTable]) -> list[tuple[str, ...]]:
    """Return every aim of the protocol against each plan as rows of text cells, the first row the header.

    Columns: the aim, its planning aim, its hard limit (Gy EQD2), then per plan (the implant arms' chosen plans, or
    the exported plan when there are no arms: ``delivered``) the value, its headroom and the two verdicts
    (:data:`AIMS_LEGEND`); the last rows: every planning aim met, every hard limit kept.

    Parameters
    ----------
    tables : mapping of str to AimsTable
        By plan (:attr:`~reachplan.planner.delivery.Delivery.aims_tables`): ``straight``, ``steered``,
        ``delivered`` (the last shown only without the others, and named after its arm otherwise).

    Returns
    -------
    list of tuple of str
        Header, one row per aim, the two verdict rows.
    """
    names: list[str] = [n for n in ("straight", "steered", "delivered") if n in tables]
    names = [n for n in names if n != "delivered"] or names
    exported = tables.get("delivered")
    head = ("aim (Gy EQD2)", "planning aim", "hard limit",
            *(f"{n}{' (exported)' if tables[n] is exported and n != 'delivered' else ''}" for n in names))
    labels = list(dict.fromkeys(r.label for n in names for r in tables[n].results))
    rows: list[tuple[str, ...]] = [head]
    for label in labels:
        found = [next((r for r in tables[n].results if r.label == label), None) for n in names]
        first = next(r for r in found if r is not None)
        cells = []
        for r in found:
            if r is None or r.value_eqd2_gy is None:
                cells.append("-" if r is None else "n/a" if r.metric == "D2cm³" else "not placed")
                continue
            h = r.headroom_eqd2_gy
            cells.append(f"{r.value_eqd2_gy:.1f} ({'-' if h is None else f'{h:+.1f}'}) "
                         f"{_flag(r.aim_met)}/{_flag(r.limit_met)}")
        rows.append((label, bounds_text(first.aim_min_eqd2_gy, first.aim_max_eqd2_gy),
                     bounds_text(first.limit_min_eqd2_gy, first.limit_max_eqd2_gy), *cells))
    rows.append(("every planning aim met", "", "", *("yes" if tables[n].aims_met else "NO" for n in names)))
    rows.append(("every hard limit kept", "", "", *("yes" if tables[n].limits_met else "NO" for n in names)))
    return rows


def format_rows(rows: Sequence[Sequence[str]]) -> str:
    """Return rows of text cells as aligned lines (:func:`aims_rows`, :func:`implant_rows`).

    Parameters
    ----------
    rows : sequence of sequence of str
        The header row first; every row as long.

    Returns
    -------
    str
        The first column left-aligned, the others right-aligned.
    """
    return "\n".join(_aligned(rows))


def _aligned(rows: Sequence[Sequence[str]], right: Collection[int] | None = None) -> list[str]:
    """Return rows as text, the columns ``right`` right-aligned (default all but the first), the others left."""
    widths = [max(len(r[i]) for r in rows) for i in range(len(rows[0]))]
    right = range(1, len(widths)) if right is None else right
    return ["  ".join(c.rjust(w) if i in right else c.ljust(w) for i, (c, w) in enumerate(zip(r, widths, strict=True)))
            .rstrip() for r in rows]



def _wrap(text: str, indent: str = "  ") -> list[str]:
    """Wrap a paragraph to :data:`WIDTH` columns, every line indented."""
    return textwrap.wrap(text, WIDTH, initial_indent=indent, subsequent_indent=indent + "  ")


#: Terminal width the paragraphs of the first screen wrap at.
WIDTH = 118


def format_insert_list(handoff: InsertList) -> list[str]:
    """Return the first screen: the research-use statement and the insert list (:meth:`InsertList.rows`).

    Parameters
    ----------
    handoff : InsertList
        The delivered plan's insert list.

    Returns
    -------
    list of str
        The statement, the list's heading and table, per needle its schedule and check depths in words, the
        applicator channels, the rule at the tension limit, the perturbation model and the applicators taken.
    """
    lines = [*textwrap.wrap(handoff.statement, WIDTH), "", handoff.title()]
    lines += _aligned(handoff.rows(), right=INSERT_NUMERIC)
    for hole, words, checks in handoff.details():
        lines += _wrap(f"{hole}: {words}", "  ")
        lines += _wrap(f"check depths: {checks}", "      ")
    lines += [f"  {a.text()}" for a in handoff.applicators]
    if handoff.tension_rule:
        lines += _wrap(handoff.tension_rule)
    lines += _wrap(handoff.perturbations)
    return [*lines, *_wrap(handoff.obstacles)]


def format_summary(result: PlanResult, *, targets: Sequence[str] | None = None, delivery: Delivery | None = None,
                   comparison: Comparison | None = None, files: Sequence[tuple[str, str]] = (),
                   applicators: str = "") -> str:
    """Return the terminal summary of a plan.

    First the research-use statement and the delivered plan's insert list (:func:`format_insert_list`), then, to
    explain it, per target (in ``targets``' order, the user's; default the ranking's) its best straight and best
    steered needle with units in every header and robustness margins, then one line per arm with the dose aims met
    or not, then the files written.

    Parameters
    ----------
    result : PlanResult
        The ranked plan.
    targets : sequence of str or None
        Target names in the user's order; None: the ranking's.
    delivery : Delivery or None
        The delivered plan (its insert list and dose lines); None: ranked only.
    comparison : Comparison or None
        Straight versus steered dose (one line per arm).
    files : sequence of (str, str)
        (what, path) of the files written.
    applicators : str
        Which ROIs were taken as applicators (printed when there is no insert list to say it).

    Returns
    -------
    str
        Lines of text (mm, N, Gy EQD2).
    """
    handoff = delivery.export.handoff if delivery is not None else None
    lines = (format_insert_list(handoff) if handoff is not None
             else [*textwrap.wrap(RESEARCH_USE, WIDTH), *([applicators] if applicators else [])])
    tol = result.config.reach_tolerance_mm
    lines += ["", "Per target (to explain the list: each target's best needles; the implant is chosen for the whole "
              "volume)"]
    head = (f"{'target':<15} {'needle':<9} {'hole':<5} {'from centre (mm)':>16} {'reach error (mm)':>16} "
            f"{'clearance (mm)':>14} {'reach margin (mm)':>17} {'peak / reserve (N)':>18}  model")
    lines += [head, ""]
    rule = len(lines) - 1
    order = [t for t in (targets or result.ranking) if t in result.ranking]
    for t in order:
        cands = result.ranking[t]
        top = cands[0] if cands and cands[0].feasible else None
        for i, steered in enumerate((False, True)):
            c = result.best(t, steered)
            kind = ("steered" if steered else "straight") + ("*" if c is not None and c is top else "")
            name = t if i == 0 else ""
            if c is None:
                lines.append(f"{name:<15} {kind:<9} none feasible")
                continue
            margin = reach_margin_mm(c, tol)
            margin_cell = "-" if not np.isfinite(margin) else f"{margin:+.1f}"
            tension = "-" if not steered else f"{c.peak_tension_n:.1f} / {_cell(tension_reserve_n(c))}"
            lines.append(f"{name:<15} {kind:<9} {c.hole_id:<5} {c.hole_distance_mm:>16.1f} {c.reach_error_mm:>16.1f} "
                         f"{_cell(c.clearance_mm):>14} {margin_cell:>17} {tension:>18}  "
                         f"{SHORT_MODELS.get(c.model.insertion, c.model.label)}")
    lines[rule] = "-" * max(len(ln) for ln in lines[rule - 1:])
    lines += [f"* ranked first for its target. Reach margin: the {tol:g} mm reach tolerance less the worst-case "
              "tip error under the perturbations (+ inside, - over); reserve: the stylet's limit less the peak.", ""]
    lines += _arm_lines(delivery, comparison)
    if files:
        width = max(len(w) for w, _ in files)
        lines += ["", *(f"{w:<{width}}  {p}" for w, p in files)]
    return "\n".join(lines)


def implant_rows(comparison: ImplantComparison, tables: Mapping[str, AimsTable] | None = None,
                 ) -> list[tuple[str, ...]]:
    """Return the implant arms side by side as rows of text cells, the first row naming the arms.

    Needles (candidates), aims, HR-CTV D90/D98/V100/V150/V200 (EQD2 totals, Gy), organ D2cm³, the needles' share of
    the dwell weight, the largest single dwell's share, loaded dwells per needle and the Pareto curve
    (needles:D90). The terminal (:func:`format_implant`) and the report print the same rows.

    Parameters
    ----------
    comparison : ImplantComparison
        Both implant arms.
    tables : mapping of str to AimsTable or None
        Each arm's aims against its protocol (:attr:`Delivery.aims_tables`): "aims met" is then the table's
        verdict (every planning aim with its headroom), else the selection's.

    Returns
    -------
    list of tuple of str
        Label then one cell per arm ("-" for an arm without an implant).
    """
    arms = comparison.arms
    rows: list[tuple[str, ...]] = [("implant", *(a.name for a in arms))]

    def cell(a: ImplantArm, f: Callable[[ImplantPlan], str]) -> str:
        return "-" if a.plan is None else f(a.plan)

    rows.append(("needles (candidates)", *(f"{cell(a, lambda p: str(p.n_needles))} ({a.n_candidates})"
                                           for a in arms)))
    verdicts = {name: t.aims_met for name, t in (tables or {}).items()}

    def met(a: ImplantArm) -> str:
        return "-" if a.plan is None else "yes" if verdicts.get(a.name, a.plan.aims_met) else "no"

    rows.append(("aims met", *(met(a) for a in arms)))
    for label, get in (("HR-CTV D90 Gy", lambda p: f"{p.target.d90_eqd2_gy:.1f}"),
                       ("HR-CTV D98 Gy", lambda p: f"{p.target.d98_eqd2_gy:.1f}"),
                       ("V100 %", lambda p: f"{p.target.v100_pct:.1f}"),
                       ("V150 %", lambda p: f"{p.target.v150_pct:.1f}"),
                       ("V200 %", lambda p: f"{p.v200_pct:.1f}")):
        rows.append((label, *(cell(a, get) for a in arms)))
    organs = list(dict.fromkeys(o.name for a in arms if a.plan for o in a.plan.oars))
    for organ in organs:
        def d2cc(p: ImplantPlan, organ: str = organ) -> str:
            return next((f"{o.d2cc_eqd2_gy:.1f}" for o in p.oars if o.name == organ), "-")

        rows.append((f"{organ} D2cc Gy", *(cell(a, d2cc) for a in arms)))
    rows.append(("needle dwell weight %", *(cell(a, lambda p: f"{100 * p.needle_time_share:.0f}") for a in arms)))
    rows.append(("IC / IS time s", *(cell(a, lambda p: f"{p.total_time_s * (1 - p.needle_time_share):.0f} / "
                                              f"{p.total_time_s * p.needle_time_share:.0f}") for a in arms)))
    rows.append(("1 needle off: D90 Gy", *(cell(a, lambda p: "-" if "worst_hrctv_d90_eqd2_gy" not in p.robustness
                                                else f"{p.robustness['worst_hrctv_d90_eqd2_gy']:.1f}") for a in arms)))
    rows.append(("1 needle off: limits", *(cell(a, lambda p: "kept" if p.robustness.get("hard_limits_met", True)
                                                else "broken") for a in arms)))
    rows.append(("largest dwell share %", *(cell(a, lambda p: f"{100 * p.max_dwell_share:.1f}") for a in arms)))
    rows.append(("loaded dwells/needle", *(cell(a, lambda p: " ".join(
        str(n) for c, n in zip(p.channels, p.loaded_dwells, strict=True) if c.is_needle)) for a in arms)))
    rows.append(("Pareto (needles:D90)", *(" ".join(f"{q.n_needles}:{q.hrctv_d90_eqd2_gy:.0f}" for q in a.pareto)
                                           or "-" for a in arms)))
    return rows


def format_implant(comparison: ImplantComparison, tables: Mapping[str, AimsTable] | None = None) -> str:
    """Return the two implant arms side by side (:func:`implant_rows`) for the terminal, then each arm's note.

    Parameters
    ----------
    comparison : ImplantComparison
        The straight and the steered arm, each with its chosen implant or reason.
    tables : mapping of str to AimsTable or None
        Each arm's aims (:func:`implant_rows`).

    Returns
    -------
    str
        The aligned table and the notes.
    """
    lines = _aligned(implant_rows(comparison, tables))
    notes = [f"{a.name}: {a.reason}" for a in comparison.arms if a.reason]
    return "\n".join([*lines, *notes])
