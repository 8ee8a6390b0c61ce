"""Planar two-link dynamics of a SCARA (seed 001) in regressor form ``τ = W(θ, θ̇, θ̈) ξ``.

Model (seed 001): joints 3–4 (quill and wrist) are lumped into link 2 as a payload and the arm
moves in the horizontal plane, so gravity does no work on joints 1–2. Link ``i`` has mass
``m_i`` (kg), length ``a_i`` (m), centre of mass at ``x_i`` (m) from its proximal joint axis along
the link, and inertia ``I_i`` (kg·m²) about the vertical axis through its COM. With
``c2 = cos θ2``, ``s2 = sin θ2``, Lagrange's equations give ``τ = M(θ)θ̈ + C(θ, θ̇)θ̇``::

    M11 = A + 2B c2,   M12 = C + B c2,   M22 = C,   h = B s2
    τ1 = M11 θ̈1 + M12 θ̈2 − h (2 θ̇1 θ̇2 + θ̇2²)
    τ2 = M12 θ̈1 + M22 θ̈2 + h θ̇1²

with the three *base parameters* (the minimal identifiable set)::

    A = I1 + I2 + m1 x1² + m2 (a1² + x2²)     (kg·m²)
    B = m2 a1 x2                              (kg·m²)
    C = I2 + m2 x2²                           (kg·m²)

**The six lumped parameters ξ.** Seed 001 identifies six parameters but its equations were lost
in extraction. Six independent combinations do not exist for this model (it has three base
parameters), so we use the form that writes each joint's equation linear in *its own* three
coefficients (row-decoupled; full column rank on any exciting trajectory)::

    τ1 = ξ1 θ̈1 + ξ2 θ̈2 + ξ3 [c2 (2θ̈1 + θ̈2) − s2 (2θ̇1θ̇2 + θ̇2²)]
    τ2 = ξ4 θ̈1 + ξ5 θ̈2 + ξ6 [c2 θ̈1 + s2 θ̇1²]

    ξ = (A, C, B, C, C, B)

Physically ``ξ2 = ξ4 = ξ5`` and ``ξ3 = ξ6``; an unconstrained fit of ξ ignores these ties
(:data:`BASE_TO_SEED` maps the base parameters onto ξ when they should be enforced).

**Friction** (optional, off by default): per joint ``f_vi θ̇_i + f_ci sign(θ̇_i)`` (viscous
N·m·s/rad, Coulomb N·m), appended as columns ``[fv1, fc1, fv2, fc2]``.

Shapes: any leading batch ``(...)``; joint arrays ``(..., 2)``; regressors ``(..., 2, k)``.
"""
from __future__ import annotations

from dataclasses import dataclass, fields

import torch
from torch import Tensor
from torch.func import jvp

from torchcal.dynamics.lagrangian import euler_lagrange
from torchcal.kinematics.robot_data import get_robot

__all__ = ["PlanarParams", "SEED_NAMES", "BASE_NAMES", "FRICTION_NAMES", "BASE_TO_SEED",
           "regressor", "base_regressor", "lumped", "base_params", "torque",
           "lagrangian_torque"]

SEED_NAMES = ("xi1", "xi2", "xi3", "xi4", "xi5", "xi6")
BASE_NAMES = ("A", "B", "C")
FRICTION_NAMES = ("fv1", "fc1", "fv2", "fc2")

#: ``(6, 3)`` map ``ξ = BASE_TO_SEED @ (A, B, C)``.
BASE_TO_SEED = torch.tensor([[1, 0, 0], [0, 0, 1], [0, 1, 0],
                             [0, 0, 1], [0, 0, 1], [0, 1, 0]], dtype=torch.float64)


@dataclass
class PlanarParams:
    """Physical parameters of the planar two-link model (floats or broadcastable tensors).

    Attributes:
        m1, m2: link masses, kg (``m2`` includes the lumped quill / joints 3–4).
        I1, I2: inertias about the COM, vertical axis, kg·m².
        a1, a2: link lengths, m (``a2`` enters no torque: the COM offset ``x2`` does).
        x1, x2: COM distance from the proximal joint axis along the link, m.
        fv, fc: optional ``(2,)`` viscous (N·m·s/rad) and Coulomb (N·m) friction per joint.
    """

    m1: float | Tensor
    m2: float | Tensor
    I1: float | Tensor
    I2: float | Tensor
    a1: float | Tensor
    a2: float | Tensor
    x1: float | Tensor
    x2: float | Tensor
    fv: tuple[float, float] | Tensor | None = None
    fc: tuple[float, float] | Tensor | None = None

    @classmethod
    def from_robot(cls, name: str = "scara", **friction) -> "PlanarParams":
        """The ``planar_dynamics`` entry of :mod:`torchcal.kinematics.robot_data` (for ``"scara"``, the
        Adept Cobra s600: ``a1``, ``a2`` published, masses / COMs / inertias ILLUSTRATIVE).
        ``friction``: optional ``fv=(.,.)``, ``fc=(.,.)``."""

        d = get_robot(name)["planar_dynamics"]
        keys = [f.name for f in fields(cls) if f.name not in ("fv", "fc")]
        return cls(**{k: float(d[k]) for k in keys}, **friction)

    @property
    def has_friction(self) -> bool:
        return self.fv is not None or self.fc is not None


