"""Device instructions for the handheld steerable stylet: the insert list, each channel's dwells, each schedule.

The user inserts the needle through its template hole and, along the insertion depth, holds the tendon
tension and the roll angle of the bending plane given in the rows (``oncoreach.md``, Actuation). Rows are
the needle's schedule breakpoints resampled piecewise-linearly every ``ExportOptions.step_mm`` from depth 0
(the entry, ``path_mm[0]``) to the tip (the path's arc length, always the last row); tension and roll are
constant before the first and after the last breakpoint. A needle without a schedule is a straight needle: it gets
no rows (not rows of zeros), and the notes say so.

With the planner's insert list (``ExportPlan.handoff``, :mod:`reachplan.plugins.exporters.handoff`) the files lead
with it: per needle the hole, needle, stylet, depth, the schedule in words with the bending direction in patient
terms, the tension reserve, the robustness margins and the check depths; then the applicator channels' length and
curvature and the rule at the tension limit.

Three exporters (the third, the printable page, is :mod:`reachplan.plugins.exporters.device_page`):

``device_json``  one ``<stem>_device.json`` (format ``reachplan-device/2``): the research-use statement, the insert
                 list, every channel's dwells and times, and per steered needle its rows
``device_csv``   ``<stem>_insert_list.csv`` (one row per needle, with the insert list), ``<stem>_dwells.csv`` (every
                 channel's dwells: distance from the tip, time) and one ``<stem>_needle_<hole>.csv`` per steered
                 needle: ``hole_id,stylet_preset,depth_mm,tension_n,roll_deg``

No patient identity is written into these files.
"""

from __future__ import annotations

import csv
import io
import json
from collections.abc import Iterable, Sequence
from datetime import datetime
from pathlib import Path

import numpy as np

from reachplan.imaging.files import atomic_write_bytes
from reachplan.plugins.exporters import base
from reachplan.plugins.exporters.base import ExportedFile, ExportedFiles, ExportOptions, ExportPlan, NeedleExport
from reachplan.plugins.exporters.handoff import RESEARCH_USE

FORMAT = "reachplan-device/2"
COLUMNS = ("hole_id", "stylet_preset", "depth_mm", "tension_n", "roll_deg")


def schedule_rows(needle: NeedleExport, step_mm: float) -> np.ndarray:
    """Resample the needle's schedule at depths ``0, step, 2 step, ...`` and at the tip.

    Parameters
    ----------
    needle : NeedleExport
        Its schedule breakpoints (none: 0 N throughout) and path length.
    step_mm : float, mm
        Depth step, > 0.

    Returns
    -------
    (n, 3) float
        Rows ``(depth_mm, tension_n, roll_deg)``; depth along the path from its entry, the last row at the tip
        (``needle.length_mm``).

    Raises
    ------
    ValueError
        ``step_mm`` not positive.
    """
    if not step_mm > 0:
        raise ValueError("step_mm must be > 0")
    end = needle.length_mm
    depth = np.arange(0.0, end, step_mm)
    depth = np.append(depth[depth < end - 1e-6], end)
    bp = needle.schedule if needle.schedule is not None else np.zeros((1, 3))
    return np.column_stack([depth, np.interp(depth, bp[:, 0], bp[:, 1]), np.interp(depth, bp[:, 0], bp[:, 2])])


def straight_notes(plan: ExportPlan) -> tuple[str, ...]:
    """Return a note per straight needle (no schedule): it gets no tension rows.

    Parameters
    ----------
    plan : ExportPlan
        The plan.

    Returns
    -------
    tuple of str
        One note per template needle without a schedule.
    """
    return tuple(f"needle {n.hole_id}: no schedule given: a straight needle, no tension rows"
                 for n in plan.needles if n.schedule is None and not n.applicator)


