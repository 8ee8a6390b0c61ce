"""What every solver returns."""
from __future__ import annotations

from dataclasses import dataclass, field

from torch import Tensor

__all__ = ["Result"]


@dataclass
class Result:
    """Outcome of one solver run.

    Attributes:
        x: ``(k,)`` best point found.
        fun: fitness at ``x`` (the problem's :meth:`~torchcal.optim.Problem.fitness`).
        history: best fitness after each iteration (index 0 = after initialisation).
        n_evals: number of points evaluated (a population of P counts P).
        n_iter: iterations run.
        wall_time_s: wall-clock time of the run, seconds.
        converged: whether a convergence test (not an iteration cap) stopped the run.
        message: why it stopped, in words.
        method: solver name.
    """

    x: Tensor
    fun: float
    history: list[float] = field(default_factory=list)
    n_evals: int = 0
    n_iter: int = 0
    wall_time_s: float = 0.0
    converged: bool = False
    message: str = ""
    method: str = ""
    extra: dict = field(default_factory=dict)
