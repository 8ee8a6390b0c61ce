"""Joint torques from a Lagrangian by automatic differentiation, and a regressor for any serial
robot built from its link inertials.

Euler–Lagrange: ``τ = d/dt(∂L/∂q̇) − ∂L/∂q``. With ``L̇ = DL·(q̇, q̈)`` (the time derivative along
the motion, ``q̈`` held independent) one has ``d/dt(∂L/∂q̇) = ∂L̇/∂q̇ − ∂L/∂q``, hence

    τ_i = ∂L̇/∂q̇_i − 2 ∂L/∂q_i,

which needs only forward-mode derivatives (``torch.func.jvp``): one nested pair per joint. The
same formula applied to a vector of energy *features* ``φ(q, q̇)`` with ``L = φ·π`` gives the
regressor ``Y`` of ``τ = Y(q, q̇, q̈) π``, since the operator is linear in ``L``.

Units: SI (rad or m, rad/s or m/s, N·m or N, kg, kg·m²). Shapes: ``N`` samples, ``n`` joints.
"""
from __future__ import annotations

from typing import Callable, Sequence

import torch
from torch import Tensor
from torch.func import jvp

__all__ = ["euler_lagrange", "inertial_vector", "serial_regressor", "INERTIAL_NAMES"]

#: Standard inertial parameters of one link, in its link frame: mass, first moment ``m·c``, and
#: the inertia tensor about the link-frame origin (not the COM).
INERTIAL_NAMES = ("m", "mx", "my", "mz", "Ixx", "Ixy", "Ixz", "Iyy", "Iyz", "Izz")


def euler_lagrange(L: Callable[[Tensor, Tensor], Tensor], q: Tensor, qd: Tensor, qdd: Tensor) -> Tensor:
    """Generalised forces ``d/dt(∂L/∂q̇) − ∂L/∂q`` by forward-mode autodiff.

    Args:
        L: ``(q, qd) -> (N,)`` Lagrangian per sample, or ``(N, K)`` energy features (then the
            result is a regressor). Samples must be independent (sample ``j``'s value depends
            only on row ``j``): derivatives are taken for the whole batch at once.
        q, qd, qdd: ``(N, n)`` positions, velocities, accelerations.
    Returns:
        ``(N, n)`` forces for a scalar ``L``, ``(N, n, K)`` for features.
    """
    def Ldot(q_: Tensor, qd_: Tensor) -> Tensor:
        # qd_ is both a primal and the tangent, so the outer derivative in qd sees both
        return jvp(L, (q_, qd_), (qd_, qdd))[1]

    cols = []
    zero = torch.zeros_like(q)
    for i in range(q.shape[-1]):
        e = torch.zeros_like(q)
        e[..., i] = 1.0
        dLdot_dqd = jvp(Ldot, (q, qd), (zero, e))[1]
        dL_dq = jvp(L, (q, qd), (e, zero))[1]
        cols.append(dLdot_dqd - 2.0 * dL_dq)
    return torch.stack(cols, 1)


def inertial_vector(inertials: dict[str, dict] | Sequence[dict]) -> Tensor:
    """``(10 n_links,)`` standard inertial parameters (:data:`INERTIAL_NAMES` per link) from
    :func:`torchcal.kinematics.robots.link_inertials`-style entries (mass kg, COM m, inertia about the COM
    ``(ixx, ixy, ixz, iyy, iyz, izz)`` kg·m², all in the link frame). The inertia is moved to
    the link origin by the parallel-axis theorem ``I_o = I_c + m (|c|² 1 − c cᵀ)``."""
    rows = list(inertials.values()) if isinstance(inertials, dict) else list(inertials)
    out = []
    for r in rows:
        m = float(r["mass"])
        c = torch.tensor(r["com"], dtype=torch.float64)
        ixx, ixy, ixz, iyy, iyz, izz = (float(v) for v in r["inertia"])
        Ic = torch.tensor([[ixx, ixy, ixz], [ixy, iyy, iyz], [ixz, iyz, izz]], dtype=torch.float64)
        Io = Ic + m * (c.dot(c) * torch.eye(3, dtype=torch.float64) - torch.outer(c, c))
        out.append(torch.stack([torch.tensor(m, dtype=torch.float64), *(m * c),
                                Io[0, 0], Io[0, 1], Io[0, 2], Io[1, 1], Io[1, 2], Io[2, 2]]))
    return torch.cat(out)


