"""Levenberg-Marquardt over a batch of independent least-squares problems (a fleet of robots).

Each problem ``b`` has its own parameter vector ``x_b`` (``(K,)``, a free mask chooses what moves),
its own residuals, damping, step acceptance and stopping test: the iteration of
:class:`~torchcal.optim.LevenbergMarquardt` (Nielsen's gain-ratio rule, Marquardt scaling, the
bound active set) run for every problem at once. The normal equations are one batched Cholesky
``(B, K, K)``; residuals and Jacobians come from batched callbacks. A problem leaves the batch when
it stops, so the remaining ones are not slowed by those already done.

Ragged problems (different numbers of rows) are padded: padded residual rows and Jacobian rows are
zero and change nothing. Fixed parameters are masked: their Jacobian columns are zeroed and they
are held like a parameter on an active bound, so each problem solves exactly its own free system.

Every decision is a batched tensor: an iteration waits for the device four times (which problems
are still going, which steps could be tried, which were taken, which need a new Jacobian),
however many problems there are. Why each problem stopped is a code and its sums of squares are
recorded per iteration; both become words and per-problem lists only when read.

The step rules are :mod:`torchcal.damping`'s, the single solver's, on a tensor per rule. The loop is
its own rather than an engine solver (:mod:`torchcal.optim.engine`): the engine follows one
iterate and ends the run when a step says so, while here every problem carries its own iterate,
damping, Jacobian age and stopping reason, and leaves the batch on its own iteration.
"""
from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Callable, NamedTuple

import torch
from torch import Tensor

from torchcal.damping import (damp_harder, gain_ratio, gradient_cosine, nielsen_update, predicted_decrease,
                              scaling_floor, small_decrease, small_step)
from torchcal.optim.lm_batched_result import (STOP_BLOWN, STOP_FTOL, STOP_GTOL, STOP_GTOL0, STOP_XTOL,
                                             BatchedLMResult)
from torchcal.options import Options

__all__ = ["lm_batched", "LMBatchedOptions", "BatchedLMResult"]

_F64 = torch.float64
# With Jacobian reuse, a Jacobian computed within this relative distance of the current point
# counts as fresh: its error moves the solution by about this fraction of the last correction.
_JTOL = 1e-6


@dataclass(frozen=True)
class LMBatchedOptions(Options):
    """Settings of :func:`lm_batched`.

    Attributes:
        max_iter: most trial steps per problem.
        tau: the initial damping ``mu0`` (dimensionless: Marquardt scaling, as ``tau`` of
            :class:`~torchcal.optim.LevenbergMarquardt` there).
        gtol, xtol, ftol: the stopping tests of :class:`~torchcal.optim.LevenbergMarquardt`
            (gradient cosine, relative step, relative decrease of the sum of squares).
        reuse: ``None``: a new Jacobian after every accepted step, as the single solver (the
            same iterates, to rounding). A gain ratio: keep the Jacobian after an accepted step
            whose gain ratio exceeds it (the linear model predicted the decrease well). A kept
            Jacobian is refreshed when a step fails and before any stopping test is believed, so
            every problem stops on a fresh Jacobian, at the single solver's minimum; it costs
            fewer Jacobians and somewhat different iterates.
    """

    max_iter: int = 500
    tau: float = 1e-6
    gtol: float = 1e-10
    xtol: float = 1e-10
    ftol: float = 1e-12
    reuse: float | None = None


def _gram(J: Tensor, free: Tensor) -> Tensor:
    """``JᵀJ`` of each problem over its free columns (fixed ones zeroed): ``(B, k, k)``."""
    J = J * free[:, None, :].to(J.dtype)
    return torch.bmm(J.transpose(-1, -2), J)


def _equations(A: Tensor | None, J: Tensor, r: Tensor, x: Tensor, free: Tensor, lower: Tensor | None,
               upper: Tensor | None):
    """``Jᵀr`` over the free columns, and the normal equations with parameters held on an active
    bound (``lower``/``upper`` given) removed too (1 on their diagonal, so their step is 0). ``A``
    is :func:`_gram` of ``J``: a step that keeps the Jacobian changes only the residuals, so only
    ``Jᵀr`` is recomputed (and, without bounds, nothing else: ``A`` None then returns ``Ae`` None)."""
    g = torch.bmm(J.transpose(-1, -2), r[..., None])[..., 0] * free.to(J.dtype)
    move = free
    if lower is not None:
        held = ((x <= lower) & (g > 0)) | ((x >= upper) & (g < 0))
        move = move & ~held
    f = move.to(g.dtype)
    Ae = None
    if A is not None:
        Ae = A * (f[:, :, None] * f[:, None, :])
        Ae.diagonal(dim1=-2, dim2=-1).add_(1.0 - f)
    ge = g * f
    return g, Ae, ge


