"""Initial estimate of the instrument frame: point-set registration (Kabsch/Horn) of the
nominal marker positions onto the measured ones."""
from __future__ import annotations

import torch

from torchcal.kinematics.transforms import kabsch, so3_log
from torchcal.measure.data import Measurements
from torchcal.params import ParamSet

__all__ = ["register_base"]

_BASE = ("base.x", "base.y", "base.z", "base.rx", "base.ry", "base.rz")


def register_base(robot, data: Measurements, params: ParamSet | None = None) -> ParamSet:
    """Set the base-frame parameters of ``params`` (a copy) to the rigid transform that best
    maps the model's marker positions (robot base frame, current non-base errors) onto the
    measured ones (instrument frame). A laser tracker may stand metres away at any rotation:
    no initial guess is needed.

    Raises when fewer than 3 non-collinear marker observations are available.
    """
    params = robot.params() if params is None else params.clone()
    v = params.values.clone()
    for n in _BASE:
        v[params.index(n)] = 0.0
    model = robot.positions(data.q, v, check=False)  # (N, M, 3), robot frame
    mk = [robot.marker_names.index(m) for m in data.marker_names]
    seen = data.seen
    src = model[:, mk][seen]
    dst = data.positions[seen]
    if src.shape[0] < 3:
        raise ValueError(f"base registration needs at least 3 marker observations, got {src.shape[0]}")
    R, t = kabsch(src, dst)
    r = so3_log(R)
    for n, val in zip(_BASE, torch.cat([t, r]).tolist()):
        params[n] = val
    return params
