"""Command correction: joint commands that make a calibrated model reach given targets.

Seed 002's step two, iterated to convergence. For each target ``T_t``::

    T_c = T_t
    q   = IK(T_c)                               # on the calibrated kinematics
    repeat:
        e = predict_pose(q) ⊖ T_t               # predicted reached pose minus target (6-D error)
        stop when |e_pos| <= tol_mm and |e_rot| <= tol_mrad
        T_c = T_c ⊕ (-e)                        # corrected target: subtract the predicted error
        q   = IK(T_c, start = q)

``predict_pose`` is the full :class:`~torchcal.deploy.model.CalibratedModel` (kinematics, effects,
learned residual), so the fixed point is the command whose *predicted* reached pose equals the
target. The iteration contracts as long as the predicted error changes slowly with the command
(errors of mm over joint motions of rad), typically two or three rounds to 1 µm. Everything is
batched over targets; a target leaves the loop when it converges or its IK fails.

Error convention (see :mod:`torchcal.deploy.model`): position difference in the instrument frame,
orientation as the rotation vector ``log(R_targetᵀ R_predicted)`` (rad, target frame).
"""
from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from torchcal.deploy.model import CalibratedModel, apply_pose_error, pose_error
from torchcal.kinematics.ik import solve_ik, target_frames
from torchcal.threads import threads_by_size
from torchcal.measure.io import UnitsError

__all__ = ["Corrector", "CorrectionResult"]


@dataclass
class CorrectionResult:
    """Corrected commands for ``N`` targets.

    Attributes:
        q: ``(N, dof)`` commands to send (rad / m).
        converged: ``(N,)`` bool: predicted reached pose within the tolerances.
        reason: per target ``"ok"``, an IK failure (``"unreachable"``, ``"joint_limits"``,
            ``"singular"``, ``"not_converged"``: see :data:`torchcal.kinematics.ik.REASONS`) or
            ``"max_outer"`` (the correction loop ran out of rounds).
        predicted_error_mm: ``(N,)`` |predicted reached position - target| (mm) at ``q``.
        predicted_rot_error_mrad: ``(N,)`` predicted rotation error (mrad); 0 for position targets.
        q_uncorrected: ``(N, dof)`` IK of the targets on the calibrated kinematics alone (what
            the robot would be sent without the effects and residual).
        n_outer: ``(N,)`` correction rounds used.
    """

    q: Tensor
    converged: Tensor
    reason: list[str]
    predicted_error_mm: Tensor
    predicted_rot_error_mrad: Tensor
    q_uncorrected: Tensor
    n_outer: Tensor

    def summary(self) -> dict[str, int]:
        return {r: self.reason.count(r) for r in sorted(set(self.reason))}


def _subset(cov, idx):
    if cov is None:
        return None
    if isinstance(cov, dict):
        return {k: (v[idx] if torch.as_tensor(v).numel() > 1 else v) for k, v in cov.items()}
    return cov[idx]


