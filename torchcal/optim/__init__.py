"""One optimiser interface for everything torchcal minimises.

A :class:`Problem` holds bounds and batched residuals / fitness; a :class:`Solver` minimises
any problem and returns a :class:`Result`. Nothing here knows about robots.
"""
from torchcal.optim.base import Solver, available, get_solver, minimize, register
from torchcal.problems.base import FunctionProblem, LeastSquaresProblem, Problem
from torchcal.optim.result import Result

__all__ = ["Problem", "LeastSquaresProblem", "FunctionProblem", "Result", "Solver",
           "register", "get_solver", "available", "minimize"]
from torchcal.optim import cpso, hybrid, pso  # noqa: F401  (registers solvers)
from torchcal.optim import gradient, lm  # noqa: F401  (registers solvers)
from torchcal.optim import ga, mayfly  # noqa: F401  (registers solvers)
