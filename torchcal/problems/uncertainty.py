"""Parameter uncertainty of a least-squares fit: ``σ² (JᵀJ)⁻¹`` and the standard errors from it,
one implementation for every problem."""
from __future__ import annotations

import torch
from torch import Tensor

__all__ = ["covariance", "standard_errors", "residual_noise", "unit_variances"]


def covariance(J: Tensor, residuals: Tensor, sigma: float | None = None) -> Tensor:
    """Parameter covariance of a least-squares fit: ``σ² (JᵀJ)⁻¹``.

    Args:
        J: ``(m, k)`` Jacobian at the solution; residuals: ``(m,)``.
        sigma: measurement σ per row (units of the residuals); default the estimate
            ``sqrt(SSR / (m - k))``.

    Returns:
        ``(k, k)``. Raises ``RuntimeError`` (from the inverse) when ``JᵀJ`` is singular.
    """
    m, k = J.shape
    s2 = float(residuals @ residuals) / max(m - k, 1) if sigma is None else float(sigma) ** 2
    return s2 * torch.linalg.inv(J.mT @ J)


def standard_errors(J: Tensor, residuals: Tensor, sigma: float | None = None) -> Tensor:
    """``(k,)`` standard errors (square roots of the covariance diagonal, :func:`covariance`);
    NaN for every parameter when ``JᵀJ`` cannot be inverted."""
    try:
        return torch.sqrt(torch.diagonal(covariance(J, residuals, sigma)).clamp(min=0))
    except RuntimeError:
        return torch.full((J.shape[1],), float("nan"), dtype=J.dtype, device=J.device)


def residual_noise(residuals: Tensor, n_params) -> Tensor:
    """The measurement noise a fit's residuals show, per component (units of the residuals): the
    σ of :func:`covariance`, ``sqrt(SSR / (m − k))``, with ``m`` the components that are not
    exactly 0 (axes not measured, rows that pad a batch) and ``k`` the fitted parameters, so that
    the standard errors judged with it are those a calibration reports.

    Args:
        residuals: ``(..., m)``; n_params: ``k``, an int or a tensor of the leading shape.
    Returns:
        ``(...)``.
    """
    m = (residuals != 0).sum(-1)
    dof = (m - torch.as_tensor(n_params, device=residuals.device)).clamp(min=1)
    return torch.sqrt((residuals * residuals).sum(-1) / dof)


def unit_variances(A: Tensor, keep: Tensor | None = None, full: bool = False) -> Tensor:
    """``diag((AᵀA)⁻¹)`` over the columns ``keep`` of ``A`` (each column's variance at unit noise).

    From the R factor of ``[A·keep; diag(1 − keep)]``, whose Gram matrix is ``AᵀA`` over the kept
    columns and the identity elsewhere: ``(RᵀR)⁻¹ = R⁻¹R⁻ᵀ``, so the diagonal is the row norms of
    ``R⁻¹``. Working on ``A`` rather than ``AᵀA`` keeps the digits a nearly dependent set needs.

    Args:
        A: ``(..., m, k)`` full column rank over ``keep``; keep: ``(..., k)`` bool (default all).
        full: return the whole inverse ``(..., k, k)`` (identity rows and columns where not kept).
    Returns:
        ``(..., k)``; 1 for columns not kept.
    """
    k = A.shape[-1]
    eye = torch.eye(k, dtype=A.dtype, device=A.device)
    if keep is None:
        R = torch.linalg.qr(A, mode="r").R
    else:
        f = keep.to(A.dtype)
        R = torch.linalg.qr(torch.cat([A * f[..., None, :], torch.diag_embed(1.0 - f)], -2), mode="r").R
    Rinv = torch.linalg.solve_triangular(R, eye.expand(R.shape), upper=True)
    return Rinv @ Rinv.transpose(-1, -2) if full else (Rinv * Rinv).sum(-1)
