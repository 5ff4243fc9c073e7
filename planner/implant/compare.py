"""Straight versus steered on given needles: each arm's dwell times optimised the same way, and the needles it needs.

The per-target comparison of the report (the chosen needle of each target, per kind); the whole-implant comparison
is two arms of :func:`reachplan.planner.implant.plan.plan_arms`.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from reachplan.planner.dose.aims import Aims
from reachplan.planner.dose.structures import PlanningStructures
from reachplan.planner.dose.tg43 import Tg43Kernel
from reachplan.planner.implant.dwells import (
    OptimisationResult,
    OptimizerSettings,
    _build,
    _optimise_columns,
    candidate_dwells,
)


@dataclass(frozen=True, eq=False)
class ArmResult:
    """One arm of a comparison: its optimised plan with all needles, and how many it needs.

    ``needles_needed`` is the smallest number of the arm's needles (taken in the given order) whose
    optimised plan reaches the D90 aim within the organ limits, found by bisection (adding a needle adds
    dwells, so the optimum cannot get worse; the post-LP scaling makes this hold only approximately);
    None when all of them do not.

    Parameters
    ----------
    name : str
        The arm's name.
    n_needles : int
        Needles offered.
    plan : OptimisationResult
        The plan with every needle loaded.
    needles_needed : int or None
        Needles needed to reach the aim (a prefix of the given order).
    """

    name: str
    n_needles: int
    plan: OptimisationResult
    needles_needed: int | None


@dataclass(frozen=True)
class ComparisonRow:
    """One row of the comparison table (per-fraction physical and total EQD2 values).

    Built by :meth:`Comparison.rows`, one per arm.

    Parameters
    ----------
    arm : str
        The arm's name, as in :class:`ArmResult`.
    n_needles, needles_needed : int, int or None
        As in :class:`ArmResult`.
    d90_gy, d98_gy : float, Gy per fraction
        HR-CTV D90 and D98, physical.
    v100_pct : float, %
        HR-CTV volume receiving at least the prescription.
    d90_eqd2_gy, d98_eqd2_gy : float, Gy EQD2
        Totals with the external beam.
    oar_d2cc_eqd2_gy : tuple of (organ, Gy EQD2)
        Each organ's D2cm³, total with the external beam.
    aim_met : bool
        HR-CTV D90 reached its aim within the organ limits.
    note : str
        The plan's reason (solved, scaled, or why not).
    """

    arm: str
    n_needles: int
    needles_needed: int | None
    d90_gy: float
    d98_gy: float
    v100_pct: float
    d90_eqd2_gy: float
    d98_eqd2_gy: float
    oar_d2cc_eqd2_gy: tuple[tuple[str, float], ...]
    aim_met: bool
    note: str


@dataclass(frozen=True, eq=False)
class Comparison:
    """Result of :func:`compare_arms`.

    Its :meth:`rows` make the comparison table.

    Parameters
    ----------
    arms : tuple of ArmResult
        One per arm, in the order given.
    aims : Aims
        The aims every arm was planned to.
    """

    arms: tuple[ArmResult, ...]
    aims: Aims

    def rows(self) -> tuple[ComparisonRow, ...]:
        """Return the table's rows.

        Returns
        -------
        tuple of ComparisonRow
            One per arm, in the arms' order.
        """
        out = []
        for a in self.arms:
            t = a.plan.target
            out.append(ComparisonRow(
                arm=a.name,
                n_needles=a.n_needles,
                needles_needed=a.needles_needed,
                d90_gy=t.d90_gy,
                d98_gy=t.d98_gy,
                v100_pct=t.v100_pct,
                d90_eqd2_gy=t.d90_eqd2_gy,
                d98_eqd2_gy=t.d98_eqd2_gy,
                oar_d2cc_eqd2_gy=tuple((o.name, o.d2cc_eqd2_gy) for o in a.plan.oars),
                aim_met=a.plan.aim_met,
                note=a.plan.reason,
            ))
        return tuple(out)

    def format_table(self) -> str:
        """Return the table as aligned text.

        Returns
        -------
        str
            A header line, then one line per arm: needles offered and needed, HR-CTV D90 and D98 (Gy EQD2 totals),
            V100 (%) and each organ's D2cm³ (Gy EQD2 total), one decimal.
        """
        rows = self.rows()
        organs = [n for n, _ in rows[0].oar_d2cc_eqd2_gy] if rows else []
        head = ["arm", "needles", "needed", "D90 EQD2", "D98 EQD2", "V100 %", *[f"{o} D2cc" for o in organs]]
        lines = [head]
        for r in rows:
            lines.append([
                r.arm, str(r.n_needles), "-" if r.needles_needed is None else str(r.needles_needed),
                f"{r.d90_eqd2_gy:.1f}", f"{r.d98_eqd2_gy:.1f}", f"{r.v100_pct:.1f}",
                *[f"{v:.1f}" for _, v in r.oar_d2cc_eqd2_gy],
            ])
        widths = [max(len(line[i]) for line in lines) for i in range(len(head))]
        return "\n".join("  ".join(c.rjust(w) for c, w in zip(line, widths, strict=True)) for line in lines)

    def figure(self) -> Any:
        """Plot the cumulative DVH of every structure, one line style per arm.

        Returns
        -------
        matplotlib.figure.Figure
            % volume against dose, Gy per fraction (physical), the prescription marked; not attached to pyplot
            (save it with ``savefig``).
        """
        from matplotlib.figure import Figure

        fig = Figure(figsize=(7.0, 4.5))
        ax = fig.add_subplot()
        styles = ["-", "--", ":", "-."]
        names = [n for n, _ in self.arms[0].plan.dvhs] if self.arms else []
        colours = {n: f"C{i}" for i, n in enumerate(names)}
        for k, arm in enumerate(self.arms):
            for n, dvh in arm.plan.dvhs:
                ax.plot(dvh.dose_gy, dvh.volume_percent, styles[k % len(styles)], color=colours.get(n, "k"),
                        label=f"{n} ({arm.name})")
        ax.axvline(self.aims.prescription_gy, color="grey", lw=0.8)
        ax.set_xlabel("dose per fraction (Gy)")
        ax.set_ylabel("volume (%)")
        ax.set_ylim(0, 102)
        ax.set_xlim(0, 3 * self.aims.prescription_gy)
        ax.legend(fontsize=7, ncol=2)
        ax.set_title("cumulative DVH")
        fig.tight_layout()
        return fig


def compare_arms(arms: Sequence[tuple[str, Sequence[np.ndarray]]], structures: PlanningStructures,
                 kernel: Tg43Kernel, air_kerma_strength_u: float, *, aims: Aims | None = None,
                 settings: OptimizerSettings | None = None) -> Comparison:
    """Optimise each arm's needles the same way and count the needles each needs to reach the aim.

    Parameters
    ----------
    arms : sequence of (name, needles)
        ``needles``: sequence of (k, 3) float, mm, LPS, ordered base → tip, in the order they would be
        inserted (the needle count uses prefixes of this order).
    structures : PlanningStructures
        HR-CTV and organ masks on the planning grid, the same for every arm.
    kernel : Tg43Kernel
        TG-43 kernel of the source.
    air_kerma_strength_u : float, U
        Source strength S_K.
    aims : Aims, optional
        The aims every arm is planned to (EMBRACE II when None).
    settings : OptimizerSettings, optional
        Dwell placement and LP size, as for :func:`reachplan.planner.implant.dwells.optimise_dwell_times`.

    Returns
    -------
    Comparison
        One :class:`ArmResult` per arm, in the given order.
    """
    aims = Aims() if aims is None else aims
    settings = OptimizerSettings() if settings is None else settings
    results = []
    for name, needles in arms:
        dwells = candidate_dwells(needles, settings)
        prob = _build(dwells, structures, kernel, air_kerma_strength_u, settings)
        full = _optimise_columns(prob, np.arange(len(dwells)), structures, aims, settings)
        needed: int | None = None
        if full.aim_met:  # bisection over prefixes: more needles never make the optimum worse
            lo, hi = 0, len(needles)  # the aim fails with lo needles (or lo = 0) and is met with hi
            while hi - lo > 1:
                mid = (lo + hi) // 2
                cols = np.flatnonzero(dwells.channels <= mid)
                if _optimise_columns(prob, cols, structures, aims, settings).aim_met:
                    hi = mid
                else:
                    lo = mid
            needed = hi
        results.append(ArmResult(name, len(needles), full, needed))
    return Comparison(tuple(results), aims)
