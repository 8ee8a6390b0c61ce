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

The damping starts from :func:`torchcal.damping.initial_damping` (the engine's rule for identity
scaling) and then moves by fixed factors, ÷3 after a step that lowers the error and ×4 after one
that does not: IK takes any decrease, where Nielsen's rule of the parameter solvers weighs each
step by its gain ratio. This module imports nothing from :mod:`torchcal.optim`: kinematics comes
before optim in the data path.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from torchcal.damping import TAU, initial_damping
from torchcal.options import Options
from torchcal.params import ParamSet
from torchcal.kinematics.transforms import check_rotations, so3_log

__all__ = ["IKResult", "IKOptions", "solve_ik", "target_frames", "REASONS"]

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


# a target still this far off (m, rad) that no joint direction helps is out of reach
_FAR_M, _FAR_RAD = 1e-3, 1e-2
# a target stops after this many steps in a row that did not lower its error
_MAX_FAILS = 30


@dataclass(frozen=True)
class IKOptions(Options):
    """Settings of :func:`solve_ik`.

    Attributes:
        marker: which marker to place (default the robot's first).
        tol_pos_m: position tolerance (m); tol_rot: rotation tolerance (rad).
        max_iter: LM iterations per attempt.
        limits: clamp to the robot's joint limits.
        rot_weight: weight of rotation errors in the step (m per rad).
        restarts: extra attempts from random joint values (seeded by ``seed``) for targets that
            did not converge; the best attempt is kept.
        seed: seed of the restarts' random joint values.
        sing_tol: ``σ_min / σ_max`` of the weighted Jacobian below which a stalled target is
            called singular.
    """

    marker: str | None = None
    tol_pos_m: float = 1e-9
    tol_rot: float = 1e-9
    max_iter: int = 100
    limits: bool = True
    rot_weight: float = 0.5
    restarts: int = 4
    seed: int = 0
    sing_tol: float = 1e-6


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
    positions (m) in the robot's frame, checked: proper rotations (orthonormal, det = +1), finite values."""
    t = torch.as_tensor(target, dtype=robot.dtype, device=robot.device)
    if t.ndim in (1, 2) and t.shape[-1] == 3 and not (t.ndim == 2 and t.shape == (4, 4)):
        t = t.reshape(-1, 3)
        R, p = None, t
    elif t.shape[-2:] == (4, 4):
        t = t.reshape(-1, 4, 4)
        R, p = t[:, :3, :3], t[:, :3, 3]
        check_rotations(R, "target")
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


@dataclass
class _Task:
    """What every attempt of one :func:`solve_ik` call shares: the model, the marker index ``m``,
    the joint limits ``lo``, ``hi`` ``(dof,)`` and the settings."""

    robot: object
    params: Tensor | None
    m: int
    lo: Tensor
    hi: Tensor
    opt: IKOptions

    def errors(self, q: Tensor, R_t: Tensor | None, p_t: Tensor) -> tuple[Tensor, Tensor | None]:
        """Pose errors of the marker at ``q``: e_p (n, 3) m, e_r (n, 3) rad (or None)."""
        R, p = self.robot.fk_rt(q, self.params, check=False)
        e_p = p_t - p[:, self.m]
        e_r = None if R_t is None else so3_log(R_t @ R[:, self.m].transpose(-1, -2))
        return e_p, e_r

    def weighted(self, q: Tensor, e_p: Tensor, e_r: Tensor | None) -> tuple[Tensor, Tensor]:
        """The marker's Jacobian ``(n, 3|6, dof)`` and error ``(n, 3|6)``, rotation rows weighted."""
        w = self.opt.rot_weight
        J = self.robot.joint_jacobian(q, self.params, check=False)[:, self.m]  # (n, 6, dof)
        if e_r is None:
            return J[:, :3], e_p
        return torch.cat([J[:, :3], w * J[:, 3:]], 1), torch.cat([e_p, w * e_r], -1)

    def cost(self, ep: Tensor, er: Tensor | None) -> Tensor:
        c = (ep * ep).sum(-1)
        return c if er is None else c + (self.opt.rot_weight * self.opt.rot_weight) * (er * er).sum(-1)

    def done(self, ep: Tensor, er: Tensor | None) -> Tensor:
        ok = ep.norm(dim=-1) <= self.opt.tol_pos_m
        return ok if er is None else ok & (er.norm(dim=-1) <= self.opt.tol_rot)


