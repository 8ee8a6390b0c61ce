"""Parameter uncertainty of a least-squares fit: ``σ² (JᵀJ)⁻¹`` and the standard errors from it,
one implementation for every problem."""
from __future__ import annotations

import torch
from torch import Tensor

__all__ = ["covariance", "standard_errors"]


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
