"""The linear step of the one Levenberg-Marquardt iteration (:func:`~torchcal.optim.lm_batched.lm_batched`),
as a strategy the iteration is given (as Theseus is given a linear solver).

The iteration decides everything else (damping, acceptance, stopping); a strategy holds the Jacobian
in its own layout and answers five questions about it: the normal matrix ``JᵀJ`` over the free
columns, the gradient ``Jᵀr``, the diagonal of ``JᵀJ`` (Marquardt's scaling, the gradient test),
the damped solve ``(JᵀJ + diag(shift)) h = rhs`` with held entries kept at 0, and ``hᵀ JᵀJ h``
(the linear model's predicted decrease).

* :class:`DenseCholesky`: ``J (B, m, c)``, ``JᵀJ (B, c, c)``, one batched Cholesky per iteration.
  A batch of independent problems (one robot, a fleet robot by robot, CV folds, prior scales).
* :class:`Arrow`: one problem (``B = 1``) made of ``R`` blocks tied by a few shared parameters
  (a fleet with a hierarchical prior or a shared payload): parameters ``x = [z_1 … z_R, s]``, the
  Jacobian as the blocks ``(Jz (1, R, m, kz), Js (1, R, m, ks))``, never assembled. The solve
  eliminates the blocks (one batched Cholesky over ``R``), solves the Schur complement for ``s`` and
  back-substitutes, as bundle adjustment does.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import torch
from torch import Tensor

__all__ = ["DenseCholesky", "Arrow", "arrow_solve", "lm_arrow", "ArrowResult"]


def _held(H: Tensor, move: Tensor) -> Tensor:
    """``H`` with the rows and columns of held entries replaced by the identity (their step is 0)."""
    f = move.to(H.dtype)
    return H * f[..., :, None] * f[..., None, :] + torch.diag_embed(1.0 - f)


class DenseCholesky:
    """Independent problems, each a dense normal matrix: ``J (B, m, c)``, ``A = JᵀJ (B, c, c)``."""

    @staticmethod
    def columns(free: Tensor) -> Tensor:
        # work on the columns some problem fits: a fleet fixes the same many parameters everywhere
        return torch.nonzero(free.any(0)).flatten()

    @staticmethod
    def take(J: Tensor, pos: Tensor) -> Tensor:
        return J[:, :, pos]

    @staticmethod
    def rows(T: Tensor, idx: Tensor) -> Tensor:
        # the iteration's index sets are ascending and unique: as many as there are rows is all of them
        return T if idx.numel() == T.shape[0] else T[idx]

    @staticmethod
    def put(T: Tensor, idx: Tensor, V: Tensor) -> None:
        T[idx] = V

    @staticmethod
    def gram(J: Tensor, free: Tensor) -> Tensor:
        J = J * free[:, None, :].to(J.dtype)
        return torch.bmm(J.transpose(-1, -2), J)

    @staticmethod
    def gradient(J: Tensor, r: Tensor, free: Tensor) -> Tensor:
        return torch.bmm(J.transpose(-1, -2), r[..., None])[..., 0] * free.to(J.dtype)

    @staticmethod
    def diagonal(A: Tensor) -> Tensor:
        return A.diagonal(dim1=-2, dim2=-1)

    @staticmethod
    def solve(A: Tensor, move: Tensor, shift: Tensor, rhs: Tensor) -> tuple[Tensor, Tensor]:
        M = _held(A, move)
        M.diagonal(dim1=-2, dim2=-1).add_(shift)
        L, info = torch.linalg.cholesky_ex(M)
        return torch.cholesky_solve(rhs[..., None], L)[..., 0], info == 0

    @staticmethod
    def curvature(A: Tensor, h: Tensor) -> Tensor:
        return (h * torch.bmm(A, h[..., None])[..., 0]).sum(-1)


def arrow_solve(Hzz: Tensor, Hzs: Tensor, Hss: Tensor, gz: Tensor, gs: Tensor, zfree: Tensor, sfree: Tensor
                ) -> tuple[Tensor, Tensor, Tensor]:
    """The step ``(dz (R, kz), ds (ks,))`` minimising the quadratic model with Hessian blocks
    ``Hzz (R, kz, kz)``, ``Hzs (R, kz, ks)``, ``Hss (ks, ks)`` and gradients ``gz``, ``gs`` (entries
    not free do not move), and the Cholesky factors of the ``Hzz`` blocks (``None``s if one is not
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


class Arrow:
    """One problem of ``R`` blocks of ``kz`` parameters and ``ks`` shared ones, ``x = [z_1 … z_R, s]``
    (see the module docstring). Its Jacobian is ``(Jz (1, R, m, kz), Js (1, R, m, ks))`` and its
    normal matrix ``(Hzz (1, R, kz, kz), Hzs (1, R, kz, ks), Hss (1, ks, ks))``; residuals ``(1, R m)``."""

    def __init__(self, R: int, kz: int, ks: int):
        self.R, self.kz, self.ks = R, kz, ks

    def _split(self, v: Tensor) -> tuple[Tensor, Tensor]:
        """``(1, R kz + ks)`` -> ``((R, kz), (ks,))``."""
        return v[0, : self.R * self.kz].reshape(self.R, self.kz), v[0, self.R * self.kz:]

    def _join(self, z: Tensor, s: Tensor) -> Tensor:
        return torch.cat([z.flatten(), s])[None]

    @staticmethod
    def columns(free: Tensor) -> Tensor:
        return torch.arange(free.shape[-1], device=free.device)  # the block layout keeps every column

    @staticmethod
    def take(J: tuple, pos: Tensor) -> tuple:
        return J

    @staticmethod
    def rows(T: tuple, idx: Tensor) -> tuple:
        return T if idx.numel() == T[0].shape[0] else tuple(t[idx] for t in T)

    @staticmethod
    def put(T: tuple, idx: Tensor, V: tuple) -> None:
        for t, v in zip(T, V):
            t[idx] = v

    def gram(self, J: tuple, free: Tensor) -> tuple:
        zf, sf = (f.to(J[0].dtype) for f in self._split(free))
        Jz, Js = J[0][0] * zf[:, None, :], J[1][0] * sf
        JzT = Jz.transpose(-1, -2)
        return torch.bmm(JzT, Jz)[None], torch.bmm(JzT, Js)[None], torch.einsum("rmi,rmj->ij", Js, Js)[None]

    def gradient(self, J: tuple, r: Tensor, free: Tensor) -> Tensor:
        zf, sf = (f.to(r.dtype) for f in self._split(free))
        rr = r[0].reshape(self.R, -1)
        gz = torch.bmm(J[0][0].transpose(-1, -2), rr[..., None])[..., 0] * zf
        return self._join(gz, torch.einsum("rmi,rm->i", J[1][0], rr) * sf)

    def diagonal(self, A: tuple) -> Tensor:
        return self._join(A[0][0].diagonal(dim1=-2, dim2=-1), A[2][0].diagonal())

    def solve(self, A: tuple, move: Tensor, shift: Tensor, rhs: Tensor) -> tuple[Tensor, Tensor]:
        (zm, sm), (dz, ds), (gz, gs) = self._split(move), self._split(shift), self._split(-rhs)
        hz, hs, L = arrow_solve(A[0][0] + torch.diag_embed(dz), A[1][0], A[2][0] + torch.diag(ds), gz, gs, zm, sm)
        if L is None:
            return torch.zeros_like(rhs), torch.zeros(1, dtype=torch.bool, device=rhs.device)
        return self._join(hz, hs), torch.ones(1, dtype=torch.bool, device=rhs.device)

    def curvature(self, A: tuple, h: Tensor) -> Tensor:
        hz, hs = self._split(h)
        Hzz, Hzs, Hss = (a[0] for a in A)
        zz = (hz * torch.bmm(Hzz, hz[..., None])[..., 0]).sum()
        return (zz + 2.0 * (hz * (Hzs @ hs)).sum() + hs @ (Hss @ hs))[None]


@dataclass
class ArrowResult:
    """What :func:`lm_arrow` found.

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


def lm_arrow(fun: Callable[[Tensor, Tensor], tuple[Tensor, Tensor, Tensor]], Z0: Tensor, s0: Tensor, zfree: Tensor,
             sfree: Tensor, settings=None, **kw) -> ArrowResult:
    """Minimise ``Σ_r ||r_r(z_r, s)||²`` with the one LM iteration and the :class:`Arrow` step.

    Args:
        fun: ``(Z (R, kz), s (ks,)) -> (r (R, m), Jz (R, m, kz), Js (R, m, ks))``.
        Z0, s0: the start; ``zfree (R, kz)``, ``sfree (ks,)``: which entries move.
        settings, kw: :class:`~torchcal.optim.lm_batched.LMBatchedOptions` and/or its fields
            (``max_iter`` defaults to 200 here).
    Returns:
        an :class:`ArrowResult` (``Jz`` over all ``kz`` columns, fixed ones zeroed).
    """
    from torchcal.optim.lm_batched import LMBatchedOptions, lm_batched  # the iteration imports this module

    opt = LMBatchedOptions.build(settings, **{"max_iter": 200, **kw})
    cols = torch.nonzero(zfree.any(0)).flatten()  # work on the columns some block fits
    R, kz, ks = Z0.shape[0], cols.numel(), s0.numel()
    zf, sf = zfree[:, cols].to(Z0.dtype), sfree.to(Z0.dtype)
    Zfull, last = Z0.clone(), {}

    def unpack(X: Tensor) -> tuple[Tensor, Tensor]:
        Z = Zfull.clone()
        Z[:, cols] = X[0, : R * kz].reshape(R, kz)
        return Z, X[0, R * kz:]

    def residuals(X: Tensor, idx: Tensor) -> Tensor:
        r, Jz, Js = fun(*unpack(X))
        last.update(x=X, J=(Jz[None, :, :, cols] * zf[None, :, None, :], (Js * sf)[None]))
        return r.reshape(1, -1)

    def jacobian(X: Tensor, idx: Tensor) -> tuple:
        if "x" not in last or not torch.equal(last["x"], X):  # asked where the residuals were not
            residuals(X, idx)
        return last["J"]

    x0 = torch.cat([Z0[:, cols].flatten(), s0])[None]
    free = torch.cat([zfree[:, cols].flatten(), sfree])[None]
    inf = torch.full_like(x0[0], float("inf"))
    res = lm_batched(residuals, jacobian, x0, free, -inf, inf, opt, linear=Arrow(R, kz, ks))
    Z, s = unpack(res.x)
    Jz, Js = res.jacobian
    Jout = Jz.new_zeros(R, Jz.shape[2], Z0.shape[1])
    Jout[:, :, cols] = Jz[0]
    return ArrowResult(Z=Z, s=s, r=res.residuals.reshape(R, -1), Jz=Jout, Js=Js[0], sse=float(res.sse[0]),
                       n_iter=int(res.n_iter[0]), n_jac=int(res.n_jac[0]), converged=bool(res.converged[0]),
                       message=res.messages[0], wall_time_s=res.wall_time_s)