def _energy_features(frames: Callable[[Tensor], Tensor], gravity: Tensor):
    """``(q, qd) -> (N, 10 n_links)`` features ``φ`` with ``L = φ·π`` (:data:`INERTIAL_NAMES`).

    For a link with body-frame linear velocity ``v`` (of the frame origin) and angular velocity
    ``ω``: ``T = ½ m v·v + h·(v × ω) + ½ ωᵀ I_o ω`` and ``−U = m g·p + h·(Rᵀ g)``.
    """
    def phi(q: Tensor, qd: Tensor) -> Tensor:
        T, Td = jvp(frames, (q,), (qd,))  # (N, L, 4, 4): poses and their time derivatives
        R, p = T[..., :3, :3], T[..., :3, 3]
        Rd, pd = Td[..., :3, :3], Td[..., :3, 3]
        Rt = R.transpose(-1, -2)
        W = Rt @ Rd  # body angular velocity as a skew matrix
        w = torch.stack([W[..., 2, 1], W[..., 0, 2], W[..., 1, 0]], -1)
        v = (Rt @ pd[..., None])[..., 0]
        g = gravity.to(q)
        gb = (Rt @ g[:, None])[..., 0]
        wx, wy, wz = w.unbind(-1)
        f = torch.stack([
            0.5 * (v * v).sum(-1) + (p * g).sum(-1),
            *(torch.linalg.cross(v, w) + gb).unbind(-1),
            0.5 * wx * wx, wx * wy, wx * wz, 0.5 * wy * wy, wy * wz, 0.5 * wz * wz,
        ], -1)  # (N, L, 10)
        return f.flatten(-2)
    return phi


def serial_regressor(robot, q: Tensor, qd: Tensor, qdd: Tensor, links: Sequence[str] | None = None,
                     gravity: Sequence[float] = (0.0, 0.0, -9.81)) -> Tensor:
    """Inverse-dynamics regressor ``τ = Y π`` of a serial (or tree) :class:`~torchcal.Robot`.

    The link poses come from ``robot.fk`` with one marker per link (build the robot with
    ``markers=links``, e.g. ``shipped("scara", source="dh", markers=["link1", ..., "link4"])``);
    energies are differentiated by :func:`euler_lagrange`. No friction, no motor inertia.

    Args:
        robot: a Robot whose markers include ``links``.
        q, qd, qdd: ``(N, dof)`` joint positions, velocities, accelerations (rad or m, per s).
        links: link (marker) names carrying inertials, in the order of ``π``; default all
            markers.
        gravity: ``(3,)`` m/s², in the robot base frame.
    Returns:
        ``(N, dof, 10 n_links)`` regressor; columns follow :data:`INERTIAL_NAMES` per link, so
        ``Y @ inertial_vector(link_inertials(name))`` is the joint torque (N·m or N).
    """
    names = list(robot.marker_names)
    links = names if links is None else list(links)
    idx = torch.tensor([names.index(n) for n in links])

    def frames(q_: Tensor) -> Tensor:
        return robot.fk(q_, check=False)[:, idx]

    # Robot caches its nominal joint origins on first use; filled inside a torch.func transform
    # the cache would hold a tensor of that transform's level and fail later, so fill it here
    # (both the small- and the large-batch FK paths).
    with torch.no_grad():
        for n in (1, 64):
            robot.fk(torch.zeros(n, q.shape[-1], dtype=q.dtype), check=False)

    g = torch.as_tensor(gravity, dtype=q.dtype)
    return euler_lagrange(_energy_features(frames, g), q, qd, qdd)
