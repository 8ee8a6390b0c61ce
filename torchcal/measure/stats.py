"""Error statistics of a model on measured data, in mm: count, mean, standard deviation, max, RMS
and median, overall and per marker. One implementation for calibration stages, loop stages and reports."""
from __future__ import annotations

import torch
from torch import Tensor

__all__ = ["error_stats", "angle_stats", "errors_by_marker", "errors_by_marker_batched"]


def error_stats(err_m: Tensor) -> dict:
    """Statistics of Euclidean errors given in metres, reported in millimetres."""
    e = err_m.detach().double().flatten() * 1e3
    if e.numel() == 0:
        return {"n": 0}
    return {"n": int(e.numel()), "mean_mm": float(e.mean()), "std_mm": float(e.std()) if e.numel() > 1 else 0.0,
            "max_mm": float(e.max()), "rmse_mm": float(torch.sqrt((e * e).mean())),
            "median_mm": float(e.median())}


def angle_stats(err_rad: Tensor) -> dict:
    """Statistics of orientation errors given in radians, reported in milliradians (the keys of
    :func:`error_stats`, ``_mrad`` for ``_mm``)."""
    return {k.replace("_mm", "_mrad"): v for k, v in error_stats(err_rad).items()}


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


def _masked_stats(e: Tensor, mask: Tensor) -> list[dict]:
    """:func:`error_stats` of each row of ``e (B, n)`` (mm) over its ``mask``: one pass per statistic
    for all rows, the same definitions (unbiased std, lower median)."""
    n = mask.sum(-1)
    w = mask.to(e.dtype)
    nn = n.clamp(min=1).to(e.dtype)
    mean = (e * w).sum(-1) / nn
    d = (e - mean[:, None]) * w
    std = torch.where(n > 1, torch.sqrt((d * d).sum(-1) / (n - 1).clamp(min=1).to(e.dtype)), torch.zeros_like(mean))
    mx = torch.where(mask, e, torch.full_like(e, -float("inf"))).amax(-1)
    rmse = torch.sqrt((e * e * w).sum(-1) / nn)
    srt = torch.where(mask, e, torch.full_like(e, float("inf"))).sort(-1).values
    med = srt.gather(-1, ((n - 1).clamp(min=0) // 2)[:, None])[:, 0]
    cols = [c.tolist() for c in (n, mean, std, mx, rmse, med)]
    return [{"n": int(k), "mean_mm": a, "std_mm": b, "max_mm": c, "rmse_mm": r, "median_mm": m} if k else {"n": 0}
            for k, a, b, c, r, m in zip(*cols)]


def errors_by_marker_batched(e: Tensor, seen: Tensor, marker_names: list[str]) -> list[dict]:
    """:func:`errors_by_marker` of many data sets at once: errors ``e (B, N, M)`` (m) of ``M``
    markers at ``N`` rows, ``seen (B, N, M)`` the real observations. One dict per data set."""
    B, N, M = e.shape
    mm = e.detach().double() * 1e3
    out = _masked_stats(mm.reshape(B, N * M), seen.reshape(B, N * M))
    per = [_masked_stats(mm[:, :, k], seen[:, :, k]) for k in range(M)]
    for b in range(B):
        out[b]["per_marker"] = {m: per[k][b] for k, m in enumerate(marker_names) if per[k][b]["n"]}
    return out
