"""Levenberg-Marquardt for least-squares problems, in torch float64.

Minimises the sum of squared residuals ``S(x) = ||r(x)||^2`` of a problem with
:meth:`~torchcal.optim.Problem.residuals`. The damping follows Nielsen's gain-ratio rule
(Madsen, Nielsen & Tingleff, *Methods for non-linear least squares problems*, 2004, Alg. 3.16).

Also holds small helpers shared with :mod:`torchcal.optim.gradient`.
"""
from __future__ import annotations

import math
from typing import Callable

import torch
from torch import Tensor

from torchcal.optim.base import Solver, progress_bar, register
from torchcal.problems.base import LeastSquaresProblem, Problem
from torchcal.optim.result import Result

__all__ = ["LevenbergMarquardt"]

_F64 = torch.float64


# -- helpers shared by the gradient solvers ---------------------------------------------------
def require_residuals(problem: Problem, who: str) -> None:
    """Raise a ``TypeError`` naming the fix when ``problem`` has no residuals."""
    if not problem.has_residuals:
        raise TypeError(
            f"{who} minimises a sum of squared residuals, but {type(problem).__name__} has no "
            "residuals(). Wrap the model in LeastSquaresProblem(residual_fn, lower, upper, ...) "
            "(or implement residuals() on your Problem subclass), or use a swarm solver such as "
            "minimize(problem, 'pso') that needs only fitness().")


def fitness_is_sum_of_squares(problem: Problem) -> bool:
    """True when ``problem.fitness`` is the sum of squared residuals, so a solver may reuse its own
    sum of squares instead of calling ``fitness`` again (:attr:`Problem.fitness_is_sse`)."""
    return problem.fitness_is_sse


def bounds64(problem: Problem) -> tuple[Tensor, Tensor, bool]:
    """``(lower, upper, bounded)``: float64 ``(k,)`` bounds on the problem's device, and whether
    any bound is finite (so clipping can be skipped entirely when none is)."""
    lower = problem.lower.to(device=problem.device, dtype=_F64)
    upper = problem.upper.to(device=problem.device, dtype=_F64)
    bounded = bool(torch.isfinite(lower).any() | torch.isfinite(upper).any())
    return lower, upper, bounded


class Reporter:
    """Per-iteration progress bar (tqdm, imported only when asked for) and user callback."""

    def __init__(self, solver: Solver, total: int, desc: str):
        self.callback: Callable[[int, float], None] | None = solver.callback
        self.bar = progress_bar(solver.progress, total, desc)

    def __call__(self, iteration: int, best: float) -> None:
        if self.bar is not None:
            self.bar.update(1)
            self.bar.set_postfix(best=f"{best:.4e}", refresh=False)
        if self.callback is not None:
            self.callback(iteration, best)

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()


_JAC_MODES = ("problem", "2-point", "3-point")


