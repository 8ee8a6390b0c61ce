"""Gradient solvers besides Levenberg-Marquardt: Gauss-Newton, L-BFGS and Adam.

* :class:`GaussNewton` (``"gn"``) minimises the sum of squared residuals with minimum-norm
  steps (SVD-based least squares), so it also works on rank-deficient problems.
* :class:`LBFGS` (``"lbfgs"``) and :class:`Adam` (``"adam"``) wrap ``torch.optim`` and
  differentiate ``problem.fitness`` with autograd; they need no residuals, only a fitness
  that torch can differentiate.

All work in float64 on the problem's device and start from ``problem.start()``.
"""
from __future__ import annotations

import math

import torch
from torch import Tensor

from torchcal.optim.base import Solver, register
from torchcal.optim.lm import _JAC_MODES, LsqEvaluator, Reporter, bounds64, fitness_is_sum_of_squares, require_residuals
from torchcal.problems.base import Problem
from torchcal.optim.result import Result

__all__ = ["GaussNewton", "LBFGS", "Adam"]

_F64 = torch.float64


def _held(x: Tensor, grad: Tensor, lower: Tensor, upper: Tensor) -> Tensor:
    """``(k,)`` bool: parameters on a bound whose gradient pushes them out of the box."""
    return ((x <= lower) & (grad > 0)) | ((x >= upper) & (grad < 0))


