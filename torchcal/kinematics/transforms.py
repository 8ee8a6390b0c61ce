"""Batched rigid-body transforms on torch tensors.

Rotations are ``(..., 3, 3)`` matrices, translations ``(..., 3)`` in metres, angles in radians.
The roll-pitch-yaw convention is URDF's: ``R = Rz(yaw) @ Ry(pitch) @ Rx(roll)``.

Quaternions are ``(w, x, y, z)``, converted as pytorch3d / pytorch-kinematics convert them (equal to
1e-15); written here because importing ``pytorch_kinematics`` loads its IK module and with it
matplotlib and scipy, seconds of start-up for four lines of algebra. The functions on the kinematics' hot path stay written here: ``rpy_to_matrix``
(pytorch-kinematics' ``euler_angles_to_matrix(..., "ZYX")`` gives the same matrices but takes
about 1.4x as long on the small batches FK builds), and ``so3_exp``/``so3_log`` with their series
near 0 and the stable branch near π that the parameter Jacobian relies on.
"""
from __future__ import annotations

import torch
from torch import Tensor

__all__ = ["check_rotations", "similarity", "quat_to_matrix", "matrix_to_quat", "skew", "rot_x", "rot_y", "rot_z", "rpy_to_matrix",
           "matrix_to_rpy", "so3_exp", "so3_log", "so3_left_jacobian", "so3_left_jacobian_inv", "homogeneous", "kabsch",
           "align_z"]


def skew(v: Tensor) -> Tensor:
    """``(..., 3) -> (..., 3, 3)`` cross-product matrix, ``skew(a) @ b == cross(a, b)``."""
    z = torch.zeros_like(v[..., 0])
    x, y, w = v.unbind(-1)
    return torch.stack([torch.stack([z, -w, y], -1),
                        torch.stack([w, z, -x], -1),
                        torch.stack([-y, x, z], -1)], -2)


def _rot(angle: Tensor, axis: int) -> Tensor:
    c, s = torch.cos(angle), torch.sin(angle)
    o, z = torch.ones_like(c), torch.zeros_like(c)
    if axis == 0:
        rows = [[o, z, z], [z, c, -s], [z, s, c]]
    elif axis == 1:
        rows = [[c, z, s], [z, o, z], [-s, z, c]]
    else:
        rows = [[c, -s, z], [s, c, z], [z, z, o]]
    return torch.stack([torch.stack(r, -1) for r in rows], -2)


def rot_x(angle: Tensor) -> Tensor:
    """``(...) rad -> (..., 3, 3)`` rotation about x."""
    return _rot(angle, 0)


def rot_y(angle: Tensor) -> Tensor:
    """``(...) rad -> (..., 3, 3)`` rotation about y."""
    return _rot(angle, 1)


def rot_z(angle: Tensor) -> Tensor:
    """``(...) rad -> (..., 3, 3)`` rotation about z."""
    return _rot(angle, 2)


def rpy_to_matrix(rpy: Tensor) -> Tensor:
    """``(..., 3)`` roll, pitch, yaw (rad) ``-> (..., 3, 3)``, ``Rz(yaw) Ry(pitch) Rx(roll)``."""
    r, p, y = rpy.unbind(-1)
    cr, sr, cp, sp, cy, sy = torch.cos(r), torch.sin(r), torch.cos(p), torch.sin(p), torch.cos(y), torch.sin(y)
    return torch.stack([
        torch.stack([cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr], -1),
        torch.stack([sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr], -1),
        torch.stack([-sp, cp * sr, cp * cr], -1)], -2)


def matrix_to_rpy(R: Tensor) -> Tensor:
    """``(..., 3, 3) -> (..., 3)`` roll, pitch, yaw (rad), inverse of :func:`rpy_to_matrix`.

    Away from pitch = ±90° the round trip is exact to machine precision; at the singularity
    roll is set to 0 and yaw absorbs the rest.
    """
    cp = torch.sqrt(R[..., 0, 0] ** 2 + R[..., 1, 0] ** 2)
    pitch = torch.atan2(-R[..., 2, 0], cp)
    singular = cp < 1e-9
    roll = torch.where(singular, torch.zeros_like(cp), torch.atan2(R[..., 2, 1], R[..., 2, 2]))
    yaw = torch.where(singular, torch.atan2(-R[..., 0, 1], R[..., 1, 1]), torch.atan2(R[..., 1, 0], R[..., 0, 0]))
    return torch.stack([roll, pitch, yaw], -1)


