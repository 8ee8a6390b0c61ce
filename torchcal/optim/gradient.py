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
from types import SimpleNamespace

import torch
from torch import Tensor

from torchcal.optim.base import register
from torchcal.optim.engine import LocalSolver
from torchcal.optim.lm import JAC_MODES, LsqEvaluator, bounds64, require_residuals
from torchcal.optim.result import Result
from torchcal.problems.base import Problem

__all__ = ["GaussNewton", "LBFGS", "Adam"]

_F64 = torch.float64


def _held(x: Tensor, grad: Tensor, lower: Tensor, upper: Tensor) -> Tensor:
    """``(k,)`` bool: parameters on a bound whose gradient pushes them out of the box."""
    return ((x <= lower) & (grad > 0)) | ((x >= upper) & (grad < 0))


# -- Gauss-Newton ----------------------------------------------------------------------------
@register
class GaussNewton(LocalSolver):
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
        if jac not in JAC_MODES:
            raise ValueError(f"jac must be one of {', '.join(JAC_MODES)}, got {jac!r}")
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

    def init(self, problem: Problem, g: torch.Generator) -> SimpleNamespace:
        require_residuals(problem, "Gauss-Newton")
        lower, upper, bounded = bounds64(problem)
        ev = LsqEvaluator(problem, self.jac, *((lower, upper) if bounded else (None, None)))
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
        st = SimpleNamespace(problem=problem, lower=lower, upper=upper, bounded=bounded, ev=ev, free_idx=free_idx,
                             sos=problem.fitness_is_sse, x=x, r=r, S=float(r @ r), n_evals=0,
                             halvings=0.5 ** torch.arange(1, self.n_backtrack + 1, dtype=_F64, device=x.device))
        st.best = self._fit_at(st)
        st.J = ev.jacobian(x, r)
        return st

    @staticmethod
    def _fit_at(st: SimpleNamespace) -> float:
        return st.S if st.sos else float(st.problem.fitness(st.x[None].to(st.problem.dtype))[0])

    def check(self, problem: Problem, st: SimpleNamespace) -> tuple[bool, str] | None:
        g = st.J.mT @ st.r
        Jf = st.J[:, st.free_idx]
        gf = g[st.free_idx]
        if st.bounded:
            # a zero column gives a zero minimum-norm step for that parameter
            held = _held(st.x[st.free_idx], gf, st.lower[st.free_idx], st.upper[st.free_idx])
            Jf = Jf * (~held).to(_F64)
            gf = gf * (~held).to(_F64)
        if float(torch.linalg.vector_norm(gf, math.inf)) < self.gtol:
            return True, "projected gradient below gtol"
        h = torch.zeros_like(st.x)
        h[st.free_idx] = self._step(Jf, st.r)
        st.h, st.slope = h, 2.0 * float(g @ h)  # dS/dt at t = 0
        # for a least-squares step the model decrease of S is -slope / 2
        if -0.5 * st.slope <= self.ftol * st.S:
            return True, "predicted relative decrease below ftol"
        return None

    def step(self, problem: Problem, st: SimpleNamespace, t: int, gen: torch.Generator) -> tuple[bool, str] | None:
        x, h, S, slope = st.x, st.h, st.S, st.slope
        x_new = x + h
        if st.bounded:
            x_new = torch.clamp(x_new, st.lower, st.upper)
        r_new = st.ev.residuals(x_new)
        S_new = float(r_new @ r_new)
        if not S_new <= S + 1e-4 * slope:
            X = x + st.halvings[:, None] * h
            if st.bounded:
                X = torch.clamp(X, st.lower, st.upper)
            R = st.ev.batch(X)
            Sb = (R * R).sum(-1)
            ok = Sb <= S + 1e-4 * st.halvings * slope
            ok = ok if bool(ok.any()) else (Sb < S)
            if not bool(ok.any()):
                return False, "line search found no decrease"
            j = int(torch.nonzero(ok)[0])
            x_new, r_new, S_new = X[j].clone(), R[j].clone(), float(Sb[j])
        step = float(torch.linalg.vector_norm(x_new - x))
        xnorm = float(torch.linalg.vector_norm(x))
        dec = S - S_new
        st.x, st.r, st.S = x_new, r_new, S_new
        st.J = st.ev.jacobian(x_new, r_new)
        st.best = self._fit_at(st)
        if step <= self.xtol * (xnorm + self.xtol):
            return True, "step below xtol"
        if dec <= self.ftol * (S_new + dec):
            return True, "relative decrease of the sum of squares below ftol"
        return None

    def finish(self, problem: Problem, st: SimpleNamespace) -> tuple[Tensor, float, dict]:
        st.n_evals = st.ev.n_res
        rank = int(torch.linalg.matrix_rank(st.J[:, st.free_idx], rtol=self.rcond))
        return st.x, st.best, {"jacobian": st.J, "residuals": st.r, "cost": 0.5 * st.S, "rank": rank,
                               "n_jac": st.ev.n_jac}


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
class LBFGS(LocalSolver):
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

    def init(self, problem: Problem, g: torch.Generator) -> SimpleNamespace:
        x0, fg = _autograd_setup(problem, "L-BFGS")
        x = x0.clone().requires_grad_(True)
        # one iteration per step() so history, callback and clipping happen per iteration;
        # max_eval bounds the line search only, and tolerance_change is ours (ftol) instead
        opt = torch.optim.LBFGS([x], lr=self.lr, max_iter=1, max_eval=1 + self.max_ls,
                                tolerance_grad=self.gtol, tolerance_change=1e-300,
                                history_size=self.history_size, line_search_fn="strong_wolfe")
        f, grad = fg(x)
        return SimpleNamespace(x=x, fg=fg, opt=opt, f=f, grad=grad, best=fg.best_f, n_evals=fg.n_evals)

    def check(self, problem: Problem, st: SimpleNamespace) -> tuple[bool, str] | None:
        return (True, "projected gradient below gtol") if float(st.grad.abs().max()) < self.gtol else None

    def step(self, problem: Problem, st: SimpleNamespace, t: int, gen: torch.Generator) -> tuple[bool, str] | None:
        x, fg = st.x, st.fg

        def closure() -> Tensor:
            f, grad = fg(x)
            x.grad = grad
            return f

        f_prev = float(st.f)
        x_prev = x.detach().clone()
        fg.cache = [c for c in fg.cache if torch.equal(c[0], x_prev)]
        st.opt.step(closure)
        if fg.bounded:
            with torch.no_grad():
                xc = torch.clamp(x, fg.lower, fg.upper)
                if not torch.equal(xc, x):
                    x.copy_(xc)
                    st.opt.state.clear()
        st.f, st.grad = fg(x)
        st.best, st.n_evals = fg.best_f, fg.n_evals
        if torch.equal(x.detach(), x_prev):
            # the line search stalls at rounding level near a minimum; count that as
            # converged only when the gradient is small, though above gtol
            return float(st.grad.abs().max()) < math.sqrt(self.gtol), "no progress along the L-BFGS direction"
        if abs(f_prev - float(st.f)) <= self.ftol * max(abs(f_prev), 1e-300):
            return True, "relative change of the fitness below ftol"
        return None

    def finish(self, problem: Problem, st: SimpleNamespace) -> tuple[Tensor, float, dict]:
        st.n_evals = st.fg.n_evals
        return st.fg.best_x, st.fg.best_f, {}


