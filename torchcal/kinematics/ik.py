"""Batched inverse kinematics by damped least squares on a robot's (calibrated) FK.

One marker, many targets: every target is solved at once with Levenberg–Marquardt steps
``dq = (JᵀJ + μ I)⁻¹ Jᵀ e`` (``J`` the geometric Jacobian from :meth:`Robot.joint_jacobian`,
``e`` the pose error), with a damping ``μ`` adapted per target (a step is taken only if it
lowers the error; otherwise ``μ`` grows). Joint limits are enforced by clamping every step.
Targets leave the batch as they converge, so a large batch costs what its hard targets cost.

Errors: position ``p_target - p`` (m) in the instrument frame; orientation
``log(R_target Rᵀ)`` (rad, rotation vector in the instrument frame, matching the angular rows
of the geometric Jacobian). The rotation rows are weighted by ``rot_weight`` (m per rad) in the
step only; convergence is judged on each part against its own tolerance.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from torchcal.params import ParamSet
from torchcal.kinematics.transforms import so3_log

__all__ = ["IKResult", "solve_ik", "target_frames", "REASONS"]

REASONS = ("ok", "joint_limits", "unreachable", "singular", "not_converged")
"""Why a target ended as it did:

* ``ok``: converged within the tolerances.
* ``joint_limits``: not converged and at least one joint sits at a limit: the solution (from this
  start) lies beyond it.
* ``unreachable``: not converged, still far off (> 1 mm or > 10 mrad) and the error is (nearly)
  orthogonal to every direction the joints can move the marker, ``|Jᵀe| < 0.01 σ_max |e|``: a
  stationary point with a residual, i.e. the target is outside the workspace (or out of reach
  from this branch; try another ``q0``).
* ``singular``: not converged, the Jacobian at the end is nearly rank deficient
  (``σ_min / σ_max < sing_tol``) and progress stalled there.
* ``not_converged``: none of the above; more iterations may help.
"""


@dataclass
class IKResult:
    """Outcome of :func:`solve_ik` for ``N`` targets.

    Attributes:
        q: ``(N, dof)`` joint values (rad / m), the best found (within the limits).
        converged: ``(N,)`` bool.
        reason: ``N`` strings from :data:`REASONS`.
        pos_err: ``(N,)`` remaining position error (m).
        rot_err: ``(N,)`` remaining rotation error (rad); zeros for position-only targets.
        n_iter: ``(N,)`` iterations used (summed over restarts).
    """

    q: Tensor
    converged: Tensor
    reason: list[str]
    pos_err: Tensor
    rot_err: Tensor
    n_iter: Tensor

    def summary(self) -> dict[str, int]:
        """Count of targets per reason."""
        return {r: self.reason.count(r) for r in REASONS if r in self.reason}


def target_frames(robot, target) -> tuple[Tensor | None, Tensor]:
    """Targets as ``(R (N, 3, 3) or None, p (N, 3) m)`` from ``(N, 4, 4)`` poses or ``(N, 3)``
    positions (m) in the robot's frame, checked: orthonormal rotations, finite values."""
    t = torch.as_tensor(target, dtype=robot.dtype, device=robot.device)
    if t.ndim in (1, 2) and t.shape[-1] == 3 and not (t.ndim == 2 and t.shape == (4, 4)):
        t = t.reshape(-1, 3)
        R, p = None, t
    elif t.shape[-2:] == (4, 4):
        t = t.reshape(-1, 4, 4)
        R, p = t[:, :3, :3], t[:, :3, 3]
        # a non-orthonormal rotation would make the orientation error meaningless
        dev = (R.transpose(-1, -2) @ R - torch.eye(3, dtype=R.dtype, device=R.device)).abs().amax((-1, -2))
        if bool((dev > 1e-6).any()):
            i = int(torch.nonzero(dev > 1e-6)[0])
            raise ValueError(f"target {i} has a rotation part that is not orthonormal (|RᵀR - I| = "
                             f"{float(dev[i]):.1e}); pass proper (N, 4, 4) poses or (N, 3) positions")
    else:
        raise ValueError(f"targets must be (N, 4, 4) poses or (N, 3) positions in m, got {tuple(t.shape)}")
    if not bool(torch.isfinite(p).all()) or (R is not None and not bool(torch.isfinite(R).all())):
        raise ValueError("targets contain NaN or inf")
    return R, p


def _marker_index(robot, marker: str | None) -> int:
    if marker is None:
        return 0
    try:
        return robot.marker_names.index(marker)
    except ValueError:
        raise ValueError(f"unknown marker {marker!r}; the robot measures {robot.marker_names}") from None