def _sinc_terms(theta2: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """sin(t)/t, (1-cos t)/t^2, (t - sin t)/t^3 from t^2, with Taylor series near 0."""
    small = theta2 < 1e-8
    t2 = torch.where(small, torch.ones_like(theta2), theta2)
    t = torch.sqrt(t2)
    a = torch.where(small, 1 - theta2 / 6, torch.sin(t) / t)
    b = torch.where(small, 0.5 - theta2 / 24, (1 - torch.cos(t)) / t2)
    c = torch.where(small, 1.0 / 6 - theta2 / 120, (t - torch.sin(t)) / (t2 * t))
    return a, b, c


def so3_exp(r: Tensor) -> Tensor:
    """``(..., 3)`` rotation vector (rad) ``-> (..., 3, 3)`` rotation matrix (Rodrigues)."""
    a, b, _ = _sinc_terms((r * r).sum(-1))
    K = skew(r)
    eye = torch.eye(3, dtype=r.dtype, device=r.device).expand_as(K)
    return eye + a[..., None, None] * K + b[..., None, None] * (K @ K)


def so3_left_jacobian(r: Tensor) -> Tensor:
    """``(..., 3) -> (..., 3, 3)``: ``d exp(r) = skew(J_l(r) dr) exp(r)``."""
    _, b, c = _sinc_terms((r * r).sum(-1))
    K = skew(r)
    eye = torch.eye(3, dtype=r.dtype, device=r.device).expand_as(K)
    return eye + b[..., None, None] * K + c[..., None, None] * (K @ K)


def so3_left_jacobian_inv(phi: Tensor) -> Tensor:
    """``(..., 3) -> (..., 3, 3)`` inverse left Jacobian of SO(3): ``d log(E) = J_l⁻¹(log E) ω`` for
    ``dE = skew(ω) E``."""
    th2 = (phi * phi).sum(-1)
    small = th2 < 1e-8
    th = torch.sqrt(torch.where(small, torch.ones_like(th2), th2))
    coef = torch.where(small, 1.0 / 12 + th2 / 720,
                       (1 - th * torch.sin(th) / (2 * (1 - torch.cos(th)))) / torch.where(small, torch.ones_like(th2), th2))
    K = skew(phi)
    eye = torch.eye(3, dtype=phi.dtype, device=phi.device).expand_as(K)
    return eye - 0.5 * K + coef[..., None, None] * (K @ K)


def so3_log(R: Tensor) -> Tensor:
    """``(..., 3, 3) -> (..., 3)`` rotation vector with angle in [0, pi]."""
    cos = ((R[..., 0, 0] + R[..., 1, 1] + R[..., 2, 2] - 1) / 2).clamp(-1.0, 1.0)
    theta = torch.acos(cos)
    w = torch.stack([R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0], R[..., 1, 0] - R[..., 0, 1]], -1)
    sin = torch.sin(theta)
    small = theta < 1e-6
    scale = torch.where(small, 0.5 + theta ** 2 / 12, theta / (2 * torch.where(small, torch.ones_like(sin), sin)))
    out = scale[..., None] * w
    # Near pi the antisymmetric part vanishes: read the axis from the symmetric part instead.
    near_pi = theta > torch.pi - 1e-4
    if bool(near_pi.any()):
        B = (R + R.transpose(-1, -2)) / 2 - cos[..., None, None] * torch.eye(3, dtype=R.dtype, device=R.device)
        diag = torch.diagonal(B, dim1=-2, dim2=-1).clamp(min=0)
        k = diag.argmax(-1, keepdim=True)
        col = torch.gather(B, -1, k[..., None].expand(*B.shape[:-1], 1))[..., 0]
        axis = col / col.norm(dim=-1, keepdim=True).clamp(min=1e-300)
        axis = torch.where((axis * w).sum(-1, keepdim=True) < 0, -axis, axis)
        out = torch.where(near_pi[..., None], axis * theta[..., None], out)
    return out


