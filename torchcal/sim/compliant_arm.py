"""An arm measured in full pose (seed 002's data): geometric errors, joint compliance under the
gravity load of point masses (link COMs and a payload), a cyclic joint error, and an instrument
with position (m) and orientation (rad) noise. Fitting code may call ``measure`` (or
``simulate``) only."""
from __future__ import annotations

import torch

from torchcal.kinematics.robot import Robot
from torchcal.kinematics.robots import link_inertials, urdf_path
from torchcal.kinematics.transforms import so3_exp
from torchcal.sim.base import Simulated
from torchcal.sim.serial import SimConfig, random_errors

__all__ = ["CompliantArm", "GRAVITY", "ur5e_masses", "CENTER", "HALF", "sample_q"]


GRAVITY = (0.0, 0.0, -9.81)  # m/s², robot base frame (z up)


# ---------------------------------------------------------------------------- the truth
class CompliantArm:
    """The simulated real robot. Fitting code may call :meth:`measure` only.

    Args:
        robot: nominal model (the first marker is the measured tool point).
        masses: ``[(marker spec "name@link=x,y,z", kg), ...]``: point masses on links (link COMs,
            payload) whose gravity load bends the joints.
        seed: seeds the geometric errors and the instrument noise.
        compliance: ``(dof,)`` rad per N m.
        cyclic: ``{joint index: (a, b)}`` rad, error ``a sin(q) + b cos(2 q)``.
        noise_m, noise_rad: instrument noise std per axis.
        length_error, angle_error: std of the geometric errors (m, rad).
    """

    def __init__(self, robot, masses: list[tuple[str, float]], seed: int = 0,
                 compliance=(0.0, 3e-5, 4e-5, 6e-5, 6e-5, 0.0), cyclic=None, noise_m: float = 2e-5,
                 noise_rad: float = 2e-5, length_error: float = 0.5e-3, angle_error: float = 1e-3):
        g = torch.Generator().manual_seed(seed)
        cfg = SimConfig(base_distance=0.0, length_error=length_error, angle_error=angle_error, seed=seed)
        self.robot = robot
        self.truth = random_errors(robot, robot.params(), cfg, g).values
        self.masses = torch.tensor([m for _, m in masses], dtype=torch.float64)
        self.mass_robot = Robot.from_urdf(urdf_path(robot.name), markers=[s for s, _ in masses])
        self.C = torch.tensor(compliance, dtype=torch.float64)
        self.cyclic = cyclic if cyclic is not None else {1: (3e-4, 1.5e-4), 2: (-3e-4, 1.5e-4), 3: (3e-4, -1.5e-4)}
        self.noise_m, self.noise_rad = noise_m, noise_rad
        self.g = torch.Generator().manual_seed(seed + 1000)

    def gravity_torque(self, q: torch.Tensor) -> torch.Tensor:
        """``(N, dof)`` N m: generalised gravity force ``Σ_k J_k(q)ᵀ m_k g``."""
        J = self.mass_robot.joint_jacobian(q)[:, :, :3]  # (N, K, 3, dof)
        f = self.masses[:, None] * torch.tensor(GRAVITY, dtype=torch.float64)  # (K, 3)
        return torch.einsum("nkid,ki->nd", J, f)

    def joint_error(self, q: torch.Tensor) -> torch.Tensor:
        """Non-geometric joint errors (rad): compliance deflection + cyclic error."""
        dq = self.C * self.gravity_torque(q)
        for j, (a, b) in self.cyclic.items():
            dq[:, j] += a * torch.sin(q[:, j]) + b * torch.cos(2 * q[:, j])
        return dq

    def pose(self, q: torch.Tensor) -> torch.Tensor:
        """True ``(N, 4, 4)`` pose of the tool for commands ``q`` (no noise)."""
        return self.robot.fk(q + self.joint_error(q), self.truth)[:, 0]

    def measure(self, q: torch.Tensor) -> torch.Tensor:
        """What the instrument reports: the true pose with noise."""
        T = self.pose(q).clone()
        n = q.shape[0]
        T[:, :3, 3] += self.noise_m * torch.randn(n, 3, generator=self.g, dtype=torch.float64)
        T[:, :3, :3] = T[:, :3, :3] @ so3_exp(self.noise_rad * torch.randn(n, 3, generator=self.g, dtype=torch.float64))
        return T

    def simulate(self, n: int, *, seed: int = 0) -> Simulated:
        """The :class:`~torchcal.sim.base.Simulator` interface: ``n`` commands drawn in the working
        region (:func:`sample_q`) and measured; ``seed`` seeds this data set alone. ``data``: ``q (n,
        dof)`` rad and the measured tool poses ``T (n, 4, 4)`` (m)."""
        saved, self.g = self.g, torch.Generator().manual_seed(int(seed) + 1)
        try:
            q = sample_q(n, torch.Generator().manual_seed(int(seed)))
            T = self.measure(q)
        finally:
            self.g = saved
        return Simulated({"q": q, "T": T}, {"params": self.truth, "compliance": self.C, "cyclic": self.cyclic})


def ur5e_masses(robot, payload: float = 2.0) -> list[tuple[str, float]]:
    """Link masses at their COMs from the UR5e's published inertials, plus a payload (kg) at
    the tool point."""
    out = [(f"com_{ln}@{ln}={c['com'][0]},{c['com'][1]},{c['com'][2]}", c["mass"])
           for ln, c in link_inertials("ur5e").items() if c["mass"] > 0]
    mk = robot.markers[0]
    out.append((f"payload@{mk.link}={mk.xyz[0]},{mk.xyz[1]},{mk.xyz[2]}", payload))
    return out


# ---------------------------------------------------------------------------- data
#: working region of the UR5e, rad: centre and half-width per joint (a table-top cell in front of
#: the robot; the patent samples targets "in the reachable workspace" of its task)
CENTER = (0.0, -1.3, 1.5, -1.8, -1.5708, 0.0)


HALF = (0.9, 0.5, 0.6, 0.9, 0.9, 1.2)


def sample_q(n: int, g: torch.Generator) -> torch.Tensor:
    c, h = torch.tensor(CENTER, dtype=torch.float64), torch.tensor(HALF, dtype=torch.float64)
    return c + h * (2 * torch.rand(n, 6, generator=g, dtype=torch.float64) - 1)
