"""The one Problem protocol: a parameter vector with bounds and batched residuals / fitness.

Every system torchcal identifies implements it (serial calibration, PSD calibration, 3-RRRU
calibration, SCARA dynamic identification, excitation design, ELM tuning), and every solver in
:mod:`torchcal.optim` takes any of them. A problem knows nothing of the solver. Shapes: a
population ``X`` is ``(P, k)``; residuals are ``(P, m)``; fitness is ``(P,)``.

The protocol, all on :class:`Problem`:

* ``lower``, ``upper``, ``x0``, ``names`` — bounds, start and names of the ``k`` free values;
* :meth:`fitness` ``(P, k) -> (P,)`` — what swarm solvers minimise;
* :meth:`residuals` ``(P, k) -> (P, m)`` and :meth:`jacobian` ``(k,) -> (m, k)`` — what
  least-squares solvers need (problems without residuals leave them unimplemented);
* :attr:`fitness_is_sse` — whether ``fitness`` equals the sum of squared residuals, so that a
  least-squares solver may use its own sum instead of calling ``fitness`` again;
* :meth:`full` — the full parameter vector from the free values (identity unless the problem
  fixes some parameters).
"""
from __future__ import annotations

from typing import Callable

import torch
from torch import Tensor

__all__ = ["Problem", "LeastSquaresProblem", "FunctionProblem"]


class Problem:
    """Base class: minimise ``fitness(x)`` for ``x`` in ``[lower, upper]``.

    Subclasses implement :meth:`fitness` (batched). Least-squares problems also implement
    :meth:`residuals` and may implement :meth:`jacobian`; gradient solvers need them.

    Attributes:
        lower, upper: ``(k,)`` bounds (may be ``-inf``/``inf`` for gradient solvers; swarm
            solvers need finite bounds and say so).
        x0: ``(k,)`` start point or ``None`` (solvers then use the centre of the bounds).
        names: optional parameter names, used in reports and error messages.
    """

    def __init__(self, lower: Tensor, upper: Tensor, x0: Tensor | None = None,
                 names: list[str] | None = None):
        lower = torch.as_tensor(lower)
        upper = torch.as_tensor(upper, dtype=lower.dtype, device=lower.device)
        if not torch.is_floating_point(lower):
            lower = lower.double()
            upper = upper.double()
        if lower.ndim != 1 or lower.shape != upper.shape:
            raise ValueError(f"bounds must be two 1-D tensors of equal length, got shapes "
                             f"{tuple(lower.shape)} and {tuple(upper.shape)}")
        if bool((lower > upper).any()):
            bad = int(torch.nonzero(lower > upper)[0])
            raise ValueError(f"lower bound above upper bound at index {bad}"
                             f" ({names[bad] if names else ''}): {float(lower[bad])} > {float(upper[bad])}")
        self.lower = lower
        self.upper = upper
        self.x0 = None if x0 is None else torch.as_tensor(x0, dtype=lower.dtype, device=lower.device)
        if self.x0 is not None and self.x0.shape != lower.shape:
            raise ValueError(f"x0 has shape {tuple(self.x0.shape)}, expected {tuple(lower.shape)}")
        if names is not None and len(names) != lower.numel():
            raise ValueError(f"{len(names)} names for {lower.numel()} parameters")
        self.names = names

    _fitness_is_sse: bool | None = None

    @property
    def fitness_is_sse(self) -> bool:
        """Whether :meth:`fitness` is the sum of squared :meth:`residuals`. True when fitness is not
        overridden; a problem that overrides it says so by assigning this attribute."""
        if self._fitness_is_sse is not None:
            return self._fitness_is_sse
        return type(self).fitness is Problem.fitness

    @fitness_is_sse.setter
    def fitness_is_sse(self, value: bool) -> None:
        self._fitness_is_sse = bool(value)

    def full(self, X: Tensor) -> Tensor:
        """Free values ``(P, k)`` or ``(k,)`` -> full parameter vectors. The identity here; problems
        that hold fixed parameters override it."""
        return X

    # -- sizes and placement -------------------------------------------------------------
    @property
    def dim(self) -> int:
        return int(self.lower.numel())

    @property
    def dtype(self) -> torch.dtype:
        return self.lower.dtype

    @property
    def device(self) -> torch.device:
        return self.lower.device

    @property
    def has_residuals(self) -> bool:
        return type(self).residuals is not Problem.residuals

    def start(self) -> Tensor:
        """``(k,)`` start point: ``x0`` or the centre of finite bounds (zeros where infinite)."""
        if self.x0 is not None:
            return self.x0.clone()
        mid = 0.5 * (self.lower + self.upper)
        return torch.where(torch.isfinite(mid), mid, torch.zeros_like(mid))

    def require_finite_bounds(self, who: str) -> None:
        if not bool(torch.isfinite(self.lower).all() & torch.isfinite(self.upper).all()):
            raise ValueError(f"{who} samples inside the bounds, so every parameter needs finite "
                             "lower and upper bounds; set them on the problem (or its ParamSet)")

    def clip(self, X: Tensor) -> Tensor:
        return torch.maximum(torch.minimum(X, self.upper), self.lower)

    # -- evaluation ----------------------------------------------------------------------
    def residuals(self, X: Tensor) -> Tensor:
        """``(P, k) -> (P, m)`` residuals. Least-squares problems implement this."""
        raise NotImplementedError(f"{type(self).__name__} has no residuals; use a swarm solver "
                                  "or a problem with residuals for gradient solvers")

    def fitness(self, X: Tensor) -> Tensor:
        """``(P, k) -> (P,)`` value to minimise. Default: sum of squared residuals."""
        r = self.residuals(X)
        return (r * r).sum(-1)

    def jacobian(self, x: Tensor) -> Tensor:
        """``(k,) -> (m, k)`` Jacobian of the residuals at ``x``. Default: forward-mode autograd
        through :meth:`residuals` (override with an analytic one where available)."""
        return torch.func.jacfwd(lambda v: self.residuals(v[None])[0])(x)