def homogeneous(R: Tensor, t: Tensor) -> Tensor:
    """``(..., 3, 3), (..., 3) -> (..., 4, 4)``."""
    top = torch.cat([R, t[..., None]], -1)
    bottom = torch.zeros_like(top[..., :1, :])
    bottom[..., 0, 3] = 1
    return torch.cat([top, bottom], -2)


def kabsch(src: Tensor, dst: Tensor, weights: Tensor | None = None) -> tuple[Tensor, Tensor]:
    """Rigid transform that best maps ``src`` onto ``dst`` (least squares, Kabsch/Horn).

    Args:
        src, dst: ``(n, 3)`` corresponding points (m), n >= 3 and not collinear; or ``(B, n, 3)``
            for B independent problems (a fleet), padded rows given weight 0.
        weights: optional ``(n,)`` (``(B, n)``) non-negative weights.
    Returns:
        ``R (3, 3)``, ``t (3,)`` with ``dst ≈ src @ R.T + t`` (``(B, 3, 3)``, ``(B, 3)`` batched).
    Raises:
        ValueError: when the points of a problem are (nearly) collinear; for a batch the message
        gives the indices of those problems.
    """
    if src.shape != dst.shape or src.ndim not in (2, 3) or src.shape[-1] != 3:
        raise ValueError(f"kabsch needs two (n, 3) point sets, got {tuple(src.shape)} and {tuple(dst.shape)}")
    if src.shape[-2] < 3:
        raise ValueError(f"kabsch needs at least 3 points, got {src.shape[-2]}")
    w = torch.ones(src.shape[:-1], dtype=src.dtype, device=src.device) if weights is None else weights
    w = w / w.sum(-1, keepdim=True)
    cs, cd = (w[..., None] * src).sum(-2), (w[..., None] * dst).sum(-2)
    H = ((src - cs[..., None, :]) * w[..., None]).transpose(-1, -2) @ (dst - cd[..., None, :])
    U, S, Vh = torch.linalg.svd(H)
    flat = S[..., 1] < 1e-12 * S[..., 0].clamp(min=1e-300)
    if bool(flat.any()):
        where = "" if src.ndim == 2 else f" in problem(s) {torch.nonzero(flat).flatten().tolist()[:10]}"
        raise ValueError(f"kabsch: the points are (nearly) collinear{where}, so the rotation about their line is "
                         "undetermined; use poses that spread the markers in 3-D")
    V, Ut = Vh.transpose(-1, -2), U.transpose(-1, -2)
    d = torch.sign(torch.det(V @ Ut))
    D = torch.diag_embed(torch.stack([torch.ones_like(d), torch.ones_like(d), d], -1))
    R = V @ D @ Ut
    return R, cd - (R @ cs[..., None])[..., 0]


def quat_to_matrix(qt: Tensor) -> Tensor:
    """``(..., 4)`` quaternion ``(w, x, y, z)`` (any non-zero norm) ``-> (..., 3, 3)``."""
    r, i, j, k = qt.unbind(-1)
    two_s = 2.0 / (qt * qt).sum(-1)
    o = torch.stack((1 - two_s * (j * j + k * k), two_s * (i * j - k * r), two_s * (i * k + j * r),
                     two_s * (i * j + k * r), 1 - two_s * (i * i + k * k), two_s * (j * k - i * r),
                     two_s * (i * k - j * r), two_s * (j * k + i * r), 1 - two_s * (i * i + j * j)), -1)
    return o.reshape(qt.shape[:-1] + (3, 3))