def _positions(columns: Tensor | None, cols: Tensor, K: int) -> Tensor:
    """Where the fitted parameters ``cols`` sit among the Jacobian callback's ``columns``."""
    if columns is None:
        return cols
    where = torch.full((K,), -1, dtype=torch.long, device=cols.device)
    where[columns] = torch.arange(columns.numel(), device=cols.device)
    pos = where[cols]
    if bool((pos < 0).any()):
        raise ValueError("lm_batched: a free parameter is missing from `columns`, the parameters the jacobian "
                         "callback returns; name every parameter any problem fits")
    return pos


class _Trial(NamedTuple):
    """A trial step of problems ``o``: the step ``h``, where it leads and how it fared."""

    h: Tensor
    x: Tensor
    r: Tensor
    S: Tensor
    rho: Tensor
    small_f: Tensor
    small_x: Tensor


class _Batch:
    """The iterates of ``B`` problems and what each step needs of them (see :func:`lm_batched`).

    ``x (B, c)``, ``free``, ``lower``, ``upper`` are over the columns some problem fits; ``J (B, m,
    c')`` over the callback's columns, ``Jc`` over the fitted ones; ``A`` (JᵀJ), ``g`` (Jᵀr), ``Ae``
    and ``ge`` (the same with held parameters removed) are filled in place, so ``dA``, a view of
    ``A``'s diagonal, follows them."""

    def __init__(self, residuals: Callable, jacobian: Callable, x0: Tensor, free: Tensor, lower: Tensor,
                 upper: Tensor, jac0: Tensor | None, columns: Tensor | None, opt: LMBatchedOptions):
        self.residuals, self.jacobian, self.opt = residuals, jacobian, opt
        x = x0.to(_F64).clone()
        B, K = x.shape
        free = free.to(torch.bool).expand(B, K)
        lower = lower.to(x).expand(B, K)
        upper = upper.to(x).expand(B, K)
        self.bounded = bool((torch.isfinite(lower) | torch.isfinite(upper))[free].any())
        if self.bounded:
            x = torch.where(free, torch.clamp(x, lower, upper), x)
        self.everyone = torch.arange(B, device=x.device)
        # work on the columns some problem fits: a fleet fixes the same many parameters everywhere
        self.cols = torch.nonzero(free.any(0)).flatten()
        self.pos = _positions(columns, self.cols, K)
        self.full = x.clone()
        self._linearise_start(jac0)
        cols = self.cols
        self.x, self.free, self.lower, self.upper = x[:, cols], free[:, cols], lower[:, cols], upper[:, cols]
        self._damping_start()

    def _linearise_start(self, jac0: Tensor | None) -> None:
        """Residuals and Jacobians at the start, and the counters."""
        B = self.full.shape[0]
        self.r = self.residuals(self.full, self.everyone).to(_F64)
        self.n_iter = torch.zeros(B, dtype=torch.long, device=self.full.device)
        self.n_evals, self.n_jac, self.n_rej = (torch.ones_like(self.n_iter), torch.zeros_like(self.n_iter),
                                                torch.zeros_like(self.n_iter))
        if jac0 is None:
            self.J = self.jacobian(self.full, self.everyone).to(_F64)  # the callback's columns, returned
            self.n_jac += 1
        else:
            self.J = jac0.to(_F64)
        self.Jc = self.J[:, :, self.pos]  # the columns the solver works on

    def _damping_start(self) -> None:
        """Normal equations, scaling, damping and the stopping state at the start."""
        opt, x = self.opt, self.x
        self.A = _gram(self.Jc, self.free)
        self.g, self.Ae, self.ge = self.equations(self.everyone)
        self.S = (self.r * self.r).sum(-1)
        self.dA = self.A.diagonal(dim1=-2, dim2=-1)  # a view: it follows A as A is filled in place
        self.gnorm = gradient_cosine(self.ge, self.dA, self.S)
        self.xnorm = torch.linalg.vector_norm(x * self.free, dim=-1)
        # floor the scaling: a near-zero column would otherwise get no damping (as the single solver)
        dmax = self.dA.amax(-1, keepdim=True) if self.dA.shape[-1] else self.dA.new_zeros(self.dA.shape[0], 1)
        self.Dvec = scaling_floor(self.dA, dmax)
        self.mu = torch.full((x.shape[0],), float(opt.tau), dtype=_F64, device=x.device)
        self.nu = torch.full_like(self.mu, 2.0)
        self.converged = self.gnorm < opt.gtol
        self.stop = torch.where(self.converged, STOP_GTOL0, 0)
        self.trace = [(self.everyone, self.S.clone())]
        self.done = self.converged.clone()
        self.xJ = x.clone()  # where each problem's Jacobian was computed

    # -- views and refreshes -----------------------------------------------------------------
    def at(self, xr: Tensor, idx: Tensor) -> Tensor:
        """Problems ``idx``'s full parameter vectors with the fitted columns ``xr``."""
        X = self.full[idx].clone()
        X[:, self.cols] = xr
        return X

    def equations(self, idx: Tensor, with_Ae: bool = True):
        if self.bounded:
            return _equations(self.A[idx], self.Jc[idx], self.r[idx], self.x[idx], self.free[idx], self.lower[idx],
                              self.upper[idx])
        return _equations(self.A[idx] if with_Ae else None, self.Jc[idx], self.r[idx], self.x[idx], self.free[idx],
                          None, None)

    def stale(self, idx: Tensor) -> Tensor:
        """The Jacobian is from a point farther than ``_JTOL`` (relative) from the current one."""
        d = torch.linalg.vector_norm((self.x[idx] - self.xJ[idx]) * self.free[idx], dim=-1)
        return d > _JTOL * (self.xnorm[idx] + _JTOL)

    def new_jacobian(self, idx: Tensor) -> None:
        if idx.numel():
            Jn = self.jacobian(self.at(self.x[idx], idx), idx).to(_F64)
            self.J[idx] = Jn
            Jn = Jn[:, :, self.pos]
            self.Jc[idx] = Jn
            self.A[idx] = _gram(Jn, self.free[idx])
            self.n_jac[idx] += 1
            self.xJ[idx] = self.x[idx]

    def relinearise(self, idx: Tensor, new_jac: bool) -> None:
        self.g[idx], Ae_i, self.ge[idx] = self.equations(idx, with_Ae=new_jac)
        if Ae_i is not None:
            self.Ae[idx] = Ae_i
        if new_jac:
            self.Dvec[idx] = torch.maximum(self.Dvec[idx], self.dA[idx])
        self.gnorm[idx] = gradient_cosine(self.ge[idx], self.dA[idx], self.S[idx])

    # -- one iteration -------------------------------------------------------------------------
    def active(self) -> Tensor:
        """The problems still going."""
        return torch.nonzero(~self.done & (self.n_iter < self.opt.max_iter)).flatten()

    def iterate(self, act: Tensor) -> None:
        """One trial step of each problem in ``act``."""
        self.n_iter[act] += 1
        L, ok = self.factor(act)
        o = act[ok]
        if o.numel():
            self.step(o, L[ok])
        self.trace.append((act, self.S[act]))
        blown = ~self.converged[act] & ~torch.isfinite(self.mu[act])
        self.stop[act] = torch.where(blown, STOP_BLOWN, self.stop[act])
        self.done[act] = self.converged[act] | blown

    def factor(self, act: Tensor) -> tuple[Tensor, Tensor]:
        """Cholesky factors of the damped normal equations, and which exist; where one does not, mu
        tiny against a singular JᵀJ lost positive definiteness: damp harder."""
        M = self.Ae[act]
        M.diagonal(dim1=-2, dim2=-1).add_(self.mu[act, None] * self.Dvec[act])
        L, info = torch.linalg.cholesky_ex(M)
        ok = info == 0
        self.mu[act], self.nu[act] = damp_harder(self.mu[act], self.nu[act], ~ok)
        self.n_rej[act] += (~ok).long()
        return L, ok

    def trial(self, o: Tensor, L: Tensor) -> _Trial:
        """Solve for the steps of problems ``o``, evaluate where they lead, and judge them."""
        opt = self.opt
        h = torch.cholesky_solve(-self.ge[o, :, None], L)[..., 0]
        xo = self.x[o]
        x_new = xo + h
        if self.bounded:
            x_new = torch.where(self.free[o], torch.clamp(x_new, self.lower[o], self.upper[o]), x_new)
            h = x_new - xo
        r_new = self.residuals(self.at(x_new, o), o).to(_F64)
        self.n_evals[o] += 1
        S_old = self.S[o]
        S_new = (r_new * r_new).sum(-1)
        hh = (h * h).sum(-1)
        # |J h|² = hᵀ JᵀJ h: h is 0 on fixed entries, where A's rows and columns are zeroed
        hAh = (h * torch.bmm(self.A[o], h[..., None])[..., 0]).sum(-1)
        pred = predicted_decrease((h * self.g[o]).sum(-1), hAh)
        gain = S_old - S_new
        rho = gain_ratio(gain, pred, S_new)
        return _Trial(h, x_new, r_new, S_new, rho, small_decrease(gain, pred, S_old, rho, opt.ftol),
                      small_step(torch.sqrt(hh), self.xnorm[o], opt.xtol))

    def step(self, o: Tensor, L: Tensor) -> None:
        """Try the steps of problems ``o``, take those that lower the sum of squares, refresh the
        Jacobians that need it and apply the stopping tests."""
        t = self.trial(o, L)
        acc = t.rho > 0
        ia = o[acc]
        stale_step = self.stale(o)
        self.x[ia], self.r[ia], self.S[ia] = t.x[acc], t.r[acc], t.S[acc]
        self.xnorm[ia] = torch.linalg.vector_norm(self.x[ia] * self.free[ia], dim=-1)
        # accepted: damping from the gain ratio; rejected on a fresh Jacobian: damp harder (a
        # step from an old Jacobian is retried with a new one)
        self.mu[o], self.nu[o] = nielsen_update(self.mu[o], self.nu[o], t.rho, grow=~acc & ~stale_step)
        self.n_rej[o] += (~acc).long()
        got = self.refresh(o, t, acc, stale_step)
        self.judge(o, t, acc | got, stale_step)

    def refresh(self, o: Tensor, t: _Trial, acc: Tensor, stale_step: Tensor) -> Tensor:
        """New Jacobians for problems ``o`` where wanted (one batched evaluation); which got one."""
        opt = self.opt
        if opt.reuse is None:
            got, need = acc, o[acc]
        else:
            # a new Jacobian where the old one predicted badly and is not from (nearly) here,
            # where a step from an old one failed, and where a stopping test fired on an old one
            # (stopping tests count only on a fresh Jacobian: gtol's at the new point, ftol's
            # and xtol's at the step's start)
            self.relinearise(o[acc], False)
            want = ((acc & ((t.rho <= opt.reuse) | (self.gnorm[o] < opt.gtol)))
                    | ((~acc | t.small_f | t.small_x) & stale_step))
            got = want & self.stale(o)
            need = o[got]
        self.new_jacobian(need)
        self.relinearise(need, True)
        return got

    def judge(self, o: Tensor, t: _Trial, moved: Tensor, stale_step: Tensor) -> None:
        """The stopping tests of problems ``o``, believed only on a fresh Jacobian."""
        fresh_now, fresh_step = ~self.stale(o), ~stale_step
        c_g = moved & (self.gnorm[o] < self.opt.gtol) & fresh_now
        c_f = ~c_g & t.small_f & fresh_step
        c_x = ~c_g & ~c_f & t.small_x & fresh_step
        why = torch.where(c_f, STOP_FTOL, torch.where(c_x, STOP_XTOL, self.stop[o]))
        self.stop[o] = torch.where(c_g, STOP_GTOL, why)
        self.converged[o] = c_g | c_f | c_x

    def result(self, wall_time_s: float) -> BatchedLMResult:
        return BatchedLMResult(x=self.at(self.x, self.everyone), residuals=self.r, jacobian=self.J, sse=self.S,
                               n_iter=self.n_iter, n_evals=self.n_evals, n_jac=self.n_jac, n_rejected=self.n_rej,
                               converged=self.converged, stop=self.stop, max_iter=self.opt.max_iter,
                               trace=self.trace, wall_time_s=wall_time_s)


