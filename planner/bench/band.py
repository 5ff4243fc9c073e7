"""Benchmark: the tissue band's rod model against the planner's reference rod (tip change, CPU per solve).

A steered needle's tissue band is its path plus the change of shape the in-tissue rod predicts when every modulus
is scaled (:mod:`reachplan.planner.steering.tissue_band`), computed on a coarse rod (``BAND_MODEL``). For ramps
from several onsets to 90 % of the stylet's limit and several tip depths, the change of the tip at the band's
scales (÷ 3 and × 3 of the gel) by the band model and by the reference (``PLANNER_REFERENCE``), their difference,
and the CPU time of each solve.

Run: ``reachplan bench band --out DIR [--quick] [--install]``. Writes ``tissue_band.csv`` (one row per case and
scale) and ``tissue_band.png`` (band model against reference; CPU per solve); ``--install`` copies both into
``docs/``.
"""

from __future__ import annotations

import argparse
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from matplotlib.figure import Figure

from reachplan.planner.bench._util import load_avg, write_csv
from reachplan.planner.bench.common import settings, write_png
from reachplan.planner.steering.insertion import SIMUGEL_MODULUS_PA
from reachplan.planner.steering.schedule import TensionSchedule
from reachplan.planner.steering.tissue_band import BAND_MODEL, ModulusBand, uniform_profile
from reachplan.planner.steering.tissue_rod import PLANNER_REFERENCE, TissueRodInsertion, forget_runs
from reachplan.rod_model.design import preset

INSTALLS = {"tissue_band.csv": "docs/tissue_band.csv", "tissue_band.png": "docs/tissue_band.png"}


@dataclass(frozen=True)
class BandSettings:
    """The cases of the comparison: one design, 5 mm ramps from each onset, tips at each depth (deeper than onset).

    Parameters
    ----------
    design : str
        Stylet preset.
    onsets_mm : tuple of float, mm
        Depths where the tension ramp starts.
    depths_mm : tuple of float, mm
        Tip depths (a case only when deeper than its onset + 20 mm).
    modulus_pa : float, Pa
        The planned modulus (the band's scales multiply it).
    factor : float
        The band's width (÷ / × factor).
    """

    design: str = "15ga-30j-tip"
    onsets_mm: tuple[float, ...] = (0.0, 40.0, 80.0)
    depths_mm: tuple[float, ...] = (90.0, 120.0, 150.0)
    modulus_pa: float = SIMUGEL_MODULUS_PA
    factor: float = 3.0


QUICK = BandSettings(onsets_mm=(20.0,), depths_mm=(45.0,))


def _tips(model: TissueRodInsertion, s: BandSettings, schedule: TensionSchedule, depth_mm: float,
          scales: tuple[float, ...]) -> tuple[np.ndarray, list[float]]:
    """Return the model's tip (mm, template frame) at each scale of the modulus, and each solve's CPU seconds."""
    tips, cpu = [], []
    for scale in scales:
        forget_runs()  # each solve timed from a cold memo: the models share runs at one step size
        t0 = time.process_time()
        path = model.insert_one(preset(s.design), schedule, depth_mm, uniform_profile(s.modulus_pa * scale))
        cpu.append(time.process_time() - t0)
        if not isinstance(path, np.ndarray):
            raise RuntimeError(f"{model.name} failed at x{scale:g}: {path.reason}")
        tips.append(path[-1])
    return np.array(tips), cpu


