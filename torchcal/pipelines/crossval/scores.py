"""How a cross-validated comparison decides (the loop, and ``calibrate``'s prior): robust per-row scores, the acceptance rule, effective parameter counts,
and the choice of an effect's modes by linearised cross-validation.

**Scores.** Every decision compares cross-validated errors row by row. With outliers in the
data a squared error lets a few rows decide everything, so a row scores the Huber loss of its
observations' Euclidean errors ``e`` (m): ``e²`` up to the threshold ``c``, ``2ce − c²`` beyond
(:func:`row_scores`), held constant past the suspect threshold (``OUTLIER_K √3 σ̂``): a gross
error says nothing about which of two models is better, and would only add noise to the
comparison. ``c = HUBER_K σ̂`` with ``σ̂`` the robust per-axis noise estimate of the current
model (:func:`torchcal.measure.noise.robust_sigma`). The fits themselves use the plain Huber loss.

**Rule.** Adding something is accepted when, on the per-row cross-validated scores, the paired
one-sided t statistic of the improvement exceeds ``T_ACCEPT`` and the penalised error
``mean · (1 + 2k / n_obs)`` falls (``k``: free parameters, or the effective number under a prior).

**Modes.** A family (bending at every joint in three directions, growth of every link) is
chosen one mode at a time (:class:`~torchcal.pipelines.loop.linear_cv.LinearCV`): around the fitted model the measurement model is
linear in small changes of its parameters and in each mode's coordinates, so the
cross-validated score of any set of modes costs a few small solves. A mode is added while one
passes the rule with the threshold raised for the number of modes tried (Bonferroni), since the
best of many noise columns passes a plain t > 3 test by chance.
"""
from __future__ import annotations

import math
from statistics import NormalDist

import torch
from torch import Tensor

__all__ = ["T_ACCEPT", "T_EXIT", "HUBER_K", "OUTLIER_K", "row_scores", "compare",
           "penalised", "rmse_mm", "effective_params", "selection_threshold"]

T_ACCEPT = 3.0
# A mode accepted earlier leaves when its t, judged as if added last, falls below this: lower than
# the entry threshold, as stepwise selection has it, so that a mode near the threshold does not
# cycle in and out from one round to the next
T_EXIT = 2.0
HUBER_K = 3.0    # Huber threshold on the 3-D error norm, in units of the per-axis noise σ̂
OUTLIER_K = 5.0  # an observation further than this many σ̂ from the model is a suspect


def row_scores(err: Tensor, rows: Tensor, n_rows: int, c: float | None) -> Tensor:
    """``(n_rows,)`` per-row score: the sum over the row's observations of the Huber loss of the
    Euclidean error ``err (n_obs,)`` (m) with threshold ``c`` (m; None: squared error), constant
    beyond the suspect threshold ``OUTLIER_K √3 c / HUBER_K``, in m²."""
    e = err.abs()
    if c is not None:
        e = e.clamp(max=OUTLIER_K * math.sqrt(3) / HUBER_K * c)
    rho = e * e if c is None else torch.where(e <= c, e * e, 2 * c * e - c * c)
    return torch.zeros(n_rows, dtype=err.dtype, device=err.device).index_add_(0, rows, rho)


def compare(old: Tensor, new: Tensor, k_old: float, k_new: float, n_obs: int) -> tuple[float, bool, bool]:
    """``(t, penalised error fell, accepted)`` for replacing per-row scores ``old`` by ``new``."""
    d = old - new
    n = d.numel()
    sd = float(d.std()) if n > 1 else 0.0
    t = float(d.mean()) / (sd / math.sqrt(n)) if sd > 0 else (math.inf if float(d.mean()) > 0 else 0.0)
    pen_old = float(old.mean()) * (1 + 2 * k_old / n_obs)
    pen_new = float(new.mean()) * (1 + 2 * k_new / n_obs)
    return t, pen_new < pen_old, t > T_ACCEPT and pen_new < pen_old


def penalised(scores: Tensor, k: float, n_obs: int) -> float:
    return float(scores.mean()) * (1 + 2 * k / n_obs)


def rmse_mm(scores: Tensor, n_obs: int) -> float:
    """Root of the mean score per observation, mm (the RMSE when no observation is beyond ``c``)."""
    return 1e3 * math.sqrt(float(scores.sum()) / max(n_obs, 1))


def effective_params(J: Tensor, prior: Tensor | None = None) -> float:
    """Effective number of parameters ``tr((JᵀJ + W²)⁻¹ JᵀJ)`` of a fit with Jacobian ``J (m, k)``
    and prior weights ``W = diag(prior)`` (``(k,)``, 0 = no prior): ``k`` without a prior, less
    as the prior holds parameters the data barely sees."""
    A = J.T @ J
    if prior is None or not bool((prior > 0).any()):
        return float(torch.linalg.matrix_rank(A))
    s = torch.sqrt(torch.clamp(A.diagonal(), min=1e-300))  # unit-free: scale columns alike
    An = A / s[:, None] / s[None, :]
    Pn = torch.diag((prior / s) ** 2)
    return float(torch.trace(torch.linalg.solve(An + Pn + 1e-12 * torch.eye(len(s), dtype=A.dtype, device=A.device), An)))


def selection_threshold(n_tried: int) -> float:
    """The t a mode must beat when ``n_tried`` modes compete: the one-sided level of
    :data:`T_ACCEPT`, shared among them (Bonferroni)."""
    nd = NormalDist()
    p = (1 - nd.cdf(T_ACCEPT)) / max(n_tried, 1)
    return max(T_ACCEPT, nd.inv_cdf(1 - p))
