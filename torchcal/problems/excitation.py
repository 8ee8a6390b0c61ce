"""Excitation design as a :class:`~torchcal.problems.base.Problem`: the Fourier coefficients of a
trajectory are the parameters, the condition number of the stacked regressor (plus a penalty for
leaving the joint limits) is the fitness, batched over a population of trajectories (seed 001)."""
from __future__ import annotations

from typing import Callable

from torch import Tensor

from torchcal.dynamics import scara
from torchcal.dynamics.excitation import FourierExcitation, condition_number, stack_regressor
from torchcal.problems.base import Problem

__all__ = ["ExcitationProblem"]


class ExcitationProblem(Problem):
    """Minimise the condition number of the stacked regressor over Fourier coefficients.

    Fitness ``(P, dim) -> (P,)``: ``cond(W)`` of the ``(T J, k)`` matrix stacked from the
    regressor at the ``T = n_samples`` grid points of one period, for the projected (feasible)
    coefficients (``constraint="scale"``, default), or for the raw coefficients plus
    ``penalty × violation`` (``constraint="penalty"``). Differentiable (autograd) for the
    gradient solvers; batched over the population for the GA.

    Args:
        excitation: the trajectory family and its limits.
        regressor_fn: ``(q, qd, qdd)`` ``(..., J)`` -> ``(..., J, k)``; default the SCARA seed
            regressor :func:`torchcal.dynamics.scara.regressor` (six columns).
        constraint: ``"scale"`` or ``"penalty"``.
        penalty: weight of the relative violation in penalty mode.
        x0: optional start point (the centre of the box is a zero-amplitude trajectory with an
            infinite condition number, so give gradient solvers a start).
    """

    def __init__(self, excitation: FourierExcitation,
                 regressor_fn: Callable[[Tensor, Tensor, Tensor], Tensor] = scara.regressor,
                 constraint: str = "scale", penalty: float = 1e3, x0: Tensor | None = None):
        if constraint not in ("scale", "penalty"):
            raise ValueError(f"constraint must be 'scale' or 'penalty', got {constraint!r}")
        lo, hi = excitation.bounds()
        super().__init__(lo, hi, x0, excitation.names())
        self.excitation, self.regressor_fn = excitation, regressor_fn
        self.constraint, self.penalty = constraint, float(penalty)

    def decode(self, x: Tensor) -> Tensor:
        """Coefficients of the trajectory actually evaluated (projected in scale mode)."""
        return self.excitation.project(x) if self.constraint == "scale" else x

    def observation_matrix(self, x: Tensor) -> Tensor:
        """``(P, T J, k)`` stacked regressor of the decoded trajectories."""
        q, qd, qdd = self.excitation.evaluate(self.decode(x))
        return stack_regressor(self.regressor_fn(q, qd, qdd))

    def fitness(self, X: Tensor) -> Tensor:
        c = condition_number(self.observation_matrix(X))
        if self.constraint == "penalty":
            c = c + self.penalty * self.excitation.violation(X)
        return c
