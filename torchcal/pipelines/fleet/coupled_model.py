"""The coupled fleet's model: residuals and Jacobians of every robot's block and of the parameters
the fleet shares (hierarchical prior means, a payload), and the names of the per-robot block
(:mod:`torchcal.pipelines.fleet.coupled` fits it)."""
from __future__ import annotations

import torch
from torch import Tensor

from torchcal.effects import JointCompliance

__all__ = ["CoupledModel", "block_layout", "fleet_compliance"]

_PAYLOAD = [("payload.m", "kg"), ("payload.mx", "kg*m"), ("payload.my", "kg*m"), ("payload.mz", "kg*m")]


class CoupledModel:
    """Residuals and Jacobians of every robot. Per robot ``z = (x (K) geometry, c (T) compliances,
    μ (4) payload when each robot has its own)``; shared ``s = (m (np) prior means, μ (4) payload
    when the fleet shares it)``. The prior rows are on when ``w`` (their weights) is set."""

    def __init__(self, robot, fd, compliance: JointCompliance | None, payload: str):
        self.robot, self.fd, self.comp = robot, fd, compliance
        self.K = robot.n_params
        self.T = len(compliance.joints) if compliance is not None else 0
        self.own_mu = compliance is not None and payload == "per_robot"
        self.n_pay = 4 if compliance is not None and payload == "shared" else 0
        self.kz = self.K + self.T + (4 if self.own_mu else 0)
        self.P, self.w = None, None  # prior: indices into the geometry, weights σ/τ (m per unit)
        self.scales: dict[str, float] = {}  # the latest estimates of σ and of each τ, by name
        self.md = fd.seen.shape[1] * fd.seen.shape[2] * 3
        if compliance is not None:
            self.dof = torch.tensor([robot.joint_names.index(j) for j in compliance.joints], device=robot.device)
            self.off = torch.tensor([robot.param_names.index(f"{j}.offset") for j in compliance.joints],
                                    device=robot.device)
            self.Wt = self.torque_features(fd)

    @property
    def np(self) -> int:
        return 0 if self.P is None else int(self.P.numel())

    @property
    def ks(self) -> int:
        return self.np + self.n_pay

    def torque_features(self, fd) -> Tensor:
        """``(R, N, T, 5)`` gravity torque on each compliant joint from the URDF bodies (0) and per
        unit payload mass moment (1–4), at every robot's commands (padded rows 0)."""
        R_, N = fd.q.shape[:2]
        out = fd.q.new_zeros(R_, N, self.T, 5)
        for r in range(R_):
            n = fd.rows[r]
            if n:
                out[r, :n] = self.comp.prepare(fd.q[r, :n], {}).features["Wt"][:, :, 0, :]
        return out

    def joints(self, Z: Tensor, pay: Tensor, Wt: Tensor, q: Tensor) -> tuple[Tensor, Tensor | None]:
        """Joint values with the twists ``(R, N, dof)``, and the torques ``(R, N, T)`` (N·m)."""
        if self.comp is None:
            return q, None
        c = Z[:, self.K: self.K + self.T]
        mu = Z[:, self.K + self.T:] if self.own_mu else pay.expand(Z.shape[0], 4)
        tau = Wt[..., 0] + torch.einsum("rntb,rb->rnt", Wt[..., 1:], mu)
        return q.index_add(2, self.dof, c[:, None, :] * tau), tau

    def data(self, Z: Tensor, pay: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """Position residuals ``(R, md)`` (m), their Jacobian in ``z`` and in a shared payload."""
        fd, R_ = self.fd, Z.shape[0]
        idx = torch.arange(R_, device=Z.device)
        x = Z[:, : self.K]
        qe, tau = self.joints(Z, pay, getattr(self, "Wt", None), fd.q)
        J = fd.jacobian(self.robot, x, idx, q=qe)
        r = ((fd.positions(self.robot, x, idx, q=qe) - fd.measured) * fd.seen[..., None]).reshape(R_, -1)
        parts, Jpay = [J], Z.new_zeros(R_, self.md, self.n_pay)
        if self.comp is not None:
            Jq = J[:, :, self.off].reshape(R_, fd.q.shape[1], -1, self.T)  # d/dq_j of each row, (R, N, M·3, T)
            parts.append((Jq * tau[:, :, None, :]).reshape(R_, -1, self.T))
            c = Z[:, self.K: self.K + self.T]
            Jmu = torch.einsum("rnkt,rt,rntb->rnkb", Jq, c, self.Wt[..., 1:]).reshape(R_, -1, 4)
            if self.own_mu:
                parts.append(Jmu)
            else:
                Jpay = Jmu
        return r, torch.cat(parts, -1), Jpay

    def __call__(self, Z: Tensor, s: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        R_, n = Z.shape[0], self.np
        r, Jz, Jpay = self.data(Z, s[n:])
        Js = torch.cat([Z.new_zeros(R_, r.shape[1], n), Jpay], -1)
        if n and self.w is not None:
            ar = torch.arange(n, device=Z.device)
            rp = self.w * (Z[:, self.P] - s[:n])
            Jp = Z.new_zeros(R_, n, self.kz)
            Jp[:, ar, self.P] = self.w
            Jsp = Z.new_zeros(R_, n, self.ks)
            Jsp[:, ar, ar] = -self.w
            r, Jz, Js = torch.cat([r, rp], 1), torch.cat([Jz, Jp], 1), torch.cat([Js, Jsp], 1)
        return r, Jz, Js


def block_layout(robot, template, model: CoupledModel) -> tuple[list[str], list[str], list[str], list[str]]:
    """Names and units of the per-robot block and of the payload the fleet may share."""
    names = list(template.names) + [f"{j}.twist" for j in (model.comp.joints if model.comp else [])]
    units = list(template.units) + ["rad/(N*m)"] * model.T
    if model.own_mu:
        names += [n for n, _ in _PAYLOAD]
        units += [u for _, u in _PAYLOAD]
    shared = _PAYLOAD if model.n_pay else []
    return names, units, [n for n, _ in shared], [u for _, u in shared]


def fleet_compliance(robot, effects, payload: str) -> JointCompliance | None:
    """The fleet-wide joint compliance ``effects`` ask for (None: none), or an error that says
    why this robot or these settings cannot have it."""
    if not effects:
        return None
    bad = [e for e in effects if e != "joint_compliance"]
    if bad:
        raise ValueError(f"fleet-wide effects: only 'joint_compliance' is supported, got {bad}; run the loop "
                         "(torchcal.run_loop) per robot for the others")
    if payload not in ("shared", "per_robot"):
        raise ValueError(f"payload must be 'shared' or 'per_robot', got {payload!r}")
    comp = JointCompliance(robot)
    if comp.lumped:
        raise ValueError("fleet-wide joint compliance needs link inertials in the URDF (the gravity torque); "
                         "this model has none")
    if any(f"{j}.offset" not in robot.param_names for j in comp.joints):
        raise ValueError("fleet-wide joint compliance needs a URDF robot (joint offsets named '<joint>.offset')")
    return comp
