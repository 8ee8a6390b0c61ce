"""Levenberg-Marquardt for problems made of many blocks tied by a few shared parameters.

A fleet with a hierarchical prior or a payload shared by every robot has per-robot parameters
``z_r`` and shared ones ``s``; robot ``r``'s residuals depend on ``z_r`` and ``s`` only. The
normal equations then have an arrow shape: block-diagonal in the ``z_r``, a dense border for
``s``. Each step eliminates the blocks (one batched Cholesky), solves the Schur complement for
``s`` and back-substitutes, as bundle adjustment does. Damping is global (one gain ratio for the
whole objective), with Marquardt scaling and Nielsen's update as in
:class:`~torchcal.optim.LevenbergMarquardt`.
"""
from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Callable

import torch
from torch import Tensor

__all__ = ["lm_arrow", "ArrowResult", "arrow_solve"]


@dataclass
class ArrowResult:
    """Solution of :func:`lm_arrow`.

    Attributes:
        Z: ``(R, kz)`` per-block parameters; ``s``: ``(ks,)`` shared ones.
        r: ``(R, m)`` residuals; ``Jz``: ``(R, m, kz)``, ``Js``: ``(R, m, ks)`` Jacobians at the
            solution (fixed columns zeroed).
        sse: the sum of squares; ``n_iter``, ``n_jac``: trial steps and Jacobian evaluations.
    """

    Z: Tensor
    s: Tensor
    r: Tensor
    Jz: Tensor
    Js: Tensor
    sse: float
    n_iter: int
    n_jac: int
    converged: bool
    message: str
    wall_time_s: float


def _held(H: Tensor, free: Tensor) -> Tensor:
    """``H`` with the rows and columns of fixed parameters replaced by the identity."""
    f = free.to(H.dtype)
    return H * f[..., :, None] * f[..., None, :] + torch.diag_embed(1.0 - f)


def arrow_solve(Hzz: Tensor, Hzs: Tensor, Hss: Tensor, gz: Tensor, gs: Tensor, zfree: Tensor, sfree: Tensor
                ) -> tuple[Tensor, Tensor, Tensor]:
    """The step ``(dz (R, kz), ds (ks,))`` minimising the quadratic model with Hessian blocks
    ``Hzz (R, kz, kz)``, ``Hzs (R, kz, ks)``, ``Hss (ks, ks)`` and gradients ``gz``, ``gs`` (fixed
    entries do not move), and the Cholesky factors of the ``Hzz`` blocks (``None`` if one is not
    positive definite). The blocks are eliminated and the Schur complement solved for ``ds``."""
    zf, sf = zfree.to(Hzz.dtype), sfree.to(Hzz.dtype)
    L, info = torch.linalg.cholesky_ex(_held(Hzz, zfree))
    if bool((info != 0).any()):
        return None, None, None
    B = Hzs * zf[..., None] * sf
    Y = torch.cholesky_solve(B, L)  # (R, kz, ks)
    a = torch.cholesky_solve((gz * zf)[..., None], L)[..., 0]
    Sc = _held(Hss - torch.einsum("rzi,rzj->ij", B, Y), sfree)
    rhs = (-(gs * sf) + torch.einsum("rzi,rz->i", B, a)) * sf
    ds = torch.linalg.solve(Sc, rhs) * sf if bool(sfree.any()) else torch.zeros_like(gs)
    dz = -(a + torch.bmm(Y, ds.expand(Hzz.shape[0], -1)[..., None])[..., 0]) * zf
    return dz, ds, L


