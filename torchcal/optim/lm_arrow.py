"""Levenberg-Marquardt for problems made of many blocks tied by a few shared parameters.

A fleet with a hierarchical prior or a payload shared by every robot has per-robot parameters
``z_r`` and shared ones ``s``; robot ``r``'s residuals depend on ``z_r`` and ``s`` only. The
normal equations then have an arrow shape: block-diagonal in the ``z_r``, a dense border for
``s``. Each step eliminates the blocks (one batched Cholesky), solves the Schur complement for
``s`` and back-substitutes, as bundle adjustment does. Damping is global (one gain ratio for the
whole objective), with Marquardt scaling and Nielsen's update as in
:class:`~torchcal.optim.LevenbergMarquardt`, from the same step rules (:mod:`torchcal.damping`).

The loop is its own rather than an engine solver (:mod:`torchcal.optim.engine`): the engine's
solvers take a :class:`~torchcal.problems.base.Problem` with a flat parameter vector and one
Jacobian ``(m, k)``, while here the iterate is a pair ``(Z (R, kz), s (ks,))`` and the Jacobian
comes in blocks that are never assembled (an ``(R m, R kz + ks)`` matrix would be mostly zeros).
"""
from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Callable

import torch
from torch import Tensor

from torchcal.damping import (damp_harder, gain_ratio, gradient_cosine, nielsen_update, predicted_decrease,
                              scaling_floor, small_decrease, small_step)

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


class _Blocks:
    """The callback seen through the columns some block fits: ``Z (R, c)`` in, fixed columns of
    the Jacobians zeroed out."""

    def __init__(self, fun, Z0: Tensor, cols: Tensor, zfree: Tensor, sfree: Tensor):
        self.fun, self.Zfull, self.cols = fun, Z0.clone(), cols
        self.zf, self.sf = zfree.to(Z0.dtype), sfree.to(Z0.dtype)

    def full(self, Z: Tensor) -> Tensor:
        X = self.Zfull.clone()
        X[:, self.cols] = Z
        return X

    def __call__(self, Z: Tensor, s: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        r, Jz, Js = self.fun(self.full(Z), s)
        return r, Jz[:, :, self.cols] * self.zf[:, None, :], Js * self.sf


def _normal_equations(r: Tensor, Jz: Tensor, Js: Tensor) -> tuple[Tensor, ...]:
    """The arrow's blocks ``Hzz (R, kz, kz)``, ``Hzs (R, kz, ks)``, ``Hss (ks, ks)`` of ``JᵀJ`` and
    the gradients ``gz (R, kz)``, ``gs (ks,)`` of ``Jᵀr``."""
    JzT = Jz.transpose(-1, -2)
    return (torch.bmm(JzT, Jz), torch.bmm(JzT, Js), torch.einsum("rmi,rmj->ij", Js, Js),
            torch.bmm(JzT, r[..., None])[..., 0], torch.einsum("rmi,rm->i", Js, r))


def _gradient_test(H: tuple, S: float, zf: Tensor, sf: Tensor) -> float:
    """MINPACK's scale-free gradient test over the free entries of both kinds."""
    Hzz, _, Hss, gz, gs = H
    d = torch.cat([(Hzz.diagonal(dim1=-2, dim2=-1) * zf).flatten(), Hss.diagonal() * sf])
    g = torch.cat([(gz * zf).flatten(), gs * sf])
    return float(gradient_cosine(g, d, torch.tensor(S, dtype=d.dtype, device=d.device)))


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
    zfree = zfree[:, cols]
    evaluate = _Blocks(fun, Z0, cols, zfree, sfree)
    zf, sf = evaluate.zf, evaluate.sf
    Z, s = Z0[:, cols].clone(), s0.clone()
    r, Jz, Js = evaluate(Z, s)
    H = _normal_equations(r, Jz, Js)
    S = float((r * r).sum())
    Dz = H[0].diagonal(dim1=-2, dim2=-1).clone()
    Ds = H[2].diagonal().clone()
    big = max(float(Dz.max()) if Dz.numel() else 0.0, float(Ds.max()) if Ds.numel() else 0.0, 1e-300)
    big = torch.tensor(big, dtype=Dz.dtype, device=Dz.device)
    mu, nu, n_jac, it = float(tau), 2.0, 1, 0
    converged, message = False, ""
    while it < max_iter:
        it += 1
        Hzz, Hzs, Hss, gz, gs = H
        dz, ds, _ = arrow_solve(Hzz + mu * torch.diag_embed(scaling_floor(Dz, big)), Hzs,
                                Hss + mu * torch.diag(scaling_floor(Ds, big)), gz, gs, zfree, sfree)
        if dz is None:
            mu, nu = damp_harder(mu, nu)
            continue
        Zn, sn = Z + dz, s + ds
        rn, Jzn, Jsn = evaluate(Zn, sn)
        Sn = float((rn * rn).sum())
        Jh = torch.bmm(Jz, dz[..., None])[..., 0] + Js @ ds
        pred = float(predicted_decrease((dz * gz).sum() + (ds * gs).sum(), (Jh * Jh).sum()))
        gain = S - Sn
        rho = gain_ratio(gain, pred, Sn)
        hn = float(torch.sqrt((dz * dz).sum() + (ds * ds).sum()))
        xn = float(torch.sqrt((Z * Z * zf).sum() + (s * s * sf).sum()))
        small_f = small_decrease(gain, pred, S, rho, ftol)
        small_x = small_step(hn, xn, xtol)
        mu, nu = nielsen_update(mu, nu, rho)
        if rho > 0:
            Z, s, r, Jz, Js, S = Zn, sn, rn, Jzn, Jsn, Sn
            n_jac += 1
            H = _normal_equations(r, Jz, Js)
            Dz = torch.maximum(Dz, H[0].diagonal(dim1=-2, dim2=-1))
            Ds = torch.maximum(Ds, H[2].diagonal())
            if _gradient_test(H, S, zf, sf) < gtol:
                converged, message = True, "projected gradient below gtol"
                break
        if small_f or small_x:
            converged = True
            message = "relative decrease of the sum of squares below ftol" if small_f else "step below xtol"
            break
    Jout = Jz.new_zeros(*Jz.shape[:2], Z0.shape[1])
    Jout[:, :, cols] = Jz
    return ArrowResult(Z=evaluate.full(Z), s=s, r=r, Jz=Jout, Js=Js, sse=S, n_iter=it, n_jac=n_jac, converged=converged,
                       message=message or f"reached max_iter={max_iter}", wall_time_s=time.perf_counter() - t0)
