"""Effects that correct the commanded joint values: ``q_true = q + Δq(q, covariates; θ)``."""
from __future__ import annotations

import torch
from torch import Tensor

from .base import Effect, Prepared
from .gravity import GRAVITY, gravity_features

__all__ = ["CyclicJointError", "JointScale", "Backlash", "JointCompliance"]


class CyclicJointError(Effect):
    """Encoder eccentricity and gear run-out: ``Δq_j = Σ_n a_jn sin(n q_j) + b_jn cos(n q_j)``,
    ``n = 1..harmonics`` (rad). A constant is a zero offset and belongs to the geometry."""

    name = "cyclic_joint_error"
    description = "harmonics of the joint angle (encoder eccentricity, gear run-out)"

    def __init__(self, robot, joints=None, harmonics: int = 2):
        self.harmonics = int(harmonics)
        super().__init__(robot, joints)

    def param_info(self):
        return [(f"{j}.{t}{n}", "rad") for j in self.joints for n in range(1, self.harmonics + 1) for t in ("s", "c")]

    def config(self) -> dict:
        return {"harmonics": self.harmonics}

    def prepare(self, q, covariates):
        idx = [self.robot.joint_names.index(j) for j in self.joints]
        qs = q[:, idx]  # (N, J)
        n = torch.arange(1, self.harmonics + 1, dtype=q.dtype, device=q.device)
        arg = qs[..., None] * n  # (N, J, H)
        basis = torch.stack([torch.sin(arg), torch.cos(arg)], -1).reshape(q.shape[0], len(idx), -1)  # (N, J, 2H)
        return Prepared({"basis": basis})

    def joint_delta(self, theta, prep):
        B = prep.features["basis"]
        th = theta.reshape(theta.shape[0], len(self.joints), -1)  # (P, J, 2H)
        return self._scatter(torch.einsum("njh,pjh->pnj", B, th))


class JointScale(Effect):
    """Encoder or gear-ratio scale error: ``Δq_j = s_j q_j`` (dimensionless ``s_j``)."""

    name = "joint_scale"
    description = "encoder or gear-ratio scale error"

    def default_joints(self):
        return list(self.robot.joint_names)

    def param_info(self):
        return [(f"{j}.scale", "1") for j in self.joints]

    def prepare(self, q, covariates):
        idx = [self.robot.joint_names.index(j) for j in self.joints]
        return Prepared({"q": q[:, idx]})

    def joint_delta(self, theta, prep):
        return self._scatter(prep.features["q"][None] * theta[:, None, :])


class Backlash(Effect):
    """Backlash: a joint offset whose sign follows the direction of the last motion,
    ``Δq_j = b_j · dir_j`` with covariate ``dir.<joint>`` = +1 / −1 (``b_j`` = half the play, rad)."""

    name = "backlash"
    description = "offset whose sign follows the direction of the last motion"

    def default_joints(self):
        return list(self.robot.joint_names)

    def param_info(self):
        return [(f"{j}.half_play", "rad" if u == "rad" else "m") for j, u in
                zip(self.joints, [self.robot.joint_units[self.robot.joint_names.index(j)] for j in self.joints])]

    @property
    def covariates(self) -> list[str]:
        return [f"dir.{j}" for j in self.joints]

    def applicable(self, data):
        missing = [j for j in self.joints if f"dir.{j}" not in data.covariates]
        if len(missing) == len(self.joints):
            return False, "no 'dir.<joint>' covariate (+1/-1 direction of the last motion) in the data"
        return True, ""

    def restrict_to_data(self, data, min_lever_m: float = 5e-3) -> "Backlash":
        """A copy acting only on joints whose direction covariate the data has (and that move
        the markers, see :meth:`Effect.restrict_to_data`)."""
        seen = Backlash(self.robot, [j for j in self.joints if f"dir.{j}" in data.covariates])
        return Effect.restrict_to_data(seen, data, min_lever_m)

    def prepare(self, q, covariates):
        cols = []
        for j in self.joints:
            d = covariates.get(f"dir.{j}")
            if d is None:
                raise ValueError(f"backlash on {j!r} needs the covariate 'dir.{j}' (+1/-1) in the data")
            cols.append(torch.sign(d.to(q)))
        return Prepared({"dir": torch.stack(cols, -1)})

    def joint_delta(self, theta, prep):
        return self._scatter(prep.features["dir"][None] * theta[:, None, :])


