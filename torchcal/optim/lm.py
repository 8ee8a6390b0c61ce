"""Levenberg-Marquardt for least-squares problems, in torch float64.

Minimises the sum of squared residuals ``S(x) = ||r(x)||^2`` of a problem with
:meth:`~torchcal.optim.Problem.residuals`. The damping follows Nielsen's gain-ratio rule
(Madsen, Nielsen & Tingleff, *Methods for non-linear least squares problems*, 2004, Alg. 3.16).

Also holds small helpers shared with :mod:`torchcal.optim.gradient`.
"""
from __future__ import annotations

import logging
import math
from types import SimpleNamespace

import torch
from torch import Tensor

from torchcal.damping import (gain_ratio, gradient_cosine, initial_damping, nielsen_update, damp_harder,
                              predicted_decrease, scaling_floor, small_decrease, small_step)
from torchcal.optim.base import register
from torchcal.optim.engine import LocalSolver
from torchcal.problems.base import Problem

__all__ = ["LevenbergMarquardt", "GPU_MIN_JACOBIAN", "note_device_size"]

_F64 = torch.float64
log = logging.getLogger(__name__)

# A least-squares problem whose Jacobian has fewer entries (m residuals x k parameters) than this
# does too little work per tensor operation for a GPU: every operation of an iteration costs about
# a kernel launch (microseconds) whatever its size, so the run is slower than on the CPU. Measured
# by scripts/gpu_check.sh (calibrate on 300 KR5 poses, 900 x ~40, ran slower on an H100 than on
# one CPU thread).
GPU_MIN_JACOBIAN = 1_000_000
_told: set[str] = set()  # device types already told about (once per process: a loop fits many)


def note_device_size(device: torch.device, m: int, k: int) -> bool:
    """Say once per process, in the log, when an ``m x k`` least-squares problem on a GPU is too
    small to gain from it (:data:`GPU_MIN_JACOBIAN`); whether it is."""
    small = device.type == "cuda" and m * k < GPU_MIN_JACOBIAN
    if small and device.type not in _told:
        _told.add(device.type)
        log.warning("this problem (%d residuals, %d parameters) is too small to gain from %s: each tensor "
                    "operation of an iteration does less work than a kernel launch costs, so it runs slower "
                    "than on the CPU; consider device='cpu' (the robot and the data on the CPU)",
                    m, k, device.type)
    return small


# -- helpers shared by the gradient solvers ---------------------------------------------------
def require_residuals(problem: Problem, who: str) -> None:
    """Raise a ``TypeError`` naming the fix when ``problem`` has no residuals."""
    if not problem.has_residuals:
        raise TypeError(
            f"{who} minimises a sum of squared residuals, but {type(problem).__name__} has no "
            "residuals(). Wrap the model in LeastSquaresProblem(residual_fn, lower, upper, ...) "
            "(or implement residuals() on your Problem subclass), or use a swarm solver such as "
            "minimize(problem, 'pso') that needs only fitness().")


def bounds64(problem: Problem) -> tuple[Tensor, Tensor, bool]:
    """``(lower, upper, bounded)``: float64 ``(k,)`` bounds on the problem's device, and whether
    any bound is finite (so clipping can be skipped entirely when none is)."""
    lower = problem.lower.to(device=problem.device, dtype=_F64)
    upper = problem.upper.to(device=problem.device, dtype=_F64)
    bounded = bool(torch.isfinite(lower).any() | torch.isfinite(upper).any())
    return lower, upper, bounded


