"""Checks on a drawn figure's data that its texts are legible: none too small, none over another.

The report's figures are rendered at :data:`reachplan.planner.report.figures.DISPLAY_DPI` (one image pixel per CSS
pixel), so a text's size in points is its size on the screen; the tests run these checks on every figure the
report draws.
"""

from __future__ import annotations

from matplotlib.figure import Figure

from reachplan.planner.report.figures import MIN_FONT_PT


def text_overlaps(fig: Figure) -> list[tuple[str, str]]:
    """Return every two visible texts of a drawn figure whose boxes overlap, and every text the figure's edge cuts.

    The figure is drawn first (at its own dpi); each text's box is its rendered extent in pixels. Used by the tests
    on every report figure: no label may hide another (a hole's name under an orientation letter).

    Parameters
    ----------
    fig : matplotlib.figure.Figure
        The figure.

    Returns
    -------
    list of (str, str)
        The two texts of each overlapping pair, or a text and ``"the figure's edge"``; empty when all are clear.
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.text import Text

    canvas = FigureCanvasAgg(fig)
    canvas.draw()
    renderer = canvas.get_renderer()
    hidden = _undrawn_tick_labels(fig)
    texts = [t for t in fig.findobj(Text) if t.get_visible() and t.get_text().strip() and id(t) not in hidden]
    boxes = [(t.get_text(), t.get_window_extent(renderer)) for t in texts]
    boxes = [(n, b) for n, b in boxes if b.width > 0 and b.height > 0]
    width, height = fig.canvas.get_width_height()
    out = [(n, "the figure's edge") for n, b in boxes if b.x0 < -0.5 or b.y0 < -0.5 or b.x1 > width + 0.5
           or b.y1 > height + 0.5]
    for i, (na, a) in enumerate(boxes):
        for nb, b in boxes[i + 1:]:
            if a.x0 < b.x1 and b.x0 < a.x1 and a.y0 < b.y1 and b.y0 < a.y1:
                out.append((na, nb))
    return out


def _undrawn_tick_labels(fig: Figure) -> set[int]:
    """Return the ids of tick labels a drawn figure leaves out: their ticks lie outside the axis' view."""
    out: set[int] = set()
    for ax in fig.axes:
        for axis in (ax.xaxis, ax.yaxis):
            lo, hi = sorted(axis.get_view_interval())
            tol = 1e-9 * max(abs(lo), abs(hi), 1.0)
            for loc, tick in zip(axis.get_majorticklocs(), axis.get_major_ticks(), strict=False):
                if not lo - tol <= loc <= hi + tol:
                    out |= {id(tick.label1), id(tick.label2)}
            out |= {id(t.label1) for t in axis.get_minor_ticks()} | {id(t.label2) for t in axis.get_minor_ticks()}
    return out


def small_texts(fig: Figure, min_pt: float = MIN_FONT_PT) -> list[tuple[str, float]]:
    """Return the visible texts of a figure smaller than ``min_pt`` points (empty when every one is legible).

    Parameters
    ----------
    fig : matplotlib.figure.Figure
        The figure (rendered at :data:`DISPLAY_DPI`, so points are points on the screen).
    min_pt : float, pt
        The smallest legible size.

    Returns
    -------
    list of (str, float)
        Each too small text and its size in points.
    """
    from matplotlib.text import Text

    hidden = _undrawn_tick_labels(fig)
    return [(t.get_text(), float(t.get_fontsize())) for t in fig.findobj(Text) if id(t) not in hidden
            and t.get_visible() and t.get_text().strip() and float(t.get_fontsize()) < min_pt - 1e-9]