def dwell_rows(plan: ExportPlan) -> list[tuple[int, str, bool, float, float]]:
    """Return every channel's dwells, tip first: ``(channel, name, applicator, distance from tip mm, time s)``.

    Parameters
    ----------
    plan : ExportPlan
        The plan; channel ``k`` (from 1) is ``plan.needles[k - 1]``.

    Returns
    -------
    list of (int, str, bool, float, float)
        One row per dwell position (times per fraction, s).
    """
    out = []
    for k, n in enumerate(plan.needles, start=1):
        dist = n.dwell_distance_from_tip_mm
        for i in np.argsort(dist, kind="stable"):
            out.append((k, n.hole_id, n.applicator, float(dist[i]), float(n.dwell_times_s[i])))
    return out


def _r(x: float, nd: int) -> float:
    return float(round(float(x), nd)) + 0.0  # + 0.0 turns -0.0 into 0.0


def device_document(plan: ExportPlan, step_mm: float) -> dict[str, object]:
    """Build the JSON document (plain dict, format ``reachplan-device/2``) of the device instructions of ``plan``.

    Rows as in :func:`schedule_rows` every ``step_mm`` mm for steered needles (none for straight ones); depths in mm,
    tensions in N, rolls in degrees. Applicator channels (tandem, ring, ovoids) are placed by hand and get no rows;
    every channel keeps its channel number of the plan and lists its dwells (distance from the tip, time).

    Parameters
    ----------
    plan : ExportPlan
        The plan, with its insert list when the planner made one.
    step_mm : float, mm
        Depth step of the rows.

    Returns
    -------
    dict
        JSON-ready: ``statement``, ``insert_list`` (None without one), ``needles``, ``channels``.
    """
    needles = []
    for k, n in enumerate(plan.needles, start=1):
        if n.applicator:
            continue
        rows = schedule_rows(n, step_mm) if n.schedule is not None else np.zeros((0, 3))
        needles.append({
            "channel_number": k,
            "hole_id": n.hole_id,
            "kind": "straight" if n.schedule is None else "steered",
            "stylet_preset": n.design or None,
            "insertion_depth_mm": _r(n.length_mm, 3),
            "rows": [{"depth_mm": _r(d, 3), "tension_n": _r(t, 4), "roll_deg": _r(r, 3)} for d, t, r in rows],
        })
    dwells = dwell_rows(plan)
    channels = [{"channel_number": k, "name": n.hole_id, "applicator": n.applicator,
                 "total_time_s": _r(float(n.dwell_times_s.sum()), 3),
                 "dwells": [{"distance_from_tip_mm": _r(d, 3), "time_s": _r(t, 3)}
                            for c, _, _, d, t in dwells if c == k]}
                for k, n in enumerate(plan.needles, start=1)]
    return {
        "format": FORMAT,
        "statement": plan.handoff.statement if plan.handoff is not None else RESEARCH_USE,
        "plan_label": plan.label,
        "created": datetime.now().replace(microsecond=0).isoformat(),
        "step_mm": step_mm,
        "depth": "insertion depth along the needle path from its entry at the template plane, mm",
        "tension": "tendon tension, N (the handheld only pulls)",
        "roll": "roll of the bending plane, degrees, template frame (0 = template +x, 90 = +y), not wrapped",
        "insert_list": None if plan.handoff is None else plan.handoff.to_json(),
        "needles": needles,
        "channels": channels,
    }


def output_paths(plan: ExportPlan, out_dir: Path, options: ExportOptions | None,
                 suffixes: list[str]) -> tuple[ExportOptions, list[Path]]:
    """Resolve the options and the file paths ``<stem><suffix>`` in ``out_dir``, checked for writing.

    Parameters
    ----------
    plan : ExportPlan
        The plan (its label is the default stem; its inputs are never written).
    out_dir : Path
        The output folder (created when missing).
    options : ExportOptions or None
        Stem and overwrite; the defaults when None.
    suffixes : list of str
        One file per suffix.

    Returns
    -------
    ExportOptions
        The options used.
    list of Path
        The files, in the order of ``suffixes``.

    Raises
    ------
    ExportError
        The output folder cannot be used, or a file may not be written (see
        :func:`~reachplan.plugins.exporters.base.check_targets`).
    """
    opts = options or ExportOptions()
    out, stem = base.prepare_out_dir(out_dir), base.file_stem(plan, opts)
    paths = [out / f"{stem}{suffix}" for suffix in suffixes]
    base.check_targets(paths, plan, opts)
    return opts, paths


