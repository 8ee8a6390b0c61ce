"""A finding of the any-parameter, any-driver family, drawn: each parameter against its driver, the
partial residual as points and the fitted shape (every term of that parameter and driver summed)
as a line, so that a step, a bow, a knee or one value per level is seen, not only read."""
from __future__ import annotations

import textwrap

import numpy as np

__all__ = ["driver_panels", "driver_figure"]


def driver_panels(ev: dict) -> dict[str, dict]:
    """Evidence panels of ``parameter_drivers`` (mode label ``param~driver~shape`` -> plot data,
    see :func:`~torchcal.pipelines.loop.evidence.evidence_for`) merged per (parameter, driver):
    ``x``, the fitted shape (the terms' values summed) and the partial residual (what the model
    leaves plus that sum), in the parameter's unit."""
    groups: dict[str, list[dict]] = {}
    for label, e in ev.items():
        groups.setdefault("~".join(label.split("~")[:2]), []).append(e)
    out = {}
    for key, es in groups.items():
        n = len(es[0]["x"])
        es = [e for e in es if len(e["x"]) == n]  # a parameter's terms share its rows
        fitted = np.sum([np.asarray(e["fitted"], dtype=float) for e in es], 0)
        left = np.asarray(es[0]["residual"], dtype=float) - np.asarray(es[0]["fitted"], dtype=float)
        out[key] = {"x": np.asarray(es[0]["x"], dtype=float), "fitted": fitted, "residual": left + fitted,
                    "xlabel": es[0]["xlabel"], "ylabel": es[0]["ylabel"], "words": es[0]["words"]}
    return out


def driver_figure(ev: dict, path):
    """One panel per (parameter, driver) of a ``parameter_drivers`` finding (:func:`driver_panels`);
    the figure saved to ``path`` and returned (None when there is nothing to draw)."""
    panels = driver_panels(ev)
    if not panels:
        return None
    from torchcal.report.plotting import pyplot, save  # matplotlib only when a figure is drawn

    plt = pyplot()
    cols = min(3, len(panels))
    rows = (len(panels) + cols - 1) // cols
    fig, axes = plt.subplots(rows, cols, figsize=(4.4 * cols, 3.6 * rows), dpi=100, squeeze=False,
                             layout="constrained")
    for ax, (key, p) in zip(axes.flat, panels.items()):
        unit = p["ylabel"].split("[")[-1].rstrip("]") if "[" in p["ylabel"] else ""
        f = {"m": 1e3, "rad": 1e3}.get(unit, 1.0)
        shown = {"m": "mm", "rad": "mrad"}.get(unit, unit)
        order = np.argsort(p["x"], kind="stable")
        ax.scatter(p["x"], p["residual"] * f, s=6, alpha=0.45, label="partial residual")
        ax.plot(p["x"][order], p["fitted"][order] * f, color="C3", lw=1.4, label="fitted shape")
        ax.set_xlabel(textwrap.fill(p["xlabel"], 48), fontsize=8)
        ax.set_ylabel(f"{p['ylabel'].split(' [')[0]} [{shown}]", fontsize=8)
        ax.set_title(textwrap.fill(p["words"], 46), fontsize=9)
        ax.tick_params(labelsize=7)
    for ax in list(axes.flat)[len(panels):]:
        ax.axis("off")
    axes[0][0].legend(fontsize=7)
    fig.suptitle("parameters against their drivers", fontsize=10)
    return save(fig, path)
