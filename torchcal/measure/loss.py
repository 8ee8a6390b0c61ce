"""Robust losses of residual vectors, per observation.

With ``s = |r|² / c²`` an observation's residual ``r`` (m) becomes ``r · sqrt(ρ(s) / s)``, so the
sum of squares is ``c² Σ ρ(s)``, and its Jacobian rows are scaled by ``sqrt(ρ'(s))`` (the usual
first-order, IRLS-style approximation).
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

    def apply(self, r: Tensor) -> Tensor:
        """Residual vectors ``r (..., n, d)`` (m, one observation per vector) robustified."""
        if self.kind == "l2":
            return r
        return r * self.scales((r * r).sum(-1))[0][..., None]

    def __repr__(self) -> str:
        return f"Loss({self.kind!r}, scale={self.scale:g} m)"
