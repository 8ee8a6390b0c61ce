"""One optimiser interface for everything torchcal minimises.

Any :class:`~torchcal.problems.base.Problem` (bounds and batched residuals / fitness) goes to any
registered :class:`Solver`, which returns a :class:`Result`. The engine
(:mod:`torchcal.optim.engine`) owns the iteration loop, stopping, history and progress of every
iterative solver; each solver module supplies its start and its step. Nothing here knows about
robots.
"""
from torchcal.optim import cpso, ga, gradient, hybrid, lm, mayfly, mma, pso  # noqa: F401  (registers solvers)
from torchcal.optim.base import Solver, available, get_solver, is_population, minimize, register, solvers
from torchcal.optim.engine import IterativeSolver, minimize_runs
from torchcal.optim.result import Result
from torchcal.problems.base import FunctionProblem, LeastSquaresProblem, Problem

__all__ = ["Problem", "LeastSquaresProblem", "FunctionProblem", "Result", "Solver", "IterativeSolver",
           "register", "get_solver", "available", "solvers", "is_population", "minimize", "minimize_runs"]
