"""Robot dynamics and dynamic-parameter identification (seed 001).

* :mod:`.scara` — planar two-link SCARA model in regressor form ``τ = W ξ`` (six lumped
  parameters), with a direct autograd Lagrangian for checking and optional friction.
* :mod:`.lagrangian` — Euler–Lagrange by forward-mode autodiff; a regressor for any serial robot
  from its link inertials.
* :mod:`.excitation` — finite-Fourier excitation trajectories, batched over a population, with
  limit enforcement and the condition-number objective as a :class:`~torchcal.optim.Problem`.
* :mod:`.identify` — ordinary and recursive least squares, and the torque-fit problem for the
  swarm solvers.
"""
from . import excitation, identify, lagrangian, scara
from .excitation import ExcitationProblem, FourierExcitation
from .identify import TorqueFitProblem, ols, physical_box, rls, torque_rmse
from .scara import PlanarParams

__all__ = ["scara", "lagrangian", "excitation", "identify", "PlanarParams", "FourierExcitation",
           "ExcitationProblem", "TorqueFitProblem", "ols", "rls", "torque_rmse", "physical_box"]