# -- Gauss-Newton ----------------------------------------------------------------------------
@register
class GaussNewton(Solver):
    """Gauss-Newton with minimum-norm steps and a backtracking line search.

    Each iteration solves ``min ||J h + r||`` for the minimum-norm ``h`` (``torch.linalg.lstsq``
    with the SVD driver ``"gelsd"`` on CPU, ``torch.linalg.pinv`` on other devices), so
    directions the residuals cannot see (singular values below ``rcond * s_max``) are left
    unchanged. Starting from ``x0``, the result is then the solution closest to ``x0`` in the
    unidentifiable directions. The step length ``t`` is the largest of ``1, 1/2, 1/4, ...``
    satisfying the Armijo condition ``S(x + t h) <= S(x) + 1e-4 * t * dS/dt`` on the sum of
    squares ``S``; ``t = 1`` is tried alone first and the shorter steps in one batched call.

    Bounds: trial points are clipped onto ``[lower, upper]``; a parameter sitting on a bound
    with the gradient pushing outward is held for that step.

    Args:
        max_iter: maximum number of Gauss-Newton iterations (Jacobian evaluations).
        free: indices of the parameters to move (e.g. the identifiable subset); the others are
            held at their start value. ``None`` moves all.
        rcond: relative cut-off for small singular values of ``J``; ``None`` uses
            ``eps * max(m, k)``.
        n_backtrack: number of halvings tried in the line search.
        gtol: stop when the projected gradient ``||Jᵀr||_inf`` over the moving parameters is
            below ``gtol`` (units of residual² per parameter unit).
        xtol: stop when the step ``||t h|| < xtol * (||x|| + xtol)``.
        ftol: stop when the relative decrease of ``S`` in an iteration is below ``ftol``.
        jac: ``"problem"``, ``"2-point"`` or ``"3-point"`` as in
            :class:`~torchcal.optim.lm.LevenbergMarquardt`.

    Result:
        ``history`` is ``problem.fitness`` after each iteration; ``n_evals`` counts residual
        evaluations (points). ``extra`` holds ``"jacobian"`` ``(m, k)`` and ``"residuals"``
        ``(m,)`` at the solution, ``"cost"`` ``= 0.5 ||r||^2``, ``"rank"`` (numerical rank of
        the Jacobian columns of the moving parameters at the solution) and ``"n_jac"``.
    """

    name = "gn"
    aliases = ("gauss-newton",)

    def __init__(self, *, max_iter: int = 100, free: list[int] | None = None,
                 rcond: float | None = None, n_backtrack: int = 30, gtol: float = 1e-10,
                 xtol: float = 1e-10, ftol: float = 1e-12, jac: str = "problem", **common):
        super().__init__(**common)
        if jac not in _JAC_MODES:
            raise ValueError(f"jac must be one of {', '.join(_JAC_MODES)}, got {jac!r}")
        self.jac = jac
        self.max_iter = int(max_iter)
        self.free = None if free is None else [int(i) for i in free]
        self.rcond = rcond
        self.n_backtrack = int(n_backtrack)
        self.gtol, self.xtol, self.ftol = float(gtol), float(xtol), float(ftol)

    def _step(self, Jf: Tensor, r: Tensor) -> Tensor:
        """Minimum-norm solution ``(kf,)`` of ``Jf h = -r``."""
        if Jf.device.type == "cpu":
            return torch.linalg.lstsq(Jf, -r[:, None], rcond=self.rcond, driver="gelsd").solution[:, 0]
        return -(torch.linalg.pinv(Jf, rtol=self.rcond) @ r)

    def _run(self, problem: Problem) -> Result:
        require_residuals(problem, "Gauss-Newton")
        lower, upper, bounded = bounds64(problem)
        ev = LsqEvaluator(problem, self.jac, *((lower, upper) if bounded else (None, None)))
        sos = fitness_is_sum_of_squares(problem)
        k = problem.dim
        if self.free is not None:
            bad = [i for i in self.free if not -k <= i < k]
            if bad:
                raise ValueError(f"free indices {bad} out of range for {k} parameters")
            free_idx = torch.tensor(sorted({i % k for i in self.free}), device=problem.device)
        else:
            free_idx = torch.arange(k, device=problem.device)

        x = problem.start().to(_F64)
        if bounded:
            x = torch.clamp(x, lower, upper)
        r = ev.residuals(x)
        S = float(r @ r)

        def fit_at(x_: Tensor, S_: float) -> float:
            return S_ if sos else float(problem.fitness(x_[None].to(problem.dtype))[0])

        halvings = 0.5 ** torch.arange(1, self.n_backtrack + 1, dtype=_F64, device=x.device)
        fit = fit_at(x, S)
        history = [fit]
        report = Reporter(self, self.max_iter, "gn")
        converged, message, it = False, "", 0
        J = ev.jacobian(x, r)
        try:
            while it < self.max_iter:
                g = J.mT @ r
                Jf = J[:, free_idx]
                gf = g[free_idx]
                if bounded:
                    # a zero column gives a zero minimum-norm step for that parameter
                    held = _held(x[free_idx], gf, lower[free_idx], upper[free_idx])
                    Jf = Jf * (~held).to(_F64)
                    gf = gf * (~held).to(_F64)
                gnorm = float(torch.linalg.vector_norm(gf, math.inf))
                if gnorm < self.gtol:
                    converged, message = True, "projected gradient below gtol"
                    break
                h = torch.zeros_like(x)
                h[free_idx] = self._step(Jf, r)
                slope = 2.0 * float(g @ h)  # dS/dt at t = 0
                # for a least-squares step the model decrease of S is -slope / 2
                if -0.5 * slope <= self.ftol * S:
                    converged, message = True, "predicted relative decrease below ftol"
                    break
                it += 1
                x_new = x + h
                if bounded:
                    x_new = torch.clamp(x_new, lower, upper)
                r_new = ev.residuals(x_new)
                S_new = float(r_new @ r_new)
                if not S_new <= S + 1e-4 * slope:
                    X = x + halvings[:, None] * h
                    if bounded:
                        X = torch.clamp(X, lower, upper)
                    R = ev.batch(X)
                    Sb = (R * R).sum(-1)
                    ok = Sb <= S + 1e-4 * halvings * slope
                    ok = ok if bool(ok.any()) else (Sb < S)
                    if not bool(ok.any()):
                        message = "line search found no decrease"
                        history.append(fit)
                        report(it, fit)
                        break
                    j = int(torch.nonzero(ok)[0])
                    x_new, r_new, S_new = X[j].clone(), R[j].clone(), float(Sb[j])
                step = float(torch.linalg.vector_norm(x_new - x))
                xnorm = float(torch.linalg.vector_norm(x))
                dec = S - S_new
                x, r, S = x_new, r_new, S_new
                J = ev.jacobian(x, r)
                fit = fit_at(x, S)
                history.append(fit)
                report(it, fit)
                if step <= self.xtol * (xnorm + self.xtol):
                    converged, message = True, "step below xtol"
                    break
                if dec <= self.ftol * (S + dec):
                    converged, message = True, "relative decrease of the sum of squares below ftol"
                    break
        finally:
            report.close()
        if not message:
            message = f"reached max_iter={self.max_iter}"
        rank = int(torch.linalg.matrix_rank(J[:, free_idx], rtol=self.rcond))
        return Result(x=x, fun=fit, history=history, n_evals=ev.n_res, n_iter=it,
                      converged=converged, message=message,
                      extra={"jacobian": J, "residuals": r, "cost": 0.5 * S, "rank": rank,
                             "n_jac": ev.n_jac})