def solve_ik(robot, params, target, q0=None, settings: IKOptions | None = None, **kw) -> IKResult:
    """Joint values that put ``marker`` on each target, batched over targets.

    Args:
        robot: a :class:`~torchcal.kinematics.robot.Robot`.
        params: error parameters (``ParamSet``, ``(K,)`` tensor) or ``None`` for the nominal model.
        target: ``(N, 4, 4)`` poses or ``(N, 3)`` positions (m) in the frame of ``params``' base
            (the instrument frame; the robot base when the base parameters are zero).
        q0: ``(N, dof)`` or ``(dof,)`` start values (the branch you want: elbow up/down, wrist
            flip); default the middle of the joint limits (0 where a joint has none).
        settings, kw: an :class:`IKOptions` and/or its fields as keywords (``marker``,
            ``tol_pos_m``, ``tol_rot``, ``max_iter``, ``limits``, ``rot_weight``, ``restarts``,
            ``seed``, ``sing_tol``).
    Returns:
        :class:`IKResult`.
    """
    opt = IKOptions.build(settings, **kw)
    R_t, p_t = target_frames(robot, target)
    m = _marker_index(robot, opt.marker)
    if isinstance(params, ParamSet):
        params = params.values
    params = None if params is None else torch.as_tensor(params, dtype=robot.dtype, device=robot.device)
    lo, hi = robot.joint_limits
    if not opt.limits:
        lo, hi = torch.full_like(lo, -math.inf), torch.full_like(hi, math.inf)
    task = _Task(robot, params, m, lo, hi, opt)
    res = _lm(task, R_t, p_t, _start(robot, q0, p_t.shape[0], lo, hi))
    g = torch.Generator(device="cpu").manual_seed(int(opt.seed))
    span_lo = torch.where(torch.isfinite(lo), lo, torch.full_like(lo, -math.pi))
    span_hi = torch.where(torch.isfinite(hi), hi, torch.full_like(hi, math.pi))
    for _ in range(int(opt.restarts)):
        bad = torch.nonzero(~res.converged).flatten()
        if bad.numel() == 0:
            break
        u = torch.rand(bad.numel(), robot.dof, generator=g, dtype=torch.float64).to(res.q)
        qr = span_lo + (span_hi - span_lo) * u
        _keep_better(res, _lm(task, None if R_t is None else R_t[bad], p_t[bad], qr), bad, opt.rot_weight)
    return res


def _start(robot, q0, N: int, lo: Tensor, hi: Tensor) -> Tensor:
    """``(N, dof)`` start values: ``q0`` clamped into the limits, or the middle of the limits."""
    if q0 is None:
        mid = torch.where(torch.isfinite(lo) & torch.isfinite(hi), (lo + hi) / 2, torch.zeros_like(lo))
        return mid.expand(N, -1).clone()
    q = robot.check_q(q0, "q0")
    if q.shape[0] == 1 and N != 1:
        q = q.expand(N, -1)
    if q.shape[0] != N:
        raise ValueError(f"q0 has {q.shape[0]} rows for {N} targets")
    return torch.minimum(torch.maximum(q, lo), hi).clone()


def _keep_better(res: IKResult, r2: IKResult, bad: Tensor, w: float) -> None:
    """Into ``res``, at targets ``bad``, the attempts of ``r2`` that did better: converged first,
    then the smaller weighted error."""
    old = res.pos_err[bad] ** 2 + (w * res.rot_err[bad]) ** 2
    new = r2.pos_err ** 2 + (w * r2.rot_err) ** 2
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


def _lm(task: _Task, R_t: Tensor | None, p_t: Tensor, q: Tensor) -> IKResult:
    """One attempt from ``q (N, dof)`` (updated in place) at every target."""
    e_p, e_r = task.errors(q, R_t, p_t)
    conv, n_iter = _descend(task, R_t, p_t, q, e_p, e_r)
    pos_err = e_p.norm(dim=-1)
    rot_err = torch.zeros_like(pos_err) if e_r is None else e_r.norm(dim=-1)
    reason = _reasons(task, q, e_p, e_r, conv, pos_err, rot_err)
    return IKResult(q=q, converged=conv, reason=reason, pos_err=pos_err, rot_err=rot_err, n_iter=n_iter)


