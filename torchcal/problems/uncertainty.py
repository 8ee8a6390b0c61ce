"""Parameter uncertainty of a least-squares fit: ``σ² (JᵀJ + W²)⁻¹`` and the standard errors from
it, one implementation for every problem: a single calibration, the loop's fits under a Gaussian
prior, and a fleet's robots in one batch (each with its own free columns and noise)."""
from __future__ import annotations

import torch
from torch import Tensor

__all__ = ["covariance", "standard_errors", "residual_noise", "unit_variances", "psd_pinv", "safe_cholesky", "PINV_RTOL"]


def covariance(J: Tensor, residuals: Tensor | None = None, sigma: float | Tensor | None = None, *,
               prior: Tensor | None = None, free: Tensor | None = None, rows: Tensor | int | None = None,
               singular: str = "nan") -> Tensor:
    """Parameter covariance of a least-squares fit: ``σ² (JᵀJ + W²)⁻¹``, one problem or a batch.

    Args:
        J: ``(..., m, k)`` Jacobian at the solution (units of the residuals per parameter unit).
        residuals: ``(..., m)``, for the estimate ``σ² = SSR / max(rows − k, 1)`` when ``sigma``
            is not given; sigma: the measurement σ per row (units of the residuals), a number or
            ``(...)``.
        prior: ``(..., k)`` weights ``W`` of a Gaussian prior (diagonal precision ``W²`` in units
            of ``JᵀJ``); free: ``(..., k)`` bool, the fitted columns (the others get an identity
            row and column, so their variance reads ``σ²``); ``k`` then counts the free ones.
        rows: the measured rows per problem (default ``m``: a padded batch counts its own).
        singular: ``"nan"``: NaN for every entry of a problem whose matrix cannot be inverted;
            ``"pinv"``: the pseudo-inverse of the matrix scaled to a unit diagonal (a prior-free
            direction the data do not see gets variance 0, not NaN).
    Returns:
        ``(..., k, k)``.
    """
    A = J.mT @ J
    if prior is not None:
        A = A + torch.diag_embed(prior * prior)
    if free is not None:
        f = free.to(J.dtype)
        A = A * f[..., :, None] * f[..., None, :] + torch.diag_embed(1.0 - f)
    if singular == "pinv":
        s = A.diagonal(dim1=-2, dim2=-1).clamp(min=1e-300).sqrt()
        inv = torch.linalg.pinv(A / s[..., :, None] / s[..., None, :]) / s[..., :, None] / s[..., None, :]
    elif singular == "nan":
        inv, info = torch.linalg.inv_ex(A)
        inv = torch.where((info != 0)[..., None, None], torch.full_like(inv, float("nan")), inv)
    else:
        raise ValueError(f"singular must be 'nan' or 'pinv', got {singular!r}")
    return _variance(J, residuals, sigma, free, rows)[..., None, None] * inv


def _variance(J: Tensor, residuals: Tensor | None, sigma, free: Tensor | None, rows) -> Tensor:
    """``σ²`` per problem ``(...)``: the given σ squared, or ``SSR / max(rows − k, 1)``."""
    if sigma is not None:
        return torch.as_tensor(sigma, dtype=J.dtype, device=J.device) ** 2
    k = J.shape[-1] if free is None else free.sum(-1)
    m = J.shape[-2] if rows is None else rows
    dof = torch.as_tensor(m - k, device=J.device).clamp(min=1).to(J.dtype)
    return (residuals * residuals).sum(-1) / dof


def standard_errors(J: Tensor, residuals: Tensor | None = None, sigma: float | Tensor | None = None,
                    **kw) -> Tensor:
    """``(..., k)`` standard errors: square roots of the diagonal of :func:`covariance` (its
    keywords ``prior``, ``free``, ``rows``, ``singular``); NaN for every parameter of a problem
    whose matrix cannot be inverted."""
    return covariance(J, residuals, sigma, **kw).diagonal(dim1=-2, dim2=-1).clamp(min=0).sqrt()


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


# pinv's cut in the normal matrices' solves: eigenvalues below this fraction of the largest count as zero
PINV_RTOL = 1e-12
# Below this bound of the condition number (‖G‖∞ ‖G⁻¹‖∞, never below the 2-norm's for a symmetric
# G) every eigenvalue is above the cut, ten times over: there the pseudo-inverse is the inverse
_SAFE_COND = 0.1 / PINV_RTOL


def safe_cholesky(G: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """The Cholesky factor ``L`` and the inverse of symmetric positive semi-definite ``G (..., k, k)``,
    and ``(...)`` bool where the inverse is also the pseudo-inverse: the factor exists and bounds the
    condition number (``‖G‖∞ ‖G⁻¹‖∞``) inside pinv's cut ten times over. Where it is not, the
    factor and inverse returned are of a stand-in and must not be used."""
    L, info = torch.linalg.cholesky_ex(G)
    failed = info != 0
    if bool(failed.any()):  # a factor that broke down holds a zero pivot: invert a stand-in, judged below
        L = torch.where(failed[..., None, None], torch.eye(G.shape[-1], dtype=G.dtype, device=G.device), L)
    H = torch.cholesky_inverse(L)
    cond = G.abs().sum(-1).amax(-1) * H.abs().sum(-1).amax(-1)
    return L, H, ~failed & torch.isfinite(cond) & (cond < _SAFE_COND)


def psd_pinv(G: Tensor) -> Tensor:
    """``pinv(G, rtol=1e-12, hermitian=True)`` of symmetric positive semi-definite ``G (..., k, k)``.

    Where a Cholesky factor exists and bounds the condition number inside the cut, the
    pseudo-inverse is the inverse, which the factor gives for a fraction of an eigendecomposition
    (the linear CV inverts thousands of these per candidate); the others take the eigendecomposition."""
    if G.shape[-1] == 0:
        return G.clone()
    _, H, ok = safe_cholesky(G)
    if not bool(ok.all()):
        bad = ~ok
        H[bad] = torch.linalg.pinv(G[bad], rtol=PINV_RTOL, hermitian=True)
    return H
