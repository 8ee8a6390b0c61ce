"""Gravity-torque features: how a mass (and its first moment) on a link loads each joint.

For a point mass ``m`` at point ``c = o + R s`` of a link (origin ``o``, rotation ``R``, ``s`` in the
link frame), the torque gravity exerts on revolute joint ``j`` (axis ``ω_j`` through ``p_j``) is
``τ_j = m gᵀ J_v(o)[:, j] + (m s)ᵀ Rᵀ (g × ω_j)`` — linear in the mass moments ``(m, m s)``. The
four features per link and joint are computed once per data set at the commanded (nominal)
configurations: millimetre geometry errors change gravity torques negligibly.
"""
from __future__ import annotations

import torch
from torch import Tensor

__all__ = ["gravity_features", "GRAVITY"]

GRAVITY = (0.0, 0.0, -9.81)  # m/s², robot base frame with z up


def gravity_features(robot, q: Tensor, links: list[str], gravity=GRAVITY) -> Tensor:
    """``(N, L, dof, 4)`` features: torque (N·m) on each actuated joint from a unit mass at each
    link's origin (feature 0) and from a unit first moment along the link's x, y, z (features 1–3,
    N·m per kg·m). Prismatic joints get the force along their axis (N) in feature 0."""
    from ..robot import Robot
    from ..tree import Marker

    aux = Robot(robot.name, robot.joints, [Marker(f"__g{i}_{l}", l) for i, l in enumerate(links)], dtype=robot.dtype,
                device=robot.device)
    cols = [aux.joint_names.index(n) for n in robot.joint_names]
    J = aux.joint_jacobian(q, check=False)[..., cols]  # (N, L, 6, dof)
    R, _ = aux.fk_rt(q, check=False)  # (N, L, 3, 3)
    g = torch.tensor(gravity, dtype=robot.dtype, device=robot.device)
    f0 = torch.einsum("i,nlij->nlj", g, J[..., :3, :])  # gᵀ J_v
    gx = torch.linalg.cross(g.expand_as(J[..., 3:, :].transpose(-1, -2)), J[..., 3:, :].transpose(-1, -2))  # (N,L,dof,3)
    f1 = torch.einsum("nlij,nlki->nlkj", R, gx)  # Rᵀ (g × ω_j)
    return torch.cat([f0[..., None], f1], -1)
