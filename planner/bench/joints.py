"""Benchmark: the discrete joint-section model against every published free-space row, and its convergence.

Run: ``reachplan bench joints --out DIR [--quick] [--install]``. Every model variant is calibrated on the three
calibration rows of the reference only (:data:`reachplan.rod_model.calibrate.CALIBRATION_ROWS`: its two global
parameters, joint stiffness scale and tube arm fraction, by :func:`~reachplan.rod_model.calibrate.calibrate`),
then predicts every published row; the validation rows (15 and 30 joints) are never fitted.

Writes

``joints_rows.csv``
    One line per variant and published row: role (``calibration`` / ``validation``), measured, predicted,
    residual, the variant's fitted parameters and its fixed friction.
``joints_family.csv`` and ``joints_trend.png``
    (a) tip deflection against the joint count (15 ga, tip, 9.9 N) for the continuum and the discrete model, the
    measured rows marked by role; (b) the one-parameter family of calibrations that reproduce the 15ga-20j-tip
    row exactly (joint stiffness scale swept, tube arm re-solved): the 30-joint, 15-joint and base rows they
    predict, against the joint/tube curvature ratio. Read, not fitted: where the family meets the 30-joint row
    the base row is off by the amount shown.
``joints_convergence.csv``
    Tip distance from the continuum's closed-form arcs (zero half-gap) by tube step and by joint count, and
    the default model's tip against a finer tube step.
``summary.json``
    The variants' worst calibration residual and 30-joint residual, the time per free-space solve.

``--install`` copies the CSVs and the chart into ``docs/``. ``--quick``: fewer variants and family points.
"""

from __future__ import annotations

import argparse
import statistics
import time
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
from matplotlib.figure import Figure
from scipy.optimize import brentq

from reachplan.planner.bench.common import settings, write_csv, write_json, write_png
from reachplan.rod_model.beam import PLANAR_BEAM
from reachplan.rod_model.calibrate import CALIBRATION_ROWS, VALIDATION_ROWS, calibrate, predict
from reachplan.rod_model.cosserat import TWO_TUBE_COSSERAT
from reachplan.rod_model.design import Calibration, preset
from reachplan.rod_model.joints import DISCRETE_JOINTS, JOINTS_CALIBRATION, DiscreteJoints
from reachplan.rod_model.protocol import RodModel

INSTALLS = {name: f"docs/{name}" for name in ("joints_rows.csv", "joints_family.csv", "joints_trend.png",
                                              "joints_convergence.csv")}
ROWS = CALIBRATION_ROWS + VALIDATION_ROWS
ROW_COLUMNS = ("variant", "preset", "tension_n", "role", "measured_mm", "predicted_mm", "residual_mm",
               "joint_stiffness_scale", "tube_arm_fraction", "tendon_friction", "joint_friction", "source")


@dataclass(frozen=True)
class Variant:
    """A model and its fixed friction, calibrated on the calibration rows.

    Parameters
    ----------
    label : str
        Name in the tables.
    model : RodModel
        The rod model.
    friction : (float, float)
        ``(tendon, joint)`` friction coefficients held fixed (ASSUMED values: nothing is published).
    refit : bool
        Calibrate the two parameters (False: the shipped :class:`Calibration`, the Cosserat model's fit).
    """

    label: str
    model: RodModel
    friction: tuple[float, float] = (0.0, 0.0)
    refit: bool = True


VARIANTS = (
    Variant("two_tube_cosserat (shipped calibration)", TWO_TUBE_COSSERAT, refit=False),
    Variant("discrete_joints", DISCRETE_JOINTS),
    Variant("discrete_joints, capstan friction 0.3", DISCRETE_JOINTS, (0.3, 0.0)),
    Variant("discrete_joints, joint friction 0.3", DISCRETE_JOINTS, (0.0, 0.3)),
    Variant("discrete_joints, routing loss 0.5 rad per disk at μ 0.3", DiscreteJoints(disk_wrap_rad=0.5), (0.3, 0.0)),
)


@dataclass(frozen=True)
class JointSettings:
    """What ``reachplan bench joints`` runs.

    Parameters
    ----------
    variants : int
        How many of :data:`VARIANTS` (in order).
    family_points : int
        Joint stiffness scales of the calibration family (log-spaced 0.02-2).
    joint_counts : tuple of int
        Joint counts of the trend panel (15 ga, tip).
    timing_repeats : int
        Free-space solves timed for the median.
    """

    variants: int = len(VARIANTS)
    family_points: int = 25
    joint_counts: tuple[int, ...] = tuple(range(10, 41, 2))
    timing_repeats: int = 200


QUICK = JointSettings(variants=2, family_points=5, joint_counts=(15, 20, 30), timing_repeats=20)


