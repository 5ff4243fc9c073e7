"""A self-contained HTML report built from plain data: text, tables and PNG figures.

Nothing here knows about plans: :mod:`reachplan.planner.report.build` turns a plan into a :class:`Report`, and
:func:`render_html` turns any :class:`Report` into one HTML document. Images are embedded as base64 PNG
data URIs and the style sheet is inline, so the file opens offline, from anywhere, in any browser. The only
script is plotly.js, embedded once when the report holds an :class:`Interactive` figure: the official gl3d
partial bundle (``plotly-gl3d.min.js`` beside this module, plotly.js 4.1.1, MIT licence in
``plotly-LICENSE.txt``; 1.75 MB against the full bundle's 4.8 MB), which has the 3-D traces the report draws. The
page's Content-Security-Policy lets it load nothing from outside.
"""

from __future__ import annotations

import base64
import html
import json
from dataclasses import dataclass, field
from importlib import resources
from typing import Any

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


@dataclass(frozen=True)
class Paragraph:
    """A paragraph of plain text (escaped when rendered).

    Parameters
    ----------
    text : str
        The text, without markup.
    """

    text: str


@dataclass(frozen=True)
class Table:
    """A table of text cells.

    Parameters
    ----------
    headers : tuple of str
        Column headings.
    rows : tuple of tuple of str
        The rows, one cell per heading.
    caption : str
        The table's caption (its summary when collapsed).
    numeric : tuple of int
        Indices of the columns to right-align.
    collapsed : bool
        Put the table in a closed ``<details>`` element (for long tables).

    Raises
    ------
    ValueError
        A row with another number of cells than the headers, or a numeric column out of range.
    """

    headers: tuple[str, ...]
    rows: tuple[tuple[str, ...], ...]
    caption: str = ""
    numeric: tuple[int, ...] = ()
    collapsed: bool = False

    def __post_init__(self) -> None:
        object.__setattr__(self, "headers", tuple(self.headers))
        object.__setattr__(self, "rows", tuple(tuple(r) for r in self.rows))
        for i, r in enumerate(self.rows):
            if len(r) != len(self.headers):
                raise ValueError(f"table {self.caption!r}: row {i} has {len(r)} cells, the header {len(self.headers)}")
        if any(not 0 <= c < len(self.headers) for c in self.numeric):
            raise ValueError(f"table {self.caption!r}: a numeric column index is out of range")


@dataclass(frozen=True, eq=False)
class Figure:
    """A PNG image with its caption.

    Parameters
    ----------
    png : bytes
        The image, PNG-encoded.
    caption : str
        Its caption.
    alt : str
        Alternative text (default: the caption).

    Raises
    ------
    ValueError
        ``png`` is not a PNG image.
    """

    png: bytes
    caption: str
    alt: str = ""

    def __post_init__(self) -> None:
        if not self.png.startswith(PNG_SIGNATURE):
            raise ValueError(f"figure {self.caption!r}: not a PNG image")


@dataclass(frozen=True, eq=False)
class Interactive:
    """A plotly.js figure with its caption.

    Parameters
    ----------
    figure : dict of str to object
        ``{"data": [...], "layout": {...}}``, JSON-ready.
    caption : str
        Its caption.

    Raises
    ------
    ValueError
        No ``data`` list of traces.
    """

    figure: dict[str, Any] = field(repr=False)
    caption: str

    def __post_init__(self) -> None:
        if not isinstance(self.figure.get("data"), list):
            raise ValueError(f"interactive figure {self.caption!r}: needs a 'data' list of traces")


Block = Paragraph | Table | Figure | Interactive


@dataclass(frozen=True, eq=False)
class Section:
    """A titled part of the report.

    Rendered as ``<section id="ANCHOR">`` with the title as its heading and the blocks in order.

    Parameters
    ----------
    title : str
        Its heading.
    anchor : str
        Its HTML id (letters, digits, ``-``).
    blocks : tuple of Block
        Paragraphs, tables and figures, in order.

    Raises
    ------
    ValueError
        An empty anchor or one with other characters.
    """

    title: str
    anchor: str
    blocks: tuple[Block, ...]

    def __post_init__(self) -> None:
        if not self.anchor or not all(ch.isalnum() or ch == "-" for ch in self.anchor):
            raise ValueError(f"section {self.title!r}: anchor must be letters, digits and '-', got {self.anchor!r}")
        object.__setattr__(self, "blocks", tuple(self.blocks))