def solve_ik(robot, params, target, q0=None, *, marker: str | None = None,
             tol_pos_m: float = 1e-9, tol_rot: float = 1e-9, max_iter: int = 100,
             limits: bool = True, rot_weight: float = 0.5, restarts: int = 4, seed: int = 0,
             sing_tol: float = 1e-6) -> IKResult:
    """Joint values that put ``marker`` on each target, batched over targets.

    Args:
        robot: a :class:`~torchcal.kinematics.robot.Robot`.
        params: error parameters (``ParamSet``, ``(K,)`` tensor) or ``None`` for the nominal model.
        target: ``(N, 4, 4)`` poses or ``(N, 3)`` positions (m) in the frame of ``params``' base
            (the instrument frame; the robot base when the base parameters are zero).
        q0: ``(N, dof)`` or ``(dof,)`` start values (the branch you want: elbow up/down, wrist
            flip); default the middle of the joint limits (0 where a joint has none).
        marker: which marker to place (default the robot's first).
        tol_pos_m: position tolerance (m); tol_rot: rotation tolerance (rad).
        max_iter: LM iterations per attempt.
        limits: clamp to the robot's joint limits.
        rot_weight: weight of rotation errors in the step (m per rad).
        restarts: extra attempts from random joint values (seeded by ``seed``) for targets that
            did not converge; the best attempt is kept.
        sing_tol: ``σ_min / σ_max`` of the weighted Jacobian below which a stalled target is
            called singular.
    Returns:
        :class:`IKResult`.
    """
    R_t, p_t = target_frames(robot, target)
    N = p_t.shape[0]
    m = _marker_index(robot, marker)
    if isinstance(params, ParamSet):
        params = params.values
    params = None if params is None else torch.as_tensor(params, dtype=robot.dtype, device=robot.device)
    lo, hi = robot.joint_limits
    if not limits:
        lo, hi = torch.full_like(lo, -math.inf), torch.full_like(hi, math.inf)
    mid = torch.where(torch.isfinite(lo) & torch.isfinite(hi), (lo + hi) / 2, torch.zeros_like(lo))
    if q0 is None:
        q = mid.expand(N, -1).clone()
    else:
        q = robot.check_q(q0, "q0")
        if q.shape[0] == 1 and N != 1:
            q = q.expand(N, -1)
        if q.shape[0] != N:
            raise ValueError(f"q0 has {q.shape[0]} rows for {N} targets")
        q = torch.minimum(torch.maximum(q, lo), hi).clone()

    res = _lm(robot, params, R_t, p_t, q, m, lo, hi, tol_pos_m, tol_rot, max_iter, rot_weight, sing_tol)
    g = torch.Generator(device="cpu").manual_seed(int(seed))
    span_lo = torch.where(torch.isfinite(lo), lo, torch.full_like(lo, -math.pi))
    span_hi = torch.where(torch.isfinite(hi), hi, torch.full_like(hi, math.pi))
    for _ in range(int(restarts)):
        bad = torch.nonzero(~res.converged).flatten()
        if bad.numel() == 0:
            break
        u = torch.rand(bad.numel(), robot.dof, generator=g, dtype=torch.float64).to(q)
        qr = span_lo + (span_hi - span_lo) * u
        r2 = _lm(robot, params, None if R_t is None else R_t[bad], p_t[bad], qr, m, lo, hi,
                 tol_pos_m, tol_rot, max_iter, rot_weight, sing_tol)
        # keep the better attempt: converged first, then the smaller weighted error
        old = res.pos_err[bad] ** 2 + (rot_weight * res.rot_err[bad]) ** 2
        new = r2.pos_err ** 2 + (rot_weight * r2.rot_err) ** 2
        take = (r2.converged & ~res.converged[bad]) | (~res.converged[bad] & ~r2.converged & (new < old))
        idx = bad[take]
        res.q[idx] = r2.q[take]
        res.converged[idx] = r2.converged[take]
        res.pos_err[idx] = r2.pos_err[take]
        res.rot_err[idx] = r2.rot_err[take]
        for k, (i, t) in enumerate(zip(bad.tolist(), take.tolist())):
            if t:
                res.reason[i] = r2.reason[k]
        res.n_iter[bad] += r2.n_iter
    return res


def _errors(robot, params, q, R_t, p_t, m):
    """Pose errors of the marker at ``q``: e_p (n, 3) m, e_r (n, 3) rad (or None)."""
    R, p = robot.fk_rt(q, params, check=False)
    e_p = p_t - p[:, m]
    e_r = None if R_t is None else so3_log(R_t @ R[:, m].transpose(-1, -2))
    return e_p, e_r


