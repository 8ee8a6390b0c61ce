"""Laser-beam geometry for tracker-free calibration (seed 003): beams from a flange laser, their
closest points and pair points, spots on a PSD surface, with analytic Jacobians.

Frames and units: a PSD pose is a rotation ``R (3, 3)`` whose columns are the surface axes ``u``,
``v`` and the normal, and its centre ``c (3,)`` (m), both in the robot base frame; a beam is a
point ``p (3,)`` (m, the laser origin) and a unit direction ``w (3,)``. Joint values are rad.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import torch
from torch import Tensor

from torchcal.kinematics.transforms import so3_exp, so3_left_jacobian

__all__ = ["Laser", "beam_pair_point", "closest_points", "laser_beam_jacobian", "laser_beams", "pair_midpoint",
           "pair_midpoint_jacobian", "plane_intersection", "psd_frame", "spot_jacobian"]


# ------------------------------------------------------------------------------- geometry
def closest_points(p1: Tensor, w1: Tensor, p2: Tensor, w2: Tensor, *,
                   parallel_tol: float = 1e-12) -> tuple[Tensor, Tensor]:
    """Closest points of two lines ``p1 + s w1`` and ``p2 + t w2``, batched.

    Args:
        p1, p2: ``(..., 3)`` points on the lines (m); w1, w2: ``(..., 3)`` directions (any
            non-zero length).
        parallel_tol: lines whose ``sin²(angle)`` is at most this are parallel.
    Returns:
        ``x1, x2`` ``(..., 3)``: the feet of the common perpendicular (equal when the lines meet).
    Raises:
        ValueError: a pair is parallel (the common perpendicular is not unique), naming it.
    """
    s, t, sin2 = _feet(p1, w1, p2, w2)
    par = sin2 <= parallel_tol
    if bool(par.any()):
        first = torch.nonzero(par.reshape(-1))[0, 0]
        where = f" at index {tuple(int(i) for i in torch.nonzero(par)[0])}" if par.ndim else ""
        ang = math.degrees(math.asin(math.sqrt(max(float(sin2.reshape(-1)[first]), 0.0))))
        raise ValueError(f"beams{where} are parallel (angle {ang:.2g}°, {int(par.sum())} pair(s)): they have "
                         "no single intersection or common perpendicular; drop the pair or aim the beams "
                         "from different directions")
    return p1 + s[..., None] * w1, p2 + t[..., None] * w2


def _feet(p1: Tensor, w1: Tensor, p2: Tensor, w2: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Line parameters ``s, t`` of the common perpendicular's feet ``p1 + s w1``, ``p2 + t w2``
    (from the normal equations of ``min |p1 + s w1 − p2 − t w2|²``) and ``sin²`` of the angle."""
    d = p2 - p1
    a, b, c = (w1 * w1).sum(-1), (w1 * w2).sum(-1), (w2 * w2).sum(-1)
    e, f = (w1 * d).sum(-1), (w2 * d).sum(-1)
    den = a * c - b * b
    return (c * e - b * f) / den, (b * e - a * f) / den, den / (a * c)


def beam_pair_point(p1: Tensor, w1: Tensor, p2: Tensor, w2: Tensor, *,
                    parallel_tol: float = 1e-12) -> tuple[Tensor, Tensor]:
    """The seed's point of two beams: their intersection, or the midpoint of their common
    perpendicular when they are skew. Returns ``point (..., 3)`` (m) and ``gap (...)`` (m, the
    length of the common perpendicular; 0 when they meet). Raises for parallel beams."""
    x1, x2 = closest_points(p1, w1, p2, w2, parallel_tol=parallel_tol)
    return 0.5 * (x1 + x2), (x2 - x1).norm(dim=-1)


def pair_midpoint(pa: Tensor, wa: Tensor, pb: Tensor, wb: Tensor) -> Tensor:
    """Midpoint of the common perpendicular, batched, without the parallel check (pairs are
    screened when a block is built)."""
    s, t, _ = _feet(pa, wa, pb, wb)
    return 0.5 * (pa + s[..., None] * wa + pb + t[..., None] * wb)


