"""Levenberg-Marquardt over a batch of least-squares problems: the one LM iteration of torchcal.

Each problem ``b`` has its own parameter vector ``x_b`` (``(K,)``, a free mask chooses what moves),
its own residuals, damping, step acceptance and stopping test: Nielsen's gain-ratio rule, Marquardt
scaling, the bound active set (:mod:`torchcal.damping` states every rule once). A single problem is
a batch of one (the engine's :class:`~torchcal.optim.LevenbergMarquardt` runs this iteration one
step at a time); a fleet is a batch of robots; the loop's CV folds and prior scales of one candidate
are a batch of problems that differ only in row masks and prior rows. A problem leaves the batch
when it stops, so the remaining ones are not slowed by those already done.

The linear step is a strategy (:mod:`torchcal.optim.lm_linear`): :class:`~torchcal.optim.lm_linear.
DenseCholesky` (one batched Cholesky, the default) or :class:`~torchcal.optim.lm_linear.Arrow` (one
problem of many blocks tied by shared parameters, solved by Schur complement: the coupled fleet).

Ragged problems (different numbers of rows) are padded, and the callbacks own row masks: a row a
problem does not use is a zero residual and a zero Jacobian row and changes nothing. Fixed
parameters are masked: their Jacobian columns are zeroed and they are held like a parameter on an
active bound, so each problem solves exactly its own free system.

Every decision is a batched tensor: an iteration waits for the device four times (which problems
are still going, which steps could be tried, which were taken, which need a new Jacobian),
however many problems there are. Why each problem stopped is a code and its sums of squares are
recorded per iteration; both become words and per-problem lists only when read.
"""
from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Callable, NamedTuple

import torch
from torch import Tensor

from torchcal.damping import (TAU, damp_harder, gain_ratio, gradient_cosine, initial_damping, nielsen_update,
                              predicted_decrease, scaling_floor, small_decrease, small_step)
from torchcal.optim.lm_batched_result import (STOP_BLOWN, STOP_FTOL, STOP_GTOL, STOP_GTOL0, STOP_XTOL,
                                             BatchedLMResult)
from torchcal.optim.lm_linear import DenseCholesky
from torchcal.options import Options

__all__ = ["lm_batched", "LMBatchedOptions", "BatchedLMResult", "Batch"]

_F64 = torch.float64
# With Jacobian reuse, a Jacobian computed within this relative distance of the current point
# counts as fresh: its error moves the solution by about this fraction of the last correction.
_JTOL = 1e-6
SCALINGS = ("marquardt", "identity")


@dataclass(frozen=True)
class LMBatchedOptions(Options):
    """Settings of the one Levenberg-Marquardt iteration.

    Attributes:
        max_iter: most trial steps per problem.
        tau: the initial damping relative to the problem's scale (:func:`torchcal.damping.initial_damping`;
            default :data:`torchcal.damping.TAU`).
        mu0: an absolute initial damping instead (overrides ``tau``).
        scaling: ``"marquardt"`` (``D = diag(JᵀJ)``, its running maximum, floored at 1e-6 of its
            largest entry so that directions the data barely see stay damped) or ``"identity"``.
        gtol, xtol, ftol: stop when MINPACK's gradient cosine ``max_i |J_iᵀr| / (|J_i| |r|)`` (on the
            projected gradient) is below ``gtol``, when ``|h| < xtol (|x| + xtol)``, or when both the
            actual and the predicted relative decrease of the sum of squares are below ``ftol``.
        reuse: ``None``: a new Jacobian after every accepted step. A gain ratio: keep the Jacobian
            after an accepted step whose gain ratio exceeds it (the linear model predicted the
            decrease well). A kept Jacobian is refreshed when a step fails and before any stopping
            test is believed, so every problem stops on a fresh Jacobian; it costs fewer Jacobians
            and somewhat different iterates.
    """

    max_iter: int = 500
    tau: float = TAU
    mu0: float | None = None
    scaling: str = "marquardt"
    gtol: float = 1e-10
    xtol: float = 1e-10
    ftol: float = 1e-12
    reuse: float | None = None

    def __post_init__(self):
        if self.scaling not in SCALINGS:
            raise ValueError(f"scaling must be 'marquardt' or 'identity', got {self.scaling!r}")
        if not self.tau > 0:
            raise ValueError(f"tau must be positive, got {self.tau}")
        if self.mu0 is not None and not self.mu0 > 0:
            raise ValueError(f"mu0 must be positive, got {self.mu0}")


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


