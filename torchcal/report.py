"""Error statistics, report files (JSON, Markdown) and plots for calibration results."""
from __future__ import annotations

import json
import math
from pathlib import Path

import torch
from torch import Tensor

__all__ = ["error_stats", "write_json", "histogram_figure"]


def error_stats(err_m: Tensor) -> dict:
    """Statistics of Euclidean errors given in metres, reported in millimetres."""
    e = err_m.detach().double().flatten() * 1e3
    if e.numel() == 0:
        return {"n": 0}
    return {"n": int(e.numel()), "mean_mm": float(e.mean()), "std_mm": float(e.std()) if e.numel() > 1 else 0.0,
            "max_mm": float(e.max()), "rmse_mm": float(torch.sqrt((e * e).mean())),
            "median_mm": float(e.median())}


def _clean(o):
    if isinstance(o, float) and not math.isfinite(o):
        return None
    if isinstance(o, dict):
        return {k: _clean(v) for k, v in o.items()}
    if isinstance(o, (list, tuple)):
        return [_clean(v) for v in o]
    if isinstance(o, Tensor):
        return _clean(o.tolist())
    return o


def write_json(path, obj) -> None:
    Path(path).write_text(json.dumps(_clean(obj), indent=2) + "\n")


def histogram_figure(stages: list[tuple[str, Tensor]], path, title: str = "Position error per observation",
                     split: str = "train") -> None:
    """One figure with overlaid error histograms (mm) for several stages, as calibration papers
    show them. ``stages``: (label, errors in m)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4), dpi=120)
    data = [(lab, e.detach().double().flatten().cpu().numpy() * 1e3) for lab, e in stages if e.numel()]
    if not data:
        plt.close(fig)
        return
    import numpy as np

    hi = max(float(d.max()) for _, d in data)
    lo = min(float(np.percentile(d[d > 0], 1)) if (d > 0).any() else hi for _, d in data)
    log = hi > 30 * max(lo, 1e-12)  # stages a thousandfold apart: only a log axis shows both
    bins = np.geomspace(max(lo, 1e-6) * 0.8, hi * 1.05, 50) if log else np.linspace(0, hi * 1.02 + 1e-12, 40)
    for lab, d in data:
        ax.hist(d, bins=bins, alpha=0.55, label=f"{lab}: mean {d.mean():.3f} mm, max {d.max():.3f} mm")
    if log:
        ax.set_xscale("log")
    ax.set_xlabel("Euclidean position error [mm]" + (" (log scale)" if log else ""))
    ax.set_ylabel("observations")
    ax.set_title(f"{title} ({split})")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
