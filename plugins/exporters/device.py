"""Device instructions for the handheld steerable stylet: per needle, its hole, stylet preset and schedule.

The user inserts the needle through its template hole and, along the insertion depth, holds the tendon
tension and the roll angle of the bending plane given in the rows (``oncoreach.md``, Actuation). Rows are
the needle's schedule breakpoints resampled piecewise-linearly every ``ExportOptions.step_mm`` from depth 0
(the entry, ``path_mm[0]``) to the tip (the path's arc length, always the last row); tension and roll are
constant before the first and after the last breakpoint. A needle without a schedule is a straight needle:
0 N throughout (said in the notes).

Two exporters:

``device_json``  one ``<stem>_device.json`` with every needle (format ``reachplan-device/1``)
``device_csv``   one ``<stem>_needle_<hole>.csv`` per needle: ``hole_id,stylet_preset,depth_mm,tension_n,roll_deg``

No patient identity is written into these files.
"""

from __future__ import annotations

import csv
import io
import json
from datetime import datetime
from pathlib import Path

import numpy as np

from reachplan.imaging.files import atomic_write_bytes
from reachplan.plugins.exporters import base
from reachplan.plugins.exporters.base import ExportedFile, ExportedFiles, ExportOptions, ExportPlan, NeedleExport

FORMAT = "reachplan-device/1"
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


def _notes(plan: ExportPlan) -> tuple[str, ...]:
    return tuple(f"needle {n.hole_id}: no schedule given, written as a straight needle (0 N)"
                 for n in plan.needles if n.schedule is None and not n.applicator)


def _r(x: float, nd: int) -> float:
    return float(round(float(x), nd)) + 0.0  # + 0.0 turns -0.0 into 0.0


def device_document(plan: ExportPlan, step_mm: float) -> dict[str, object]:
    """Build the JSON document (plain dict, format ``reachplan-device/1``) of the device instructions of ``plan``.

    Rows as in :func:`schedule_rows` every ``step_mm`` mm; depths in mm, tensions in N, rolls in degrees.
    Applicator channels (tandem, ring, ovoids) are placed by hand and get no rows; every needle keeps its channel
    number of the plan.
    """
    needles = []
    for k, n in enumerate(plan.needles, start=1):
        if n.applicator:
            continue
        rows = schedule_rows(n, step_mm)
        needles.append({
            "channel_number": k,
            "hole_id": n.hole_id,
            "stylet_preset": n.design,
            "insertion_depth_mm": _r(n.length_mm, 3),
            "rows": [{"depth_mm": _r(d, 3), "tension_n": _r(t, 4), "roll_deg": _r(r, 3)} for d, t, r in rows],
        })
    return {
        "format": FORMAT,
        "plan_label": plan.label,
        "created": datetime.now().replace(microsecond=0).isoformat(),
        "step_mm": step_mm,
        "depth": "insertion depth along the needle path from its entry at the template plane, mm",
        "tension": "tendon tension, N (the handheld only pulls)",
        "roll": "roll of the bending plane, degrees, template frame (0 = template +x, 90 = +y), not wrapped",
        "needles": needles,
    }


def _paths(plan: ExportPlan, out_dir: Path, options: ExportOptions | None,
           suffixes: list[str]) -> tuple[ExportOptions, list[Path]]:
    """Resolve the options and the file paths ``<stem><suffix>`` in ``out_dir``, checked for writing.

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
    """Write ``<stem>_device.json`` (all needles) into ``out_dir``; errors as in :func:`_paths`."""
    opts, (path,) = _paths(plan, out_dir, options, ["_device.json"])
    text = json.dumps(device_document(plan, opts.step_mm), indent=2, allow_nan=False) + "\n"
    atomic_write_bytes(path, text.encode("utf-8"))
    return ExportedFiles("device_json", (ExportedFile("device_json", path),), _notes(plan))


def export_device_csv(plan: ExportPlan, out_dir: Path, options: ExportOptions | None = None) -> ExportedFiles:
    """Write one ``<stem>_needle_<hole>.csv`` per needle (not per applicator channel) into ``out_dir``.

    Errors as in :func:`_paths`.
    """
    needles = [(k, n) for k, n in enumerate(plan.needles, 1) if not n.applicator]
    opts, paths = _paths(plan, out_dir, options, [
        f"_needle_{base.safe_name(n.hole_id, fallback=f'channel{k}')}.csv" for k, n in needles])
    for (_, n), path in zip(needles, paths, strict=True):
        buf = io.StringIO()
        w = csv.writer(buf, lineterminator="\n")
        w.writerow(COLUMNS)
        for d, t, r in schedule_rows(n, opts.step_mm):
            w.writerow([n.hole_id, n.design, _r(d, 3), _r(t, 4), _r(r, 3)])
        atomic_write_bytes(path, buf.getvalue().encode("utf-8"))
    return ExportedFiles("device_csv", tuple(ExportedFile("device_csv", p) for p in paths), _notes(plan))


JSON_EXPORTER: base.Exporter = base.FunctionExporter(
    "device_json", "stylet device instructions, one JSON file: per needle hole, preset and schedule rows",
    export_device_json)
CSV_EXPORTER: base.Exporter = base.FunctionExporter(
    "device_csv", "stylet device instructions, one CSV per needle: hole, preset, depth, tension, roll",
    export_device_csv)