def compare(s: BandSettings) -> list[dict[str, float]]:
    """Return one row per case and non-nominal scale: each model's tip change (mm) and the CPU of its solves (s).

    Parameters
    ----------
    s : BandSettings
        The cases.

    Returns
    -------
    list of dict
        ``onset_mm``, ``depth_mm``, ``scale``, ``modulus_pa``, the reference's and the band model's tip change
        (``*_lateral_mm``, ``*_axial_mm``), ``difference_mm`` (their distance) and ``reference_cpu_s``,
        ``band_cpu_s`` (mean CPU per solve of the case).
    """
    design = preset(s.design)
    scales = ModulusBand(s.factor).scales
    rows: list[dict[str, float]] = []
    for onset in s.onsets_mm:
        for depth in (d for d in s.depths_mm if d >= onset + 20.0):
            schedule = TensionSchedule.ramp(onset, 5.0, 0.9 * design.max_tension_n, 0.0)
            ref, ref_cpu = _tips(PLANNER_REFERENCE, s, schedule, depth, scales)
            band, band_cpu = _tips(BAND_MODEL, s, schedule, depth, scales)
            mid = scales.index(1.0)
            for k, scale in enumerate(scales):
                if k == mid:
                    continue
                dr, db = ref[k] - ref[mid], band[k] - band[mid]
                rows.append({"onset_mm": onset, "depth_mm": depth, "scale": round(scale, 4),
                             "modulus_pa": round(s.modulus_pa * scale, 1),
                             "reference_lateral_mm": round(float(dr[0]), 3),
                             "reference_axial_mm": round(float(dr[2]), 3),
                             "band_lateral_mm": round(float(db[0]), 3), "band_axial_mm": round(float(db[2]), 3),
                             "difference_mm": round(float(np.linalg.norm(dr - db)), 3),
                             "reference_cpu_s": round(float(np.mean(ref_cpu)), 3),
                             "band_cpu_s": round(float(np.mean(band_cpu)), 3)})
    return rows


def _figure(rows: list[dict[str, float]]) -> Figure:
    fig = Figure(figsize=(10.0, 4.4))
    ax, bx = fig.subplots(1, 2)
    ref = np.array([float(r["reference_lateral_mm"]) for r in rows])
    band = np.array([float(r["band_lateral_mm"]) for r in rows])
    soft = np.array([float(r["scale"]) < 1 for r in rows])
    ax.plot(ref[soft], band[soft], "o", color="C0", label="softer (÷)")
    ax.plot(ref[~soft], band[~soft], "s", color="C3", label="stiffer (×)")
    lim = max(1e-3, float(np.max(np.abs(np.r_[ref, band])))) * 1.1
    ax.plot([-lim, lim], [-lim, lim], "k:", lw=1)
    ax.set_xlabel("reference rod: lateral tip change (mm)")
    ax.set_ylabel("band model: lateral tip change (mm)")
    ax.set_title("tip change over the modulus band", fontsize=10)
    ax.legend(fontsize=9)
    ax.grid(True, alpha=0.3)
    cases = sorted({(float(r["onset_mm"]), float(r["depth_mm"])) for r in rows})
    cpu = {c: next(r for r in rows if (r["onset_mm"], r["depth_mm"]) == c) for c in cases}
    x = np.arange(len(cases))
    bx.bar(x - 0.2, [float(cpu[c]["reference_cpu_s"]) for c in cases], 0.4, label="reference rod")
    bx.bar(x + 0.2, [float(cpu[c]["band_cpu_s"]) for c in cases], 0.4, label="band model")
    bx.set_xticks(x, [f"{o:.0f}→{d:.0f}" for o, d in cases], fontsize=9)
    bx.set_xlabel("ramp onset → tip depth (mm)")
    bx.set_ylabel("CPU per solve (s)")
    bx.set_title("cost of one insertion", fontsize=10)
    bx.legend(fontsize=9)
    fig.tight_layout()
    return fig


def run(args: argparse.Namespace) -> int:
    """Run ``reachplan bench band`` into ``args.out``: ``tissue_band.csv`` and ``tissue_band.png``.

    Parameters
    ----------
    args : argparse.Namespace
        ``out`` and ``quick`` of ``reachplan bench band``.

    Returns
    -------
    int
        0 once the CSV and chart are written.
    """
    s = settings(args, BandSettings(), QUICK)
    out: Path = args.out  # made by the bench command
    rows = compare(s)
    csv_rows: list[dict[str, object]] = [{**r} for r in rows]
    write_csv(out / "tissue_band.csv", csv_rows)
    write_png(out / "tissue_band.png", _figure(rows))
    ratio = np.median([float(r["reference_cpu_s"]) / max(float(r["band_cpu_s"]), 1e-9)
                       for r in rows])
    print(f"{len(rows)} band paths: band model within {max(float(r['difference_mm']) for r in rows):.3f} mm "
          f"of the reference's tip change; median CPU per solve {np.median([r['band_cpu_s'] for r in rows]):.3f} s "
          f"against {np.median([r['reference_cpu_s'] for r in rows]):.3f} s ({ratio:.1f}x; load {load_avg():.1f})")
    return 0