@dataclass(frozen=True, eq=False)
class Report:
    """A whole report.

    Parameters
    ----------
    title : str
        The page's ``<title>`` and its ``<h1>`` heading (escaped).
    subtitle : str
        A one-line subtitle.
    sections : tuple of Section
        Its sections in order, anchors unique.
    statement : str
        A statement shown in the header, above everything (the research-use statement); "" for none.

    Raises
    ------
    ValueError
        Two sections with the same anchor.
    """

    title: str
    subtitle: str
    sections: tuple[Section, ...]
    statement: str = ""

    def __post_init__(self) -> None:
        anchors = [s.anchor for s in self.sections]
        if len(set(anchors)) != len(anchors):
            raise ValueError("report sections need unique anchors")
        object.__setattr__(self, "sections", tuple(self.sections))

    @property
    def figures(self) -> tuple[Figure, ...]:
        """Every figure, in document order."""
        return tuple(b for s in self.sections for b in s.blocks if isinstance(b, Figure))

    @property
    def interactive(self) -> tuple[Interactive, ...]:
        """Every interactive figure, in document order."""
        return tuple(b for s in self.sections for b in s.blocks if isinstance(b, Interactive))


STYLE = """
body { font: 14px/1.45 system-ui, -apple-system, "Segoe UI", Helvetica, Arial, sans-serif; color: #1d2330;
       margin: 0; background: #f5f6f8; }
header { background: #1d2b45; color: #fff; padding: 18px 32px; }
header h1 { margin: 0 0 4px 0; font-size: 24px; }
header p { margin: 0; opacity: 0.85; }
nav { padding: 8px 32px; background: #e8ebf0; font-size: 13px; }
nav a { margin-right: 14px; color: #1d2b45; }
main { padding: 8px 32px 40px 32px; max-width: 1400px; }
section { background: #fff; border-radius: 6px; padding: 6px 20px 16px 20px; margin: 16px 0;
          box-shadow: 0 1px 2px rgba(0,0,0,0.08); }
h2 { font-size: 19px; border-bottom: 1px solid #dde1e7; padding-bottom: 4px; }
.scroll { overflow-x: auto; }
table { border-collapse: collapse; margin: 8px 0 12px 0; font-size: 12.5px; }
caption { text-align: left; font-weight: 600; padding: 4px 0; }
th, td { border: 1px solid #d6dbe3; padding: 3px 7px; vertical-align: top; }
th { background: #eef1f5; text-align: left; }
td.num { text-align: right; font-variant-numeric: tabular-nums; }
tbody tr:nth-child(even) { background: #fafbfc; }
figure { margin: 10px 0 16px 0; }
figure img { max-width: 100%; height: auto; border: 1px solid #e1e4ea; }
.plot { width: 100%; min-height: 500px; border: 1px solid #e1e4ea; }
figcaption { font-size: 12.5px; color: #4a5263; margin-top: 4px; }
details summary { cursor: pointer; font-weight: 600; margin: 6px 0; }
footer { color: #6b7280; font-size: 12px; padding: 0 32px 24px 32px; }
header p.statement { opacity: 1; margin-top: 8px; padding: 6px 10px; background: #7a1010; font-weight: 600; }
"""


def _e(text: str) -> str:
    return html.escape(text, quote=True)


def _table(t: Table) -> str:
    head = "".join(f"<th>{_e(h)}</th>" for h in t.headers)
    body = []
    for row in t.rows:
        cells = "".join(f'<td class="num">{_e(c)}</td>' if i in t.numeric else f"<td>{_e(c)}</td>"
                        for i, c in enumerate(row))
        body.append(f"<tr>{cells}</tr>")
    caption = f"<caption>{_e(t.caption)}</caption>" if t.caption and not t.collapsed else ""
    out = (f'<div class="scroll"><table>{caption}<thead><tr>{head}</tr></thead>'
           f"<tbody>{''.join(body)}</tbody></table></div>")
    if t.collapsed:
        out = f"<details><summary>{_e(t.caption or 'table')}</summary>{out}</details>"
    return out