# -- autograd solvers ------------------------------------------------------------------------
class _AutogradFitness:
    """Fitness and its gradient at one float64 point ``x`` ``(k,)``, with bound handling.

    The fitness is evaluated at ``clip(x)``, so no point outside ``[lower, upper]`` is ever
    passed to the problem (a line search may probe beyond a bound); gradient components of
    parameters on a bound that push outward are zeroed (projected gradient). Tracks the best
    point evaluated and caches evaluations by exact ``x`` so an optimiser asking twice for the
    same point costs one evaluation.
    """

    def __init__(self, problem: Problem, lower: Tensor, upper: Tensor, bounded: bool, who: str):
        self.problem, self.lower, self.upper, self.bounded, self.who = problem, lower, upper, bounded, who
        self.n_evals = 0
        self.best_f = math.inf
        self.best_x: Tensor | None = None
        self.cache: list[tuple[Tensor, Tensor, Tensor]] = []

    def __call__(self, x: Tensor) -> tuple[Tensor, Tensor]:
        """``(f, grad)``: detached scalar fitness and ``(k,)`` projected gradient at ``x``."""
        xd = x.detach()
        for xc, fc, gc in self.cache:
            if torch.equal(xc, xd):
                return fc, gc.clone()
        v = xd.clone().requires_grad_(True)
        with torch.enable_grad():
            X = torch.clamp(v, self.lower, self.upper) if self.bounded else v
            f = self.problem.fitness(X[None])[0]
            if not f.requires_grad:
                raise TypeError(
                    f"{self.who} differentiates problem.fitness with autograd, but the fitness of "
                    f"{type(self.problem).__name__} does not depend differentiably on x (computed "
                    "outside torch, or detached). Write it in torch ops, or use 'lm'/'gn' with a "
                    "jacobian_fn, or a swarm solver such as 'pso'.")
            (grad,) = torch.autograd.grad(f, v)
        self.n_evals += 1
        f = f.detach().to(_F64)
        grad = grad.to(_F64)
        xin = X.detach()
        if self.bounded:
            grad = torch.where(_held(xin, grad, self.lower, self.upper), 0.0, grad)
        fv = float(f)
        # NaN never beats a number, but a NaN start still yields a point to return
        if self.best_x is None or fv < self.best_f or (self.best_f != self.best_f and fv == fv):
            self.best_f, self.best_x = fv, xin.clone()
        self.cache.append((xd.clone(), f, grad))
        return f, grad.clone()


def _autograd_setup(problem: Problem, who: str):
    lower, upper, bounded = bounds64(problem)
    x = problem.start().to(_F64)
    if bounded:
        x = torch.clamp(x, lower, upper)
    return x, _AutogradFitness(problem, lower, upper, bounded, who)


