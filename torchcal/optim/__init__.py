"""One optimiser interface for everything torchcal minimises.

A :class:`Problem` holds bounds and batched residuals / fitness; a :class:`Solver` minimises
any problem and returns a :class:`Result`. Nothing here knows about robots.
"""
from .base import Solver, available, get_solver, minimize, register
from .problem import FunctionProblem, LeastSquaresProblem, Problem
from .result import Result

__all__ = ["Problem", "LeastSquaresProblem", "FunctionProblem", "Result", "Solver",
           "register", "get_solver", "available", "minimize"]
from . import cpso, hybrid, pso  # noqa: F401  (registers solvers)
from . import gradient, lm  # noqa: F401  (registers solvers)
from . import ga, mayfly  # noqa: F401  (registers solvers)