@register
class Adam(LocalSolver):
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

    def init(self, problem: Problem, g: torch.Generator) -> SimpleNamespace:
        x0, fg = _autograd_setup(problem, "Adam")
        x = x0.clone().requires_grad_(True)
        f, grad = fg(x)
        return SimpleNamespace(x=x, fg=fg, opt=torch.optim.Adam([x], lr=self.lr, betas=self.betas), grad=grad,
                               best=fg.best_f, n_evals=fg.n_evals)

    def check(self, problem: Problem, st: SimpleNamespace) -> tuple[bool, str] | None:
        return (True, "projected gradient below gtol") if float(st.grad.abs().max()) < self.gtol else None

    def step(self, problem: Problem, st: SimpleNamespace, t: int, gen: torch.Generator) -> None:
        st.fg.cache.clear()  # Adam never revisits a point; keep the cache from growing
        st.x.grad = st.grad
        st.opt.step()
        if st.fg.bounded:
            with torch.no_grad():
                st.x.clamp_(st.fg.lower, st.fg.upper)
        _, st.grad = st.fg(st.x)
        st.best, st.n_evals = st.fg.best_f, st.fg.n_evals
        return None

    def finish(self, problem: Problem, st: SimpleNamespace) -> tuple[Tensor, float, dict]:
        return st.fg.best_x, st.fg.best_f, {}