@register
class LBFGS(Solver):
    """L-BFGS (``torch.optim.LBFGS``) with a strong-Wolfe line search on ``problem.fitness``.

    Gradients come from autograd through ``problem.fitness`` on a ``(1, k)`` batch; the problem
    needs no residuals. One outer iteration is one L-BFGS iteration (one line search).

    Bounds: the fitness is evaluated at ``clip(x)`` (line-search probes beyond a bound see the
    value on the bound), ``x`` is clipped after each step, and gradient components pushing
    a parameter on its bound outward are zeroed. When clipping moves ``x`` the curvature
    memory is discarded, since its last step pair no longer matches the actual step. For
    bound-constrained least squares prefer ``"lm"``.

    Note ``torch.optim.LBFGS`` only stores curvature pairs with ``sᵀy > 1e-10`` (absolute),
    so fitness values that are tiny in absolute terms should be rescaled first.

    Args:
        max_iter: maximum number of iterations.
        history_size: number of curvature pairs kept.
        lr: initial step length of each line search (1 is right for L-BFGS).
        max_ls: maximum fitness evaluations per line search.
        gtol: stop when the projected gradient ``||grad||_inf < gtol``. When the line search
            makes no progress the run stops too, and counts as converged if the gradient is
            below ``sqrt(gtol)``.
        ftol: stop when an iteration changes the fitness by less than ``ftol`` relative.

    Result:
        ``x`` is the best point evaluated; ``history`` the best fitness after each iteration;
        ``n_evals`` counts fitness(+gradient) evaluations.
    """

    name = "lbfgs"

    def __init__(self, *, max_iter: int = 500, history_size: int = 20, lr: float = 1.0,
                 max_ls: int = 25, gtol: float = 1e-10, ftol: float = 1e-14, **common):
        super().__init__(**common)
        self.max_iter = int(max_iter)
        self.history_size = int(history_size)
        self.lr = float(lr)
        self.max_ls = int(max_ls)
        self.gtol, self.ftol = float(gtol), float(ftol)

    def _run(self, problem: Problem) -> Result:
        x0, fg = _autograd_setup(problem, "L-BFGS")
        x = x0.clone().requires_grad_(True)
        # one iteration per step() so history, callback and clipping happen per iteration;
        # max_eval bounds the line search only, and tolerance_change is ours (ftol) instead
        opt = torch.optim.LBFGS([x], lr=self.lr, max_iter=1, max_eval=1 + self.max_ls,
                                tolerance_grad=self.gtol, tolerance_change=1e-300,
                                history_size=self.history_size, line_search_fn="strong_wolfe")

        def closure() -> Tensor:
            f, grad = fg(x)
            x.grad = grad
            return f

        f, grad = fg(x)
        history = [fg.best_f]
        report = Reporter(self, self.max_iter, "lbfgs")
        converged, message, it = False, "", 0
        try:
            while it < self.max_iter:
                if float(grad.abs().max()) < self.gtol:
                    converged, message = True, "projected gradient below gtol"
                    break
                it += 1
                f_prev = float(f)
                x_prev = x.detach().clone()
                fg.cache = [c for c in fg.cache if torch.equal(c[0], x_prev)]
                opt.step(closure)
                if fg.bounded:
                    with torch.no_grad():
                        xc = torch.clamp(x, fg.lower, fg.upper)
                        if not torch.equal(xc, x):
                            x.copy_(xc)
                            opt.state.clear()
                f, grad = fg(x)
                history.append(fg.best_f)
                report(it, fg.best_f)
                if torch.equal(x.detach(), x_prev):
                    # the line search stalls at rounding level near a minimum; count that as
                    # converged only when the gradient is small, though above gtol
                    converged = float(grad.abs().max()) < math.sqrt(self.gtol)
                    message = "no progress along the L-BFGS direction"
                    break
                if abs(f_prev - float(f)) <= self.ftol * max(abs(f_prev), 1e-300):
                    converged, message = True, "relative change of the fitness below ftol"
                    break
        finally:
            report.close()
        if not message:
            message = f"reached max_iter={self.max_iter}"
        return Result(x=fg.best_x, fun=fg.best_f, history=history, n_evals=fg.n_evals,
                      n_iter=it, converged=converged, message=message)


@register
class Adam(Solver):
    """Adam (``torch.optim.Adam``) on ``problem.fitness`` with autograd gradients.

    A first-order method with a fixed learning rate: it gets near a minimum, not to machine
    precision; use it for non-least-squares fitness or as a baseline. Bounds as in
    :class:`LBFGS` (evaluate at ``clip(x)``, clip after each step, zero outward gradients).

    Args:
        max_iter: number of Adam steps.
        lr: learning rate, in parameter units per step (roughly the largest step taken).
        betas: Adam's moment decay rates.
        gtol: stop when the projected gradient ``||grad||_inf < gtol``.

    Result:
        ``x`` is the best point evaluated; ``history`` the best fitness after each step;
        ``n_evals`` counts fitness(+gradient) evaluations.
    """

    name = "adam"

    def __init__(self, *, max_iter: int = 2000, lr: float = 1e-2,
                 betas: tuple[float, float] = (0.9, 0.999), gtol: float = 1e-10, **common):
        super().__init__(**common)
        self.max_iter = int(max_iter)
        self.lr = float(lr)
        self.betas = (float(betas[0]), float(betas[1]))
        self.gtol = float(gtol)

    def _run(self, problem: Problem) -> Result:
        x0, fg = _autograd_setup(problem, "Adam")
        x = x0.clone().requires_grad_(True)
        opt = torch.optim.Adam([x], lr=self.lr, betas=self.betas)
        f, grad = fg(x)
        history = [fg.best_f]
        report = Reporter(self, self.max_iter, "adam")
        converged, message, it = False, "", 0
        try:
            while it < self.max_iter:
                if float(grad.abs().max()) < self.gtol:
                    converged, message = True, "projected gradient below gtol"
                    break
                it += 1
                fg.cache.clear()  # Adam never revisits a point; keep the cache from growing
                x.grad = grad
                opt.step()
                if fg.bounded:
                    with torch.no_grad():
                        x.clamp_(fg.lower, fg.upper)
                f, grad = fg(x)
                history.append(fg.best_f)
                report(it, fg.best_f)
        finally:
            report.close()
        if not message:
            message = f"reached max_iter={self.max_iter}"
        return Result(x=fg.best_x, fun=fg.best_f, history=history, n_evals=fg.n_evals,
                      n_iter=it, converged=converged, message=message)
