"""Levenberg-Marquardt for a least-squares problem, in torch float64, as an engine solver
(``minimize(problem, "lm")``): the one LM iteration (:mod:`torchcal.optim.lm_batched`) on a batch of one.

Also holds small helpers shared with :mod:`torchcal.optim.gradient`.
"""
from __future__ import annotations

import logging
from types import SimpleNamespace
from typing import Callable

import torch
from torch import Tensor

from torchcal.optim.base import register
from torchcal.optim.engine import LocalSolver
from torchcal.optim.lm_batched import Batch, LMBatchedOptions
from torchcal.optim.lm_batched_result import stop_message
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
    """Levenberg-Marquardt on one problem: the one batched iteration
    (:func:`~torchcal.optim.lm_batched.lm_batched`) on a batch of one, run step by step by the engine
    (history, callback, progress bar).

    Each iteration solves ``(JᵀJ + mu D) h = -Jᵀr`` by Cholesky and tries ``x + h``; Nielsen's
    gain-ratio rule moves ``mu``; a rejected step reuses ``J``. Bounds: trial points are clipped onto
    ``[lower, upper]`` and a parameter on a bound with the gradient pushing outward is held for that
    step (a simple active set; not a trust-region reflective method).

    Args:
        settings, options: an :class:`~torchcal.optim.lm_batched.LMBatchedOptions` and/or its fields
            (``max_iter``, ``tau`` (default :data:`torchcal.damping.TAU`), ``mu0``, ``scaling``, ``gtol``,
            ``xtol``, ``ftol``, ``reuse``).
        jac: ``"problem"`` (``problem.jacobian``: analytic where given, else autograd), ``"2-point"`` or
            ``"3-point"`` (batched finite differences, see :class:`LsqEvaluator`).
        seed, progress, callback: see :class:`~torchcal.optim.Solver`; ``callback(iteration,
            fitness)`` is called after every trial step.
        checkpoint: ``(x (k,)) -> str | None``, the caller's look at the iterate every
            ``checkpoint_every`` trial steps of a run still going: a string ends the run there (not
            converged, the string its message). A fit that creeps along a valley of nearly equal
            solutions can be judged while it creeps, not after ``max_iter`` steps.

    Result:
        ``history`` holds ``problem.fitness`` at the current point after each trial step, ``n_evals``
        counts residual evaluations, ``n_iter`` trial steps. ``extra`` holds ``"jacobian"`` ``(m, k)``
        and ``"residuals"`` ``(m,)`` at the solution, ``"cost"`` ``= 0.5 ||r||^2``, ``"mu_history"``
        (damping after each trial step), ``"n_jac"`` and ``"n_rejected"``.
    """

    name = "lm"
    aliases = ("levenberg-marquardt",)

    def __init__(self, settings: LMBatchedOptions | None = None, *, jac: str = "problem", seed: int | None = 0,
                 progress: bool = False, callback=None, checkpoint: Callable[[Tensor], str | None] | None = None,
                 checkpoint_every: int = 30, **options):
        super().__init__(seed=seed, progress=progress, callback=callback)
        if jac not in JAC_MODES:
            raise ValueError(f"jac must be one of {', '.join(JAC_MODES)}, got {jac!r}")
        if not (isinstance(checkpoint_every, int) and checkpoint_every >= 1):
            raise ValueError(f"checkpoint_every must be a whole number of trial steps ≥ 1, got {checkpoint_every!r}")
        self.jac = jac
        self.checkpoint, self.checkpoint_every = checkpoint, checkpoint_every
        self.opt = LMBatchedOptions.build(settings, **options)
        self.max_iter = self.opt.max_iter

    def init(self, problem: Problem, g: torch.Generator) -> SimpleNamespace:
        require_residuals(problem, "Levenberg-Marquardt")
        lower, upper, bounded = bounds64(problem)
        ev = LsqEvaluator(problem, self.jac, *((lower, upper) if bounded else (None, None)))
        last = {}

        def residuals(X: Tensor, idx: Tensor) -> Tensor:
            last["x"], last["r"] = X[0], ev.batch(X)[0]
            return last["r"][None]

        def jacobian(X: Tensor, idx: Tensor) -> Tensor:
            # the iteration asks for J where it last evaluated the residuals: 2-point reuses them
            r = last["r"] if ev.jac == "2-point" and torch.equal(last["x"], X[0]) else None
            return ev.jacobian(X[0], r)[None]

        x0 = problem.start().to(_F64)[None]
        batch = Batch(residuals, jacobian, x0, torch.ones_like(x0, dtype=torch.bool), lower, upper, opt=self.opt)
        note_device_size(x0.device, batch.r.shape[-1], x0.shape[-1])
        st = SimpleNamespace(problem=problem, ev=ev, batch=batch, sos=problem.fitness_is_sse, mu_history=[],
                             n_evals=ev.n_res, t=0)
        st.best = self._fit_at(st)
        if bool(batch.done[0]):
            st.stop = (True, "projected gradient below gtol at the start")
        return st

    @staticmethod
    def _fit_at(st: SimpleNamespace):
        b = st.batch
        return b.S[0] if st.sos else float(st.problem.fitness(b.at(b.x, b.everyone).to(st.problem.dtype))[0])

    def check(self, problem: Problem, st: SimpleNamespace) -> tuple[bool, str] | None:
        if self.checkpoint is None or st.t == 0 or st.t % self.checkpoint_every:
            return None
        b = st.batch
        why = self.checkpoint(b.at(b.x, b.everyone)[0])
        return None if why is None else (False, why)

    def step(self, problem: Problem, st: SimpleNamespace, t: int, gen: torch.Generator) -> tuple[bool, str] | None:
        b = st.batch
        st.t = t
        b.iterate(b.everyone)
        st.mu_history.append(b.mu[0].clone())
        st.best = self._fit_at(st)
        st.n_evals = st.ev.n_res
        done, converged, code = torch.stack([b.done[0].long(), b.converged[0].long(), b.stop[0]]).tolist()  # one wait
        return (bool(converged), stop_message(code, self.max_iter)) if done else None

    def finish(self, problem: Problem, st: SimpleNamespace) -> tuple[Tensor, float, dict]:
        b = st.batch
        st.n_evals = st.ev.n_res
        # one read: the sum of squares, the counts and the damping after each step
        S, n_jac, n_rej, *mu = torch.cat([torch.stack([b.S[0], b.n_jac[0].to(_F64), b.n_rej[0].to(_F64)]),
                                          *(m[None] for m in st.mu_history)]).tolist()
        return b.at(b.x, b.everyone)[0], S if st.sos else float(st.best), {
            "jacobian": b.J[0], "residuals": b.r[0], "cost": 0.5 * S, "mu_history": mu,
            "n_jac": int(n_jac), "n_rejected": int(n_rej)}