def calibrated_rows(v: Variant) -> tuple[Calibration, list[dict[str, object]]]:
    """Calibrate ``v`` on the calibration rows and predict every published row.

    Parameters
    ----------
    v : Variant
        The model variant.

    Returns
    -------
    calibration : Calibration
        Its parameters.
    rows : list of dict
        One per published row, by :data:`ROW_COLUMNS`.
    """
    cal = calibrate(model=v.model, friction=v.friction).calibration if v.refit else Calibration()
    pred = predict(cal, ROWS, v.model, v.friction)
    return cal, [{"variant": v.label, "preset": r.preset, "tension_n": r.tension_n,
                  "role": "calibration" if r in CALIBRATION_ROWS else "validation",
                  "measured_mm": r.tip_deflection_mm, "predicted_mm": round(float(p), 3),
                  "residual_mm": round(float(p) - r.tip_deflection_mm, 3),
                  "joint_stiffness_scale": round(cal.joint_stiffness_scale, 4),
                  "tube_arm_fraction": round(cal.tube_arm_fraction, 4), "tendon_friction": v.friction[0],
                  "joint_friction": v.friction[1], "source": r.source} for r, p in zip(ROWS, pred, strict=True)]


def family(points: int) -> list[dict[str, float]]:
    """Sweep the calibrations that reproduce the 15ga-20j-tip row exactly (discrete model).

    Parameters
    ----------
    points : int
        Joint stiffness scales, log-spaced over 0.02-2.

    Returns
    -------
    list of dict
        ``joint_stiffness_scale``, ``tube_arm_fraction``, ``curvature_ratio`` (joint over tube section
        curvature at 9.9 N) and the predicted deflection (mm) of every published row, by preset.
    """
    tip_row = CALIBRATION_ROWS[0]
    out = []
    for scale in np.geomspace(0.02, 2.0, points):
        def miss(f: float, s: float = float(scale)) -> float:
            return float(predict(Calibration(s, f), (tip_row,), DISCRETE_JOINTS)[0]) - tip_row.tip_deflection_mm

        if miss(0.05) * miss(1.0) > 0:
            continue  # no tube arm reproduces the row at this joint stiffness
        cal = Calibration(float(scale), brentq(miss, 0.05, 1.0, xtol=1e-10))
        d = preset(tip_row.preset, cal)
        secs = {s.kind: s for s in d.sections()}
        ratio = (secs["joints"].arm_m / (secs["joints"].ei1 + secs["joints"].ei2)) / (
            secs["tube"].arm_m / (secs["tube"].ei1 + secs["tube"].ei2))
        pred = predict(cal, ROWS, DISCRETE_JOINTS)
        out.append({"joint_stiffness_scale": cal.joint_stiffness_scale, "tube_arm_fraction": cal.tube_arm_fraction,
                    "curvature_ratio": ratio, **{r.preset: float(p) for r, p in zip(ROWS, pred, strict=True)}})
    return out


def convergence() -> list[dict[str, object]]:
    """Tip distance (mm) from the continuum arcs (zero half-gap) by tube step and joint count, and the default's step.

    Returns
    -------
    list of dict
        ``check``, ``joints``, ``tube_step_mm``, ``tip_error_mm``.
    """
    d = preset("15ga-20j-tip")
    rows: list[dict[str, object]] = []
    for n, step in [(160, h) for h in (2.0, 1.0, 0.5, 0.25)] + [(n, 0.125) for n in (5, 10, 20, 40)]:
        st = replace(d.stylet, n_joints=n, joint_pitch_mm=d.stylet.joint_length_mm / n)
        dn = replace(d, stylet=st)
        tip = DiscreteJoints(tube_step_mm=step, joint_half_gap_mm=0.0).solve(dn, dn.loads(10.0))
        exact = PLANAR_BEAM.solve(dn, dn.loads(10.0)).tip_position_mm
        rows.append({"check": "vs continuum arcs, zero half-gap", "joints": n, "tube_step_mm": step,
                     "tip_error_mm": float(np.linalg.norm(tip.tip_position_mm - exact))})  # type: ignore[union-attr]
    d30 = preset("15ga-30j-tip")
    ref = DiscreteJoints(tube_step_mm=0.125).solve(d30, d30.loads(10.0)).tip_position_mm  # type: ignore[union-attr]
    for step in (2.0, 1.0, 0.5, 0.25):
        at = DiscreteJoints(tube_step_mm=step).solve(d30, d30.loads(10.0)).tip_position_mm  # type: ignore[union-attr]
        rows.append({"check": "15ga-30j-tip at 10 N vs tube step 0.125 mm", "joints": 30, "tube_step_mm": step,
                     "tip_error_mm": float(np.linalg.norm(at - ref))})
    return rows


def _trend(counts: tuple[int, ...], cal: Calibration) -> tuple[list[float], list[float]]:
    cont, disc = [], []
    for n in counts:
        d = preset(f"15ga-{n}j-tip", Calibration())
        cont.append(TWO_TUBE_COSSERAT.solve(d, d.loads(9.9)).tip_deflection_mm)  # type: ignore[union-attr]
        d = preset(f"15ga-{n}j-tip", cal)
        disc.append(DISCRETE_JOINTS.solve(d, d.loads(9.9)).tip_deflection_mm)  # type: ignore[union-attr]
    return cont, disc