def pair_midpoint_jacobian(pa: Tensor, wa: Tensor, pb: Tensor, wb: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Derivatives of :func:`pair_midpoint` w.r.t. ``pa, wa, pb, wb``: four ``(..., 3, 3)``.

    With ``M = ½(pa + s wa + pb + t wb)``: ``∂M/∂x = ½(coef I + wa ∇ₓsᵀ + wb ∇ₓtᵀ)`` (``coef`` 1 for
    the points, ``s`` or ``t`` for the directions); ``∇s, ∇t`` by the quotient rule on the
    closed form (written out rather than autodiffed: no forward-AD start-up, no graph)."""
    d = pb - pa
    a, b, c = (wa * wa).sum(-1), (wa * wb).sum(-1), (wb * wb).sum(-1)
    e, f = (wa * d).sum(-1), (wb * d).sum(-1)
    den = a * c - b * b
    s, t = (c * e - b * f) / den, (b * e - a * f) / den
    z = torch.zeros_like(pa)
    # gradients of the scalars w.r.t. (pa, wa, pb, wb), stacked on axis -2: (..., 4, 3)
    ga = torch.stack([z, 2 * wa, z, z], -2)
    gb = torch.stack([z, wb, z, wa], -2)
    gc = torch.stack([z, z, z, 2 * wb], -2)
    ge = torch.stack([-wa, d, wa, z], -2)
    gf = torch.stack([-wb, z, wb, d], -2)
    x = lambda v: v[..., None, None]  # noqa: E731  scalar (...) against (..., 4, 3)
    gden = x(c) * ga + x(a) * gc - 2 * x(b) * gb
    gs = (x(e) * gc + x(c) * ge - x(f) * gb - x(b) * gf - x(s) * gden) / x(den)
    gt = (x(e) * gb + x(b) * ge - x(f) * ga - x(a) * gf - x(t) * gden) / x(den)
    outer = wa[..., None, :, None] * gs[..., :, None, :] + wb[..., None, :, None] * gt[..., :, None, :]
    eye = torch.eye(3, dtype=pa.dtype, device=pa.device)
    one = torch.ones_like(s)
    coef = torch.stack([one, s, one, t], -1)[..., None, None]  # (..., 4, 1, 1)
    G = 0.5 * (coef * eye + outer)  # (..., 4, 3, 3)
    return G[..., 0, :, :], G[..., 1, :, :], G[..., 2, :, :], G[..., 3, :, :]


def plane_intersection(p: Tensor, w: Tensor, c: Tensor, R: Tensor, *,
                       parallel_tol: float = 1e-12) -> tuple[Tensor, Tensor]:
    """Where beams meet a PSD surface, batched.

    Args:
        p, w: ``(..., 3)`` beam points (m) and directions.
        c: ``(..., 3)`` PSD centres (m); R: ``(..., 3, 3)`` PSD rotations (columns u, v, normal).
    Returns:
        ``s (..., 3)`` the spot in the base frame (m) and ``uv (..., 2)`` the spot in PSD
        coordinates (m).
    Raises:
        ValueError: a beam runs parallel to the surface.
    """
    n = R[..., :, 2]
    nw = (n * w).sum(-1)
    bad = nw.abs() <= parallel_tol * w.norm(dim=-1)
    if bool(bad.any()):
        raise ValueError(f"{int(bad.sum())} beam(s) run parallel to the PSD surface: no spot")
    lam = (n * (c - p)).sum(-1) / nw
    s = p + lam[..., None] * w
    uv = (R.transpose(-1, -2) @ (s - c)[..., None])[..., :2, 0]
    return s, uv


def spot_jacobian(p: Tensor, w: Tensor, rv: Tensor, c: Tensor, R0: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Derivatives of a spot ``(u, v) = Eᵀ(p + λw − c)`` on a PSD with rotation ``R = exp(rv) R0``
    (``E`` its first two columns, ``n`` the third, ``λ = n·(c − p)/(n·w)``) w.r.t. ``p, w, rv, c``:
    four ``(..., 2, 3)``.

    With the oblique projector ``Π = I − w nᵀ/(n·w)``: ``∂/∂p = EᵀΠ``, ``∂/∂w = λ EᵀΠ``,
    ``∂/∂c = −EᵀΠ``; a small rotation ``φ`` (``dR = [φ]× R``, ``φ = J_l(rv) drv``) gives rows
    ``(e_i × y)ᵀ − e_iᵀ w (n × y)ᵀ/(n·w)`` with ``y = s − c``."""
    R = so3_exp(rv) @ R0
    E, n = R[..., :, :2], R[..., :, 2]
    nw = (n * w).sum(-1)
    lam = (n * (c - p)).sum(-1) / nw
    y = p + lam[..., None] * w - c
    eye = torch.eye(3, dtype=p.dtype, device=p.device)
    Pi = eye - w[..., :, None] * n[..., None, :] / nw[..., None, None]
    EP = E.transpose(-1, -2) @ Pi
    ew = (E * w[..., :, None]).sum(-2)  # (..., 2): e_i · w
    ny = torch.linalg.cross(n, y)
    ey = torch.linalg.cross(E.transpose(-1, -2), y[..., None, :].expand(*y.shape[:-1], 2, 3))
    Gphi = ey - ew[..., :, None] * ny[..., None, :] / nw[..., None, None]
    return EP, lam[..., None, None] * EP, Gphi @ so3_left_jacobian(rv), -EP


def psd_frame(normal, spin: float = 0.0) -> Tensor:
    """A PSD rotation ``(3, 3)`` with the given outward ``normal`` as third column and its
    ``u`` axis turned by ``spin`` (rad) about the normal from the horizontal."""
    n = torch.as_tensor(normal, dtype=torch.float64)
    n = n / n.norm()
    ref = torch.tensor([0.0, 0.0, 1.0], dtype=n.dtype) if abs(float(n[2])) < 0.9 else \
        torch.tensor([1.0, 0.0, 0.0], dtype=n.dtype)
    u = torch.linalg.cross(ref, n)
    u = u / u.norm()
    v = torch.linalg.cross(n, u)
    cs, sn = math.cos(spin), math.sin(spin)
    return torch.stack([cs * u + sn * v, -sn * u + cs * v, n], 1)


# ------------------------------------------------------------------------------- the laser
@dataclass
class Laser:
    """A laser line fixed to a marker frame (known from a tool calibration).

    The default is the seed-003 script's mounting: 40 mm off the flange axis, 80 mm out, tilted
    25° about the flange x axis. Tilt and offset matter: a beam parallel to the flange axis cannot
    see the flange's offset along that axis (``joint_a6.dd`` of the KR5 moves it along itself).

    Attributes:
        origin: ``(3,)`` a point of the beam in the marker frame (m).
        direction: ``(3,)`` beam direction in the marker frame (normalised here).
        marker: the robot's marker carrying it (default the first).
    """

    origin: Sequence[float] | Tensor = (0.04, 0.0, 0.08)
    direction: Sequence[float] | Tensor = (0.0, math.sin(math.radians(25.0)), math.cos(math.radians(25.0)))
    marker: str | None = None

    def __post_init__(self):
        self.origin = torch.as_tensor(self.origin, dtype=torch.float64).reshape(3)
        d = torch.as_tensor(self.direction, dtype=torch.float64).reshape(3)
        if float(d.norm()) == 0:
            raise ValueError("the laser direction must be non-zero")
        self.direction = d / d.norm()

    def index(self, robot) -> int:
        if self.marker is None:
            return 0
        if self.marker not in robot.marker_names:
            raise ValueError(f"laser marker {self.marker!r} is not one of the robot's markers {robot.marker_names}")
        return robot.marker_names.index(self.marker)


def laser_beams(robot, laser: Laser, q: Tensor, params) -> tuple[Tensor, Tensor]:
    """Beam points and unit directions in the robot base frame.

    Args:
        q: ``(N, dof)`` rad; params: ``(K,)`` or a population ``(P, K)``.
    Returns:
        ``p, w``: ``(N, 3)`` or ``(P, N, 3)`` (m, unit).
    """
    R, t = robot.fk_rt(q, params, check=False)
    i = laser.index(robot)
    R, t = R[..., i, :, :], t[..., i, :]
    o, u = laser.origin.to(R), laser.direction.to(R)
    return t + R @ o, R @ u


def laser_beam_jacobian(robot, laser: Laser, q: Tensor, params: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Beams and their analytic derivatives w.r.t. all ``K`` parameters at one vector.

    Returns ``p, w (N, 3)`` and ``Jp, Jw (N, 3, K)``: with the marker's linear velocity ``v`` and
    angular velocity ``ω`` per parameter, ``dp = v + ω × (R o)`` and ``dw = ω × w``.
    """
    R, t = robot.fk_rt(q, params, check=False)
    i = laser.index(robot)
    R, t = R[:, i], t[:, i]
    ro = R @ laser.origin.to(R)
    w = R @ laser.direction.to(R)
    J = robot.param_jacobian(q, params, kind="pose", check=False)[:, i]  # (N, 6, K)
    v, om = J[:, :3], J[:, 3:]
    Jp = v + torch.linalg.cross(om, ro[..., None].expand_as(om), dim=1)
    Jw = torch.linalg.cross(om, w[..., None].expand_as(om), dim=1)
    return t + ro, w, Jp, Jw
