"""Robot models: URDF and DH robots with error parameters, batched differentiable forward
kinematics, parameter Jacobians, inverse kinematics, the shipped robots and the 3-RRRU parallel
robot. Metres and radians throughout; float64 by default."""
from torchcal.kinematics.robot import Robot
from torchcal.kinematics.tree import Marker

__all__ = ["Robot", "Marker"]