def figure(counts: tuple[int, ...], trend: tuple[list[float], list[float]], fam: list[dict[str, float]]) -> Figure:
    """Draw the joint-count trend and the calibration family.

    Parameters
    ----------
    counts : tuple of int
        Joint counts of the trend.
    trend : (list of float, list of float)
        Continuum and discrete tip deflections (mm) at those counts.
    fam : list of dict
        :func:`family`'s rows.

    Returns
    -------
    matplotlib.figure.Figure
    """
    fig = Figure(figsize=(12, 5))
    ax, bx = fig.subplots(1, 2)
    ax.plot(counts, trend[0], "-", color="tab:green", label="two_tube_cosserat (shipped calibration)")
    ax.plot(counts, trend[1], "--", color="tab:blue", label="discrete_joints (its own calibration)")
    for r in ROWS:
        if r.preset.endswith("-tip") and r.preset.startswith("15ga"):
            fitted = r in CALIBRATION_ROWS
            ax.plot(int(r.preset.split("-")[1][:-1]), r.tip_deflection_mm, "o", ms=9, color="k",
                    mfc="k" if fitted else "w", label="measured, calibration row" if fitted else None)
    ax.plot([], [], "o", ms=9, color="k", mfc="w", label="measured, validation row (never fitted)")
    ax.set_xlabel("joints in the section (15 ga, tip placement, pitch 1.65 mm)", fontsize=10)
    ax.set_ylabel("free-space tip deflection at 9.9 N (mm)", fontsize=10)
    ax.set_title("(a) tip deflection against the joint count", fontsize=11)
    ax.legend(fontsize=9)
    ratio = [f["curvature_ratio"] for f in fam]
    for name, color in (("15ga-30j-tip", "tab:red"), ("15ga-15j-tip", "tab:purple"), ("15ga-20j-base", "tab:brown")):
        row = next(r for r in ROWS if r.preset == name)
        role = "calibration" if row in CALIBRATION_ROWS else "validation"
        bx.plot(ratio, [f[name] - row.tip_deflection_mm for f in fam], "o-", color=color,
                label=f"{name} ({role}): predicted − measured")
    bx.axhline(0.0, color="k", lw=0.8)
    bx.set_xlabel("joint / tube section curvature (calibrations that reproduce 15ga-20j-tip exactly)", fontsize=10)
    bx.set_ylabel("residual (mm)", fontsize=10)
    bx.set_title("(b) no calibration meets the 30-joint and the base rows at once", fontsize=11)
    bx.legend(fontsize=9)
    for a in (ax, bx):
        a.grid(True, which="both", alpha=0.3)
        a.tick_params(labelsize=9)
    fig.tight_layout()
    return fig


def run(args: argparse.Namespace) -> int:
    """Run ``reachplan bench joints`` into ``args.out`` (CSV, PNG, summary); prints one line per variant.

    Parameters
    ----------
    args : argparse.Namespace
        ``out`` and ``quick`` of ``reachplan bench joints``.

    Returns
    -------
    int
        0 once the files are written.
    """
    s = settings(args, JointSettings(), QUICK)
    out: Path = args.out
    rows: list[dict[str, object]] = []
    summary: dict[str, object] = {}
    own, own_cal = DISCRETE_JOINTS, JOINTS_CALIBRATION
    for v in VARIANTS[: s.variants]:
        cal, vrows = calibrated_rows(v)
        rows += vrows
        if v.model is own and v.friction == (0.0, 0.0):
            own_cal = cal
        worst = max(abs(float(r["residual_mm"])) for r in vrows if r["role"] == "calibration")  # type: ignore[arg-type]
        thirty = next(float(r["residual_mm"]) for r in vrows if r["preset"] == "15ga-30j-tip")  # type: ignore[arg-type]
        summary[v.label] = {"worst_calibration_residual_mm": worst, "residual_30_joints_mm": thirty,
                            "joint_stiffness_scale": cal.joint_stiffness_scale,
                            "tube_arm_fraction": cal.tube_arm_fraction}
        print(f"{v.label}: calibration rows within {worst:.2f} mm, 15ga-30j-tip {thirty:+.2f} mm", flush=True)
    fam = family(s.family_points)
    d = preset("15ga-30j-tip", own_cal)
    times = []
    for _ in range(s.timing_repeats):
        t0 = time.perf_counter()
        own.solve(d, d.loads(9.9))
        times.append((time.perf_counter() - t0) * 1e3)
    write_csv(out / "joints_rows.csv", ROW_COLUMNS, rows)
    write_csv(out / "joints_family.csv", list(fam[0]), fam)
    write_csv(out / "joints_convergence.csv", ("check", "joints", "tube_step_mm", "tip_error_mm"), convergence())
    write_png(out / "joints_trend.png", figure(s.joint_counts, _trend(s.joint_counts, own_cal), fam))
    write_json(out / "summary.json", {"variants": summary, "median_solve_ms": statistics.median(times)})
    return 0
