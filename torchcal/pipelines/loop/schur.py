"""Minimum-norm solves of the linear CV's normal equations through the base block's Schur complement.

Every column set the linear CV scores is the fitted model's base columns plus a few candidate
columns, and every fold's (and the whole data's) normal matrix holds the same base block. Once
that block is factored per system, a set costs a solve the size of its candidate columns: the
Schur complement of the base in the set's matrix is a principal submatrix of the one over all
candidate columns.

A set's pseudo-inverse (pinv's cut at :data:`~torchcal.problems.uncertainty.PINV_RTOL` of the
largest eigenvalue) is the block solve with the Schur complement's pseudo-inverse, projected off
the null space, which the Schur complement's null vectors span (``(-Y n, n)`` for ``S n = 0``).
A set is solved whole (:func:`~torchcal.problems.uncertainty.psd_pinv`) unless bounds that hold
whatever the rounding put every eigenvalue clearly on one side of the cut, and so is every set
when a base block is not safely invertible: both ways give the same steps to rounding.
"""
from __future__ import annotations

from types import SimpleNamespace

import torch
from torch import Tensor

from torchcal.problems.uncertainty import PINV_RTOL, psd_pinv, safe_cholesky

__all__ = ["BaseSchur"]

# How far the eigenvalue bounds must clear the cut for a set's solve to count as pinv's
_MARGIN = 10.0
# the rounding of a computed eigenvalue of the Schur complement, in units of eps times the set's largest
# diagonal entry (formed through the base's factor, an exact dependence leaves about one)
_ULPS = 16.0


