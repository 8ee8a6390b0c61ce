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
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Callable

import torch
from torch import Tensor

from torchcal.optim.result import Result

__all__ = ["lm_batched", "BatchedLMResult"]

_F64 = torch.float64
# With Jacobian reuse, a Jacobian computed within this relative distance of the current point
# counts as fresh: its error moves the solution by about this fraction of the last correction.
_JTOL = 1e-6


@dataclass
class BatchedLMResult:
    """What :func:`lm_batched` found for each of ``B`` problems.

    Attributes:
        x: ``(B, K)`` solutions (fixed entries keep their start values).
        residuals: ``(B, m)`` residuals at ``x`` (padded rows zero); ``jacobian``: ``(B, m, K)``
            Jacobian at ``x``, all K columns (fixed ones included: judging the parameters again at
            the solution needs them).
        sse: ``(B,)`` sums of squares (m² for position residuals).
        n_iter, n_evals, n_jac, n_rejected: ``(B,)`` trial steps, residual evaluations, Jacobian
            evaluations and rejected steps per problem.
        converged: ``(B,)`` bool; ``messages``: why each stopped; ``history``: the sum of squares
            at the current point after each trial step, per problem.
    """

    x: Tensor
    residuals: Tensor
    jacobian: Tensor
    sse: Tensor
    n_iter: Tensor
    n_evals: Tensor
    n_jac: Tensor
    n_rejected: Tensor
    converged: Tensor
    messages: list[str]
    history: list[list[float]] = field(default_factory=list)
    wall_time_s: float = 0.0

    def result(self, b: int, free: Tensor) -> Result:
        """Problem ``b`` as a single solver's :class:`~torchcal.optim.Result` (``x`` over its
        free entries ``free (K,)``)."""
        S = float(self.sse[b])
        return Result(x=self.x[b, free].clone(), fun=S, history=list(self.history[b]), n_evals=int(self.n_evals[b]),
                      n_iter=int(self.n_iter[b]), wall_time_s=self.wall_time_s, converged=bool(self.converged[b]),
                      message=self.messages[b], method="lm",
                      extra={"cost": 0.5 * S, "n_jac": int(self.n_jac[b]), "n_rejected": int(self.n_rejected[b])})


def _gram(J: Tensor, free: Tensor) -> Tensor:
    """``JᵀJ`` of each problem over its free columns (fixed ones zeroed): ``(B, k, k)``."""
    J = J * free[:, None, :].to(J.dtype)
    return torch.bmm(J.transpose(-1, -2), J)


def _equations(A: Tensor, J: Tensor, r: Tensor, x: Tensor, free: Tensor, lower: Tensor, upper: Tensor,
               bounded: bool):
    """``Jᵀr`` over the free columns, and the normal equations with parameters held on an active
    bound removed too (1 on their diagonal, so their step is 0). ``A`` is :func:`_gram` of ``J``:
    a step that keeps the Jacobian changes only the residuals, so only ``Jᵀr`` is recomputed."""
    g = torch.bmm(J.transpose(-1, -2), r[..., None])[..., 0] * free.to(J.dtype)
    move = free
    if bounded:
        held = ((x <= lower) & (g > 0)) | ((x >= upper) & (g < 0))
        move = move & ~held
    f = move.to(A.dtype)
    Ae = A * f[:, :, None] * f[:, None, :] + torch.diag_embed(1.0 - f)
    ge = g * f
    return g, Ae, ge


def _gcos(ge: Tensor, A: Tensor, S: Tensor) -> Tensor:
    """MINPACK's scale-free gradient test per problem: the largest cosine between r and a column of J."""
    den = torch.sqrt(A.diagonal(dim1=-2, dim2=-1).clamp(min=1e-300) * S.clamp(min=1e-300)[:, None])
    return torch.where(S > 0, (ge.abs() / den).amax(-1), torch.zeros_like(S))


