"""Robust losses of residual vectors, per observation.

With ``s = |r|² / c²`` an observation's residual ``r`` (m) becomes ``r̃ = r · f(s)``, ``f = sqrt(ρ(s) / s)``,
so the sum of squares is ``c² Σ ρ(s)``. The Jacobian a solver gets (:meth:`Loss.jacobian`) makes
``J̃ᵀ r̃`` the exact gradient ``Σ ρ' Jᵀ r`` of ``c² Σ ρ / 2``, with the curvature ``ρ' JᵀJ`` across each
residual. The IRLS shortcut ``sqrt(ρ'(s)) J`` does not: beyond Huber's threshold its gradient is off
by up to √2, so Levenberg-Marquardt ended where that false gradient and the true one disagree, in a
tail of refused steps at damping in the millions, short of the robust optimum and at a point that
depended on the path. ``sqrt(ρ'(s))`` stays the weight of an observation in the linear screens
(:meth:`Loss.scales`).
"""
from __future__ import annotations

import torch
from torch import Tensor

__all__ = ["Loss"]


class Loss:
    """Robust loss ``ρ(s)`` of a squared, scaled norm ``s``: ``"l2"``, ``"huber"`` or ``"cauchy"``.

    Args:
        scale: ``c`` in metres: observations with ``|r| <~ c`` count as inliers.
    """

    KINDS = ("l2", "huber", "cauchy")

    def __init__(self, kind: str = "l2", scale: float = 1e-3):
        if kind not in self.KINDS:
            raise ValueError(f"loss must be one of {self.KINDS}, got {kind!r}")
        if not scale > 0:
            raise ValueError(f"loss scale must be > 0 (metres), got {scale}")
        self.kind, self.scale = kind, float(scale)

    def rho(self, s: Tensor) -> tuple[Tensor, Tensor]:
        """``ρ(s)`` and ``ρ'(s)``."""
        if self.kind == "l2":
            return s, torch.ones_like(s)
        if self.kind == "huber":
            root = torch.sqrt(s.clamp(min=1.0))
            return torch.where(s <= 1, s, 2 * root - 1), torch.where(s <= 1, torch.ones_like(s), 1 / root)
        return torch.log1p(s), 1 / (1 + s)

    def scales(self, sq_norm: Tensor) -> tuple[Tensor, Tensor]:
        """Factors for residuals and Jacobian rows from squared norms (m²)."""
        if self.kind == "l2":
            one = torch.ones_like(sq_norm)
            return one, one
        s = sq_norm / self.scale ** 2
        rho, drho = self.rho(s)
        safe = torch.where(s > 1e-300, s, torch.ones_like(s))
        r_fac = torch.where(s > 1e-300, torch.sqrt(rho / safe), torch.ones_like(s))
        return r_fac, torch.sqrt(drho)

    def jacobian(self, r: Tensor, J: Tensor) -> Tensor:
        """The Jacobian ``(..., n, d, k)`` a least-squares solver uses for :meth:`apply`'s residuals, from
        each observation's residual vector ``r (..., n, d)`` (m) and its Jacobian ``J (..., n, d, k)``:
        ``sqrt(ρ') (I − α r̂ r̂ᵀ) J`` with ``1 − α = sqrt(ρ') / f``, so that with the residual ``f r`` it
        gives the exact gradient ``ρ' Jᵀ r`` of ``c² Σ ρ / 2`` and the curvature ``ρ' JᵀJ`` across ``r``."""
        if self.kind == "l2":
            return J
        sq = (r * r).sum(-1)
        f, w = self.scales(sq)
        # ρ is concave, so ρ(s) / s ≥ ρ'(s) and 0 ≤ α < 1: the rows along r are shortened, never
        # turned; α = 0 inside Huber's threshold and at r = 0 (f = w = 1 there)
        alpha = 1 - w / f
        rJ = (r[..., None] * J).sum(-2, keepdim=True)  # (..., n, 1, k): rᵀ J per observation
        return w[..., None, None] * (J - (alpha / sq.clamp(min=1e-300))[..., None, None] * r[..., None] * rJ)

    def apply(self, r: Tensor) -> Tensor:
        """Residual vectors ``r (..., n, d)`` (m, one observation per vector) robustified."""
        if self.kind == "l2":
            return r
        return r * self.scales((r * r).sum(-1))[0][..., None]

    def __repr__(self) -> str:
        return f"Loss({self.kind!r}, scale={self.scale:g} m)"