def lumped(p: PlanarParams, friction: bool = False) -> Tensor:
    """``(6,)`` lumped parameters ξ (kg·m²) of :mod:`this module <torchcal.dynamics.scara>`,
    plus ``[fv1, fc1, fv2, fc2]`` when ``friction`` (missing friction counts as zero)."""
    A, B, C = base_params(p).unbind(-1)
    xi = torch.stack([A, C, B, C, C, B], -1)
    if not friction:
        return xi
    fv = torch.as_tensor(p.fv if p.fv is not None else (0.0, 0.0), dtype=xi.dtype)
    fc = torch.as_tensor(p.fc if p.fc is not None else (0.0, 0.0), dtype=xi.dtype)
    return torch.cat([xi, torch.stack([fv[0], fc[0], fv[1], fc[1]])], -1)


def base_params(p: PlanarParams) -> Tensor:
    """``(3,)`` base parameters ``(A, B, C)``, kg·m² (see the module docstring)."""
    t = {k: torch.as_tensor(getattr(p, k), dtype=torch.float64)
         for k in ("m1", "m2", "I1", "I2", "a1", "x1", "x2")}
    A = t["I1"] + t["I2"] + t["m1"] * t["x1"] ** 2 + t["m2"] * (t["a1"] ** 2 + t["x2"] ** 2)
    B = t["m2"] * t["a1"] * t["x2"]
    C = t["I2"] + t["m2"] * t["x2"] ** 2
    return torch.stack([A, B, C], -1)


def regressor(q: Tensor, qd: Tensor, qdd: Tensor, friction: bool = False) -> Tensor:
    """Seed regressor ``W`` with ``τ = W ξ``.

    Args:
        q, qd, qdd: ``(..., 2)`` joint angles (rad), velocities (rad/s), accelerations (rad/s²).
        friction: append the four friction columns ``[θ̇1, sign θ̇1]`` (row 1) and
            ``[θ̇2, sign θ̇2]`` (row 2).
    Returns:
        ``(..., 2, 6)`` (``(..., 2, 10)`` with friction), units kg·m² → N·m per column.
    """
    c2, s2 = torch.cos(q[..., 1]), torch.sin(q[..., 1])
    d1, d2 = qd[..., 0], qd[..., 1]
    dd1, dd2 = qdd[..., 0], qdd[..., 1]
    z = torch.zeros_like(c2)
    r1 = [dd1, dd2, c2 * (2 * dd1 + dd2) - s2 * (2 * d1 * d2 + d2 * d2), z, z, z]
    r2 = [z, z, z, dd1, dd2, c2 * dd1 + s2 * d1 * d1]
    if friction:
        r1 += [d1, torch.sign(d1), z, z]
        r2 += [z, z, d2, torch.sign(d2)]
    return torch.stack([torch.stack(r1, -1), torch.stack(r2, -1)], -2)


def base_regressor(q: Tensor, qd: Tensor, qdd: Tensor, friction: bool = False) -> Tensor:
    """``(..., 2, 3)`` regressor of the base parameters ``(A, B, C)`` (``(..., 2, 7)`` with
    friction): the seed regressor with the tied columns summed, ``W @ BASE_TO_SEED``."""
    W = regressor(q, qd, qdd, friction)
    Wb = W[..., :6] @ BASE_TO_SEED.to(W)
    return torch.cat([Wb, W[..., 6:]], -1)


def torque(W: Tensor, xi: Tensor) -> Tensor:
    """``(..., 2)`` joint torques (N·m) ``W ξ`` from ``W`` ``(..., 2, k)`` and ``ξ`` ``(k,)``
    (or ``(P, k)`` for a population with ``W`` ``(N, 2, k)``: returns ``(P, N, 2)``)."""
    if xi.ndim == 1:
        return W @ xi
    return torch.einsum("njk,pk->pnj", W, xi)


def lagrangian_torque(p: PlanarParams, q: Tensor, qd: Tensor, qdd: Tensor) -> Tensor:
    """``(N, 2)`` joint torques (N·m) from the Lagrangian by autograd — an independent check of
    :func:`regressor` (no hand-derived M or C).

    ``L = T = ½ m1 |ṗ1|² + ½ I1 θ̇1² + ½ m2 |ṗ2|² + ½ I2 (θ̇1 + θ̇2)²`` with COM positions
    ``p1 = x1 (cos θ1, sin θ1)``, ``p2 = a1 (cos θ1, sin θ1) + x2 (cos θ12, sin θ12)`` whose
    velocities come from forward-mode autodiff; friction (if set) is added to the result.
    """
    f = {k: torch.as_tensor(getattr(p, k), dtype=q.dtype) for k in
         ("m1", "m2", "I1", "I2", "a1", "x1", "x2")}

    def coms(th: Tensor) -> tuple[Tensor, Tensor]:
        t1, t12 = th[..., 0], th[..., 0] + th[..., 1]
        u1 = torch.stack([torch.cos(t1), torch.sin(t1)], -1)
        u12 = torch.stack([torch.cos(t12), torch.sin(t12)], -1)
        return f["x1"] * u1, f["a1"] * u1 + f["x2"] * u12

    def L(th: Tensor, thd: Tensor) -> Tensor:
        _, (v1, v2) = jvp(coms, (th,), (thd,))
        w1, w12 = thd[..., 0], thd[..., 0] + thd[..., 1]
        return 0.5 * (f["m1"] * (v1 * v1).sum(-1) + f["I1"] * w1 * w1
                      + f["m2"] * (v2 * v2).sum(-1) + f["I2"] * w12 * w12)

    tau = euler_lagrange(L, q, qd, qdd)
    if p.fv is not None:
        tau = tau + torch.as_tensor(p.fv, dtype=q.dtype) * qd
    if p.fc is not None:
        tau = tau + torch.as_tensor(p.fc, dtype=q.dtype) * torch.sign(qd)
    return tau
