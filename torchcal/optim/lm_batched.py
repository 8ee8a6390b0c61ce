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
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field
from functools import cached_property
from typing import Callable

import torch
from torch import Tensor

from torchcal.optim.result import Result

__all__ = ["lm_batched", "BatchedLMResult"]

_F64 = torch.float64
# With Jacobian reuse, a Jacobian computed within this relative distance of the current point
# counts as fresh: its error moves the solution by about this fraction of the last correction.
_JTOL = 1e-6
# Why a problem stopped, by code (0: the iteration cap).
_GTOL, _FTOL, _XTOL, _BLOWN, _GTOL0 = 1, 2, 3, 4, 5
_WHY = {_GTOL: "projected gradient below gtol", _FTOL: "relative decrease of the sum of squares below ftol",
        _XTOL: "step below xtol", _BLOWN: "damping overflowed: no decrease found along any step",
        _GTOL0: "projected gradient below gtol at the start"}


@dataclass
class BatchedLMResult:
    """What :func:`lm_batched` found for each of ``B`` problems.

    Attributes:
        x: ``(B, K)`` solutions (fixed entries keep their start values).
        residuals: ``(B, m)`` residuals at ``x`` (padded rows zero); ``jacobian``: ``(B, m, c)``
            Jacobian at ``x`` over the callback's columns (all K unless ``columns`` named them;
            fixed ones included: judging the parameters again at the solution needs them).
        sse: ``(B,)`` sums of squares (m² for position residuals).
        n_iter, n_evals, n_jac, n_rejected: ``(B,)`` trial steps, residual evaluations, Jacobian
            evaluations and rejected steps per problem.
        converged: ``(B,)`` bool; ``stop``: ``(B,)`` why each stopped, as a code (:attr:`messages`
            in words); ``trace``: per trial step, the problems that took it and their sums of
            squares afterwards (index 0: every problem at the start; :attr:`history` per problem).
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
    stop: Tensor
    max_iter: int
    trace: list[tuple[Tensor, Tensor]] = field(default_factory=list)
    wall_time_s: float = 0.0

    @cached_property
    def messages(self) -> list[str]:
        """Why each problem stopped, in words."""
        cap = f"reached max_iter={self.max_iter}"
        return [_WHY.get(c, cap) for c in self.stop.tolist()]

    @cached_property
    def history(self) -> list[list[float]]:
        """Per problem, the sum of squares at its current point after each trial step."""
        B = self.sse.shape[0]
        who = torch.cat([w for w, _ in self.trace])
        val = torch.cat([s for _, s in self.trace])
        order = torch.sort(who, stable=True).indices  # per problem, in the order the steps came
        counts = torch.bincount(who, minlength=B).tolist()
        flat = val[order].tolist()
        out, at = [], 0
        for n in counts:
            out.append(flat[at:at + n])
            at += n
        return out

    @cached_property
    def _numbers(self) -> dict[str, list]:
        """The per-problem counts and flags as Python lists, read from the device once."""
        return {k: getattr(self, k).tolist() for k in ("sse", "n_evals", "n_iter", "converged", "n_jac", "n_rejected")}

    def result(self, b: int, free: Tensor) -> Result:
        """Problem ``b`` as a single solver's :class:`~torchcal.optim.Result` (``x`` over its
        free entries ``free (K,)``)."""
        h = self._numbers
        S = h["sse"][b]
        return Result(x=self.x[b, free], fun=S, history=list(self.history[b]), n_evals=h["n_evals"][b],
                      n_iter=h["n_iter"][b], wall_time_s=self.wall_time_s, converged=h["converged"][b],
                      message=self.messages[b], method="lm",
                      extra={"cost": 0.5 * S, "n_jac": h["n_jac"][b], "n_rejected": h["n_rejected"][b]})


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


def _gcos(ge: Tensor, dA: Tensor, S: Tensor) -> Tensor:
    """MINPACK's scale-free gradient test per problem: the largest cosine between r and a column of J
    (``dA``: the diagonal of JᵀJ, the columns' squared norms)."""
    den = torch.sqrt(dA.clamp(min=1e-300) * S.clamp(min=1e-300)[:, None])
    return torch.where(S > 0, (ge.abs() / den).amax(-1), torch.zeros_like(S))



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


def lm_batched(residuals: Callable[[Tensor, Tensor], Tensor], jacobian: Callable[[Tensor, Tensor], Tensor],
               x0: Tensor, free: Tensor, lower: Tensor, upper: Tensor, *, jac0: Tensor | None = None,
               columns: Tensor | None = None, max_iter: int = 500,
               tau: float = 1e-6, gtol: float = 1e-10, xtol: float = 1e-10, ftol: float = 1e-12,
               reuse: float | None = None) -> BatchedLMResult:
    """Minimise ``B`` independent sums of squares with Levenberg-Marquardt (Marquardt scaling).

    Args:
        residuals: ``(X (b, K), idx (b,)) -> (b, m)`` residuals of problems ``idx`` at ``X``.
        jacobian: ``(X (b, K), idx (b,)) -> (b, m, c)`` their Jacobians over ``columns``.
        columns: ``(c,)`` the parameters (indices into K) whose columns the jacobian callback
            returns (default all K); every parameter a problem fits must be among them.
        jac0: ``(B, m, c)`` the Jacobian at ``x0`` when the caller has it (saves one evaluation);
            float64 is used as it is and updated in place (it becomes the returned ``jacobian``).
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
    pos = _positions(columns, cols, K)
    full = x.clone()

    def at(xr: Tensor, idx: Tensor) -> Tensor:
        X = full[idx].clone()
        X[:, cols] = xr
        return X

    def equations(idx: Tensor, with_Ae: bool = True):
        if bounded:
            return _equations(A[idx], Jc[idx], r[idx], x[idx], free[idx], lower[idx], upper[idx])
        return _equations(A[idx] if with_Ae else None, Jc[idx], r[idx], x[idx], free[idx], None, None)

    r = residuals(full, everyone).to(_F64)
    n_iter = torch.zeros(B, dtype=torch.long, device=x.device)
    n_evals, n_jac, n_rej = torch.ones_like(n_iter), torch.zeros_like(n_iter), torch.zeros_like(n_iter)
    if jac0 is None:
        J = jacobian(full, everyone).to(_F64)  # the callback's columns, returned
        n_jac += 1
    else:
        J = jac0.to(_F64)
    Jc = J[:, :, pos]  # the columns the solver works on
    x, free, lower, upper = x[:, cols], free[:, cols], lower[:, cols], upper[:, cols]
    A = _gram(Jc, free)  # JᵀJ of the current Jacobians; these are filled in place from here on
    g, Ae, ge = equations(everyone)
    S = (r * r).sum(-1)
    dA = A.diagonal(dim1=-2, dim2=-1)  # a view: it follows A as A is filled in place
    gnorm = _gcos(ge, dA, S)
    xnorm = torch.linalg.vector_norm(x * free, dim=-1)
    dmax = dA.amax(-1, keepdim=True)
    # floor the scaling: a near-zero column would otherwise get no damping (as the single solver)
    Dvec = torch.where(dmax > 0, torch.maximum(dA, 1e-6 * dmax), torch.ones_like(dA))
    mu = torch.full((B,), float(tau), dtype=_F64, device=x.device)
    nu = torch.full_like(mu, 2.0)
    converged = gnorm < gtol
    stop = torch.where(converged, _GTOL0, 0)
    trace = [(everyone, S.clone())]
    done = converged.clone()
    xJ = x.clone()  # where each problem's Jacobian was computed

    def stale(idx: Tensor) -> Tensor:
        """The Jacobian is from a point farther than ``_JTOL`` (relative) from the current one."""
        return torch.linalg.vector_norm((x[idx] - xJ[idx]) * free[idx], dim=-1) > _JTOL * (xnorm[idx] + _JTOL)

    def new_jacobian(idx: Tensor) -> None:
        if idx.numel():
            Jn = jacobian(at(x[idx], idx), idx).to(_F64)
            J[idx] = Jn
            Jn = Jn[:, :, pos]
            Jc[idx] = Jn
            A[idx] = _gram(Jn, free[idx])
            n_jac[idx] += 1
            xJ[idx] = x[idx]

    def relinearise(idx: Tensor, new_jac: bool) -> None:
        g[idx], Ae_i, ge[idx] = equations(idx, with_Ae=new_jac)
        if Ae_i is not None:
            Ae[idx] = Ae_i
        if new_jac:
            Dvec[idx] = torch.maximum(Dvec[idx], dA[idx])
        gnorm[idx] = _gcos(ge[idx], dA[idx], S[idx])

    while True:
        act = torch.nonzero(~done & (n_iter < max_iter)).flatten()
        if act.numel() == 0:
            break
        n_iter[act] += 1
        M = Ae[act]
        M.diagonal(dim1=-2, dim2=-1).add_(mu[act, None] * Dvec[act])
        L, info = torch.linalg.cholesky_ex(M)
        ok = info == 0
        # mu tiny against a singular JᵀJ lost positive definiteness: damp harder
        mu_a, nu_a = mu[act], nu[act]
        mu[act] = torch.where(ok, mu_a, mu_a * nu_a)
        nu[act] = torch.where(ok, nu_a, nu_a * 2.0)
        n_rej[act] += (~ok).long()
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
            ia = o[acc]
            stale_step = stale(o)
            x[ia], r[ia], S[ia] = x_new[acc], r_new[acc], S_new[acc]
            xnorm[ia] = torch.linalg.vector_norm(x[ia] * free[ia], dim=-1)
            # accepted: damping from the gain ratio; rejected on a fresh Jacobian: damp harder (a
            # step from an old Jacobian is retried with a new one)
            grow = ~acc & ~stale_step
            mu_o, nu_o = mu[o], nu[o]
            mu[o] = torch.where(acc, mu_o * torch.clamp(1.0 - (2.0 * rho - 1.0) ** 3, min=1.0 / 3.0),
                                torch.where(grow, mu_o * nu_o, mu_o))
            nu[o] = torch.where(acc, torch.full_like(nu_o, 2.0), torch.where(grow, nu_o * 2.0, nu_o))
            n_rej[o] += (~acc).long()
            if reuse is None:
                got, need = acc, ia
            else:
                # a new Jacobian where the old one predicted badly and is not from (nearly) here,
                # where a step from an old one failed, and where a stopping test fired on an old one
                # (stopping tests count only on a fresh Jacobian: gtol's at the new point, ftol's
                # and xtol's at the step's start); one batched evaluation for all of them
                relinearise(ia, False)
                want = (acc & ((rho <= reuse) | (gnorm[o] < gtol))) | ((~acc | small_f | small_x) & stale_step)
                got = want & stale(o)
                need = o[got]
            new_jacobian(need)
            relinearise(need, True)
            fresh_now, fresh_step = ~stale(o), ~stale_step
            c_g = (acc | got) & (gnorm[o] < gtol) & fresh_now
            c_f = ~c_g & small_f & fresh_step
            c_x = ~c_g & ~c_f & small_x & fresh_step
            why = torch.where(c_g, _GTOL, torch.where(c_f, _FTOL, torch.where(c_x, _XTOL, stop[o])))
            stop[o] = why
            converged[o] = c_g | c_f | c_x
        trace.append((act, S[act]))
        blown = ~converged[act] & ~torch.isfinite(mu[act])
        stop[act] = torch.where(blown, _BLOWN, stop[act])
        done[act] = converged[act] | blown
    return BatchedLMResult(x=at(x, everyone), residuals=r, jacobian=J, sse=S, n_iter=n_iter, n_evals=n_evals,
                           n_jac=n_jac, n_rejected=n_rej, converged=converged, stop=stop, max_iter=max_iter,
                           trace=trace, wall_time_s=time.perf_counter() - t0)
