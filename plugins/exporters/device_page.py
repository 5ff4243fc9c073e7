"""The bedside page: the device instructions as one printable, self-contained HTML file (``<stem>_device.html``).

It leads with the research-use statement and the insert list (:class:`~reachplan.plugins.exporters.handoff.InsertList`:
the same rows the terminal and the report print), then per needle its tension schedule in words, its check depths
with the expected tip positions and, for a steered needle, the resampled rows the handheld follows
(:func:`~reachplan.plugins.exporters.device.schedule_rows`); then the applicator channels' length and curvature, every
channel's dwells and times, the rule at the tension limit and the perturbation model behind the margins. Print it
from a browser (A4, one needle per block; no scripts, no network). No patient identity is written.
"""

from __future__ import annotations

from collections.abc import Sequence
from datetime import datetime
from html import escape
from pathlib import Path

from reachplan.imaging.files import atomic_write_bytes
from reachplan.plugins.exporters import base
from reachplan.plugins.exporters.base import ExportedFile, ExportedFiles, ExportOptions, ExportPlan
from reachplan.plugins.exporters.device import dwell_rows, output_paths, schedule_rows, straight_notes
from reachplan.plugins.exporters.handoff import NUMERIC_COLUMNS, RESEARCH_USE, mm

_CSS = """
body { font-family: system-ui, sans-serif; font-size: 11pt; margin: 1.5em; color: #111; }
h1 { font-size: 16pt; margin: 0 0 .3em 0; } h2 { font-size: 13pt; margin: 1.2em 0 .3em 0; }
.statement { border: 2px solid #b00; padding: .5em .8em; font-weight: bold; color: #b00; }
table { border-collapse: collapse; margin: .4em 0; } th, td { border: 1px solid #999; padding: 2px 6px; }
th { background: #eee; text-align: left; } td.n { text-align: right; font-variant-numeric: tabular-nums; }
.needle { break-inside: avoid; page-break-inside: avoid; border-top: 1px solid #ccc; margin-top: .8em; }
p.small { font-size: 9.5pt; color: #333; }
@media print { body { margin: 0; } @page { size: A4; margin: 12mm; } }
"""


def _table(head: Sequence[str], rows: Sequence[Sequence[object]], cls: str = "", numeric: Sequence[int] = ()) -> str:
    """Return an HTML table; numbers and the ``numeric`` columns right-aligned."""
    def cell(i: int, v: object) -> str:
        right = isinstance(v, (int, float)) or i in numeric
        return f'<td class="n">{escape(str(v))}</td>' if right else f"<td>{escape(str(v))}</td>"

    th = "".join(f"<th>{escape(h)}</th>" for h in head)
    body = "".join("<tr>" + "".join(cell(i, v) for i, v in enumerate(r)) + "</tr>" for r in rows)
    return f'<table class="{cls}"><tr>{th}</tr>{body}</table>'


def _needle_block(plan: ExportPlan, k: int, step_mm: float) -> str:
    """One needle's block: schedule in words, check depths, the rows of a steered one."""
    n = plan.needles[k - 1]
    parts = [f'<div class="needle" id="needle-{escape(n.hole_id)}"><h2>Channel {k}: hole {escape(n.hole_id)}</h2>']
    item = next((x for x in plan.handoff.needles if x.hole_id == n.hole_id), None) if plan.handoff else None
    if item is not None:
        parts.append(f"<p><b>{escape(item.needle)}</b>; stylet {escape(item.stylet or 'plain (straight needle)')}; "
                     f"insert to <b>{item.depth_mm:.1f} mm</b>. Tension: {escape(item.schedule_text())}.</p>")
        parts.append(_table(("check depth (mm)", "when", "expected tip from the hole's line", "expected tip (mm, LPS)"),
                            [(round(c.depth_mm, 1), c.what,
                              f"{c.offset_mm:.1f} mm {c.toward}" if c.toward else "on the line",
                              ", ".join(mm(v) for v in c.tip_mm)) for c in item.checks]))
    else:
        parts.append(f"<p>Stylet {escape(n.design or 'plain')}; insert to <b>{n.length_mm:.1f} mm</b>.</p>")
    if item is not None and item.scenarios:
        parts.append(_table(("perturbation", "tip displacement (mm)", "clearance (mm)", "organ"),
                            [(s.label, round(s.reach_mm, 1), round(s.clearance_mm, 1), s.organ or "-")
                             for s in item.scenarios], "scenarios"))
    if n.schedule is not None:
        rows = schedule_rows(n, step_mm)
        parts.append(_table(("depth (mm)", "tension (N)", "roll (deg, template frame)"),
                            [(round(d, 1), round(t, 2), round(r, 1)) for d, t, r in rows], "rows"))
    parts.append("</div>")
    return "".join(parts)