def _lm(robot, params, R_t, p_t, q, m, lo, hi, tol_p, tol_r, max_iter, w, sing_tol,
        far_m=1e-3, far_rad=1e-2) -> IKResult:
    # Damped least squares per target, all N targets in one batch, each with its own damping,
    # joint-limit clamp, singularity test and stop. This is not the parameter LM of
    # torchcal.optim (one problem, one damping, bound projection) run N times: the solvers there
    # minimise one problem at a time, and IK at the shop floor needs thousands of small ones at once.
    N, dof = q.shape
    dt = dict(dtype=q.dtype, device=q.device)
    pose = R_t is not None
    e_p, e_r = _errors(robot, params, q, R_t, p_t, m)

    def cost(ep, er):
        c = (ep * ep).sum(-1)
        return c if er is None else c + (w * w) * (er * er).sum(-1)

    def done(ep, er):
        ok = ep.norm(dim=-1) <= tol_p
        return ok if er is None else ok & (er.norm(dim=-1) <= tol_r)

    c = cost(e_p, e_r)
    conv = done(e_p, e_r)
    mu = torch.full((N,), -1.0, **dt)  # set from the first Jacobian
    fails = torch.zeros(N, dtype=torch.long, device=q.device)
    n_iter = torch.zeros(N, dtype=torch.long, device=q.device)
    stalled = torch.zeros(N, dtype=torch.bool, device=q.device)
    eye = torch.eye(dof, **dt)
    for _ in range(int(max_iter)):
        act = torch.nonzero(~conv & ~stalled).flatten()
        if act.numel() == 0:
            break
        qa = q[act]
        J = robot.joint_jacobian(qa, params, check=False)[:, m]  # (n, 6, dof)
        J = torch.cat([J[:, :3], w * J[:, 3:]], 1) if pose else J[:, :3]
        e = e_p[act] if not pose else torch.cat([e_p[act], w * e_r[act]], -1)
        JtJ = J.transpose(-1, -2) @ J
        g = (J.transpose(-1, -2) @ e[..., None])[..., 0]
        mua = mu[act]
        first = mua < 0
        if bool(first.any()):
            # start with light damping relative to the Jacobian's scale
            scale = torch.diagonal(JtJ, dim1=-2, dim2=-1).amax(-1)
            mua = torch.where(first, 1e-6 * scale, mua)
        dq = torch.linalg.solve(JtJ + mua[:, None, None] * eye, g[..., None])[..., 0]
        qn = torch.minimum(torch.maximum(qa + dq, lo), hi)
        ep_n, er_n = _errors(robot, params, qn, None if R_t is None else R_t[act], p_t[act], m)
        cn = cost(ep_n, er_n)
        better = cn < c[act]
        n_iter[act] += 1
        acc = act[better]
        q[acc] = qn[better]
        e_p[acc] = ep_n[better]
        if pose:
            e_r[acc] = er_n[better]
        c[acc] = cn[better]
        # Nielsen-style damping: relax after a good step, stiffen after a bad one
        mu[act] = torch.where(better, mua / 3, mua * 4)
        fails[act] = torch.where(better, torch.zeros_like(fails[act]), fails[act] + 1)
        conv[act] = done(e_p[act], None if e_r is None else e_r[act])
        # no step helps any more: damping has grown far past the Jacobian's scale
        scale = torch.diagonal(JtJ, dim1=-2, dim2=-1).amax(-1)
        stalled[act] = ~conv[act] & ((fails[act] >= 30) | (mu[act] > 1e12 * scale.clamp(min=1e-300)))

    pos_err = e_p.norm(dim=-1)
    rot_err = torch.zeros(N, **dt) if e_r is None else e_r.norm(dim=-1)
    reason = ["ok"] * N
    bad = torch.nonzero(~conv).flatten()
    if bad.numel():
        qb = q[bad]
        J = robot.joint_jacobian(qb, params, check=False)[:, m]
        J = torch.cat([J[:, :3], w * J[:, 3:]], 1) if pose else J[:, :3]
        e = e_p[bad] if not pose else torch.cat([e_p[bad], w * e_r[bad]], -1)
        sv = torch.linalg.svdvals(J)  # (n, min(r, dof))
        smax = sv[:, 0].clamp(min=1e-300)
        # rank deficiency that matters: fewer usable directions than the task needs
        need = min(J.shape[1], dof)
        smin = sv[:, need - 1]
        g = (J.transpose(-1, -2) @ e[..., None])[..., 0]
        # how much of the error the joints can still reduce: |Jᵀe| / (σ_max |e|) is ~0 at a
        # stationary point with a residual (a target out of reach), ~σ/σ_max near a singularity
        grad_ratio = g.norm(dim=-1) / (smax * e.norm(dim=-1).clamp(min=1e-300))
        at_lim = ((qb - lo).abs() <= 1e-9) | ((hi - qb).abs() <= 1e-9)
        at_lim = at_lim.any(-1)
        far = (pos_err[bad] > far_m) | (rot_err[bad] > far_rad)
        singular = smin / smax < sing_tol
        for k, i in enumerate(bad.tolist()):
            if bool(at_lim[k]):
                reason[i] = "joint_limits"
            elif bool(far[k]) and bool(grad_ratio[k] < 1e-2):
                reason[i] = "unreachable"
            elif bool(singular[k]):
                reason[i] = "singular"
            elif bool(grad_ratio[k] < 1e-6):
                reason[i] = "unreachable"
            else:
                reason[i] = "not_converged"
    return IKResult(q=q, converged=conv, reason=reason, pos_err=pos_err, rot_err=rot_err, n_iter=n_iter)
