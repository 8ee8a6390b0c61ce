"""Error statistics of a model on measured data, in mm: count, mean, standard deviation, max, RMS
and median, overall and per marker. One implementation for calibration stages, loop stages and reports."""
from __future__ import annotations

import torch
from torch import Tensor

__all__ = ["error_stats", "errors_by_marker"]


def error_stats(err_m: Tensor) -> dict:
    """Statistics of Euclidean errors given in metres, reported in millimetres."""
    e = err_m.detach().double().flatten() * 1e3
    if e.numel() == 0:
        return {"n": 0}
    return {"n": int(e.numel()), "mean_mm": float(e.mean()), "std_mm": float(e.std()) if e.numel() > 1 else 0.0,
            "max_mm": float(e.max()), "rmse_mm": float(torch.sqrt((e * e).mean())),
            "median_mm": float(e.median())}


def errors_by_marker(e: Tensor, marker: Tensor, marker_names: list[str]) -> dict:
    """:func:`error_stats` of errors ``e (n_obs,)`` (m), overall and per marker
    (``marker (n_obs,)`` indexes ``marker_names``)."""
    out = error_stats(e)
    per = {}
    for k, m in enumerate(marker_names):
        sel = marker == k
        if bool(sel.any()):
            per[m] = error_stats(e[sel])
    out["per_marker"] = per
    return out