def device_page(plan: ExportPlan, step_mm: float) -> str:
    """Return the printable page of ``plan``'s device instructions (module docstring).

    Parameters
    ----------
    plan : ExportPlan
        The plan, with its insert list when the planner made one.
    step_mm : float, mm
        Depth step of a steered needle's rows.

    Returns
    -------
    str
        A self-contained HTML document.
    """
    h = plan.handoff
    out = ['<!DOCTYPE html><html lang="en"><head><meta charset="utf-8">',
           f"<title>Device instructions: {escape(plan.label)}</title><style>{_CSS}</style></head><body>",
           f'<p class="statement" id="statement">{escape(h.statement if h else RESEARCH_USE)}</p>',
           f"<h1>Device instructions: {escape(plan.label)}</h1>",
           f'<p class="small">Written {datetime.now().replace(microsecond=0).isoformat()}. Depths are arc lengths '
           "beyond the template plane; tensions in N; roll of the bending plane in the template frame (0 = template "
           "+x, 90 = +y); directions in patient terms from the template pose.</p>"]
    if h is not None:
        out.append(f'<h2 id="insert-these">{escape(h.title())}</h2>')
        rows = h.rows()
        out.append(_table(rows[0], rows[1:], "insert", NUMERIC_COLUMNS))
        out.append(f'<p class="small">{escape(h.perturbations)}</p>')
        if h.tension_rule:
            out.append(f'<p id="tension-rule"><b>{escape(h.tension_rule)}</b></p>')
        out += [f"<p>{escape(a.text())}</p>" for a in h.applicators]
        out.append(f'<p class="small">{escape(h.obstacles)}</p>')
    out += [_needle_block(plan, k, step_mm) for k, n in enumerate(plan.needles, start=1) if not n.applicator]
    out.append('<h2 id="dwells">Every channel\'s dwells (per fraction)</h2>')
    out.append(_table(("channel", "name", "distance from tip (mm)", "time (s)"),
                      [(k, name + (" (applicator)" if a else ""), round(d, 1), round(t, 1))
                       for k, name, a, d, t in dwell_rows(plan)], "dwells"))
    out.append("</body></html>\n")
    return "".join(out)


def export_device_html(plan: ExportPlan, out_dir: Path, options: ExportOptions | None = None) -> ExportedFiles:
    """Write ``<stem>_device.html`` into ``out_dir``.

    Errors as in :func:`~reachplan.plugins.exporters.device.output_paths`.

    Parameters
    ----------
    plan : ExportPlan
        The plan.
    out_dir : Path
        The output folder.
    options : ExportOptions or None
        Stem, overwrite and step (the defaults when None).

    Returns
    -------
    ExportedFiles
        The page (role ``device_html``) and the notes.
    """
    opts, (path,) = output_paths(plan, out_dir, options, ["_device.html"])
    atomic_write_bytes(path, device_page(plan, opts.step_mm).encode("utf-8"))
    return ExportedFiles("device_html", (ExportedFile("device_html", path),), straight_notes(plan))


HTML_EXPORTER: base.Exporter = base.FunctionExporter(
    "device_html", "stylet device instructions as one printable HTML page: the insert list, check depths, each "
    "steered needle's rows, the tandem, every channel's dwells", export_device_html)