class LsqEvaluator:
    """Single-point float64 views of a problem's batched residuals and its Jacobian.

    ``residuals(x)`` maps ``(k,) -> (m,)`` and ``jacobian(x)`` maps ``(k,) -> (m, k)``. Shapes
    are checked on the first call, so a wrong ``residual_fn``/``jacobian_fn`` fails with a
    message instead of a broadcasting error deep inside a solver.

    ``jac="problem"`` uses ``problem.jacobian`` (analytic where the problem has one, else
    forward-mode autograd). ``"2-point"``/``"3-point"`` use forward/central finite differences
    evaluated as one batched ``residuals`` call of ``k``/``2k`` points (steps
    ``eps**(1/2)``/``eps**(1/3)`` times ``max(1, |x_i|)``, kept inside the bounds); they suit
    residuals that autograd cannot differentiate or where ``jacfwd`` is slow.
    """

    def __init__(self, problem: Problem, jac: str = "problem", lower: Tensor | None = None,
                 upper: Tensor | None = None):
        if jac not in _JAC_MODES:
            raise ValueError(f"jac must be one of {', '.join(_JAC_MODES)}, got {jac!r}")
        self.problem = problem
        self.jac = jac
        self.lower, self.upper = lower, upper
        self.k = problem.dim
        self.m: int | None = None
        self.n_res = 0
        self.n_jac = 0
        self._eye: Tensor | None = None

    def batch(self, X: Tensor) -> Tensor:
        """``(P, k) -> (P, m)`` float64 residuals, counted as ``P`` evaluations."""
        R = self.problem.residuals(X)
        self.n_res += X.shape[0]
        if self.m is None:
            if R.ndim != 2 or R.shape[0] != X.shape[0]:
                raise ValueError(f"residuals of a ({X.shape[0]}, {self.k}) batch must have shape "
                                 f"({X.shape[0]}, m), got {tuple(R.shape)}")
            self.m = int(R.shape[1])
        return R if R.dtype is _F64 else R.to(_F64)

    def residuals(self, x: Tensor) -> Tensor:
        return self.batch(x.unsqueeze(0))[0]

    def jacobian(self, x: Tensor, r: Tensor | None = None) -> Tensor:
        """``(k,) -> (m, k)``; ``r`` = ``residuals(x)`` if known (saves one evaluation for
        ``"2-point"``)."""
        self.n_jac += 1
        if self.jac != "problem":
            return self._finite_difference(x, r)
        J = self.problem.jacobian(x)
        if J.shape != (self.m, self.k):
            raise ValueError(f"jacobian must have shape (m, k) = ({self.m}, {self.k}), got "
                             f"{tuple(J.shape)}")
        return J if J.dtype is _F64 else J.to(_F64)

    def _finite_difference(self, x: Tensor, r: Tensor | None) -> Tensor:
        if self._eye is None:
            self._eye = torch.eye(self.k, dtype=_F64, device=x.device)
        central = self.jac == "3-point"
        eps = torch.finfo(_F64).eps
        step = (eps ** (1 / 3) if central else eps ** 0.5) * torch.clamp(x.abs(), min=1.0)
        if not central and self.upper is not None:
            step = torch.where(x + step > self.upper, -step, step)  # step back from an upper bound
        Xp = x + self._eye * step
        Xm = x - self._eye * step if central else x[None]
        if self.lower is not None:
            Xp = torch.clamp(Xp, self.lower, self.upper)
            Xm = torch.clamp(Xm, self.lower, self.upper)
        if central:
            R = self.batch(torch.cat([Xp, Xm]))
            dR = R[: self.k] - R[self.k:]
        else:
            dR = self.batch(Xp) - (self.residuals(x) if r is None else r)
        # divide by the step actually taken, which clipping may have shortened (to zero for a
        # parameter with lower == upper, whose column is then zero)
        den = (Xp - Xm).diagonal()[:, None]
        return torch.where(den != 0, dR / den, 0.0).mT


