"""Initial estimate of the instrument frame: point-set registration (Kabsch/Horn) of the
nominal marker positions onto the measured ones."""
from __future__ import annotations

import torch

from torchcal.kinematics.transforms import kabsch, matrix_to_rpy, quat_to_matrix, so3_log
from torchcal.measure.data import Measurements
from torchcal.params import ParamSet

__all__ = ["register_base", "register_marker_rotations"]

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


def register_marker_rotations(robot, data: Measurements, params: ParamSet) -> ParamSet:
    """Free the rotation (``<marker>.droll/dpitch/dyaw``, rad) of each marker whose orientation
    ``data`` measured, started from the mean rotation between the model's marker frame (at
    ``params``, its own rotation at zero) and the measured frames: a camera target's frame may
    be turned any way on its link, as the instrument may stand anywhere."""
    params = params.clone()
    if data.quaternions is None:
        return params
    names = ("droll", "dpitch", "dyaw")
    v = params.values.clone()
    for m in data.marker_names:
        for a in names:
            v[params.index(f"{m}.{a}")] = 0.0
    R, _ = robot.fk_rt(data.q, v, check=False)  # (N, M, 3, 3), instrument frame
    for k, m in enumerate(data.marker_names):
        ok = torch.isfinite(data.quaternions[:, k]).all(-1)
        if not bool(ok.any()):
            continue
        A = (R[ok, robot.marker_names.index(m)].transpose(-1, -2) @ quat_to_matrix(data.quaternions[ok, k])).sum(0)
        U, _, Vh = torch.linalg.svd(A)  # the chordal mean: the rotation nearest the summed ones
        d = torch.ones(3, dtype=A.dtype, device=A.device)
        d[2] = torch.sign(torch.linalg.det(U @ Vh))
        for a, val in zip(names, matrix_to_rpy(U @ torch.diag(d) @ Vh).tolist()):
            params[f"{m}.{a}"] = val
        params.unfix(*[f"{m}.{a}" for a in names])
    return params
