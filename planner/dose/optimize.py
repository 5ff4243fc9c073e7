"""Dwell-time optimisation for a set of needle paths, and the straight-versus-steered comparison.

Formulation (linear programme, scipy HiGHS, deterministic)::

    minimise   (1/m) Σ_i u_i + ε Σ_j t_j / t_ref
    subject to A_T t + u >= P          (target points: dose plus underdose slack reaches the prescription)
               A_O t <= L_o             (OAR points outside their hottest 2 cm³)
               t >= 0, u >= 0

``A`` holds TG-43 dose per second of dwell (Gy s⁻¹, per fraction), ``P`` is the per-fraction dose that
brings HR-CTV D90 to the aim in EQD2 (α/β 10, with the external-beam course), ``L_o`` the per-fraction
D2cm³ limit of each organ (α/β 3). D2cm³ ≤ L is not linear; it is handled by constraining every
candidate OAR point at first (max dose ≤ L, which implies D2cm³ ≤ L), then releasing the points in the
hottest 2 cm³ of each organ and solving again (twice). The final plan is checked on every voxel of every
organ; if a D2cm³ still exceeds its limit all times are scaled down until none does, and the result
says so. Organ limits are therefore always respected.

Default aims are the EMBRACE II planning aims (Pötter et al., Clin. Transl. Radiat. Oncol. 9:48, 2018;
``reference/oncoreach.md``): HR-CTV D90 >= 85 Gy, D98 >= 75 Gy EQD2 (α/β 10); D2cm³ bladder < 80 Gy,
rectum < 65 Gy, sigmoid < 70 Gy, bowel < 70 Gy EQD2 (α/β 3); 45 Gy / 25 fractions external beam plus
4 brachytherapy fractions.

Needle paths are ``(k, 3)`` polylines in mm, LPS, ordered from the template (base) to the tip.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy import optimize as sopt
from scipy import sparse

from reachplan.imaging.types import Grid
from reachplan.planner.dose.coverage import (
    Dvh,
    Fractionation,
    StructureMetrics,
    cumulative_dvh,
    dose_to_fraction,
    dose_to_volume,
    structure_metrics,
    voxel_volume_cc,
)
from reachplan.planner.dose.dwells import DwellSet, dwells_along_path, grid_points_mm
from reachplan.planner.dose.tg43 import Tg43Kernel


@dataclass(frozen=True, eq=False)
class Structure:
    """A structure as a mask on the planning grid.

    Parameters
    ----------
    name : str
    mask : (nk, nj, ni) bool
        True inside, on :attr:`PlanningStructures.grid`.
    """

    name: str
    mask: np.ndarray

    def __post_init__(self) -> None:
        m = np.asarray(self.mask, dtype=bool)
        if m.ndim != 3:
            raise ValueError(f"structure {self.name}: mask must be 3-D (nk, nj, ni), got {m.shape}")
        m.setflags(write=False)
        object.__setattr__(self, "mask", m)


@dataclass(frozen=True, eq=False)
class PlanningStructures:
    """The target (HR-CTV) and organs at risk on one grid."""

    grid: Grid
    target: Structure
    oars: tuple[Structure, ...] = ()

    def __post_init__(self) -> None:
        object.__setattr__(self, "oars", tuple(self.oars))
        for s in (self.target, *self.oars):
            if s.mask.shape != self.grid.shape:
                raise ValueError(f"structure {s.name}: mask {s.mask.shape} is not on the grid {self.grid.shape}")
        if not self.target.mask.any():
            raise ValueError(f"target {self.target.name} is empty")


#: EMBRACE II D2cm³ planning aims, EQD2 Gy (α/β 3), matched case-insensitively to organ names.
EMBRACE_II_OAR_D2CC: tuple[tuple[str, float], ...] = (
    ("bladder", 80.0),
    ("rectum", 65.0),
    ("sigmoid", 70.0),
    ("bowel", 70.0),
)


@dataclass(frozen=True)
class Aims:
    """Coverage aim and organ limits (EQD2, totals with the external-beam course).

    Defaults: EMBRACE II (see the module docstring). The prescription (V100) and ``aim_met`` use the D90
    aim; the D98 aim is carried for reports. Organ limits match organ names case-insensitively, also as
    a substring (``"Bladder_P"`` gets the bladder limit); organs without a limit are reported only.
    """

    target_d90_eqd2_gy: float = 85.0
    target_d98_eqd2_gy: float = 75.0
    #: GTV_res D98 > 90 Gy EQD2 (ESGO/ESTRO quality indicators 2023, reached in 90 % of patients); used by implant
    #: planning when a GTV is given.
    gtv_d98_eqd2_gy: float = 90.0
    oar_d2cc_eqd2_gy: tuple[tuple[str, float], ...] = EMBRACE_II_OAR_D2CC
    alpha_beta_target_gy: float = 10.0
    alpha_beta_oar_gy: float = 3.0
    fractionation: Fractionation = field(default_factory=Fractionation)

    def __post_init__(self) -> None:
        if not (self.target_d90_eqd2_gy > 0 and self.alpha_beta_target_gy > 0 and self.alpha_beta_oar_gy > 0):
            raise ValueError("aims: the D90 aim and both α/β must be > 0 Gy")
        if any(limit <= 0 for _, limit in self.oar_d2cc_eqd2_gy):
            raise ValueError("aims: organ limits must be > 0 Gy")

    @property
    def prescription_gy(self) -> float:
        """Per-fraction physical dose whose D90 meets the aim, Gy."""
        return self.fractionation.per_fraction_for(self.target_d90_eqd2_gy, self.alpha_beta_target_gy)

    def oar_limit_gy(self, name: str) -> float | None:
        """Per-fraction physical D2cm³ limit of organ ``name`` (None when it has none)."""
        key = name.casefold()
        for organ, limit in self.oar_d2cc_eqd2_gy:
            if organ.casefold() == key or organ.casefold() in key:
                return self.fractionation.per_fraction_for(limit, self.alpha_beta_oar_gy)
        return None


@dataclass(frozen=True)
class OptimizerSettings:
    """Dwell placement and problem size (lengths in mm).

    Parameters
    ----------
    dwell_step_mm, tip_offset_mm, active_length_mm : float
        Distance between candidate dwells along a needle; of the first dwell from the needle tip; length along
        each needle (from the first dwell) where dwells may be placed.
    max_target_points, max_oar_points : int
        Target voxels used in the LP (an even stride through them) and candidate voxels per organ (those
        with the highest dose for equal dwell times, i.e. nearest to the needles).
    time_weight : float
        ε: weight of the total time (breaks ties toward shorter plans).
    relax_iterations : int
        Re-solves that release each organ's hottest 2 cm³ from the point constraints.
    """

    dwell_step_mm: float = 5.0
    tip_offset_mm: float = 6.0
    active_length_mm: float = 60.0
    max_target_points: int = 3000
    max_oar_points: int = 1500
    time_weight: float = 1e-3
    relax_iterations: int = 2

    def __post_init__(self) -> None:
        if not (self.dwell_step_mm > 0 and self.tip_offset_mm >= 0 and self.active_length_mm >= 0):
            raise ValueError("dwell step must be > 0 mm; tip offset and active length >= 0 mm")
        if self.max_target_points < 1 or self.max_oar_points < 1 or self.relax_iterations < 0:
            raise ValueError("point limits must be >= 1 and relax iterations >= 0")


@dataclass(frozen=True, eq=False)
class OptimisationResult:
    """Optimised dwell times and the resulting metrics (per fraction; EQD2 totals in the metrics).

    ``success`` is False with a ``reason`` when the LP did not solve; ``scaled`` tells that the times
    were scaled down by ``scale`` after the LP so that every organ limit holds on all its voxels;
    ``aim_met`` that HR-CTV D90 (EQD2) reached its aim.
    """

    dwells: DwellSet
    target: StructureMetrics
    oars: tuple[StructureMetrics, ...]
    success: bool
    reason: str
    scaled: bool = False
    scale: float = 1.0
    dvhs: tuple[tuple[str, Dvh], ...] = ()
    aim_met: bool = False


def candidate_dwells(needles: Sequence[np.ndarray], settings: OptimizerSettings) -> DwellSet:
    """Candidate dwells on every needle (channel number = needle index + 1), times zero.

    Parameters
    ----------
    needles : sequence of (k, 3) float, mm, LPS, ordered base → tip
    settings : OptimizerSettings
    """
    parts = []
    for i, path in enumerate(needles):
        p = np.asarray(path, dtype=float)
        if p.ndim != 2 or p.shape[1] != 3 or len(p) < 2 or not np.all(np.isfinite(p)):
            raise ValueError(f"needle {i + 1}: path must be a finite (k >= 2, 3) array in mm")
        pos, dirs = dwells_along_path(
            p[::-1],
            step_mm=settings.dwell_step_mm,
            tip_offset_mm=settings.tip_offset_mm,
            active_length_mm=settings.active_length_mm,
        )
        parts.append(DwellSet(pos, dirs, np.zeros(len(pos)), np.full(len(pos), i + 1)))
    return DwellSet.concatenate(parts)


def _stride(idx: np.ndarray, n: int) -> np.ndarray:
    if len(idx) <= n:
        return idx
    return idx[np.linspace(0, len(idx) - 1, n).round().astype(int)]


@dataclass(frozen=True, eq=False)
class _Problem:
    """Dose-rate matrices (Gy per second of dwell, per fraction) of one arm's candidate dwells."""

    dwells: DwellSet
    target_idx: np.ndarray  # flat voxel indices of the target
    a_target: np.ndarray  # (n_target_voxels, n_dwells)
    oar_idx: tuple[np.ndarray, ...]
    a_oar: tuple[np.ndarray, ...]  # (n_oar_voxels, n_dwells) each
    lp_target_rows: np.ndarray
    lp_oar_rows: tuple[np.ndarray, ...]