def matrix_to_quat(R: Tensor) -> Tensor:
    """``(..., 3, 3) -> (..., 4)`` unit quaternion ``(w, x, y, z)`` with ``w >= 0``, accurate near
    every angle: of the four ways to read it, the one with the largest divisor is taken."""
    if R.shape[-2:] != (3, 3):
        raise ValueError(f"matrix_to_quat needs (..., 3, 3) rotation matrices, got {tuple(R.shape)}")
    m00, m01, m02, m10, m11, m12, m20, m21, m22 = R.reshape(R.shape[:-2] + (9,)).unbind(-1)
    q_abs = torch.stack([1.0 + m00 + m11 + m22, 1.0 + m00 - m11 - m22, 1.0 - m00 + m11 - m22,
                         1.0 - m00 - m11 + m22], -1).clamp(min=0.0).sqrt()
    # row c is the quaternion times its c-th component (w, x, y, z)
    by_c = torch.stack([torch.stack([q_abs[..., 0] ** 2, m21 - m12, m02 - m20, m10 - m01], -1),
                        torch.stack([m21 - m12, q_abs[..., 1] ** 2, m10 + m01, m02 + m20], -1),
                        torch.stack([m02 - m20, m10 + m01, q_abs[..., 2] ** 2, m12 + m21], -1),
                        torch.stack([m10 - m01, m20 + m02, m21 + m12, q_abs[..., 3] ** 2], -1)], -2)
    candidates = by_c / (2.0 * q_abs[..., None].clamp(min=0.1))
    best = q_abs.argmax(-1)[..., None, None].expand(*R.shape[:-2], 1, 4)
    q = candidates.gather(-2, best).squeeze(-2)
    return torch.where(q[..., :1] < 0, -q, q)


def similarity(src: Tensor, dst: Tensor, scale: bool = True) -> tuple[Tensor, float]:
    """``src`` mapped by the best ``s R x + t`` onto ``dst`` (least squares, Umeyama), and ``s``.

    Args:
        src, dst: ``(n, 3)`` corresponding points (m), n >= 3 and not collinear.
        scale: fit ``s`` too; False keeps ``s = 1`` (a rigid motion).
    Returns:
        ``(n, 3)`` the mapped ``src`` (m), and ``s``.
    """
    ms, md = src.mean(0), dst.mean(0)
    A, B = src - ms, dst - md
    U, S, Vh = torch.linalg.svd(B.T @ A)
    D = torch.eye(3, dtype=src.dtype, device=src.device)
    D[2, 2] = torch.sign(torch.det(U @ Vh))
    R = U @ D @ Vh
    s = float((S * D.diagonal()).sum() / (A * A).sum()) if scale else 1.0
    return s * src @ R.T + (md - s * (R @ ms)), s


def align_z(axis: Tensor) -> Tensor:
    """A rotation C with C @ e_z = axis (unit): the identity for z, a half turn about x for -z."""
    z = torch.tensor([0.0, 0.0, 1.0], dtype=axis.dtype, device=axis.device)
    v = torch.linalg.cross(z, axis)
    c = float(axis @ z)
    if float(v.norm()) < 1e-12:
        return torch.eye(3, dtype=axis.dtype, device=axis.device) if c > 0 else \
            torch.diag(torch.tensor([1.0, -1.0, -1.0], dtype=axis.dtype, device=axis.device))
    return so3_exp(v / v.norm() * torch.atan2(v.norm(), torch.tensor(c, dtype=axis.dtype, device=axis.device)))


def check_rotations(R: Tensor, what: str = "rotation", tol: float = 1e-6) -> None:
    """Refuse (``ValueError`` naming the first bad ``what`` by index) rotation matrices ``R``
    (N, 3, 3) that are not proper rotations: not finite, not orthonormal (|RᵀR - I| > ``tol``), or
    mirrored (det = -1, a frame with one axis flipped, which no joint motion reaches)."""
    R = R.reshape(-1, 3, 3)
    bad = ~torch.isfinite(R).all(dim=(-1, -2))
    if bool(bad.any()):
        i = int(torch.nonzero(bad)[0])
        raise ValueError(f"{what} {i} has a rotation part with NaN or inf; pass finite rotations")
    dev = (R.transpose(-1, -2) @ R - torch.eye(3, dtype=R.dtype, device=R.device)).abs().amax((-1, -2))
    if bool((dev > tol).any()):
        i = int(torch.nonzero(dev > tol)[0])
        raise ValueError(f"{what} {i} has a rotation part that is not orthonormal (|RᵀR - I| = {float(dev[i]):.1e}); "
                         "pass proper (N, 4, 4) poses or (N, 3) positions")
    det = torch.linalg.det(R)
    if bool((det < 0).any()):
        i = int(torch.nonzero(det < 0)[0])
        raise ValueError(f"{what} {i} has a mirrored rotation part (det = {float(det[i]):+.3f}: one axis flipped, a "
                         "left-handed frame no robot reaches); pass a right-handed rotation (det = +1), e.g. flip a "
                         "second axis or build it from a quaternion")
