"""The effect-model interface: one physical effect the geometric model lacks, as a small,
differentiable, batched model with named parameters.

An effect acts in one of two places:

* ``kind = "joint"``: a correction ``Δq (P, N, dof)`` added to the commanded joint values
  before the kinematics (compliance, backlash, cyclic errors, scale errors);
* ``kind = "position"``: a map of robot-base marker positions ``(P, N, M, 3)`` before the
  instrument frame is applied (thermal expansion of the links).

Effects are fitted jointly with the geometry. Data-dependent features (gravity torques,
harmonics of the commands, covariates) depend only on the commanded state, so they are
computed once per data set by :meth:`Effect.prepare` and reused at every evaluation.
"""
from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

__all__ = ["Effect", "Prepared"]


@dataclass
class Prepared:
    """Per-data-set features of an effect (whatever the effect needs; tensors on the robot's device)."""

    features: dict


class Effect:
    """Base class. Subclasses set ``name`` and ``kind`` and implement :meth:`param_info`,
    :meth:`prepare` and :meth:`joint_delta` (kind "joint") or :meth:`position_map` (kind
    "position").

    Args:
        robot: the :class:`~torchcal.robot.Robot` the effect belongs to.
        joints: joints the effect acts on (default: all actuated joints it applies to).
    """

    name = "effect"
    kind = "joint"
    description = ""

    def __init__(self, robot, joints: list[str] | None = None):
        self.robot = robot
        known = list(robot.joint_names)
        if joints is not None:
            bad = [j for j in joints if j not in known]
            if bad:
                raise ValueError(f"{self.name}: unknown joint(s) {bad}; the robot's joints are {known}")
        self.joints = list(joints) if joints is not None else self.default_joints()
        self.theta = torch.zeros(len(self.param_names), dtype=robot.dtype, device=robot.device)

    # -- description --------------------------------------------------------------------
    def default_joints(self) -> list[str]:
        return [n for n, u in zip(self.robot.joint_names, self.robot.joint_units) if u == "rad"]

    def param_info(self) -> list[tuple[str, str]]:
        """``[(name, unit), …]`` of this effect's parameters."""
        raise NotImplementedError

    @property
    def param_names(self) -> list[str]:
        return [f"{self.name}.{n}" for n, _ in self.param_info()]

    @property
    def param_units(self) -> list[str]:
        return [u for _, u in self.param_info()]

    @property
    def n_params(self) -> int:
        return len(self.param_info())

    def applicable(self, data) -> tuple[bool, str]:
        """Whether this effect can be fitted on ``data`` (e.g. backlash needs direction
        covariates), with the reason in words when not."""
        return True, ""

    def restrict_to_data(self, data, min_lever_m: float = 5e-3) -> "Effect":
        """A copy acting only on joints whose motion moves the measured markers: median lever
        over the data at least ``min_lever_m`` (m per rad; prismatic joints always count). A
        joint that barely moves the markers cannot show an effect, and fitting one there only
        invents values no measurement can check."""
        J = self.robot.joint_jacobian(data.q, check=False)[:, :, :3, :]  # (N, M, 3, dof)
        mk = [self.robot.marker_names.index(m) for m in data.marker_names]
        lever = J[:, mk].norm(dim=-2).amax(1).median(0).values  # (dof,)
        keep = [j for j in self.joints if self.robot.joint_units[self.robot.joint_names.index(j)] == "m"
                or float(lever[self.robot.joint_names.index(j)]) >= min_lever_m]
        return type(self)(self.robot, keep, **self.config())

    def init_theta(self, data=None) -> Tensor:
        """Start values (zeros: no effect)."""
        return torch.zeros(self.n_params, dtype=self.robot.dtype, device=self.robot.device)

    def bounds(self) -> tuple[Tensor, Tensor]:
        big = torch.full((self.n_params,), float("inf"), dtype=self.robot.dtype, device=self.robot.device)
        return -big, big

    # -- evaluation -----------------------------------------------------------------------
    def prepare(self, q: Tensor, covariates: dict[str, Tensor]) -> Prepared:
        """Features for commands ``q (N, dof)`` and covariates (name -> ``(N,)``)."""
        raise NotImplementedError

    def joint_delta(self, theta: Tensor, prep: Prepared) -> Tensor:
        """``theta (P, k) -> Δq (P, N, dof)`` (rad / m), for kind "joint"."""
        raise NotImplementedError

    def position_map(self, p: Tensor, theta: Tensor, prep: Prepared) -> Tensor:
        """``p (P, N, M, 3)`` robot-base positions (m) -> corrected, for kind "position"."""
        raise NotImplementedError

    def _scatter(self, per_joint: Tensor) -> Tensor:
        """``(P, N, len(self.joints)) -> (P, N, dof)`` with zeros for the other joints."""
        idx = torch.tensor([self.robot.joint_names.index(j) for j in self.joints], device=per_joint.device)
        out = per_joint.new_zeros(*per_joint.shape[:-1], self.robot.dof)
        return out.index_copy(-1, idx, per_joint)

    # -- deployment -------------------------------------------------------------------------
    def joint_correction(self, q: Tensor, covariates: dict[str, Tensor] | None = None) -> Tensor:
        """``Δq (N, dof)`` for commands ``q`` with the fitted parameters (the hook
        :class:`~torchcal.model.CalibratedModel` calls before FK)."""
        if self.kind != "joint":
            return torch.zeros_like(q)
        return self.joint_delta(self.theta[None], self.prepare(q, covariates or {}))[0]

    @property
    def covariates(self) -> list[str]:
        """Covariates the effect reads (every prediction must be given them)."""
        return []

    def position_correction(self, p: Tensor, q: Tensor, covariates: dict[str, Tensor] | None = None) -> Tensor:
        """``p (N, M, 3)`` robot-base marker positions (m) -> corrected, with the fitted
        parameters (the hook :class:`~torchcal.model.CalibratedModel` calls after FK)."""
        if self.kind != "position":
            return p
        return self.position_map(p[None], self.theta[None], self.prepare(q, covariates or {}))[0]

    def state_dict(self) -> dict:
        """What :func:`torchcal.persist.save` stores: tensors bit-exactly, the rest as JSON."""
        return {"name": self.name, "joints": list(self.joints), "theta": self.theta.detach().clone(),
                "config": self.config()}

    @classmethod
    def from_state_dict(cls, state: dict, robot) -> "Effect":
        eff = cls(robot, list(state["joints"]), **dict(state.get("config") or {}))
        eff.theta = torch.as_tensor(state["theta"], dtype=robot.dtype, device=robot.device).clone()
        return eff

    def config(self) -> dict:
        """Constructor settings beyond ``joints`` needed to rebuild the effect."""
        return {}

    def __repr__(self) -> str:
        return f"{type(self).__name__}(joints={self.joints}, n_params={self.n_params})"
