"""Matplotlib for report figures, drawn without a display.

matplotlib stays off torchcal's import path (it costs about half a second and only figures need
it): :func:`pyplot` imports it on the first figure, with the non-interactive Agg backend. Every
figure module draws through it; :func:`overlapping_labels` is how figures (and their tests)
check that no two pieces of text sit on each other."""
from __future__ import annotations

__all__ = ["pyplot", "overlapping_labels", "save"]


def pyplot():
    """The ``matplotlib.pyplot`` module, set to the Agg backend."""
    import matplotlib

    matplotlib.use("Agg")
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


def _overlaps(fig, texts: list, pad: float) -> list[tuple]:
    canvas = fig.canvas
    if not hasattr(canvas, "get_renderer"):  # a figure pyplot has closed keeps a bare canvas
        from matplotlib.backends.backend_agg import FigureCanvasAgg

        canvas = FigureCanvasAgg(fig)
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


def save(fig, path) -> object:
    """Write ``fig`` as PNG to ``path``, free its memory and return it (its artists stay
    readable for checks). Where two tick labels collide (an x and a y tick meeting in an axes'
    corner), the later one is hidden: a tick label less reads better than two on each other."""
    plt = pyplot()
    for _ in range(3):  # hiding one may let the layout move the others
        clash = _overlaps(fig, _tick_labels(fig), 0.5)
        if not clash:
            break
        for _, b in clash:
            b.set_visible(False)
    fig.savefig(path)
    plt.close(fig)
    return fig
