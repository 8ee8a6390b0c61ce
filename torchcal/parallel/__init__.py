"""Closed-chain (parallel) robots, which URDF cannot describe: their own model classes on the same
tensor conventions as :class:`torchcal.Robot` (batched over poses and parameter populations,
float64, differentiable; metres and radians).

* :mod:`torchcal.parallel.rrru`: the 3-RRRU translational robot of seed 004 (``RRRU``).
* :mod:`torchcal.parallel.calibration`: its calibration problem, identifiability analysis and the
  seed's line and spiral trajectories.
"""
from .rrru import N_PARAMS, PARAM_NAMES, PARAM_UNITS, RRRU, WorkspaceError

__all__ = ["RRRU", "WorkspaceError", "PARAM_NAMES", "PARAM_UNITS", "N_PARAMS"]
