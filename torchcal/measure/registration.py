"""Initial estimate of the instrument frame: point-set registration (Kabsch/Horn) of the
nominal marker positions onto the measured ones."""
from __future__ import annotations

import torch
from torch import Tensor

from torchcal.kinematics.transforms import kabsch, matrix_to_rpy, quat_to_matrix, so3_log
from torchcal.measure.data import Measurements
from torchcal.measure.records import Suspect
from torchcal.params import ParamSet

__all__ = ["register_base", "register_marker_rotations", "registration_inliers", "gross_errors", "leave_out_gross",
           "GROSS_K", "GROSS_FLOOR"]

# An observation further from the registered nominal model than GROSS_K times the median error,
# and than GROSS_FLOOR (m), is a gross error (a glitch, a wrong row): the geometric errors of a robot
# spread its errors far less, and a robot in working order is not 0.1 m off its model.
GROSS_K = 10.0
GROSS_FLOOR = 0.1

_BASE = ("base.x", "base.y", "base.z", "base.rx", "base.ry", "base.rz")


def register_base(robot, data: Measurements, params: ParamSet | None = None) -> ParamSet:
    """Set the base-frame parameters of ``params`` (a copy) to the rigid transform that best
    maps the model's marker positions (robot base frame, current non-base errors) onto the
    measured ones (instrument frame). A laser tracker may stand metres away at any rotation:
    no initial guess is needed. A gross error (a tracker glitch metres off) does not drag it: see
    :func:`registration_inliers`.

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
    R, t, _ = registration_inliers(src, dst)
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


def _within(e: Tensor) -> Tensor:
    return e <= max(GROSS_K * float(e.median()), GROSS_FLOOR)


def registration_inliers(src: Tensor, dst: Tensor, rounds: int = 10) -> tuple[Tensor, Tensor, Tensor]:
    """Rigid transform ``dst ≈ src Rᵀ + t`` that gross errors do not drag: Kabsch on every point,
    then again on the points that are not gross errors (:data:`GROSS_K`, :data:`GROSS_FLOOR`),
    until that set stops changing. A nominal model's errors are millimetres, a glitch metres: one glitch of 6 m
    in 100 points moves a plain fit's centre by 6 cm and turns it, so every error looks gross.

    Args:
        src, dst: ``(n, 3)`` corresponding points (m), n ≥ 3.
    Returns:
        ``(R (3, 3), t (3,), inliers (n,) bool)``.
    """
    keep = torch.ones(src.shape[0], dtype=torch.bool, device=src.device)
    R, t = kabsch(src, dst)
    for _ in range(rounds):
        e = (src @ R.T + t - dst).norm(dim=-1)
        nxt = _within(e)
        if int(nxt.sum()) < 3 or bool((nxt == keep).all()):
            break
        keep = nxt
        R, t = kabsch(src, dst, keep.to(src.dtype))
    return R, t, keep


def gross_errors(robot, data: Measurements, params: ParamSet | Tensor) -> Tensor:
    """``(N, M)`` bool: the full-position observations that are gross errors at ``params`` (the
    registered nominal model; a ParamSet or its ``(K,)`` values): further from it than
    :data:`GROSS_K` times the median error and than :data:`GROSS_FLOOR`. No fit should follow
    them; a report lists them."""
    values = params.values if isinstance(params, ParamSet) else params
    mk = [robot.marker_names.index(m) for m in data.marker_names]
    seen = data.seen
    out = torch.zeros_like(seen)
    if int(seen.sum()) < 3:
        return out
    e = (robot.positions(data.q, values, check=False)[:, mk] - data.positions).norm(dim=-1)
    out[seen] = ~_within(e[seen])
    return out


def leave_out_gross(robot, data: Measurements, params: ParamSet | None = None) -> tuple[Measurements, list[Suspect]]:
    """``data`` with its gross errors (:func:`gross_errors` at ``params``, by default the nominal
    model registered here) marked not seen, for a fit, and the list of them for a report."""
    if params is None:
        params = register_base(robot, data) if int(data.seen.sum()) >= 3 else robot.params()
    gross = gross_errors(robot, data, params)
    if not bool(gross.any()):
        return data, []
    mk = [robot.marker_names.index(m) for m in data.marker_names]
    e = (robot.positions(data.q, params.values, check=False)[:, mk] - data.positions).norm(dim=-1)
    out = [Suspect(i, data.marker_names[m], 1e3 * float(e[i, m])) for i, m in torch.nonzero(gross).tolist()]
    return data.hide(gross), out