def _build(
    dwells: DwellSet, structures: PlanningStructures, kernel: Tg43Kernel, sk: float, settings: OptimizerSettings
) -> _Problem:
    to_gy_per_s = sk / 360000.0

    def rates(idx: np.ndarray) -> np.ndarray:
        # the compiled float32 kernel (within 1e-4 of the float64 table; threads over voxels)
        out = kernel.compiled_rates(grid_points_mm(structures.grid, idx), dwells.positions_mm, dwells.directions)
        out *= to_gy_per_s
        return out

    t_idx = np.flatnonzero(structures.target.mask.ravel())
    a_t = rates(t_idx)
    o_idx = tuple(np.flatnonzero(o.mask.ravel()) for o in structures.oars)
    a_o = tuple(rates(i) for i in o_idx)
    lp_t = _stride(np.arange(len(t_idx)), settings.max_target_points)
    lp_o = []
    for a in a_o:
        k = min(len(a), settings.max_oar_points)
        near = np.argsort(-a.sum(axis=1), kind="stable")[:k] if len(a) else np.zeros(0, dtype=int)
        lp_o.append(np.sort(near))
    return _Problem(dwells, t_idx, a_t, o_idx, a_o, lp_t, tuple(lp_o))


def _solve_lp(
    prob: _Problem, cols: np.ndarray, limits: Sequence[float | None], released: Sequence[np.ndarray],
    prescription: float, settings: OptimizerSettings,
) -> tuple[np.ndarray | None, str]:
    n = len(cols)
    at = prob.a_target[prob.lp_target_rows][:, cols]
    m = len(at)
    # variables x = [t (n), u (m)]
    # objective: mean underdose + ε · mean target dose (both Gy), so ε is unit-free
    c = np.concatenate([settings.time_weight * at.mean(axis=0), np.full(m, 1.0 / m)])
    rows = [sparse.hstack([sparse.csr_matrix(-at), -sparse.identity(m, format="csr")])]
    rhs = [np.full(m, -prescription)]
    for a, lp_rows, limit, free in zip(prob.a_oar, prob.lp_oar_rows, limits, released, strict=True):
        if limit is None:
            continue
        keep = np.setdiff1d(lp_rows, free, assume_unique=False)
        if len(keep):
            rows.append(sparse.hstack([sparse.csr_matrix(a[keep][:, cols]), sparse.csr_matrix((len(keep), m))]))
            rhs.append(np.full(len(keep), limit))
    res = sopt.linprog(
        c, A_ub=sparse.vstack(rows, format="csr"), b_ub=np.concatenate(rhs), bounds=(0, None), method="highs",
    )
    if res.status != 0 or res.x is None:
        return None, f"linear programme did not solve: {res.message}"
    return np.maximum(res.x[:n], 0.0), "solved"