def _figure(f: Figure) -> str:
    data = base64.b64encode(f.png).decode("ascii")
    return (f'<figure><img src="data:image/png;base64,{data}" alt="{_e(f.alt or f.caption)}">'
            f"<figcaption>{_e(f.caption)}</figcaption></figure>")


def _script_json(value: Any) -> str:
    """JSON that is safe inside a <script> element."""
    return json.dumps(value, separators=(",", ":")).replace("</", "<\\/")


def _interactive(f: Interactive, div_id: str) -> str:
    config = {"displaylogo": False, "responsive": True}
    return (f'<figure><div id="{div_id}" class="plot"></div><script>Plotly.newPlot("{div_id}", '
            f'{_script_json(f.figure["data"])}, {_script_json(f.figure.get("layout", {}))}, '
            f"{_script_json(config)});</script><figcaption>{_e(f.caption)}</figcaption></figure>")


def _block(b: Block, div_id: str) -> str:
    if isinstance(b, Paragraph):
        return f"<p>{_e(b.text)}</p>"
    if isinstance(b, Table):
        return _table(b)
    if isinstance(b, Interactive):
        return _interactive(b, div_id)
    return _figure(b)


#: The plotly.js bundle embedded in the report (the trace types it has: mesh3d, scatter3d, scatter, surface, ...).
PLOTLY_BUNDLE = "plotly-gl3d.min.js"


def plotly_js() -> str:
    """Return the plotly.js gl3d partial bundle packaged beside this module (1.75 MB, minified).

    Returns
    -------
    str
        The script.
    """
    return (resources.files("reachplan.planner.report") / PLOTLY_BUNDLE).read_text(encoding="utf-8")


def render_html(report: Report, footer: str = "") -> str:
    """Render the report as one self-contained HTML5 document (no external resource; plotly.js inline when needed).

    Interactive figures get the ids ``plot-1``, ``plot-2``, ... in document order.

    Parameters
    ----------
    report : Report
        The report.
    footer : str
        The footer's text.

    Returns
    -------
    str
        The HTML document.

    Raises
    ------
    ValueError
        The plotly.js bundle contains ``</script`` and cannot be inlined.
    """
    nav = "".join(f'<a href="#{s.anchor}">{_e(s.title)}</a>' for s in report.sections)
    n_plots = 0
    parts = []
    for s in report.sections:
        blocks = []
        for b in s.blocks:
            n_plots += isinstance(b, Interactive)
            blocks.append(_block(b, f"plot-{n_plots}"))
        parts.append(f'<section id="{s.anchor}"><h2>{_e(s.title)}</h2>{"".join(blocks)}</section>')
    sections = "\n".join(parts)
    script_src = "script-src 'unsafe-inline'; " if n_plots else ""
    lib = ""
    if n_plots:
        js = plotly_js()
        if "</script" in js.casefold():  # would end the inline element early
            raise ValueError("this plotly.js bundle cannot be inlined: it contains '</script'")
        lib = f"<script>{js}</script>"
    return (
        "<!DOCTYPE html>\n"
        '<html lang="en"><head><meta charset="utf-8">'
        '<meta name="viewport" content="width=device-width, initial-scale=1">'
        f"<meta http-equiv=\"Content-Security-Policy\" content=\"default-src 'none'; {script_src}img-src data:; "
        "style-src 'unsafe-inline'\">"
        f"<title>{_e(report.title)}</title><style>{STYLE}</style>{lib}</head>\n"
        f"<body><header><h1>{_e(report.title)}</h1><p>{_e(report.subtitle)}</p>"
        + (f'<p class="statement" id="statement">{_e(report.statement)}</p>' if report.statement else "")
        + "</header>\n"
        f"<nav>{nav}</nav>\n<main>\n{sections}\n</main>\n"
        f"<footer>{_e(footer)}</footer></body></html>\n"
    )

