"""Problems: parameters with bounds and batched residuals / fitness, one protocol
(:class:`~torchcal.problems.base.Problem`) that every system implements, plus identifiability
analysis and the fit of the identifiable subset."""
from torchcal.problems.base import FunctionProblem, LeastSquaresProblem, Problem

__all__ = ["Problem", "LeastSquaresProblem", "FunctionProblem"]