def lm_batched(residuals: Callable[[Tensor, Tensor], Tensor], jacobian: Callable[[Tensor, Tensor], Tensor],
               x0: Tensor, free: Tensor, lower: Tensor, upper: Tensor, settings: LMBatchedOptions | None = None, *,
               jac0: Tensor | None = None, columns: Tensor | None = None, **kw) -> BatchedLMResult:
    """Minimise ``B`` independent sums of squares with Levenberg-Marquardt (Marquardt scaling).

    Args:
        residuals: ``(X (b, K), idx (b,)) -> (b, m)`` residuals of problems ``idx`` at ``X``.
        jacobian: ``(X (b, K), idx (b,)) -> (b, m, c)`` their Jacobians over ``columns``.
        x0: ``(B, K)`` start; ``free``: ``(B, K)`` bool, what each problem fits.
        lower, upper: ``(K,)`` or ``(B, K)`` bounds, as :class:`~torchcal.optim.LevenbergMarquardt`
            uses them (clipping plus an active set).
        settings, kw: an :class:`LMBatchedOptions` and/or its fields as keywords (``max_iter``,
            ``tau``, ``gtol``, ``xtol``, ``ftol``, ``reuse``).
        columns: ``(c,)`` the parameters (indices into K) whose columns the jacobian callback
            returns (default all K); every parameter a problem fits must be among them.
        jac0: ``(B, m, c)`` the Jacobian at ``x0`` when the caller has it (saves one evaluation);
            float64 is used as it is and updated in place (it becomes the returned ``jacobian``).
    Returns:
        a :class:`BatchedLMResult`.
    """
    opt = LMBatchedOptions.build(settings, **kw)
    t0 = time.perf_counter()
    batch = _Batch(residuals, jacobian, x0, free, lower, upper, jac0, columns, opt)
    while (act := batch.active()).numel():
        batch.iterate(act)
    return batch.result(time.perf_counter() - t0)