class Batch:
    """The iterates of ``B`` problems and what each step needs of them (see :func:`lm_batched`).

    ``x (B, c)``, ``free``, ``lower``, ``upper`` are over the columns the iteration works on
    (``linear.columns``); ``J`` is the Jacobian over the callback's columns and ``Jc`` over the
    worked ones, in the strategy's layout; ``A`` (JᵀJ, the strategy's layout), ``g`` (Jᵀr), ``move``
    (free and not held on an active bound) and ``ge`` (the gradient over ``move``) per problem."""

    def __init__(self, residuals: Callable, jacobian: Callable, x0: Tensor, free: Tensor, lower: Tensor,
                 upper: Tensor, jac0=None, columns: Tensor | None = None, opt: LMBatchedOptions | None = None,
                 linear=None):
        self.residuals, self.jacobian = residuals, jacobian
        self.opt = opt or LMBatchedOptions()
        self.lin = linear or DenseCholesky()
        x = x0.to(_F64).clone()
        B, K = x.shape
        free = free.to(torch.bool).expand(B, K)
        lower = lower.to(x).expand(B, K)
        upper = upper.to(x).expand(B, K)
        self.bounded = bool((torch.isfinite(lower) | torch.isfinite(upper))[free].any())
        if self.bounded:
            x = torch.where(free, torch.clamp(x, lower, upper), x)
        self.everyone = torch.arange(B, device=x.device)
        self.cols = self.lin.columns(free)
        self.pos = _positions(columns, self.cols, K)
        # every one of the callback's columns is worked on, in order: its Jacobian is used as it comes
        self.as_given = columns is None and self.cols.numel() == K
        self.full = x.clone()
        self._linearise_start(jac0)
        cols = self.cols
        self.x, self.free, self.lower, self.upper = x[:, cols], free[:, cols], lower[:, cols], upper[:, cols]
        self._damping_start()

    def _linearise_start(self, jac0) -> None:
        """Residuals and Jacobians at the start, and the counters."""
        B = self.full.shape[0]
        self.r = self.residuals(self.full, self.everyone).to(_F64)
        self.n_iter = torch.zeros(B, dtype=torch.long, device=self.full.device)
        self.n_evals, self.n_jac, self.n_rej = (torch.ones_like(self.n_iter), torch.zeros_like(self.n_iter),
                                                torch.zeros_like(self.n_iter))
        if jac0 is None:
            self.J = self.jacobian(self.full, self.everyone)  # the callback's columns, returned
            self.n_jac += 1
        else:
            self.J = jac0
        if isinstance(self.J, Tensor):
            self.J = self.J.to(_F64)
        self.Jc = self.J if self.as_given else self.lin.take(self.J, self.pos)  # the columns the solver works on

    def _damping_start(self) -> None:
        """Normal equations, scaling, damping and the stopping state at the start."""
        opt, x = self.opt, self.x
        self.A = self.lin.gram(self.Jc, self.free)
        self.g, self.move, self.ge = self.equations(self.everyone)
        self.S = (self.r * self.r).sum(-1)
        dA = self.lin.diagonal(self.A)
        self.gnorm = gradient_cosine(self.ge, dA, self.S)
        self.xnorm = torch.linalg.vector_norm(x * self.free, dim=-1)
        dmax = dA.amax(-1, keepdim=True) if dA.shape[-1] else dA.new_zeros(dA.shape[0], 1)
        self.marquardt = opt.scaling == "marquardt"
        # floor the scaling: a near-zero column would otherwise get no damping
        self.Dvec = scaling_floor(dA, dmax) if self.marquardt else torch.ones_like(dA)
        if opt.mu0 is not None:
            self.mu = torch.full((x.shape[0],), float(opt.mu0), dtype=_F64, device=x.device)
        else:  # Marquardt's scaling carries the problem's units: mu0 = tau; identity: relative to max diag
            self.mu = initial_damping(opt.tau, dmax[:, 0]) if not self.marquardt else \
                torch.full((x.shape[0],), float(opt.tau), dtype=_F64, device=x.device)
        self.nu = torch.full_like(self.mu, 2.0)
        self.converged = self.gnorm < opt.gtol
        self.stop = torch.where(self.converged, STOP_GTOL0, 0)
        self.trace = [(self.everyone, self.S.clone())]
        self.done = self.converged.clone()
        self.xJ = x.clone()  # where each problem's Jacobian was computed

    # -- views and refreshes -----------------------------------------------------------------
    def at(self, xr: Tensor, idx: Tensor) -> Tensor:
        """Problems ``idx``'s full parameter vectors with the worked columns ``xr``."""
        X = self.full[idx].clone()
        X[:, self.cols] = xr
        return X

    def equations(self, idx: Tensor):
        """``Jᵀr`` over the free columns, which entries move (free and, with bounds, not held on an
        active bound) and the gradient over those."""
        g = self.lin.gradient(self.lin.rows(self.Jc, idx), self.r[idx], self.free[idx])
        move = self.free[idx]
        if self.bounded:
            x, lo, up = self.x[idx], self.lower[idx], self.upper[idx]
            move = move & ~(((x <= lo) & (g > 0)) | ((x >= up) & (g < 0)))
        return g, move, g * move.to(g.dtype)

    def stale(self, idx: Tensor) -> Tensor:
        """The Jacobian is from a point farther than ``_JTOL`` (relative) from the current one."""
        d = torch.linalg.vector_norm((self.x[idx] - self.xJ[idx]) * self.free[idx], dim=-1)
        return d > _JTOL * (self.xnorm[idx] + _JTOL)

    def new_jacobian(self, idx: Tensor) -> None:
        if idx.numel():
            Jn = self.jacobian(self.at(self.x[idx], idx), idx)
            if isinstance(Jn, Tensor):
                Jn = Jn.to(_F64)
            lin = self.lin
            # every problem at once (a single fit, always): the new Jacobian replaces the old, no copy
            whole = idx.numel() == self.everyone.numel()
            if whole:
                self.J = Jn
            else:
                lin.put(self.J, idx, Jn)
            Jn = Jn if self.as_given else lin.take(Jn, self.pos)
            if whole:
                self.Jc = Jn
            else:
                lin.put(self.Jc, idx, Jn)
            lin.put(self.A, idx, lin.gram(Jn, self.free[idx]))
            self.n_jac[idx] += 1
            self.xJ[idx] = self.x[idx]

    def relinearise(self, idx: Tensor, new_jac: bool) -> None:
        if not idx.numel():  # nothing to do (and a strategy need not read an empty batch)
            return
        self.g[idx], self.move[idx], self.ge[idx] = self.equations(idx)
        dA = self.lin.diagonal(self.lin.rows(self.A, idx))
        if new_jac and self.marquardt:
            self.Dvec[idx] = torch.maximum(self.Dvec[idx], dA)
        self.gnorm[idx] = gradient_cosine(self.ge[idx], dA, self.S[idx])

    # -- one iteration -------------------------------------------------------------------------
    def active(self) -> Tensor:
        """The problems still going."""
        return torch.nonzero(~self.done & (self.n_iter < self.opt.max_iter)).flatten()

    def iterate(self, act: Tensor) -> None:
        """One trial step of each problem in ``act``."""
        self.n_iter[act] += 1
        h, ok = self.factor(act)
        # one wait: usually every factor exists, and the whole batch steps without picking rows
        if bool(ok.all()):
            o = act
        else:
            keep = torch.nonzero(ok).flatten()
            o, h = act[keep], h[keep]
        if o.numel():
            self.step(o, h)
        self.trace.append((act, self.S[act]))
        blown = ~self.converged[act] & ~torch.isfinite(self.mu[act])
        self.stop[act] = torch.where(blown, STOP_BLOWN, self.stop[act])
        self.done[act] = self.converged[act] | blown

    def factor(self, act: Tensor) -> tuple[Tensor, Tensor]:
        """The damped steps, and which exist; where one does not, mu tiny against a singular JᵀJ lost
        positive definiteness: damp harder."""
        h, ok = self.lin.solve(self.lin.rows(self.A, act), self.move[act], self.mu[act, None] * self.Dvec[act],
                               -self.ge[act])
        self.mu[act], self.nu[act] = damp_harder(self.mu[act], self.nu[act], ~ok)
        self.n_rej[act] += (~ok).long()
        return h, ok

    def trial(self, o: Tensor, h: Tensor) -> _Trial:
        """Evaluate where the steps ``h`` of problems ``o`` lead, and judge them."""
        opt = self.opt
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
        pred = predicted_decrease((h * self.g[o]).sum(-1), self.lin.curvature(self.lin.rows(self.A, o), h))
        gain = S_old - S_new
        rho = gain_ratio(gain, pred, S_new)
        return _Trial(h, x_new, r_new, S_new, rho, small_decrease(gain, pred, S_old, rho, opt.ftol),
                      small_step(torch.sqrt(hh), self.xnorm[o], opt.xtol))

    def step(self, o: Tensor, h: Tensor) -> None:
        """Try the steps of problems ``o``, take those that lower the sum of squares, refresh the
        Jacobians that need it and apply the stopping tests."""
        t = self.trial(o, h)
        acc = t.rho > 0
        stale_step = self.stale(o)
        # taken steps written by mask, not by picked rows: no wait for the device
        a1 = acc[:, None]
        self.x[o] = torch.where(a1, t.x, self.x[o])
        self.r[o] = torch.where(a1, t.r, self.r[o])
        self.S[o] = torch.where(acc, t.S, self.S[o])
        self.xnorm[o] = torch.where(acc, torch.linalg.vector_norm(t.x * self.free[o], dim=-1), self.xnorm[o])
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
               jac0=None, columns: Tensor | None = None, linear=None, **kw) -> BatchedLMResult:
    """Minimise ``B`` sums of squares with Levenberg-Marquardt.

    Args:
        residuals: ``(X (b, K), idx (b,)) -> (b, m)`` residuals of problems ``idx`` at ``X``.
        jacobian: ``(X (b, K), idx (b,)) -> (b, m, c)`` their Jacobians over ``columns``.
        x0: ``(B, K)`` start; ``free``: ``(B, K)`` bool, what each problem fits.
        lower, upper: ``(K,)`` or ``(B, K)`` bounds, as :class:`~torchcal.optim.LevenbergMarquardt`
            uses them (clipping plus an active set).
        settings, kw: an :class:`LMBatchedOptions` and/or its fields as keywords (``max_iter``,
            ``tau``, ``mu0``, ``scaling``, ``gtol``, ``xtol``, ``ftol``, ``reuse``).
        linear: the linear-step strategy (:mod:`torchcal.optim.lm_linear`; default
            :class:`~torchcal.optim.lm_linear.DenseCholesky`, independent problems).
        columns: ``(c,)`` the parameters (indices into K) whose columns the jacobian callback
            returns (default all K); every parameter a problem fits must be among them.
        jac0: ``(B, m, c)`` the Jacobian at ``x0`` when the caller has it (saves one evaluation);
            float64 is used as it is, and may be written in place.
    Returns:
        a :class:`BatchedLMResult`.
    """
    opt = LMBatchedOptions.build(settings, **kw)
    t0 = time.perf_counter()
    batch = Batch(residuals, jacobian, x0, free, lower, upper, jac0, columns, opt, linear)
    while (act := batch.active()).numel():
        batch.iterate(act)
    return batch.result(time.perf_counter() - t0)
