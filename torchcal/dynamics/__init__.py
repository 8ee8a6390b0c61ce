"""Rigid-body dynamics models (seed 001): the robot-model stage for dynamic identification.

* :mod:`.scara` — planar two-link SCARA model in regressor form ``τ = W ξ`` (six lumped
  parameters), with a direct autograd Lagrangian for checking and optional friction.
* :mod:`.lagrangian` — Euler–Lagrange by forward-mode autodiff; a regressor for any serial robot
  from its link inertials.
* :mod:`.excitation` — finite-Fourier excitation trajectories, batched over a population.
"""
from torchcal.dynamics import excitation, lagrangian, scara
from torchcal.dynamics.excitation import FourierExcitation
from torchcal.dynamics.scara import PlanarParams

__all__ = ["scara", "lagrangian", "excitation", "PlanarParams", "FourierExcitation"]
