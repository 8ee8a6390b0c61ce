"""Matplotlib for report figures, drawn without a display and without pyplot.

matplotlib stays off torchcal's import path (it costs about half a second and only figures need
it). A figure here is a bare :class:`matplotlib.figure.Figure` on an Agg canvas (:func:`figure`,
:func:`subplots`), laid out by constrained layout: no global backend is chosen or changed, so a
notebook's ``MPLBACKEND`` (``module://matplotlib_inline.backend_inline``) neither breaks a report
nor is switched off by one. :func:`save` draws a figure once and writes those pixels; :func:`overlapping_labels` is how
figures (and their tests) check that no two pieces of text sit on each other."""
from __future__ import annotations

import importlib.util
import os
import sys

__all__ = ["figure", "subplots", "pyplot", "overlapping_labels", "save"]


def _matplotlib():
    """``matplotlib``, imported so that an ``MPLBACKEND`` naming a module this interpreter does not
    have (a notebook kernel's, leaked into a shell) does not make the import fail: report figures
    never use that backend."""
    if "matplotlib" in sys.modules:
        return sys.modules["matplotlib"]
    wanted = os.environ.get("MPLBACKEND", "")
    missing = wanted.startswith("module://") and importlib.util.find_spec(wanted[9:].split(".")[0]) is None
    if missing:
        del os.environ["MPLBACKEND"]
    try:
        import matplotlib
    finally:
        if missing:
            os.environ["MPLBACKEND"] = wanted
    return matplotlib


def figure(figsize: tuple[float, float], dpi: float = 100, layout: str | None = "constrained"):
    """A new figure of ``figsize`` inches on its own Agg canvas, constrained layout by default."""
    _matplotlib()
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=figsize, dpi=dpi, layout=layout)
    FigureCanvasAgg(fig)
    return fig


def subplots(nrows: int = 1, ncols: int = 1, *, figsize: tuple[float, float], dpi: float = 100,
             layout: str | None = "constrained", **kw):
    """``(figure, axes)`` as ``pyplot.subplots`` gives them, on an Agg canvas (see :func:`figure`)."""
    fig = figure(figsize, dpi, layout)
    return fig, fig.subplots(nrows, ncols, **kw)


def pyplot():
    """The ``matplotlib.pyplot`` module, on the Agg backend unless pyplot is already in use (a
    notebook's own backend is left alone). Report figures use :func:`subplots` instead."""
    mpl = _matplotlib()
    if "matplotlib.pyplot" not in sys.modules:
        mpl.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _texts(fig) -> list:
    """Every visible, non-empty text of a figure: titles, axis and tick labels, annotations,
    legend entries."""
    from matplotlib.text import Text

    out, seen = [], set(_idle_tick_labels(fig))
    for t in fig.findobj(Text):
        if id(t) not in seen and t.get_visible() and t.get_text().strip() and t.figure is fig:
            seen.add(id(t))
            out.append(t)
    return out


def _idle_tick_labels(fig) -> list[int]:
    """Ids of the tick labels an axis keeps but does not draw (their tick lies outside the view)."""
    out = []
    for ax in fig.axes:
        for axis in (ax.xaxis, ax.yaxis):
            lo, hi = sorted(axis.get_view_interval())
            tol = 1e-9 * max(abs(lo), abs(hi), 1.0)
            for tick in axis.get_major_ticks() + axis.get_minor_ticks():
                if not lo - tol <= tick.get_loc() <= hi + tol:
                    out += [id(tick.label1), id(tick.label2)]
    return out


def _canvas(fig):
    if not hasattr(fig.canvas, "get_renderer"):  # a figure pyplot has closed keeps a bare canvas
        from matplotlib.backends.backend_agg import FigureCanvasAgg

        FigureCanvasAgg(fig)
    return fig.canvas


def _overlaps(fig, texts: list, pad: float, draw: bool = True) -> list[tuple]:
    """Pairs of ``texts`` whose boxes overlap by more than ``pad`` pixels; ``draw=False`` reads the
    boxes of the last drawing (the one :func:`save` just made) instead of drawing again."""
    canvas = _canvas(fig)
    if draw:
        canvas.draw()
    r = canvas.get_renderer()
    boxes = [(t, t.get_window_extent(r)) for t in texts if t.get_visible()]
    bad = []
    for i, (a, ba) in enumerate(boxes):
        for b, bb in boxes[i + 1:]:
            w = min(ba.x1, bb.x1) - max(ba.x0, bb.x0)
            h = min(ba.y1, bb.y1) - max(ba.y0, bb.y0)
            if w > pad and h > pad:
                bad.append((a, b))
    return bad


def overlapping_labels(fig, pad: float = 0.5) -> list[tuple[str, str]]:
    """Pairs of texts of ``fig`` whose boxes overlap by more than ``pad`` pixels, once drawn;
    empty when every label can be read."""
    return [(a.get_text(), b.get_text()) for a, b in _overlaps(fig, _texts(fig), pad)]


def _tick_labels(fig) -> list:
    idle = set(_idle_tick_labels(fig))
    out = []
    for ax in fig.axes:
        out += [t for t in ax.get_xticklabels() + ax.get_yticklabels() if t.get_text().strip() and id(t) not in idle]
    return out


def _write_png(canvas, path) -> None:
    """The pixels ``canvas`` holds as a PNG: ``savefig`` would lay the figure out and draw it again."""
    from PIL import Image

    w, h = canvas.get_width_height(physical=True)
    Image.frombuffer("RGBA", (w, h), canvas.buffer_rgba(), "raw", "RGBA", 0, 1).save(path, format="png")


def save(fig, path) -> object:
    """Write ``fig`` as PNG to ``path`` and return it (its artists stay readable for checks).

    One drawing, which lays the figure out (constrained layout) and renders it; its pixels are
    written as they are. Where that drawing shows two tick labels on each other (an x and a y
    tick meeting in an axes' corner), the later one is hidden and the figure drawn again: a tick
    label less reads better than two on each other."""
    canvas = _canvas(fig)
    canvas.draw()
    clash = _overlaps(fig, _tick_labels(fig), 0.5, draw=False)
    if clash:
        for _, b in clash:
            b.set_visible(False)
        canvas.draw()
    _write_png(canvas, path)
    if "matplotlib.pyplot" in sys.modules:  # a figure made through pyplot() is freed there too
        sys.modules["matplotlib.pyplot"].close(fig)
    return fig
