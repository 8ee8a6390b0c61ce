"""Error statistics of a model on measured data, in mm: count, mean, standard deviation, max, RMS,
median and 95th percentile (linear interpolation, numpy's default), overall and per marker. One implementation for calibration stages, loop stages and reports."""
from __future__ import annotations

import math
from dataclasses import replace

import torch
from torch import Tensor

from torchcal.measure.records import ErrorStats

__all__ = ["error_stats", "angle_stats", "errors_by_marker", "errors_by_marker_batched", "noise_floor", "chi2_sf", "chi2_isf"]


def error_stats(err_m: Tensor, unit: str = "mm") -> ErrorStats:
    """Statistics of Euclidean errors given in metres (or radians), reported in millimetres (or,
    with ``unit="mrad"``, milliradians)."""
    e = err_m.detach().double().flatten() * 1e3
    if e.numel() == 0:
        return ErrorStats(n=0, unit=unit)
    return ErrorStats(n=int(e.numel()), mean=float(e.mean()), std=float(e.std()) if e.numel() > 1 else 0.0,
                      max=float(e.max()), rmse=float(torch.sqrt((e * e).mean())), median=float(e.median()),
                      p95=float(torch.quantile(e, 0.95)), unit=unit)


def angle_stats(err_rad: Tensor) -> ErrorStats:
    """Statistics of orientation errors given in radians, reported in milliradians."""
    return error_stats(err_rad, unit="mrad")


def errors_by_marker(e: Tensor, marker: Tensor, marker_names: list[str]) -> ErrorStats:
    """:func:`error_stats` of errors ``e (n_obs,)`` (m), overall and per marker
    (``marker (n_obs,)`` indexes ``marker_names``)."""
    per = {}
    for k, m in enumerate(marker_names):
        sel = marker == k
        if bool(sel.any()):
            per[m] = error_stats(e[sel])
    return replace(error_stats(e), per_marker=per)


def _masked_stats(e: Tensor, mask: Tensor) -> list[ErrorStats]:
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
    pos = (n - 1).clamp(min=0).to(e.dtype) * 0.95  # torch.quantile's linear interpolation
    lo = pos.floor().long()
    hi = torch.minimum(lo + 1, (n - 1).clamp(min=0))
    a_lo, a_hi = srt.gather(-1, lo[:, None])[:, 0], srt.gather(-1, hi[:, None])[:, 0]
    p95 = a_lo + (pos - lo.to(e.dtype)) * torch.where(hi > lo, a_hi - a_lo, torch.zeros_like(a_lo))
    cols = [c.tolist() for c in (n, mean, std, mx, rmse, med, p95)]
    return [ErrorStats(n=int(k), mean=a, std=b, max=c, rmse=r, median=m, p95=p) if k else ErrorStats(n=0)
            for k, a, b, c, r, m, p in zip(*cols)]


def errors_by_marker_batched(e: Tensor, seen: Tensor, marker_names: list[str]) -> list[ErrorStats]:
    """:func:`errors_by_marker` of many data sets at once: errors ``e (B, N, M)`` (m) of ``M``
    markers at ``N`` rows, ``seen (B, N, M)`` the real observations. One record per data set."""
    B, N, M = e.shape
    mm = e.detach().double() * 1e3
    out = _masked_stats(mm.reshape(B, N * M), seen.reshape(B, N * M))
    per = [_masked_stats(mm[:, :, k], seen[:, :, k]) for k in range(M)]
    return [replace(out[b], per_marker={m: per[k][b] for k, m in enumerate(marker_names) if per[k][b].n})
            for b in range(B)]


# mean Euclidean norm of 3-D isotropic Gaussian noise, per unit of its per-axis σ: 2·sqrt(2/π)
_MEAN_NORM_3D = 2.0 * math.sqrt(2.0 / math.pi)