# -- Levenberg-Marquardt ---------------------------------------------------------------------
@register
class LevenbergMarquardt(Solver):
    """Levenberg-Marquardt with Nielsen's gain-ratio damping update.

    Each iteration solves ``(JᵀJ + mu D) h = -Jᵀr`` by Cholesky and tries ``x + h``. With
    ``rho = (S(x) - S(x+h)) / (S_model(0) - S_model(h))`` the step is accepted when
    ``rho > 0`` (then ``mu *= max(1/3, 1 - (2 rho - 1)^3)``, ``nu = 2``), otherwise rejected
    (``mu *= nu``, ``nu *= 2``). A rejected step reuses ``J``, ``JᵀJ`` and ``Jᵀr``; only an
    accepted one computes a new Jacobian (with ``problem.jacobian``, analytic when the problem
    provides it).

    Bounds: trial points are clipped onto ``[lower, upper]``, and a parameter that sits on a
    bound with the gradient pushing it outward is held fixed for that step (a simple active
    set), so the iteration converges to the bound-constrained minimum rather than stalling.
    Convergence tests use this projected gradient. This is not a full trust-region
    reflective method; use it for a few active bounds, not for heavily constrained problems.

    Args:
        max_iter: maximum number of trial steps (accepted or rejected); each costs one
            residual evaluation.
        tau: initial damping relative to the problem's scale: ``mu0 = tau * max(diag(JᵀJ))``
            for ``scaling="identity"``, ``mu0 = tau`` for ``scaling="marquardt"``.
        mu0: absolute initial damping (overrides ``tau``), e.g. ``0.1``.
        scaling: ``"marquardt"`` (default, as MINPACK: ``D = diag(JᵀJ)``, the running maximum
            over iterations, floored at 1e-6 of its largest entry so that directions the data
            barely sees stay damped) or ``"identity"`` (``D = I``). With unidentifiable
            parameters inside tight bounds, identity scaling crawls (seed 000: 500 iterations,
            4.6e-4 mm) where Marquardt scaling converges (16 iterations, 5e-13 mm).
        gtol: stop when the largest cosine between the residual vector and a column of J,
            ``max_i |J_iᵀr| / (|J_i| |r|)``, is below ``gtol`` (MINPACK's scale-free test, computed
            on the projected gradient): it does not depend on the units of residuals or parameters.
        xtol: stop when ``||h|| < xtol * (||x|| + xtol)``.
        ftol: stop when both the actual and the predicted relative decrease of ``S`` are
            below ``ftol``.
        jac: ``"problem"`` (``problem.jacobian``: analytic where given, else autograd),
            ``"2-point"`` or ``"3-point"`` (batched finite differences, see
            :class:`LsqEvaluator`).
        seed, progress, callback: see :class:`~torchcal.optim.Solver`; ``callback(iteration,
            fitness)`` is called after every trial step.

    Result:
        ``history`` holds ``problem.fitness`` at the current point after each trial step,
        ``n_evals`` counts residual evaluations, ``n_iter`` trial steps. ``extra`` holds
        ``"jacobian"`` ``(m, k)`` and ``"residuals"`` ``(m,)`` at the solution, ``"cost"``
        ``= 0.5 ||r||^2``, ``"mu_history"`` (damping after each trial step), ``"n_jac"``
        (Jacobian evaluations) and ``"n_rejected"``.
    """

    name = "lm"
    aliases = ("levenberg-marquardt",)

    def __init__(self, *, max_iter: int = 500, tau: float = 1e-3, mu0: float | None = None,
                 scaling: str = "marquardt", gtol: float = 1e-10, xtol: float = 1e-10,
                 ftol: float = 1e-12, jac: str = "problem", **common):
        super().__init__(**common)
        if jac not in _JAC_MODES:
            raise ValueError(f"jac must be one of {', '.join(_JAC_MODES)}, got {jac!r}")
        self.jac = jac
        if scaling not in ("identity", "marquardt"):
            raise ValueError(f"scaling must be 'identity' or 'marquardt', got {scaling!r}")
        if mu0 is not None and not mu0 > 0:
            raise ValueError(f"mu0 must be positive, got {mu0}")
        if not tau > 0:
            raise ValueError(f"tau must be positive, got {tau}")
        self.max_iter = int(max_iter)
        self.tau = float(tau)
        self.mu0 = None if mu0 is None else float(mu0)
        self.scaling = scaling
        self.gtol, self.xtol, self.ftol = float(gtol), float(xtol), float(ftol)

    def _run(self, problem: Problem) -> Result:
        require_residuals(problem, "Levenberg-Marquardt")
        lower, upper, bounded = bounds64(problem)
        ev = LsqEvaluator(problem, self.jac, *((lower, upper) if bounded else (None, None)))
        sos = fitness_is_sum_of_squares(problem)
        marquardt = self.scaling == "marquardt"
        gtol, xtol, ftol = self.gtol, self.xtol, self.ftol
        # the loop calls torch functions rather than operators (x + h, a @ b): on small CPU
        # tensors the operator dispatch costs about as much as the arithmetic
        add, dot, mv, mm = torch.add, torch.dot, torch.mv, torch.mm
        chol, chol_solve = torch.linalg.cholesky_ex, torch.cholesky_solve

        x = problem.start().to(_F64)
        if bounded:
            x = torch.clamp(x, lower, upper)
        r = ev.residuals(x)
        J = ev.jacobian(x, r)
        k = x.numel()

        def fit_at(x_: Tensor, S_: float) -> float:
            return S_ if sos else float(problem.fitness(x_[None].to(problem.dtype))[0])

        def linearise(x_: Tensor, r_: Tensor, J_: Tensor):
            """``JᵀJ``, ``Jᵀr`` at ``x_``, the same with parameters held on an active bound
            removed, and the right-hand side ``-Jᵀr`` as a ``(k, 1)`` column."""
            Jt = J_.t()
            A_ = mm(Jt, J_)
            g_ = mv(Jt, r_)
            if bounded:
                held = ((x_ <= lower) & (g_ > 0)) | ((x_ >= upper) & (g_ < 0))
                free = (~held).to(_F64)
                # zeroing rows/columns and putting 1 on the diagonal gives h = 0 for held ones
                Ae = A_ * free[:, None] * free[None, :] + torch.diag_embed(1.0 - free)
                ge = g_ * free
            else:
                Ae, ge = A_, g_
            return A_, g_, Ae, ge, torch.neg(ge).unsqueeze(1)

        def gcos(ge_: Tensor, A_: Tensor, S_: Tensor) -> Tensor:
            """Scale-free gradient test (MINPACK's): the largest cosine between r and a column of J."""
            den = torch.sqrt(A_.diagonal().clamp(min=1e-300) * S_.clamp(min=1e-300))
            return torch.where(S_ > 0, (ge_.abs() / den).max(), torch.zeros_like(S_))

        A, g, Ae, ge, rhs = linearise(x, r, J)
        S0 = dot(r, r)
        S, gnorm, xnorm, Amax = torch.stack([
            S0, gcos(ge, A, S0), torch.linalg.vector_norm(x), A.diagonal().max()]).tolist()
        if marquardt:
            # floor the scaling: a near-zero column would otherwise get no damping and its
            # parameter would run off in a direction the data cannot see
            dA = A.diagonal()
            Dvec = dA.clamp(min=1e-6 * float(dA.max())) if float(dA.max()) > 0 else torch.ones_like(dA)
            Dm = torch.diag_embed(Dvec)
            mu = self.mu0 if self.mu0 is not None else self.tau
        else:
            Dm = torch.eye(k, dtype=_F64, device=x.device)
            mu = self.mu0 if self.mu0 is not None else self.tau * (Amax if Amax > 0 else 1.0)
        nu = 2.0

        fit = fit_at(x, S)
        history = [fit]
        mu_history: list[float] = []
        report = Reporter(self, self.max_iter, "lm")
        n_rejected = 0
        it = 0
        converged = gnorm < gtol
        message = "projected gradient below gtol at the start" if converged else ""
        try:
            while not converged and it < self.max_iter:
                it += 1
                L, info = chol(add(Ae, Dm, alpha=mu))
                if info.item() != 0:
                    # mu tiny against a singular JᵀJ lost positive definiteness: damp harder
                    mu *= nu
                    nu *= 2.0
                    n_rejected += 1
                else:
                    h = chol_solve(rhs, L).view(-1)
                    x_new = add(x, h)
                    if bounded:
                        x_new = torch.clamp(x_new, lower, upper)
                        h = torch.sub(x_new, x)
                    r_new = ev.residuals(x_new)
                    S_new = dot(r_new, r_new).item()
                    hh = dot(h, h).item()
                    if bounded or marquardt:
                        Jh = mv(J, h)
                        pred = -2.0 * dot(h, g).item() - dot(Jh, Jh).item()
                    else:
                        # (A + mu I) h = -g  =>  S(0) - S_model(h) = mu h·h - h·g
                        pred = mu * hh - dot(h, g).item()
                    act = S - S_new
                    rho = act / pred if (pred > 0 and math.isfinite(S_new)) else -1.0
                    small_f = abs(act) <= ftol * S and pred <= ftol * S and rho <= 2.0
                    small_x = math.sqrt(hh) <= xtol * (xnorm + xtol)
                    if rho > 0:
                        x, r, S = x_new, r_new, S_new
                        J = ev.jacobian(x, r)
                        A, g, Ae, ge, rhs = linearise(x, r, J)
                        if marquardt:
                            Dvec = torch.maximum(Dvec, A.diagonal())
                            Dm = torch.diag_embed(Dvec)
                        gnorm = gcos(ge, A, dot(r, r)).item()
                        xnorm = torch.linalg.vector_norm(x).item()
                        mu *= max(1.0 / 3.0, 1.0 - (2.0 * rho - 1.0) ** 3)
                        nu = 2.0
                        fit = fit_at(x, S)
                    else:
                        mu *= nu
                        nu *= 2.0
                        n_rejected += 1
                    if rho > 0 and gnorm < gtol:
                        converged, message = True, "projected gradient below gtol"
                    elif small_f:
                        converged, message = True, "relative decrease of the sum of squares below ftol"
                    elif small_x:
                        converged, message = True, "step below xtol"
                mu_history.append(mu)
                history.append(fit)
                report(it, fit)
                if not converged and not math.isfinite(mu):
                    message = "damping overflowed: no decrease found along any step"
                    break
        finally:
            report.close()
        if not message:
            message = f"reached max_iter={self.max_iter}"
        return Result(
            x=x, fun=fit, history=history, n_evals=ev.n_res, n_iter=it, converged=converged,
            message=message,
            extra={"jacobian": J, "residuals": r, "cost": 0.5 * S, "mu_history": mu_history,
                   "n_jac": ev.n_jac, "n_rejected": n_rejected})
