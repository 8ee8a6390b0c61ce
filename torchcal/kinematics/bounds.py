"""The joint box a robot's configurations are drawn from: its joint limits, ±π where a joint has
none, with a margin kept clear at both ends (candidate poses of a plan, random poses of a
simulation)."""
from __future__ import annotations

import math

import torch
from torch import Tensor

__all__ = ["config_bounds"]


def config_bounds(robot, margin: float = 0.1) -> tuple[Tensor, Tensor]:
    """``(dof,)`` lower and upper joint values (rad / m, CPU float64): the joint limits (±π where
    a joint has none), ``margin`` (a fraction) of each range left out at both ends."""
    lo, hi = (x.cpu().to(torch.float64) for x in robot.joint_limits)
    lo, hi = lo.clamp(min=-math.pi), hi.clamp(max=math.pi)
    span = hi - lo
    return lo + margin * span, hi - margin * span