def noise_floor(data, given_mm: float | None = None) -> tuple[float | None, str | None]:
    """The noise floor of a data set (the mean Euclidean error a perfect model would leave, mm)
    and where it comes from, in words.

    In order: the pure error of rows that repeat a command (their pooled per-axis spread, which
    holds the robot's repeatability too, as the mean norm of 3-D noise of that σ); ``given_mm``
    (the caller's, e.g. ``--noise-floor-mm``, from the instrument's specification); the median of a
    ``marker_std_mm`` covariate (each pose's measured spread, as ``torchcal import-bag`` writes it;
    divided by √``marker_samples`` when the rows are means of that many samples). ``(None, None)``
    when none applies."""
    pure = _pure_error_mm(data)
    if pure is not None:
        return pure
    if given_mm is not None:
        return float(given_mm), "given by the caller (noise_mm, --noise-floor-mm: from the instrument's specification)"
    if "marker_std_mm" in data.covariates:
        med = float(torch.quantile(data.covariates["marker_std_mm"].double(), 0.5))  # the mean of the two middle
        if "marker_samples" in data.covariates:
            n = float(torch.quantile(data.covariates["marker_samples"].double(), 0.5))
            return med / math.sqrt(max(n, 1.0)), (f"the median of the data's `marker_std_mm` column over √(median "
                                                  f"`marker_samples` = {n:g}): the spread of a mean of that many samples")
        return med, "the median of the data's `marker_std_mm` column (each pose's measured spread)"
    return None, None


def _pure_error_mm(data) -> tuple[float, str] | None:
    """The floor from rows that repeat a command (see :func:`noise_floor`), or None without repeats."""
    q, pos, seen = data.q, data.positions, data.seen
    _, group = torch.unique(q, dim=0, return_inverse=True)
    n_groups = int(group.max()) + 1 if group.numel() else 0
    if n_groups == len(q):
        return None
    ss, dof = 0.0, 0
    for m in range(pos.shape[1]):
        ok = seen[:, m]
        g, p = group[ok], pos[ok, m].double()
        counts = torch.bincount(g, minlength=n_groups)
        mean = torch.zeros(n_groups, 3, dtype=p.dtype, device=p.device).index_add_(0, g, p) / counts.clamp(min=1)[:, None]
        ss += float(((p - mean[g]) ** 2).sum())
        dof += 3 * int((counts[counts > 0] - 1).sum())
    if dof < 6:
        return None
    sigma_mm = math.sqrt(ss / dof) * 1e3
    reps = int((torch.bincount(group) > 1).sum())
    return (_MEAN_NORM_3D * sigma_mm, f"the pure error of {reps} repeated command(s): their pooled spread, "
            f"σ = {sigma_mm:.4g} mm per axis, as the mean norm of 3-D noise (it includes the robot's repeatability)")


def chi2_sf(x: float, k: int) -> float:
    """P(χ²_k > x) (scipy's ``chi2.sf``) for an integer ``k ≥ 1``, in closed form: the regularised
    upper incomplete gamma function of a whole or half-whole order. Written here, not imported,
    because importing scipy.stats costs most of a second: a report's significance bounds and the
    loop's screening would pay it on every run."""
    h = x / 2.0
    if k % 2 == 0:
        term, total = 1.0, 1.0
        for i in range(1, k // 2):
            term *= h / i
            total += term
        return math.exp(-h) * total
    total, term = math.erfc(math.sqrt(h)), math.sqrt(h) / math.gamma(1.5)
    for i in range((k - 1) // 2):
        total += math.exp(-h) * term
        term *= h / (i + 1.5)
    return total


def chi2_isf(alpha: float, k: int) -> float:
    """The bound a χ²_k exceeds with chance ``alpha`` (scipy's ``chi2.isf``), by bisection."""
    lo, hi = 0.0, float(k) + 10.0
    while chi2_sf(hi, k) > alpha:
        hi *= 2.0
    for _ in range(200):
        mid = 0.5 * (lo + hi)
        if chi2_sf(mid, k) > alpha:
            lo = mid
        else:
            hi = mid
        if hi - lo <= 1e-13 * hi:
            break
    return 0.5 * (lo + hi)
