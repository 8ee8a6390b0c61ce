"""An instrument frame that differs by row (a set-up per level, a tracker knocked mid-session), carried
exactly: each row's frame from the base parameters plus the row's offsets (``base.x, y, z`` m, the
rotation vector ``base.rx, ry, rz`` rad: the same coordinates as the one frame, so a rotation turns
about the robot's base origin, as a robot base moved on its fixture turns), and the Jacobian columns at
that frame. :class:`~torchcal.problems.effect_calibration.EffectCalibrationProblem` uses these when an
effect moves the frame (:meth:`~torchcal.effects.base.Effect.frame_delta`); a first-order column taken
once would turn a 60 mm tool wrongly by its length times the frame's turn."""
from __future__ import annotations

import torch
from torch import Tensor

from torchcal.kinematics.transforms import so3_exp, so3_left_jacobian

__all__ = ["row_frames", "base_columns", "turned"]

def row_frames(base: Tensor, delta: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Each row's instrument frame from ``base (P, 6)`` (shift m, rotation vector rad) plus ``delta
    (P, N, 6)``: rotations ``(P, N, 3, 3)``, translations ``(P, N, 3)`` and the left Jacobians of the
    rotation vectors ``(P, N, 3, 3)``."""
    b = base[:, None] + delta
    return so3_exp(b[..., 3:]), b[..., :3], so3_left_jacobian(b[..., 3:])


def base_columns(p: Tensor, t: Tensor, Jl: Tensor, turns: bool) -> Tensor:
    """``(P, N, M, 3|6, 6)`` the derivatives of the instrument-frame positions ``p (P, N, M, 3)`` (and,
    with ``turns``, of the marker orientations: the angular rate, three rows more) by the six base
    parameters at each row's frame (translation ``t (P, N, 3)``, left Jacobian ``Jl (P, N, 3, 3)``):
    a shift moves every marker along its axis; a turn ``k`` about ``J_l e_k`` at the frame's origin."""
    P, N, M = p.shape[:3]
    rows = 6 if turns else 3
    out = p.new_zeros(P, N, M, rows, 6)
    out[..., :3, :3] = torch.eye(3, dtype=p.dtype, device=p.device)
    axes = Jl[:, :, None].expand(P, N, M, 3, 3)  # column k: the axis of turn k
    out[..., :3, 3:] = torch.linalg.cross(axes, (p - t[:, :, None])[..., None].expand(P, N, M, 3, 3), dim=-2)
    if turns:
        out[..., 3:, 3:] = axes
    return out


def turned(J: Tensor, M: Tensor) -> Tensor:
    """``J (P, N, M, 3|6, C)`` columns turned by each row's ``M (P, N, 3, 3)`` (both the displacement
    rows and, where there are six, the angular-rate rows)."""
    out = M[:, :, None] @ J[..., :3, :]
    if J.shape[-2] == 3:
        return out
    return torch.cat([out, M[:, :, None] @ J[..., 3:, :]], -2)