def lm_arrow(fun: Callable[[Tensor, Tensor], tuple[Tensor, Tensor, Tensor]], Z0: Tensor, s0: Tensor, zfree: Tensor,
             sfree: Tensor, *, max_iter: int = 200, tau: float = 1e-6, gtol: float = 1e-10, xtol: float = 1e-10,
             ftol: float = 1e-12) -> ArrowResult:
    """Minimise ``Σ_r ||r_r(z_r, s)||²``.

    Args:
        fun: ``(Z (R, kz), s (ks,)) -> (r (R, m), Jz (R, m, kz), Js (R, m, ks))``.
        Z0, s0: the start; ``zfree (R, kz)``, ``sfree (ks,)``: which entries move.
        max_iter, tau, gtol, xtol, ftol: as for :class:`~torchcal.optim.LevenbergMarquardt`.
    Returns:
        an :class:`ArrowResult` (``Jz`` over all ``kz`` columns, fixed ones zeroed).
    """
    t0 = time.perf_counter()
    cols = torch.nonzero(zfree.any(0)).flatten()  # work on the columns some block fits
    kz = Z0.shape[1]
    Zfull = Z0.clone()
    Z, s = Z0[:, cols].clone(), s0.clone()
    zfree = zfree[:, cols]
    zf, sf = zfree.to(Z.dtype), sfree.to(Z.dtype)

    def evaluate(Z_, s_):
        X = Zfull.clone()
        X[:, cols] = Z_
        r_, Jz_, Js_ = fun(X, s_)
        return r_, Jz_[:, :, cols] * zf[:, None, :], Js_ * sf

    def normal(r_, Jz_, Js_):
        JzT = Jz_.transpose(-1, -2)
        return (torch.bmm(JzT, Jz_), torch.bmm(JzT, Js_), torch.einsum("rmi,rmj->ij", Js_, Js_),
                torch.bmm(JzT, r_[..., None])[..., 0], torch.einsum("rmi,rm->i", Js_, r_))

    r, Jz, Js = evaluate(Z, s)
    Hzz, Hzs, Hss, gz, gs = normal(r, Jz, Js)
    S = float((r * r).sum())
    Dz = Hzz.diagonal(dim1=-2, dim2=-1).clone()
    Ds = Hss.diagonal().clone()
    big = max(float(Dz.max()) if Dz.numel() else 0.0, float(Ds.max()) if Ds.numel() else 0.0, 1e-300)
    mu, nu, n_jac, it = float(tau), 2.0, 1, 0
    converged, message = False, ""

    def gcos():
        d = torch.cat([(Hzz.diagonal(dim1=-2, dim2=-1) * zf).flatten(), Hss.diagonal() * sf]).clamp(min=1e-300)
        g = torch.cat([(gz * zf).flatten(), gs * sf])
        return float((g.abs() / torch.sqrt(d * max(S, 1e-300))).max()) if S > 0 else 0.0

    while it < max_iter:
        it += 1
        Dzf = Dz.clamp(min=1e-6 * big)
        Dsf = Ds.clamp(min=1e-6 * big)
        dz, ds, _ = arrow_solve(Hzz + mu * torch.diag_embed(Dzf), Hzs, Hss + mu * torch.diag(Dsf), gz, gs, zfree,
                                sfree)
        if dz is None:
            mu, nu = mu * nu, nu * 2.0
            continue
        Zn, sn = Z + dz, s + ds
        rn, Jzn, Jsn = evaluate(Zn, sn)
        Sn = float((rn * rn).sum())
        Jh = torch.bmm(Jz, dz[..., None])[..., 0] + Js @ ds
        pred = float(-2.0 * ((dz * gz).sum() + (ds * gs).sum()) - (Jh * Jh).sum())
        gain = S - Sn
        rho = gain / pred if pred > 0 and Sn == Sn else -1.0
        hn = float(torch.sqrt((dz * dz).sum() + (ds * ds).sum()))
        xn = float(torch.sqrt((Z * Z * zf).sum() + (s * s * sf).sum()))
        small_f = abs(gain) <= ftol * S and pred <= ftol * S and rho <= 2.0
        small_x = hn <= xtol * (xn + xtol)
        if rho > 0:
            Z, s, r, Jz, Js, S = Zn, sn, rn, Jzn, Jsn, Sn
            n_jac += 1
            Hzz, Hzs, Hss, gz, gs = normal(r, Jz, Js)
            Dz = torch.maximum(Dz, Hzz.diagonal(dim1=-2, dim2=-1))
            Ds = torch.maximum(Ds, Hss.diagonal())
            mu *= max(1.0 / 3.0, 1.0 - (2.0 * rho - 1.0) ** 3)
            nu = 2.0
            if gcos() < gtol:
                converged, message = True, "projected gradient below gtol"
                break
        else:
            mu, nu = mu * nu, nu * 2.0
        if small_f or small_x:
            converged = True
            message = "relative decrease of the sum of squares below ftol" if small_f else "step below xtol"
            break
    Zout = Zfull.clone()
    Zout[:, cols] = Z
    Jout = Jz.new_zeros(*Jz.shape[:2], kz)
    Jout[:, :, cols] = Jz
    return ArrowResult(Z=Zout, s=s, r=r, Jz=Jout, Js=Js, sse=S, n_iter=it, n_jac=n_jac, converged=converged,
                       message=message or f"reached max_iter={max_iter}", wall_time_s=time.perf_counter() - t0)