def lm_batched(residuals: Callable[[Tensor, Tensor], Tensor], jacobian: Callable[[Tensor, Tensor], Tensor],
               x0: Tensor, free: Tensor, lower: Tensor, upper: Tensor, *, jac0: Tensor | None = None,
               max_iter: int = 500, tau: float = 1e-6, gtol: float = 1e-10, xtol: float = 1e-10,
               ftol: float = 1e-12, reuse: float | None = None) -> BatchedLMResult:
    """Minimise ``B`` independent sums of squares with Levenberg-Marquardt (Marquardt scaling).

    Args:
        residuals: ``(X (b, K), idx (b,)) -> (b, m)`` residuals of problems ``idx`` at ``X``.
        jacobian: ``(X (b, K), idx (b,)) -> (b, m, K)`` their Jacobians (all K columns).
        jac0: the Jacobian at ``x0`` when the caller has it (saves one evaluation).
        x0: ``(B, K)`` start; ``free``: ``(B, K)`` bool, what each problem fits.
        lower, upper: ``(K,)`` or ``(B, K)`` bounds, as :class:`~torchcal.optim.LevenbergMarquardt`
            uses them (clipping plus an active set).
        max_iter, tau, gtol, xtol, ftol: as for :class:`~torchcal.optim.LevenbergMarquardt`
            (``tau`` is the initial damping ``mu0``, as under Marquardt scaling there).
        reuse: ``None``: a new Jacobian after every accepted step, as the single solver (the
            same iterates, to rounding). A gain ratio: keep the Jacobian after an accepted step
            whose gain ratio exceeds it (the linear model predicted the decrease well). A kept
            Jacobian is refreshed when a step fails and before any stopping test is believed, so
            every problem stops on a fresh Jacobian, at the single solver's minimum; it costs
            fewer Jacobians and somewhat different iterates.
    Returns:
        a :class:`BatchedLMResult`.
    """
    t0 = time.perf_counter()
    x = x0.to(_F64).clone()
    B, K = x.shape
    free = free.to(torch.bool).expand(B, K)
    lower = lower.to(x).expand(B, K)
    upper = upper.to(x).expand(B, K)
    bounded = bool((torch.isfinite(lower) | torch.isfinite(upper))[free].any())
    if bounded:
        x = torch.where(free, torch.clamp(x, lower, upper), x)
    everyone = torch.arange(B, device=x.device)
    # work on the columns some problem fits: a fleet fixes the same many parameters everywhere
    cols = torch.nonzero(free.any(0)).flatten()
    full = x.clone()

    def at(xr: Tensor, idx: Tensor) -> Tensor:
        X = full[idx].clone()
        X[:, cols] = xr
        return X

    def equations(idx: Tensor):
        return _equations(A[idx], Jc[idx], r[idx], x[idx], free[idx], lower[idx], upper[idx], bounded)

    r = residuals(full, everyone).to(_F64)
    J = (jacobian(full, everyone) if jac0 is None else jac0).to(_F64).clone()  # all K columns, returned
    Jc = J[:, :, cols]  # the columns the solver works on
    x, free, lower, upper = x[:, cols], free[:, cols], lower[:, cols], upper[:, cols]
    A = _gram(Jc, free)  # JᵀJ of the current Jacobians; these are filled in place from here on
    g, Ae, ge = equations(everyone)
    S = (r * r).sum(-1)
    gnorm = _gcos(ge, A, S)
    xnorm = torch.linalg.vector_norm(x * free, dim=-1)
    dA = A.diagonal(dim1=-2, dim2=-1)
    dmax = dA.amax(-1, keepdim=True)
    # floor the scaling: a near-zero column would otherwise get no damping (as the single solver)
    Dvec = torch.where(dmax > 0, torch.maximum(dA, 1e-6 * dmax), torch.ones_like(dA))
    mu = torch.full((B,), float(tau), dtype=_F64, device=x.device)
    nu = torch.full_like(mu, 2.0)
    n_iter = torch.zeros(B, dtype=torch.long, device=x.device)
    n_evals, n_jac, n_rej = torch.ones_like(n_iter), torch.ones_like(n_iter), torch.zeros_like(n_iter)
    if jac0 is not None:
        n_jac.zero_()
    converged = gnorm < gtol
    messages = ["projected gradient below gtol at the start" if c else "" for c in converged.tolist()]
    history = [[s] for s in S.tolist()]
    done = converged.clone()
    xJ = x.clone()  # where each problem's Jacobian was computed

    def stale(idx: Tensor) -> Tensor:
        """The Jacobian is from a point farther than ``_JTOL`` (relative) from the current one."""
        return torch.linalg.vector_norm((x[idx] - xJ[idx]) * free[idx], dim=-1) > _JTOL * (xnorm[idx] + _JTOL)

    def new_jacobian(idx: Tensor) -> None:
        if idx.numel():
            Jn = jacobian(at(x[idx], idx), idx).to(_F64)
            J[idx] = Jn
            Jn = Jn[:, :, cols]
            Jc[idx] = Jn
            A[idx] = _gram(Jn, free[idx])
            n_jac[idx] += 1
            xJ[idx] = x[idx]

    def relinearise(idx: Tensor, new_jac: bool) -> None:
        g[idx], Ae[idx], ge[idx] = equations(idx)
        if new_jac:
            Dvec[idx] = torch.maximum(Dvec[idx], A[idx].diagonal(dim1=-2, dim2=-1))
        gnorm[idx] = _gcos(ge[idx], A[idx], S[idx])

    while True:
        act = torch.nonzero(~done & (n_iter < max_iter)).flatten()
        if act.numel() == 0:
            break
        n_iter[act] += 1
        L, info = torch.linalg.cholesky_ex(Ae[act] + mu[act, None, None] * torch.diag_embed(Dvec[act]))
        ok = info == 0
        fail = act[~ok]
        # mu tiny against a singular JᵀJ lost positive definiteness: damp harder
        mu[fail] *= nu[fail]
        nu[fail] *= 2.0
        n_rej[fail] += 1
        o = act[ok]
        if o.numel():
            h = torch.cholesky_solve(-ge[o, :, None], L[ok])[..., 0]
            xo = x[o]
            x_new = xo + h
            if bounded:
                x_new = torch.where(free[o], torch.clamp(x_new, lower[o], upper[o]), x_new)
                h = x_new - xo
            r_new = residuals(at(x_new, o), o).to(_F64)
            n_evals[o] += 1
            S_old = S[o]
            S_new = (r_new * r_new).sum(-1)
            hh = (h * h).sum(-1)
            # |J h|² = hᵀ JᵀJ h: h is 0 on fixed entries, where A's rows and columns are zeroed
            hAh = (h * torch.bmm(A[o], h[..., None])[..., 0]).sum(-1)
            pred = -2.0 * (h * g[o]).sum(-1) - hAh
            gain = S_old - S_new
            rho = torch.where((pred > 0) & torch.isfinite(S_new), gain / pred, torch.full_like(pred, -1.0))
            small_f = (gain.abs() <= ftol * S_old) & (pred <= ftol * S_old) & (rho <= 2.0)
            small_x = torch.sqrt(hh) <= xtol * (xnorm[o] + xtol)
            acc = rho > 0
            ia, rj = o[acc], o[~acc]
            stale_step = stale(o)
            if ia.numel():
                x[ia], r[ia], S[ia] = x_new[acc], r_new[acc], S_new[acc]
                xnorm[ia] = torch.linalg.vector_norm(x[ia] * free[ia], dim=-1)
                mu[ia] *= torch.clamp(1.0 - (2.0 * rho[acc] - 1.0) ** 3, min=1.0 / 3.0)
                nu[ia] = 2.0
            n_rej[rj] += 1
            grow = rj[~stale_step[~acc]]  # a step from an old Jacobian is retried with a new one
            mu[grow] *= nu[grow]
            nu[grow] *= 2.0
            if reuse is None:
                need = ia
            else:
                # a new Jacobian where the old one predicted badly and is not from (nearly) here,
                # where a step from an old one failed, and where a stopping test fired on an old one
                # (stopping tests count only on a fresh Jacobian: gtol's at the new point, ftol's
                # and xtol's at the step's start); one batched evaluation for all of them
                relinearise(ia, False)
                want = (acc & ((rho <= reuse) | (gnorm[o] < gtol))) | ((~acc | small_f | small_x) & stale_step)
                need = o[want]
                need = need[stale(need)]
            new_jacobian(need)
            relinearise(ia if reuse is None else need, True)
            fresh_now, fresh_step = ~stale(o), ~stale_step
            c_g = (acc | torch.isin(o, need)) & (gnorm[o] < gtol) & fresh_now
            c_f = ~c_g & small_f & fresh_step
            c_x = ~c_g & ~c_f & small_x & fresh_step
            for b, why in zip(o.tolist(), (c_g.long() + 2 * c_f.long() + 3 * c_x.long()).tolist()):
                if why:
                    messages[b] = ("projected gradient below gtol", "relative decrease of the sum of squares below "
                                   "ftol", "step below xtol")[why - 1]
            converged[o] = c_g | c_f | c_x
        for b, s in zip(act.tolist(), S[act].tolist()):
            history[b].append(s)
        blown = act[~converged[act] & ~torch.isfinite(mu[act])]
        for b in blown.tolist():
            messages[b] = "damping overflowed: no decrease found along any step"
        done[act] = converged[act]
        done[blown] = True
    for b in range(B):
        if not messages[b]:
            messages[b] = f"reached max_iter={max_iter}"
    return BatchedLMResult(x=at(x, everyone), residuals=r, jacobian=J, sse=S, n_iter=n_iter, n_evals=n_evals, n_jac=n_jac,
                           n_rejected=n_rej, converged=converged, messages=messages, history=history,
                           wall_time_s=time.perf_counter() - t0)