class LeastSquaresProblem(Problem):
    """A least-squares problem from plain functions.

    Args:
        residual_fn: ``(P, k) -> (P, m)``.
        lower, upper: ``(k,)`` bounds.
        jacobian_fn: optional ``(k,) -> (m, k)``.
        fitness_fn: optional ``(P, k) -> (P,)`` used by swarm solvers instead of the sum of
            squares (e.g. seed 000's sum of Euclidean errors).
    """

    def __init__(self, residual_fn: Callable[[Tensor], Tensor], lower: Tensor, upper: Tensor,
                 x0: Tensor | None = None, jacobian_fn: Callable[[Tensor], Tensor] | None = None,
                 fitness_fn: Callable[[Tensor], Tensor] | None = None, names: list[str] | None = None):
        super().__init__(lower, upper, x0, names)
        self._residual_fn = residual_fn
        self._jacobian_fn = jacobian_fn
        self._fitness_fn = fitness_fn
        self.fitness_is_sse = fitness_fn is None and type(self).fitness is LeastSquaresProblem.fitness

    def residuals(self, X: Tensor) -> Tensor:
        return self._residual_fn(X)

    def fitness(self, X: Tensor) -> Tensor:
        if self._fitness_fn is not None:
            return self._fitness_fn(X)
        return super().fitness(X)

    def jacobian(self, x: Tensor) -> Tensor:
        if self._jacobian_fn is not None:
            return self._jacobian_fn(x)
        return super().jacobian(x)


class FunctionProblem(Problem):
    """A problem given by a batched fitness function ``(P, k) -> (P,)`` alone (no residuals)."""

    def __init__(self, fitness_fn: Callable[[Tensor], Tensor], lower: Tensor, upper: Tensor,
                 x0: Tensor | None = None, names: list[str] | None = None):
        super().__init__(lower, upper, x0, names)
        self._fitness_fn = fitness_fn
        self.fitness_is_sse = False

    def fitness(self, X: Tensor) -> Tensor:
        return self._fitness_fn(X)