def _evaluate(
    prob: _Problem, cols: np.ndarray, times: np.ndarray, structures: PlanningStructures, aims: Aims,
) -> tuple[StructureMetrics, tuple[StructureMetrics, ...], tuple[tuple[str, Dvh], ...]]:
    vox = voxel_volume_cc(structures.grid)
    rx = aims.prescription_gy
    dt = prob.a_target[:, cols] @ times
    target = structure_metrics(structures.target.name, dt, vox, rx, aims.alpha_beta_target_gy, aims.fractionation)
    dvhs = [(structures.target.name, cumulative_dvh(dt, vox))]
    oars = []
    for s, a in zip(structures.oars, prob.a_oar, strict=True):
        if len(a) == 0:
            continue
        d = a[:, cols] @ times
        oars.append(structure_metrics(s.name, d, vox, rx, aims.alpha_beta_oar_gy, aims.fractionation))
        dvhs.append((s.name, cumulative_dvh(d, vox)))
    return target, tuple(oars), tuple(dvhs)


def _optimise_columns(
    prob: _Problem, cols: np.ndarray, structures: PlanningStructures, aims: Aims, settings: OptimizerSettings,
) -> OptimisationResult:
    vox = voxel_volume_cc(structures.grid)
    limits = [aims.oar_limit_gy(o.name) for o in structures.oars]
    released: list[np.ndarray] = [np.zeros(0, dtype=int) for _ in structures.oars]
    n_hot = max(1, math.ceil(2.0 / vox - 1e-9) - 1)  # voxels allowed above the limit
    reason = "no dwells"
    best: tuple[np.ndarray, float, float] | None = None  # (LP times, scale to the limits, D90)
    for _ in range(settings.relax_iterations + 1):
        t, reason = _solve_lp(prob, cols, limits, released, aims.prescription_gy, settings)
        if t is None:
            break
        scale = _limit_scale(prob, cols, t, limits, vox)
        d90 = dose_to_fraction(prob.a_target[:, cols] @ (t * scale), 0.9)
        if best is None or d90 > best[2] + 1e-12:
            best = (t, scale, d90)
        released = [
            lp_rows[np.argsort(-(a[lp_rows][:, cols] @ t), kind="stable")[:n_hot]]
            for a, lp_rows in zip(prob.a_oar, prob.lp_oar_rows, strict=True)
        ]
    dwells = prob.dwells.select(np.isin(np.arange(len(prob.dwells)), cols))
    if best is None:
        zero = np.zeros(len(cols))
        target, oars, dvhs = _evaluate(prob, cols, zero, structures, aims)
        return OptimisationResult(dwells.with_times(zero), target, oars, False, reason, dvhs=dvhs)
    t, scale, _ = best
    final = t * scale
    target, oars, dvhs = _evaluate(prob, cols, final, structures, aims)
    scaled = scale < 1.0
    note = "solved" if not scaled else "solved; times scaled down so every organ D2cm³ meets its limit"
    return OptimisationResult(
        dwells.with_times(final), target, oars, True, note, scaled=scaled, scale=scale, dvhs=dvhs,
        aim_met=target.d90_eqd2_gy >= aims.target_d90_eqd2_gy - 1e-9,
    )


