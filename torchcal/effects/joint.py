"""Effects that correct the commanded joint values: ``q_true = q + Δq(q, covariates; θ)``."""
from __future__ import annotations

import torch
from torch import Tensor

from torchcal.effects.base import Effect, Prepared

__all__ = ["CyclicJointError", "JointScale", "Backlash"]


class CyclicJointError(Effect):
    """Encoder eccentricity and gear run-out: ``Δq_j = Σ_n a_jn sin(n q_j) + b_jn cos(n q_j)``,
    ``n = 1..harmonics`` (rad). A constant is a zero offset and belongs to the geometry."""

    name = "cyclic_joint_error"
    description = "harmonics of the joint angle (encoder eccentricity, gear run-out)"

    def __init__(self, robot, joints=None, geometry=None, harmonics: int = 2):
        self.harmonics = int(harmonics)
        super().__init__(robot, joints, geometry)

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
        return Prepared({"basis": basis, "q": qs})

    def joint_delta(self, theta, prep):
        B = prep.features["basis"]
        th = theta.reshape(theta.shape[0], len(self.joints), -1)  # (P, J, 2H)
        return self._scatter(torch.einsum("njh,pjh->pnj", B, th))

    def signature(self, prep, label, theta):
        return self._joint_signature(prep, label, theta, prep.features["q"][:, self.joints.index(label)],
                                     "joint angle [rad]", "joint error [rad]")

    def mode_words(self, label: str) -> str:
        return f"{label} has a cyclic error (harmonics 1–{self.harmonics} of its angle)"


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

    def signature(self, prep, label, theta):
        return self._joint_signature(prep, label, theta, prep.features["q"][:, self.joints.index(label)],
                                     "joint angle [rad]", "joint error [rad]")

    def mode_words(self, label: str) -> str:
        return f"{label} reads its angle with a scale error"


class Backlash(Effect):
    """Backlash: a joint offset whose sign follows the direction of the last motion,
    ``Δq_j = b_j · dir_j`` with covariate ``dir.<joint>`` = +1 / −1 (``b_j`` = half the play, rad)."""

    name = "backlash"
    description = "offset whose sign follows the direction of the last motion"
    reads = ("direction",)

    def default_joints(self):
        return list(self.robot.joint_names)

    def param_info(self):
        return [(f"{j}.half_play", "rad" if u == "rad" else "m") for j, u in
                zip(self.joints, [self.robot.joint_units[self.robot.joint_names.index(j)] for j in self.joints])]

    @property
    def covariates(self) -> list[str]:
        return [f"dir.{j}" for j in self.joints]

    def direction_flips(self) -> list[int]:
        return [self.robot.joint_names.index(j) for j in self.joints]

    def applicable(self, data):
        missing = [j for j in self.joints if f"dir.{j}" not in data.covariates]
        if len(missing) == len(self.joints):
            return False, "no 'dir.<joint>' covariate (+1/-1 direction of the last motion) in the data"
        return True, ""

    def bind(self, data, min_lever_m: float = 5e-3) -> "Backlash":
        """A copy acting only on joints whose direction covariate the data has (and that move
        the markers, see :meth:`Effect.bind`)."""
        seen = self._copy(joints=[j for j in self.joints if f"dir.{j}" in data.covariates])
        return Effect.bind(seen, data, min_lever_m)

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

    def signature(self, prep, label, theta):
        return self._joint_signature(prep, label, theta, prep.features["dir"][:, self.joints.index(label)],
                                     "direction of the last motion [±1]", "joint offset [rad]")

    def mode_words(self, label: str) -> str:
        return f"{label} has backlash (an offset that follows the direction of its last motion)"
