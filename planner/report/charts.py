"""Charts of the HTML report: rod models' speed against accuracy, DVHs with the aims, implant Pareto curves.

Drawn on :class:`matplotlib.figure.Figure` objects, not pyplot, like :mod:`reachplan.planner.report.figures`
(whose colours and PNG writer they share). The functions ending in ``_figure`` return the figure (tests read its
coordinates); the others return PNG bytes.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
from matplotlib.figure import Figure
from matplotlib.lines import Line2D
from matplotlib.ticker import MaxNLocator

from reachplan.planner.report.figures import (
    MIN_FONT_PT,
    STEERED_COLOUR,
    STRAIGHT_COLOUR,
    TITLE_Y,
    organ_colour,
    png_bytes,
)


def speed_accuracy(rows: Sequence[Any], used: Mapping[str, str]) -> bytes:
    """Rod models: median time per solve against worst tip error (log-log), from the measured error table.

    Parameters
    ----------
    rows : sequence of ErrorRow
        The packaged benchmark table (``rod_model/model_errors.json``, :class:`reachplan.rod_model.select.ErrorRow`).
    used : mapping of str to str
        Rod model name -> how this plan used it (e.g. ``"screening"``); the registered (``default``) configuration
        of these models is ringed and labelled.

    Returns
    -------
    bytes
        PNG (ms against mm).
    """
    floor = 1e-10
    fig = Figure(figsize=(8.5, 5.4))
    ax = fig.add_subplot()
    models = list(dict.fromkeys(r.model for r in rows))
    for i, name in enumerate(models):
        pts = sorted((r for r in rows if r.model == name), key=lambda r: r.median_ms)
        ax.plot([r.median_ms for r in pts], [max(r.max_tip_error_mm, floor) for r in pts],
                "o-" if len(pts) > 1 else "o", color=f"C{i}", label=name, ms=6)
        for r in pts:
            if r.resolution == "default" and name in used:
                y = max(r.max_tip_error_mm, floor)
                ax.scatter([r.median_ms], [y], s=260, facecolors="none", edgecolors="k", lw=1.5, zorder=5)
                ax.annotate(f"{name}: {used[name]}\n{r.median_ms:.2f} ms, max error {r.max_tip_error_mm:.2g} mm",
                            (r.median_ms, y), xytext=(12, -4), textcoords="offset points", fontsize=MIN_FONT_PT,
                            bbox={"boxstyle": "round", "fc": "#fffbe6", "ec": "#c9b458"})
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("median time per solve (ms, log)")
    ax.set_ylabel(f"max tip error vs converged two-tube reference (mm; floor {floor:g})")
    ax.set_title("Rod models: speed vs accuracy (ringed: used in this plan)", fontsize=11, y=TITLE_Y)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=MIN_FONT_PT, loc="upper right")
    fig.subplots_adjust(left=0.1, right=0.97, top=0.93, bottom=0.1)  # fixed margins: no tight-layout pass
    return png_bytes(fig)


#: Line style of each implant arm in the shared figures (steered solid, straight dashed, as the needles).
ARM_STYLES = {"straight": "--", "steered": "-"}


def _dvh_curves(ax: Any, dvhs: Sequence[tuple[str, Any]], aims: Any, target: str, style: str = "-",
                arm: str = "", marks: bool = True) -> None:
    """Draw cumulative DVHs (log volume) on ``ax``; with ``marks`` the D90 aim and the organ limits.

    Curves carry the gid ``dvh:NAME`` (``dvh:ARM:NAME``, and no legend label, when ``arm`` is given); the
    target's is drawn thicker.
    """
    for name, dvh in dvhs:
        colour = organ_colour(name)
        v = np.maximum(np.asarray(dvh.volume_cc, dtype=float), 1e-3)
        ax.plot(dvh.dose_gy, v, style, color=colour, lw=2.2 if name == target else 1.4,
                label="_nolegend_" if arm else name, gid=f"dvh:{arm}:{name}" if arm else f"dvh:{name}")
        if not marks:
            continue
        if name == target:
            ax.plot([aims.prescription_gy], [0.9 * v[0]], "D", color=colour, mec="k", ms=8, gid="aim:D90",
                    label=f"{name} D90 aim ({aims.target_d90_eqd2_gy:g} Gy EQD2)")
        elif (limit := aims.oar_gy(name)) is not None:
            ax.plot([limit], [2.0], "X", color=colour, mec="k", ms=9, gid=f"limit:{name}",
                    label=f"{name} D2cm³ limit")


def _dvh_frame(fig: Figure, ax: Any, aims: Any, title: str, ncol: int = 3, extra: Sequence[Line2D] = ()) -> Figure:
    """Axes, title and the legend below (``extra`` handles first) of a DVH figure, at fixed margins."""
    ax.axvline(aims.prescription_gy, color="grey", lw=0.8, ls=":")
    ax.set_yscale("log")
    ax.set_xlim(0, 3 * aims.prescription_gy)
    ax.set_ylim(0.1, None)
    ax.set_xlabel("dose per fraction (Gy)")
    ax.set_ylabel("volume receiving at least the dose (cm³, log)")
    ax.set_title(f"cumulative DVH, {title}\n◆ the target's curve must pass right of its aim, "
                 "✕ an organ's curve left of its limit", fontsize=10, y=TITLE_Y)
    ax.grid(True, which="both", alpha=0.25)
    handles, labels = ax.get_legend_handles_labels()
    handles, labels = [*extra, *handles], [*(h.get_label() for h in extra), *labels]
    fig.legend(handles, labels, fontsize=MIN_FONT_PT, ncol=ncol, loc="lower center", frameon=False)
    rows = (len(labels) + ncol - 1) // ncol
    height_in = fig.get_size_inches()[1]
    fig.subplots_adjust(left=0.1, right=0.97, top=1 - 0.6 / height_in,
                        bottom=(0.66 + 0.2 * rows) / height_in)  # fixed margins: no tight-layout pass
    return fig


def dvh_aims_figure(dvhs: Sequence[tuple[str, Any]], aims: Any, target: str = "HR-CTV",
                    title: str = "delivered plan") -> Figure:
    """Cumulative DVHs of one plan (volume in cm³, log scale, against Gy per fraction) with the aims marked.

    Parameters
    ----------
    dvhs : sequence of (str, Dvh)
        Structure name and its :class:`reachplan.planner.dose.coverage.Dvh` (Gy per fraction, cm³).
    aims : Aims
        :class:`reachplan.planner.dose.aims.Aims`: its D90 aim becomes a diamond at (prescription, 90 % of the
        target volume) that the target's curve must pass to the right of; each organ limit a cross at (D2cm³ limit
        per fraction, 2 cm³) that the organ's curve must pass to the left of.
    target : str
        The target's structure name (drawn thicker).
    title : str
        The axes' title.

    Returns
    -------
    matplotlib.figure.Figure
    """
    fig = Figure(figsize=(7.5, 5.6))
    ax = fig.add_subplot()
    _dvh_curves(ax, dvhs, aims, target)
    return _dvh_frame(fig, ax, aims, title)


def implant_dvh_figure(arms: Sequence[Any], aims: Any, target: str = "HR-CTV",
                       whole: Mapping[str, Sequence[tuple[str, Any]]] | None = None) -> Figure:
    """Both implant arms' cumulative DVHs on one axes, the arms told apart by line style (:data:`ARM_STYLES`).

    Parameters
    ----------
    arms : sequence of ImplantArm
        :class:`reachplan.planner.implant.arms.ImplantArm`: each arm with a chosen plan contributes its ``plan.dvhs``
        (Gy per fraction, cm³); curves carry the gid ``dvh:ARM:NAME``.
    aims : Aims
        :class:`reachplan.planner.dose.aims.Aims`, marked as in :func:`dvh_aims_figure` (once: the marks do not
        depend on the arm).
    target : str
        The target's structure name (drawn thicker, its D90 aim marked).
    whole : mapping of str to sequence of (str, Dvh), optional
        By arm name, whole-structure DVHs on one grid (:attr:`reachplan.planner.delivery.Delivery.whole_dvhs`)
        drawn instead of the arm's own (which cover the voxels near its dwells only).

    Returns
    -------
    matplotlib.figure.Figure
    """
    fig = Figure(figsize=(8.0, 5.6))
    ax = fig.add_subplot()
    curves = {a.name: (whole[a.name] if whole is not None and a.name in whole else a.plan.dvhs) for a in arms
              if a.plan is not None and a.plan.dvhs}
    with_plan = [a for a in arms if a.name in curves]
    for i, a in enumerate(with_plan):
        _dvh_curves(ax, curves[a.name], aims, target, ARM_STYLES.get(a.name, ":"), a.name, marks=i == 0)
    names = list(dict.fromkeys(n for a in with_plan for n, _ in curves[a.name]))
    extra = [Line2D([], [], color="k", ls=ARM_STYLES.get(a.name, ":"), label=f"{a.name} arm") for a in with_plan]
    extra += [Line2D([], [], color=organ_colour(n), lw=2.2 if n == target else 1.4, label=n) for n in names]
    return _dvh_frame(fig, ax, aims, "implant arms (" + ", ".join(
        f"{a.name}: {'solid' if ARM_STYLES.get(a.name) == '-' else 'dashed'}" for a in with_plan) + ")", ncol=4,
        extra=extra)


def pareto_figure(arms: Sequence[Any], aim_gy: float) -> Figure:
    """Draw the implant arms' Pareto curves on one axes: needles against HR-CTV D90 (EQD2, Gy), organ limits held.

    Parameters
    ----------
    arms : sequence of ImplantArm
        :class:`reachplan.planner.implant.arms.ImplantArm`: each arm's ``pareto`` points are one curve (gid
        ``pareto:ARM``), the points that meet every aim filled (gid ``met:ARM``) and the others hollow
        (``unmet:ARM``); the chosen plan (``plan.n_needles``, ``plan.target.d90_eqd2_gy``) is circled (gid
        ``chosen:ARM``).
    aim_gy : float, Gy
        The HR-CTV D90 aim (EQD2; EMBRACE II: 85 Gy), a horizontal line (gid ``aim:D90``).

    Returns
    -------
    matplotlib.figure.Figure
    """
    fig = Figure(figsize=(7.5, 4.6))
    ax = fig.add_subplot()
    colours = {"straight": STRAIGHT_COLOUR, "steered": STEERED_COLOUR}
    for i, a in enumerate(arms):
        colour = colours.get(a.name, f"C{i}")
        ms = 10 if i == 0 else 6  # the first arm's markers are larger: coinciding points stay visible
        n = np.array([p.n_needles for p in a.pareto], dtype=float)
        d90 = np.array([p.hrctv_d90_eqd2_gy for p in a.pareto], dtype=float)
        met = np.array([p.aims_met for p in a.pareto], dtype=bool)
        ax.plot(n, d90, ARM_STYLES.get(a.name, ":"), color=colour, lw=1.6, label=f"{a.name} arm",
                gid=f"pareto:{a.name}")
        ax.plot(n[met], d90[met], "o", color=colour, mec="k", ms=ms, ls="", gid=f"met:{a.name}", label="_nolegend_")
        ax.plot(n[~met], d90[~met], "o", mfc="none", mec=colour, mew=1.6, ms=ms, ls="", gid=f"unmet:{a.name}",
                label="_nolegend_")
        if a.plan is not None:
            ax.plot([a.plan.n_needles], [a.plan.target.d90_eqd2_gy], "o", mfc="none", mec="k", mew=1.5,
                    ms=ms + 10, ls="", gid=f"chosen:{a.name}", label="_nolegend_")
    ax.axhline(aim_gy, color="#d62728", lw=1.0, ls=":", gid="aim:D90", label=f"D90 aim {aim_gy:g} Gy EQD2")
    handles, _ = ax.get_legend_handles_labels()
    handles += [Line2D([], [], marker="o", ls="", color="#888888", mec="k", label="every aim met"),
                Line2D([], [], marker="o", ls="", mfc="none", mec="#888888", mew=1.6, label="an aim not met"),
                Line2D([], [], marker="o", ls="", mfc="none", mec="k", ms=14, label="chosen implant")]
    ax.set_xlabel("template needles loaded")
    ax.xaxis.set_major_locator(MaxNLocator(integer=True))
    ax.set_ylabel("HR-CTV D90 (Gy EQD2), organ limits held")
    ax.set_title("Implant: needles against HR-CTV D90, straight against steered", fontsize=10, y=TITLE_Y)
    ax.grid(True, alpha=0.3)
    ax.legend(handles=handles, fontsize=MIN_FONT_PT, loc="center left", bbox_to_anchor=(1.02, 0.5))
    fig.subplots_adjust(left=0.1, right=0.72, top=0.92, bottom=0.12)  # fixed margins: no tight-layout pass
    return fig


def dvh_png(comparison: Any) -> bytes:
    """Render the DVH figure of a :class:`reachplan.planner.implant.compare.Comparison` as PNG bytes.

    Parameters
    ----------
    comparison : Comparison
        The straight-versus-steered comparison.

    Returns
    -------
    bytes
        PNG at the report's display resolution.
    """
    return png_bytes(comparison.figure())