def _descend(task: _Task, R_t: Tensor | None, p_t: Tensor, q: Tensor, e_p: Tensor, e_r: Tensor | None
             ) -> tuple[Tensor, Tensor]:
    """Damped least squares per target, all in one batch, each with its own damping, joint-limit
    clamp and stop; ``q``, ``e_p``, ``e_r`` are updated in place. Whether each converged, and its
    iterations. This is not the parameter LM of torchcal.optim (one problem, one damping, bound
    projection) run N times: IK at the shop floor needs thousands of small problems at once."""
    N, dof = q.shape
    dt = dict(dtype=q.dtype, device=q.device)
    c = task.cost(e_p, e_r)
    conv = task.done(e_p, e_r)
    mu = torch.full((N,), -1.0, **dt)  # set from the first Jacobian
    fails = torch.zeros(N, dtype=torch.long, device=q.device)
    n_iter = torch.zeros(N, dtype=torch.long, device=q.device)
    stalled = torch.zeros(N, dtype=torch.bool, device=q.device)
    eye = torch.eye(dof, **dt)
    for _ in range(int(task.opt.max_iter)):
        act = torch.nonzero(~conv & ~stalled).flatten()
        if act.numel() == 0:
            break
        J, e = task.weighted(q[act], e_p[act], None if e_r is None else e_r[act])
        JtJ = J.transpose(-1, -2) @ J
        g = (J.transpose(-1, -2) @ e[..., None])[..., 0]
        scale = torch.diagonal(JtJ, dim1=-2, dim2=-1).amax(-1)
        mua = mu[act]
        first = mua < 0
        if bool(first.any()):
            # start with light damping relative to the Jacobian's scale
            mua = torch.where(first, initial_damping(TAU, scale), mua)
        dq = torch.linalg.solve(JtJ + mua[:, None, None] * eye, g[..., None])[..., 0]
        qn = torch.minimum(torch.maximum(q[act] + dq, task.lo), task.hi)
        ep_n, er_n = task.errors(qn, None if R_t is None else R_t[act], p_t[act])
        cn = task.cost(ep_n, er_n)
        better = cn < c[act]
        n_iter[act] += 1
        acc = act[better]
        q[acc] = qn[better]
        e_p[acc] = ep_n[better]
        if e_r is not None:
            e_r[acc] = er_n[better]
        c[acc] = cn[better]
        # fixed factors: relax after a good step, stiffen after a bad one
        mu[act] = torch.where(better, mua / 3, mua * 4)
        fails[act] = torch.where(better, torch.zeros_like(fails[act]), fails[act] + 1)
        conv[act] = task.done(e_p[act], None if e_r is None else e_r[act])
        # no step helps any more: damping has grown far past the Jacobian's scale
        stalled[act] = ~conv[act] & ((fails[act] >= _MAX_FAILS) | (mu[act] > 1e12 * scale.clamp(min=1e-300)))
    return conv, n_iter


def _reasons(task: _Task, q: Tensor, e_p: Tensor, e_r: Tensor | None, conv: Tensor, pos_err: Tensor,
             rot_err: Tensor) -> list[str]:
    """Why each target ended as it did (:data:`REASONS`), judged at its end point."""
    reason = ["ok"] * q.shape[0]
    bad = torch.nonzero(~conv).flatten()
    if not bad.numel():
        return reason
    qb = q[bad]
    J, e = task.weighted(qb, e_p[bad], None if e_r is None else e_r[bad])
    sv = torch.linalg.svdvals(J)  # (n, min(r, dof))
    smax = sv[:, 0].clamp(min=1e-300)
    # rank deficiency that matters: fewer usable directions than the task needs
    smin = sv[:, min(J.shape[1], q.shape[1]) - 1]
    g = (J.transpose(-1, -2) @ e[..., None])[..., 0]
    # how much of the error the joints can still reduce: |Jᵀe| / (σ_max |e|) is ~0 at a
    # stationary point with a residual (a target out of reach), ~σ/σ_max near a singularity
    grad_ratio = g.norm(dim=-1) / (smax * e.norm(dim=-1).clamp(min=1e-300))
    at_lim = (((qb - task.lo).abs() <= 1e-9) | ((task.hi - qb).abs() <= 1e-9)).any(-1)
    far = (pos_err[bad] > _FAR_M) | (rot_err[bad] > _FAR_RAD)
    singular = smin / smax < task.opt.sing_tol
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
    return reason
