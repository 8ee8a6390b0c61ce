"""Quaternion conversions, written in torchcal so that importing it does not load pytorch-kinematics:
checked against the closed form of a rotation about an axis, and against pytorch-kinematics."""
from __future__ import annotations

import math

import pytest
import torch

from torchcal.kinematics.transforms import matrix_to_quat, quat_to_matrix, so3_exp


def _axis_angle(n: int, seed: int) -> tuple[torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    u = torch.randn(n, 3, generator=g, dtype=torch.float64)
    u = u / u.norm(dim=-1, keepdim=True)
    # every regime of the conversion: near 0, generic, and near a half turn (w -> 0)
    theta = torch.cat([torch.rand(n // 3, generator=g, dtype=torch.float64) * 1e-6,
                       torch.rand(n // 3, generator=g, dtype=torch.float64) * math.pi,
                       math.pi - torch.rand(n - 2 * (n // 3), generator=g, dtype=torch.float64) * 1e-6])
    return u, theta


def test_quaternions_follow_the_closed_form_of_a_rotation_about_an_axis():
    u, theta = _axis_angle(300, 0)
    q = torch.cat([torch.cos(theta / 2)[:, None], torch.sin(theta / 2)[:, None] * u], -1)  # w >= 0 for θ ≤ π
    R = so3_exp(u * theta[:, None])
    torch.testing.assert_close(quat_to_matrix(q), R, rtol=0, atol=1e-14)
    torch.testing.assert_close(quat_to_matrix(3.0 * q), R, rtol=0, atol=1e-14)  # any non-zero norm
    got = matrix_to_quat(R)
    assert (got[:, 0] >= 0).all()
    # near a half turn q and -q are the same rotation with w ~ 0: compare up to that sign
    sign = torch.where((got * q).sum(-1, keepdim=True) < 0, -1.0, 1.0)
    torch.testing.assert_close(got * sign, q, rtol=0, atol=1e-12)


def test_quaternions_equal_pytorch_kinematics():
    pk = pytest.importorskip("pytorch_kinematics.transforms")
    u, theta = _axis_angle(300, 1)
    R = so3_exp(u * theta[:, None]).reshape(10, 30, 3, 3)  # batched shapes pass through
    torch.testing.assert_close(matrix_to_quat(R), pk.standardize_quaternion(pk.matrix_to_quaternion(R)),
                               rtol=0, atol=1e-15)
    q = torch.randn(10, 30, 4, dtype=torch.float64, generator=torch.Generator().manual_seed(2))
    torch.testing.assert_close(quat_to_matrix(q), pk.quaternion_to_matrix(q), rtol=0, atol=1e-15)


def test_a_matrix_of_the_wrong_shape_is_refused():
    with pytest.raises(ValueError, match=r"\(\.\.\., 3, 3\)"):
        matrix_to_quat(torch.eye(4, dtype=torch.float64))