class BaseSchur:
    """Minimum-norm solves ``pinv(G[set]) b[set]`` of ``E`` normal equations (the whole data and the
    folds) over column sets that all begin with the first ``kb`` columns (the base).

    Args:
        G: ``(E, K, K)`` symmetric positive semi-definite normal matrices; b: ``(E, K)``.
        kb: the number of base columns.

    ``usable``: every base block is safely invertible (else every set is solved whole)."""

    def __init__(self, G: Tensor, b: Tensor, kb: int):
        self.kb, self.G, self.b = kb, G, b
        self.usable = kb > 0  # without a base there is nothing to eliminate: every set is solved whole
        if not self.usable:
            return
        Gbb = G[:, :kb, :kb]
        Lb, Hbb, ok = safe_cholesky(Gbb)
        self.usable = bool(ok.all())
        if not self.usable:
            return
        # through the factor, not the inverse: S = Ggg − WᵀW with W = L⁻¹C is then as accurate as
        # the matrix itself (an exactly dependent column leaves an eigenvalue at rounding level), however
        # ill-conditioned the base
        W = torch.linalg.solve_triangular(Lb, G[:, :kb, kb:], upper=False)
        u = torch.linalg.solve_triangular(Lb, b[:, :kb, None], upper=False)
        self.Hbb = Hbb
        self.Y = torch.linalg.solve_triangular(Lb.mT, W, upper=True)  # (E, kb, g): each candidate's regression on the base
        self.z = torch.linalg.solve_triangular(Lb.mT, u, upper=True)[..., 0]
        S = G[:, kb:, kb:] - W.mT @ W
        self.S = 0.5 * (S + S.mT)
        self.s = b[:, kb:] - (W.mT @ u)[..., 0]
        self.Gg_abs = G[:, kb:, kb:].abs()
        self.Gg_diag = G[:, kb:, kb:].diagonal(dim1=-2, dim2=-1)
        self.base_diag = Gbb.diagonal(dim1=-2, dim2=-1).amax(-1)
        # λmin(Gbb) ≥ 1/‖Gbb⁻¹‖∞ and λmax(Gbb) ≤ ‖Gbb‖∞ (symmetric matrices)
        self.base_lo = 1.0 / Hbb.abs().sum(-1).amax(-1)
        self.base_hi = Gbb.abs().sum(-1).amax(-1)

    def _factor(self, J: Tensor, e: Tensor) -> SimpleNamespace:
        """The sets ``base + J (L, g)`` (candidate columns counted from the first after the base)
        of systems ``e (E',)``: the Schur complement's pseudo-inverse ``Sp (E', L, g, g)``, which of
        its eigenvalues count as zero, the null vectors ``N (E', L, k, g)`` (zero columns for the
        kept ones) with their Gram ``M`` (identity on the kept), and ``ok (E', L)``."""
        S = self.S[e][:, J[:, :, None], J[:, None, :]]
        YJ = self.Y[e][:, :, J].permute(0, 2, 1, 3)  # (E', L, kb, g)
        mu, V = torch.linalg.eigh(S)
        # λmax of the set's matrix lies between its largest diagonal entry and the sum of its two
        # blocks' λmax bounds
        top_lo = torch.maximum(self.base_diag[e, None], self.Gg_diag[e][:, J].amax(-1))
        top_hi = self.base_hi[e, None] + self.Gg_abs[e][:, J[:, :, None], J[:, None, :]].sum(-1).amax(-1)
        # each computed μ within rounding of S's own: a few ulps of the set's largest diagonal entry
        err = _ULPS * torch.finfo(mu.dtype).eps * top_lo[..., None]
        # an eigenvalue μ of S leaves one of the set's matrix below μ: zero far under the cut
        zero = mu + err <= (PINV_RTOL / _MARGIN) * top_lo[..., None]
        # the others stay above min(λmin(Gbb), μ₊) / (2 + 2‖Y‖²) (Courant-Fischer on (vb + Y vg, vg))
        mu_plus = torch.where(zero, torch.full_like(mu, float("inf")), mu - err).amin(-1)
        floor = torch.minimum(self.base_lo[e, None], mu_plus) / (2.0 + 2.0 * (YJ * YJ).sum((-1, -2)))
        ok = floor > (PINV_RTOL * _MARGIN) * top_hi
        inv = torch.where(zero, torch.zeros_like(mu), 1.0 / torch.where(zero, torch.ones_like(mu), mu))
        Sp = (V * inv[..., None, :]) @ V.mT
        f = SimpleNamespace(YJ=YJ, Sp=Sp, zero=zero, ok=ok, N=None)
        if bool(zero.any()):
            Ng = V * zero[..., None, :].to(V.dtype)
            Nb = -(YJ @ Ng)
            f.Nb, f.Ng, f.N = Nb, Ng, torch.cat([Nb, Ng], -2)
            f.M = f.N.mT @ f.N + torch.diag_embed((~zero).to(V.dtype))
        return f

    def _unnull(self, f: SimpleNamespace, x: Tensor) -> Tensor:
        """``x (E', L, k)`` less its part along the null vectors."""
        if f.N is None:
            return x
        return x - (f.N @ torch.linalg.solve(f.M, f.N.mT @ x[..., None]))[..., 0]

    def _solve(self, J: Tensor, e: Tensor) -> tuple[Tensor, Tensor]:
        """``pinv(G[set]) b[set]`` of the sets ``base + J (L, g)`` in systems ``e (E',)``: ``(E', L,
        kb + g)`` (base columns first), and ``(E', L)`` bool, where it is pinv's to rounding."""
        if J.shape[1] == 0:
            return self.z[e][:, None].expand(-1, J.shape[0], -1), torch.ones(e.numel(), J.shape[0], dtype=torch.bool,
                                                                                device=J.device)
        f = self._factor(J, e)
        xg = (f.Sp @ self.s[e][:, J][..., None])[..., 0]
        xb = self.z[e][:, None] - (f.YJ @ xg[..., None])[..., 0]
        return self._unnull(f, torch.cat([xb, xg], -1)), f.ok

    def _pinv_diagonal(self, J: Tensor, e: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """The diagonal of ``pinv(G[set])`` ``(E', L, kb + g)``, the rank under the cut ``(E', L)``
        and where both are pinv's ``(E', L)``, for the sets ``base + J`` in systems ``e``."""
        kb = self.kb
        if J.shape[1] == 0:
            d = self.Hbb[e].diagonal(dim1=-2, dim2=-1)[:, None].expand(-1, J.shape[0], -1)
            ones = torch.ones(e.numel(), J.shape[0], dtype=torch.bool, device=J.device)
            return d, torch.full(ones.shape, float(kb), dtype=d.dtype, device=d.device), ones
        f = self._factor(J, e)
        Hb = self.Hbb[e][:, None]
        # the block inverse X with S's pseudo-inverse: X_bb = Hbb + Y Sp Yᵀ, X_gg = Sp
        d = torch.cat([Hb.diagonal(dim1=-2, dim2=-1) + ((f.YJ @ f.Sp) * f.YJ).sum(-1),
                       f.Sp.diagonal(dim1=-2, dim2=-1)], -1)
        if f.N is not None:  # pinv = (I − Π) X (I − Π), Π the projector onto the null vectors
            T = f.YJ.mT @ f.Nb - f.Ng
            XN = torch.cat([Hb @ f.Nb + f.YJ @ (f.Sp @ T), -(f.Sp @ T)], -2)
            Minv = torch.linalg.inv(f.M)
            W = Minv @ (f.N.mT @ XN) @ Minv
            d = d - 2.0 * (f.N * (XN @ Minv)).sum(-1) + ((f.N @ W) * f.N).sum(-1)
        rank = kb + (~f.zero).sum(-1).to(d.dtype)
        return d, rank, f.ok

    def solve(self, idx: Tensor, e: Tensor) -> Tensor:
        """``pinv(G_e[set]) b_e[set]`` of the column sets ``idx (L, k)`` (each the base, then
        candidate columns) in systems ``e (E',)``: ``(E', L, k)``."""
        x, todo = None, None
        if self.usable:
            x, ok = self._solve(idx[:, self.kb:] - self.kb, e)
            todo = ~ok.all(0)
            if not bool(todo.any()):
                return x
            x = x.clone()
        sub = idx if todo is None else idx[todo]
        ii, jj = sub[:, :, None], sub[:, None, :]
        xs = (psd_pinv(self.G[e][:, ii, jj]) @ self.b[e][:, sub][..., None])[..., 0]
        if x is None:
            return xs
        x[:, todo] = xs
        return x

    def effective(self, idx: Tensor, Gd: Tensor, e: int = 0) -> Tensor:
        """``trace(pinv(G_e[set]) Gd[set])`` of the column sets ``idx (L, k)``: ``(L,)``, the
        effective number of parameters when ``G_e = Gd + diag(P²)`` adds a prior to the data's
        ``Gd (K, K)``."""
        k = torch.empty(idx.shape[0], dtype=self.G.dtype, device=self.G.device)
        todo = torch.ones(idx.shape[0], dtype=torch.bool, device=idx.device)
        if self.usable:  # trace(G⁺ Gd) = trace(G⁺ (G − P²)) = rank − Σ P² diag(G⁺)
            d, rank, ok = self._pinv_diagonal(idx[:, self.kb:] - self.kb, torch.tensor([e], device=idx.device))
            P2 = (self.G[e] - Gd).diagonal()
            k[:] = rank[0] - (P2[idx] * d[0]).sum(-1)
            todo = ~ok[0]
        if bool(todo.any()):
            sub = idx[todo]
            ii, jj = sub[:, :, None], sub[:, None, :]
            k[todo] = (psd_pinv(self.G[e][ii, jj]) * Gd[ii, jj].mT).sum((-1, -2))
        return k