class JointCompliance(Effect):
    """Joint deflection proportional to the gravity torque: ``Δq_j = c_j τ_j(q)`` (``c_j`` in
    rad/(N·m)).

    With inertials in the URDF, ``τ`` is computed from them plus an unknown payload on the tool
    link (mass ``m`` kg and first moment ``m s`` kg·m, identified: tools are rarely in the URDF).
    Without usable masses (``lumped=True`` or no inertials), gravity torque is linear in the
    unknown mass moments of the links, so the products compliance × mass moment are identified
    directly: ``Δq_j = Σ_links θ_{j,link} · features`` (4 per joint and link, most of them
    dropped again by identifiability).
    """

    name = "joint_compliance"
    description = "joint deflection proportional to the gravity torque (incl. an unknown payload)"

    def __init__(self, robot, joints=None, tool_link: str | None = None, lumped: bool | None = None,
                 gravity=GRAVITY):
        from ..urdf import read_inertials

        self.gravity = tuple(float(v) for v in gravity)
        inert = read_inertials(robot._urdf_text) if getattr(robot, "_urdf_text", None) else {}
        chain_links = {jt.child for jt in robot.joints} | {robot.root}
        self.inertials = {l: v for l, v in inert.items() if l in chain_links}
        self.lumped = (not self.inertials) if lumped is None else bool(lumped)
        self.tool_link = tool_link or robot.markers[0].link
        # links that move with some actuated joint (their mass can load a joint)
        self.moving_links = [jt.child for jt in robot.joints if jt.child != robot.root]
        super().__init__(robot, joints)

    def config(self) -> dict:
        return {"tool_link": self.tool_link, "lumped": self.lumped, "gravity": list(self.gravity)}

    def param_info(self):
        if self.lumped:
            return [(f"{j}.{l}.{t}", u) for j in self.joints for l in self._lump_links()
                    for t, u in (("m", "rad/N"), ("mx", "rad/N/m"), ("my", "rad/N/m"), ("mz", "rad/N/m"))]
        return ([(f"{j}.c", "rad/(N*m)") for j in self.joints]
                + [("payload.m", "kg"), ("payload.mx", "kg*m"), ("payload.my", "kg*m"), ("payload.mz", "kg*m")])

    def _lump_links(self) -> list[str]:
        # one lumped body per link that follows an actuated joint (fixed children move with it)
        return [jt.child for jt in self.robot.joints if jt.movable and jt.mimic is None]

    def init_theta(self, data=None):
        th = super().init_theta(data)
        if not self.lumped:
            # a small compliance so that the payload columns are not zero at the start
            th[: len(self.joints)] = 1e-7
        return th

    def prepare(self, q, covariates):
        idx = torch.tensor([self.robot.joint_names.index(j) for j in self.joints], device=q.device)
        if self.lumped:
            F = gravity_features(self.robot, q, self._lump_links(), self.gravity)  # (N, L, dof, 4)
            return Prepared({"F": F[:, :, idx, :].permute(0, 2, 1, 3).reshape(q.shape[0], len(self.joints), -1)})
        links = list(self.inertials)
        F = gravity_features(self.robot, q, links + [self.tool_link], self.gravity)[:, :, idx, :]  # (N, L+1, J, 4)
        mm = torch.tensor([[v["mass"], *(v["mass"] * v["com"]).tolist()] for v in self.inertials.values()],
                          dtype=q.dtype, device=q.device).reshape(-1, 4)  # mass moments (L, 4)
        tau = torch.einsum("nljf,lf->nj", F[:, :-1], mm) if links else q.new_zeros(q.shape[0], len(self.joints))
        return Prepared({"tau": tau, "Fp": F[:, -1]})  # (N, J), (N, J, 4)

    def joint_delta(self, theta, prep):
        J = len(self.joints)
        if self.lumped:
            th = theta.reshape(theta.shape[0], J, -1)  # (P, J, 4L)
            return self._scatter(torch.einsum("njf,pjf->pnj", prep.features["F"], th))
        c, mp = theta[:, :J], theta[:, J:]  # (P, J), (P, 4)
        tau = prep.features["tau"][None] + torch.einsum("njf,pf->pnj", prep.features["Fp"], mp)
        return self._scatter(c[:, None, :] * tau)

    def torques(self, q, covariates=None, theta: Tensor | None = None) -> Tensor:
        """Gravity torque per effect joint (N·m) at ``q`` with the identified payload
        (URDF-inertial mode), for evidence plots."""
        prep = self.prepare(q, covariates or {})
        th = self.theta if theta is None else theta
        if self.lumped:
            raise ValueError("lumped compliance has no separate torque; plot its Δq instead")
        return prep.features["tau"] + torch.einsum("njf,f->nj", prep.features["Fp"], th[len(self.joints):])