JAC_MODES = ("problem", "2-point", "3-point")


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
        if jac not in JAC_MODES:
            raise ValueError(f"jac must be one of {', '.join(JAC_MODES)}, got {jac!r}")
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
class LevenbergMarquardt(LocalSolver):
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
        if jac not in JAC_MODES:
            raise ValueError(f"jac must be one of {', '.join(JAC_MODES)}, got {jac!r}")
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

    # -- steps of the engine -------------------------------------------------------------------
    def init(self, problem: Problem, g: torch.Generator) -> SimpleNamespace:
        require_residuals(problem, "Levenberg-Marquardt")
        lower, upper, bounded = bounds64(problem)
        ev = LsqEvaluator(problem, self.jac, *((lower, upper) if bounded else (None, None)))
        st = SimpleNamespace(problem=problem, lower=lower, upper=upper, bounded=bounded, ev=ev,
                             sos=problem.fitness_is_sse, marquardt=self.scaling == "marquardt",
                             mu_history=[], n_rejected=0)
        x = problem.start().to(_F64)
        if bounded:
            x = torch.clamp(x, lower, upper)
        r = ev.residuals(x)
        J = ev.jacobian(x, r)
        k = x.numel()
        note_device_size(x.device, r.numel(), k)
        A, gr, Ae, ge, rhs = self._linearise(st, x, r, J)
        S0 = torch.dot(r, r)
        S, gnorm, xnorm, Amax = torch.stack([
            S0, gradient_cosine(ge, A.diagonal(), S0), torch.linalg.vector_norm(x), A.diagonal().max()]).tolist()
        if st.marquardt:
            # floor the scaling: a near-zero column would otherwise get no damping and its
            # parameter would run off in a direction the data cannot see
            st.Dvec = scaling_floor(A.diagonal(), A.diagonal().max())
            st.Dm = torch.diag_embed(st.Dvec)
            st.mu = self.mu0 if self.mu0 is not None else self.tau
        else:
            st.Dm = torch.eye(k, dtype=_F64, device=x.device)
            st.mu = self.mu0 if self.mu0 is not None else initial_damping(self.tau, Amax)
        st.nu = 2.0
        st.x, st.r, st.J, st.S, st.gnorm, st.xnorm = x, r, J, S, gnorm, xnorm
        st.A, st.g, st.Ae, st.ge, st.rhs = A, gr, Ae, ge, rhs
        st.best = self._fit_at(st, x, S)
        st.n_evals = 0
        if gnorm < self.gtol:
            st.stop = (True, "projected gradient below gtol at the start")
        return st

    @staticmethod
    def _fit_at(st: SimpleNamespace, x: Tensor, S: float) -> float:
        return S if st.sos else float(st.problem.fitness(x[None].to(st.problem.dtype))[0])

    @staticmethod
    def _linearise(st: SimpleNamespace, x: Tensor, r: Tensor, J: Tensor):
        """``JᵀJ``, ``Jᵀr`` at ``x``, the same with parameters held on an active bound removed,
        and the right-hand side ``-Jᵀr`` as a ``(k, 1)`` column."""
        Jt = J.t()
        A = torch.mm(Jt, J)
        g = torch.mv(Jt, r)
        if st.bounded:
            held = ((x <= st.lower) & (g > 0)) | ((x >= st.upper) & (g < 0))
            free = (~held).to(_F64)
            # zeroing rows/columns and putting 1 on the diagonal gives h = 0 for held ones
            Ae = A * free[:, None] * free[None, :] + torch.diag_embed(1.0 - free)
            ge = g * free
        else:
            Ae, ge = A, g
        return A, g, Ae, ge, torch.neg(ge).unsqueeze(1)

    def step(self, problem: Problem, st: SimpleNamespace, t: int, gen: torch.Generator) -> tuple[bool, str] | None:
        # torch functions rather than operators (x + h, a @ b): on small CPU tensors the
        # operator dispatch costs about as much as the arithmetic. The host reads the device at
        # most three times per step (on a GPU each read waits for all queued work): whether the
        # Cholesky factor exists, the step's scalars together, and the new gradient test.
        add, dot, mv = torch.add, torch.dot, torch.mv
        x, g, S, mu, nu = st.x, st.g, st.S, st.mu, st.nu
        stop = None
        L, info = torch.linalg.cholesky_ex(add(st.Ae, st.Dm, alpha=mu))
        if info.item() != 0:
            # mu tiny against a singular JᵀJ lost positive definiteness: damp harder
            mu, nu = damp_harder(mu, nu)
            st.n_rejected += 1
        else:
            h = torch.cholesky_solve(st.rhs, L).view(-1)
            x_new = add(x, h)
            if st.bounded:
                x_new = torch.clamp(x_new, st.lower, st.upper)
                h = torch.sub(x_new, x)
            r_new = st.ev.residuals(x_new)
            model = st.bounded or st.marquardt
            SS = dot(r_new, r_new)
            parts = [SS, dot(h, h), dot(h, g), torch.linalg.vector_norm(x_new)]
            if model:
                Jh = mv(st.J, h)
                parts.append(dot(Jh, Jh))
            S_new, hh, hg, xnorm_new, *JhJh = torch.stack(parts).tolist()
            # S(0) - S_model(h): from J h, or as (A + mu I) h = -g gives mu h·h - h·g
            pred = predicted_decrease(hg, JhJh[0]) if model else mu * hh - hg
            act = S - S_new
            rho = gain_ratio(act, pred, S_new)
            small_f = small_decrease(act, pred, S, rho, self.ftol)
            small_x = small_step(math.sqrt(hh), st.xnorm, self.xtol)
            if rho > 0:
                st.x, st.r, st.S = x_new, r_new, S_new
                st.J = st.ev.jacobian(x_new, r_new)
                st.A, st.g, st.Ae, st.ge, st.rhs = self._linearise(st, x_new, r_new, st.J)
                if st.marquardt:
                    st.Dvec = torch.maximum(st.Dvec, st.A.diagonal())
                    st.Dm = torch.diag_embed(st.Dvec)
                st.gnorm = gradient_cosine(st.ge, st.A.diagonal(), SS).item()
                st.xnorm = xnorm_new
                st.best = self._fit_at(st, x_new, S_new)
            else:
                st.n_rejected += 1
            mu, nu = nielsen_update(mu, nu, rho)
            if rho > 0 and st.gnorm < self.gtol:
                stop = (True, "projected gradient below gtol")
            elif small_f:
                stop = (True, "relative decrease of the sum of squares below ftol")
            elif small_x:
                stop = (True, "step below xtol")
        st.mu, st.nu = mu, nu
        st.mu_history.append(mu)
        st.n_evals = st.ev.n_res
        if stop is None and not math.isfinite(mu):
            stop = (False, "damping overflowed: no decrease found along any step")
        return stop

    def finish(self, problem: Problem, st: SimpleNamespace) -> tuple[Tensor, float, dict]:
        st.n_evals = st.ev.n_res
        return st.x, st.best, {"jacobian": st.J, "residuals": st.r, "cost": 0.5 * st.S,
                               "mu_history": st.mu_history, "n_jac": st.ev.n_jac, "n_rejected": st.n_rejected}