def _limit_scale(
    prob: _Problem, cols: np.ndarray, times: np.ndarray, limits: Sequence[float | None], vox: float
) -> float:
    """Largest factor <= 1 that keeps every organ's D2cm³ (all its voxels) within its limit."""
    scale = 1.0
    for a, limit in zip(prob.a_oar, limits, strict=True):
        if limit is None or len(a) == 0:
            continue
        d2 = dose_to_volume(a[:, cols] @ times, vox, 2.0)
        if d2 > limit:
            scale = min(scale, limit / d2 * (1 - 1e-9))
    return scale


def optimise_dwell_times(
    needles: Sequence[np.ndarray],
    structures: PlanningStructures,
    kernel: Tg43Kernel,
    air_kerma_strength_u: float,
    aims: Aims | None = None,
    settings: OptimizerSettings | None = None,
) -> OptimisationResult:
    """Optimise dwell times on the given needles (straight or steered).

    Parameters
    ----------
    needles : sequence of (k, 3) float, mm, LPS, ordered base → tip
    structures : PlanningStructures
    kernel : Tg43Kernel
    air_kerma_strength_u : float, U
    aims : Aims, optional (EMBRACE II)
    settings : OptimizerSettings, optional

    Returns
    -------
    OptimisationResult
        Per-fraction dwell times; organ D2cm³ limits always hold; ``aim_met`` says whether HR-CTV D90
        reached its aim.
    """
    aims = Aims() if aims is None else aims
    settings = OptimizerSettings() if settings is None else settings
    dwells = candidate_dwells(needles, settings)
    prob = _build(dwells, structures, kernel, air_kerma_strength_u, settings)
    return _optimise_columns(prob, np.arange(len(dwells)), structures, aims, settings)


# --- straight versus steered --------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class ArmResult:
    """One arm of a comparison: its optimised plan with all needles, and how many it needs.

    ``needles_needed`` is the smallest number of the arm's needles (taken in the given order) whose
    optimised plan reaches the D90 aim within the organ limits, found by bisection (adding a needle adds
    dwells, so the optimum cannot get worse; the post-LP scaling makes this hold only approximately);
    None when all of them do not.
    """

    name: str
    n_needles: int
    plan: OptimisationResult
    needles_needed: int | None


@dataclass(frozen=True)
class ComparisonRow:
    """One row of the comparison table (per-fraction physical and total EQD2 values)."""

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
    """Result of :func:`compare_arms`."""

    arms: tuple[ArmResult, ...]
    aims: Aims

    def rows(self) -> tuple[ComparisonRow, ...]:
        """Return one :class:`ComparisonRow` per arm, in the arms' order."""
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
        """Return the table as aligned text (EQD2 totals)."""
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
        """Cumulative DVHs (% volume against Gy per fraction) of every structure, one line style per arm.

        Returns a :class:`matplotlib.figure.Figure` (not attached to pyplot; save it with ``savefig``).
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
    structures, kernel, air_kerma_strength_u, aims, settings
        As for :func:`optimise_dwell_times`.
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