class Corrector:
    """Batched command correction with a :class:`~torchcal.deploy.model.CalibratedModel`.

    Args:
        model: the calibrated model.
        marker: the marker to place (default the model's residual marker).
        tol_mm: convergence tolerance on the predicted position error (mm).
        tol_mrad: convergence tolerance on the predicted rotation error (mrad; pose targets).
        max_outer: correction rounds at most.
        ik_options: passed to :func:`torchcal.kinematics.ik.solve_ik` (``rot_weight``, ``max_iter``,
            ``restarts`` for the first IK, ``limits`` ...). The IK tolerances default to 1/1000
            of the correction tolerances so that IK never limits the correction.
        frame: the frame targets are given in: ``"base"`` (default: the robot's own base frame,
            as a cell's programs know it) or ``"instrument"`` (the frame the model was calibrated
            in, e.g. the laser tracker's).
    """

    FRAMES = ("base", "instrument")

    def __init__(self, model: CalibratedModel, marker: str | None = None, tol_mm: float = 1e-3,
                 tol_mrad: float = 1e-3, max_outer: int = 10, ik_options: dict | None = None,
                 frame: str = "base"):
        if frame not in self.FRAMES:
            raise ValueError(f"frame must be one of {self.FRAMES}, got {frame!r}")
        self.frame = frame
        if not isinstance(model, CalibratedModel):
            raise TypeError(f"model must be a CalibratedModel, got {type(model).__name__}")
        if not (tol_mm > 0 and tol_mrad > 0):
            raise ValueError(f"tolerances must be positive, got tol_mm={tol_mm}, tol_mrad={tol_mrad}")
        if int(max_outer) < 1:
            raise ValueError(f"max_outer must be >= 1, got {max_outer}")
        self.model = model
        self.marker = marker or model.marker
        if self.marker not in model.robot.marker_names:
            raise ValueError(f"unknown marker {self.marker!r}; the robot measures {model.robot.marker_names}")
        self.m = model.robot.marker_names.index(self.marker)
        self.tol_mm, self.tol_mrad, self.max_outer = float(tol_mm), float(tol_mrad), int(max_outer)
        opts = {"tol_pos_m": self.tol_mm * 1e-6, "tol_rot": self.tol_mrad * 1e-6}
        opts.update(ik_options or {})
        self.ik_options = opts

    def _check_units(self, p: Tensor) -> None:
        """Refuse targets far beyond the robot's reach (from the frame's origin): millimetres."""
        robot = self.model.robot
        reach = sum(float(torch.as_tensor(j.origin[:3, 3]).norm()) for j in robot.joints) + \
            max(float(torch.as_tensor(m.xyz).norm()) for m in robot.markers)
        if self.frame == "instrument":
            reach += float(robot.base_transform(self.model.params.values)[1].norm())
        far = float(p.norm(dim=-1).max()) if p.numel() else 0.0
        if far > 10 * reach + 1.0:
            raise UnitsError(f"targets lie up to {far:.4g} from the {self.frame} frame's origin, but the robot reaches "
                             f"about {reach:.3g} m: they look like millimetres; torchcal expects metres (divide by "
                             "1000)")

    @threads_by_size("targets")
    def correct(self, targets, q0=None, covariates=None) -> CorrectionResult:
        """Commands that make the model's predicted pose of the marker equal the targets.

        Args:
            targets: ``(N, 4, 4)`` poses or ``(N, 3)`` positions (m), in the corrector's ``frame``.
            q0: ``(N, dof)`` or ``(dof,)`` IK start (choose the branch); default the middle of
                the joint limits with random restarts.
            covariates: the model's covariates, ``name -> (N,)`` (or ``(N, C)``), if any.
        Returns:
            :class:`CorrectionResult`.
        """
        model, robot = self.model, self.model.robot
        R_t, p_t = target_frames(robot, targets)
        self._check_units(p_t)
        if self.frame == "base":  # into the instrument frame the model predicts in
            Rb, tb = robot.base_transform(model.params.values)
            p_t = p_t @ Rb.T + tb
            R_t = None if R_t is None else Rb @ R_t
        pose = R_t is not None
        N = p_t.shape[0]
        if pose:
            T_t = torch.eye(4, dtype=robot.dtype, device=robot.device).repeat(N, 1, 1)
            T_t[:, :3, :3], T_t[:, :3, 3] = R_t, p_t
        else:
            T_t = p_t
        params = model.params.values
        ik = solve_ik(robot, params, T_t, q0, marker=self.marker, **self.ik_options)
        q, q_unc = ik.q.clone(), ik.q.clone()
        reason = list(ik.reason)
        failed = ~ik.converged
        converged = torch.zeros(N, dtype=torch.bool, device=robot.device)
        n_outer = torch.zeros(N, dtype=torch.long, device=robot.device)
        err_p = torch.full((N,), float("nan"), dtype=robot.dtype, device=robot.device)
        err_r = torch.zeros(N, dtype=robot.dtype, device=robot.device)
        T_c = T_t.clone()
        warm = {k: v for k, v in self.ik_options.items() if k != "restarts"}
        active = torch.nonzero(~failed).flatten()
        for it in range(self.max_outer + 1):
            if active.numel() == 0:
                break
            T_pred = model.predict_pose(q[active], _subset(covariates, active))[:, self.m]
            if not pose:
                T_pred = T_pred[:, :3, 3]
            e = pose_error(T_t[active], T_pred)  # predicted - target
            ep = e[:, :3].norm(dim=-1)
            er = e[:, 3:].norm(dim=-1) if pose else torch.zeros_like(ep)
            err_p[active], err_r[active] = ep, er
            ok = (ep <= self.tol_mm * 1e-3) & (er <= self.tol_mrad * 1e-3)
            converged[active[ok]] = True
            active, e = active[~ok], e[~ok]
            if active.numel() == 0 or it == self.max_outer:
                break
            T_c[active] = apply_pose_error(T_c[active], -e)
            ik = solve_ik(robot, params, T_c[active], q[active], marker=self.marker, restarts=0, **warm)
            q[active] = ik.q
            n_outer[active] += 1
            bad = ~ik.converged
            for i, r in zip(active[bad].tolist(), [r for r, b in zip(ik.reason, bad.tolist()) if b]):
                reason[i] = r
            active = active[~bad]
        for i in torch.nonzero(~converged).flatten().tolist():
            if reason[i] == "ok":
                reason[i] = "max_outer"
        if not bool(converged.all()):
            # failed targets: report the predicted error at the commands they end with
            fi = torch.nonzero(~converged).flatten()
            T_pred = model.predict_pose(q[fi], _subset(covariates, fi))[:, self.m]
            if not pose:
                T_pred = T_pred[:, :3, 3]
            e = pose_error(T_t[fi], T_pred)
            err_p[fi] = e[:, :3].norm(dim=-1)
            if pose:
                err_r[fi] = e[:, 3:].norm(dim=-1)
        return CorrectionResult(q=q, converged=converged, reason=reason, predicted_error_mm=err_p * 1e3,
                                predicted_rot_error_mrad=err_r * 1e3, q_uncorrected=q_unc, n_outer=n_outer)