def export_device_json(plan: ExportPlan, out_dir: Path, options: ExportOptions | None = None) -> ExportedFiles:
    """Write ``<stem>_device.json`` (all needles) into ``out_dir``; errors as in :func:`output_paths`."""
    opts, (path,) = output_paths(plan, out_dir, options, ["_device.json"])
    text = json.dumps(device_document(plan, opts.step_mm), indent=2, allow_nan=False) + "\n"
    atomic_write_bytes(path, text.encode("utf-8"))
    return ExportedFiles("device_json", (ExportedFile("device_json", path),), straight_notes(plan))


def _csv(rows: Iterable[Sequence[object]]) -> bytes:
    """Return rows as CSV text (UTF-8, newline-terminated)."""
    buf = io.StringIO()
    csv.writer(buf, lineterminator="\n").writerows(rows)
    return buf.getvalue().encode("utf-8")


def export_device_csv(plan: ExportPlan, out_dir: Path, options: ExportOptions | None = None) -> ExportedFiles:
    """Write the insert list, the dwells and one schedule CSV per steered needle into ``out_dir``.

    ``<stem>_insert_list.csv`` (only with the planner's insert list), ``<stem>_dwells.csv`` and
    ``<stem>_needle_<hole>.csv`` per steered needle (a straight one has no rows). Errors as in :func:`output_paths`.
    """
    steered = [(k, n) for k, n in enumerate(plan.needles, 1) if not n.applicator and n.schedule is not None]
    head = ["_insert_list.csv"] if plan.handoff is not None else []
    opts, paths = output_paths(plan, out_dir, options, [*head, "_dwells.csv", *(
        f"_needle_{base.safe_name(n.hole_id, fallback=f'channel{k}')}.csv" for k, n in steered)])
    written: list[ExportedFile] = []
    if plan.handoff is not None:
        details = {h: (words, checks) for h, words, checks in plan.handoff.details()}
        rows = plan.handoff.rows()
        table = [[*rows[0], "tension schedule", "check depths"],
                 *([*r, *details[r[1]]] for r in rows[1:])]
        atomic_write_bytes(paths[0], _csv(table))
        written.append(ExportedFile("device_insert_list", paths[0]))
    dwell_path = paths[len(head)]
    atomic_write_bytes(dwell_path, _csv([["channel", "name", "applicator", "distance_from_tip_mm", "time_s"],
                                         *([k, h, int(a), _r(d, 3), _r(t, 3)] for k, h, a, d, t in dwell_rows(plan))]))
    written.append(ExportedFile("device_dwells", dwell_path))
    for (_, n), path in zip(steered, paths[len(head) + 1:], strict=True):
        atomic_write_bytes(path, _csv([list(COLUMNS), *([n.hole_id, n.design, _r(d, 3), _r(t, 4), _r(r, 3)]
                                                         for d, t, r in schedule_rows(n, opts.step_mm))]))
        written.append(ExportedFile("device_csv", path))
    return ExportedFiles("device_csv", tuple(written), straight_notes(plan))


JSON_EXPORTER: base.Exporter = base.FunctionExporter(
    "device_json", "stylet device instructions, one JSON file: the insert list, each channel's dwells, each steered "
    "needle's schedule rows",
    export_device_json)
CSV_EXPORTER: base.Exporter = base.FunctionExporter(
    "device_csv", "stylet device instructions as CSV: the insert list, every channel's dwells, one schedule per "
    "steered needle (hole, preset, depth, tension, roll)",
    export_device_csv)
