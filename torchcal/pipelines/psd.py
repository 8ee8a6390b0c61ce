"""Tracker-free calibration with a flange laser and a position-sensitive detector (seed 003, PMPSD).

A laser fixed to a marker frame (the flange) shines on a PSD placed at ``m`` locations; at each
location the robot takes ``k`` poses whose beams land anywhere on the PSD surface, and the PSD
reports the 2-D spot ``(u, v)`` (m) in its own surface frame. Nothing is measured in an
instrument frame: every quantity here lives in the robot base frame, and the PSD poses are
unknown.

Frames and units: a PSD pose is a rotation ``R (3, 3)`` whose columns are the surface axes
``u``, ``v`` and the normal, and its centre ``c (3,)`` (m), both in the robot base frame;
``(u, v) = (Rᵀ (s - c))[:2]`` for a spot ``s`` on the surface. A beam is a point ``p (3,)`` (m,
the laser origin) and a unit direction ``w (3,)``. Joint values are rad.

Two residual blocks, both batched over parameter populations ``(P, k) -> (P, rows)`` (m) with an
analytic Jacobian ``(rows, k)``:

* :class:`PointConstraint`, the seed's *multi-point virtual constraint*: at one location every
  pair of beams gives its intersection or, for skew beams, the midpoint of their common
  perpendicular; the residual is each such point minus the mean of the location's points (3
  rows per pair), so ``Σ rows² = Σ_pairs ‖point − mean‖²`` — the seed's "distance of the points to
  their mean", squared for least squares (a sum of plain distances is not differentiable at the
  solution). The mean moves with the parameters (the seed computes it once at zero errors,
  which leaves a non-zero residual at the true parameters). It needs beams that really meet:
  beams aimed at the PSD centre, or beams made to by :func:`modify_poses`.
* :class:`SpotResidual`: the measured spots used directly; each PSD pose (6 unknowns per
  location) is estimated together with the robot errors, rows = predicted minus measured
  ``(u, v)``.

The seed's *pose modification* (:func:`modify_poses`): with the PSD pose estimated under the
current model (:func:`fit_psd_poses`), rotate each beam about the laser origin so that it would
move its spot by ``-(u, v)`` onto the PSD centre, and replace the recorded joint values by the IK
solution of that virtual beam. Under the true model the virtual beams meet in the centre. Under
the nominal model they do not: the PSD orientation fitted with a model that is off by ~1 mm is
off by tens of mrad, which turns a spot offset of a few mm into ~0.1-1 mm of inconsistency.
:func:`calibrate_psd` repeats the step with the calibrated model (``rounds``); the truth is its
fixed point.

Expected spot errors (:func:`spot_covariance`): encoder noise reaches a spot through the arm and
the laser's lever, ``Σ = σ_q² G Gᵀ + σ_uv² I`` with ``G = ∂(u, v)/∂q``; at 10 µrad it is 10-16 µm
per beam, ten times a 1 µm PSD, and it sets the worst fresh-pose error. ``calibrate_psd(...,
noise=...)`` weights the spot residuals by it; :mod:`torchcal.pipelines.psd_design` chooses the PSD
placements and aims.

Observability (numbers in ``scripts/seed003_pmpsd.py``): a point constraint is blind to rigid
motions of the whole world (the first joint's Δθ and Δd of a DH robot) and to a uniform scale
of all lengths (scaled beams still meet) whenever the last DH row can absorb the scaled laser
offset, as it can for a beam parallel to the flange axis or tilted about flange x with the
offset along flange x. A known distance between two PSD centres (``distances=[(a, b, D)]``)
restores the scale. The direct-spot residual sees the scale weakly through the metric PSD
coordinates (a scale error ``ε`` moves a spot by ``ε ×`` its offset from the centre).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Sequence

import torch
from torch import Tensor

from torchcal.kinematics.ik import solve_ik
from torchcal.optim import LeastSquaresProblem, Result, get_solver
from torchcal.params import ParamSet
from torchcal.kinematics.transforms import so3_exp, so3_left_jacobian

__all__ = ["Laser", "PSDData", "closest_points", "beam_pair_point", "plane_intersection", "laser_beams",
           "laser_beam_jacobian", "psd_frame", "simulate_psd", "PointConstraint", "SpotResidual",
           "fit_psd_poses", "modify_poses", "analyse_block", "calibrate_psd", "PSDCalibration", "SEED_LM",
           "spot_sensitivity", "spot_covariance", "spot_whitening"]

#: The seed's LM settings for :func:`~torchcal.optim.get_solver` (Δs0 = 0 comes from the start
#: point): μ0 = 0.1 on an identity damping matrix, ν = 2, accept when the gain ratio ρ > 0, else
#: μ ← μν, ν ← 2ν. The seed's formula for shrinking μ did not survive in its text; torchcal's LM
#: uses Nielsen's μ·max(1/3, 1 − (2ρ − 1)³). Its stop test ‖Jᵀr‖ < ε is the scale-free version
#: (largest cosine between r and a column of J below ``gtol``), plus step and decrease tests.
SEED_LM = dict(mu0=0.1, scaling="identity", max_iter=300, gtol=1e-12, xtol=1e-14, ftol=1e-15)

# Distance rows compare with point residuals (m); this weight makes one known distance count
# like a well-measured coordinate without dominating the fit.
_DIST_W = 1.0


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


def _mid(pa: Tensor, wa: Tensor, pb: Tensor, wb: Tensor) -> Tensor:
    """Midpoint of the common perpendicular, batched, without the parallel check (pairs are
    screened when a block is built)."""
    s, t, _ = _feet(pa, wa, pb, wb)
    return 0.5 * (pa + s[..., None] * wa + pb + t[..., None] * wb)


def _mid_jac(pa: Tensor, wa: Tensor, pb: Tensor, wb: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Derivatives of :func:`_mid` w.r.t. ``pa, wa, pb, wb``: four ``(..., 3, 3)``.

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


def _spot_jac(p: Tensor, w: Tensor, rv: Tensor, c: Tensor, R0: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
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


# ------------------------------------------------------------------------------- data
@dataclass
class PSDData:
    """PSD measurements: recorded joints, spots and the location of each sample.

    Attributes:
        q: ``(N, dof)`` recorded joint values (rad).
        uv: ``(N, 2)`` measured spots on the PSD surface (m, PSD coordinates).
        loc: ``(N,)`` long, the PSD location (``0 .. n_locations-1``) of each sample.
        n_locations: ``m``.
    """

    q: Tensor
    uv: Tensor
    loc: Tensor
    n_locations: int

    def __post_init__(self):
        N = self.q.shape[0]
        if self.uv.shape != (N, 2) or self.loc.shape != (N,):
            raise ValueError(f"PSDData: q {tuple(self.q.shape)}, uv {tuple(self.uv.shape)} and loc "
                             f"{tuple(self.loc.shape)} must describe the same N samples: (N, dof), (N, 2), (N,)")
        self.loc = self.loc.long()
        if N and (int(self.loc.min()) < 0 or int(self.loc.max()) >= self.n_locations):
            raise ValueError(f"loc must lie in 0..{self.n_locations - 1}")

    def subset(self, locations: Sequence[int], k: int) -> "PSDData":
        """The first ``k`` samples of each of ``locations``, renumbered ``0 .. len-1``."""
        rows, new = [], []
        for j, L in enumerate(locations):
            idx = torch.nonzero(self.loc == L).flatten()[:k]
            if idx.numel() < k:
                raise ValueError(f"location {L} has {idx.numel()} samples, fewer than k = {k}")
            rows.append(idx)
            new.append(torch.full((k,), j, dtype=torch.long))
        i = torch.cat(rows)
        return PSDData(self.q[i], self.uv[i], torch.cat(new), len(locations))


def simulate_psd(robot, params, laser: Laser, psd_R: Tensor, psd_c: Tensor, k: int, *,
                 generator: torch.Generator, cone_deg: float = 35.0, standoff=(0.25, 0.45),
                 spot_half: float = 8e-3, roll_deg: float = 90.0, q_noise: float = 0.0,
                 uv_noise: float = 0.0, psd_half: float = 10e-3, q0: Tensor | None = None,
                 ik_tol: float = 1e-13) -> tuple[PSDData, Tensor]:
    """What the PSD procedure would record on a robot with errors ``params``.

    Per location the robot aims its laser at a random point of the surface (``|u|, |v| <=
    spot_half``) from a random direction within ``cone_deg`` of the normal, ``standoff`` m away,
    at a random roll about the beam (``±roll_deg``); IK on the *true* model gives the joints (the
    operator jogs until the spot is on the PSD). Unreachable aims are redrawn.

    Args:
        params: ``(K,)`` true errors. psd_R, psd_c: ``(m, 3, 3)``, ``(m, 3)`` true PSD poses.
        q_noise: encoder noise, std per joint (rad), added to the recorded joints.
        uv_noise: PSD noise, std per axis (m), added to the spots.
        psd_half: half the side of the PSD's active area (m); spots outside it are redrawn.
        q0: ``(dof,)`` start of the aiming IK (the arm branch); ik_tol: its tolerance (m, rad).
            The spots are computed from the joints IK found, so they are exact whatever the
            tolerance; it matters only for aims at the centre (``spot_half=0``).
    Returns:
        ``(data, q_true)``: :class:`PSDData` with ``k`` samples per location (location-major)
        and the true joints ``(m*k, dof)``.
    """
    dt = dict(dtype=robot.dtype, device=robot.device)
    params = torch.as_tensor(params, **dt)
    m = psd_R.shape[0]
    qs, uvs, locs = [], [], []
    cone = math.radians(cone_deg)
    u_l = laser.direction.to(**dt)
    R_u = psd_frame(u_l).to(**dt)  # a frame whose z is the laser direction (in the marker frame)
    for j in range(m):
        Rj, cj = psd_R[j].to(**dt), psd_c[j].to(**dt)
        got_q, got_uv = [], []
        for _ in range(50):
            need = k - sum(x.shape[0] for x in got_q)
            if need <= 0:
                break
            n = 2 * need + 8
            r = lambda *s: torch.rand(*s, generator=generator, dtype=torch.float64).to(**dt)  # noqa: E731
            uv = (2 * r(n, 2) - 1) * spot_half
            hit = cj + uv[:, :1] * Rj[:, 0] + uv[:, 1:] * Rj[:, 1]
            # direction from the spot back to the laser, uniform in the cone's cap
            cos_t = 1 - r(n) * (1 - math.cos(cone))
            phi = 2 * math.pi * r(n)
            sin_t = torch.sqrt(1 - cos_t ** 2)
            dloc = torch.stack([sin_t * torch.cos(phi), sin_t * torch.sin(phi), cos_t], -1)
            back = dloc @ Rj.T
            L = standoff[0] + (standoff[1] - standoff[0]) * r(n)
            p = hit + L[:, None] * back
            w = -back
            roll = math.radians(roll_deg) * (2 * r(n) - 1)
            Rw = torch.stack([psd_frame(wi, float(ri)) for wi, ri in zip(w, roll)]).to(**dt)
            Rf = Rw @ R_u.T  # marker rotation with Rf @ u_l = w
            tf = p - Rf @ laser.origin.to(**dt)
            T = torch.zeros(n, 4, 4, **dt)
            T[:, :3, :3], T[:, :3, 3], T[:, 3, 3] = Rf, tf, 1.0
            ik = solve_ik(robot, params, T, q0=q0, marker=robot.marker_names[laser.index(robot)],
                          tol_pos_m=ik_tol, tol_rot=ik_tol, restarts=3, seed=int(torch.randint(0, 2**31 - 1, (1,),
                                                                                              generator=generator)))
            ok = ik.converged
            if not bool(ok.any()):
                continue
            qt = ik.q[ok]
            pb, wb = laser_beams(robot, laser, qt, params)
            _, uv_t = plane_intersection(pb, wb, cj.expand_as(pb), Rj.expand(pb.shape[0], 3, 3))
            inside = (uv_t.abs() <= psd_half).all(-1) & ((wb @ Rj[:, 2]) < 0)
            got_q.append(qt[inside])
            got_uv.append(uv_t[inside])
        qj, uvj = torch.cat(got_q)[:k], torch.cat(got_uv)[:k]
        if qj.shape[0] < k:
            raise RuntimeError(f"PSD location {j}: only {qj.shape[0]} of {k} aims were reachable; move the PSD "
                               "or widen the cone/standoff")
        qs.append(qj)
        uvs.append(uvj)
        locs.append(torch.full((k,), j, dtype=torch.long, device=robot.device))
    q_true = torch.cat(qs)
    uv = torch.cat(uvs)
    q_rec = q_true + q_noise * torch.randn(q_true.shape, generator=generator, dtype=torch.float64).to(**dt)
    uv_meas = uv + uv_noise * torch.randn(uv.shape, generator=generator, dtype=torch.float64).to(**dt)
    return PSDData(q_rec, uv_meas, torch.cat(locs), m), q_true


# ------------------------------------------------------------------------------- expected spot errors
def spot_sensitivity(robot, laser: Laser, q: Tensor, loc: Tensor, psd_R: Tensor, psd_c: Tensor,
                     params: Tensor) -> Tensor:
    """``(N, 2, dof)``: derivative of each spot ``(u, v)`` (m) w.r.t. the joint values (rad), with
    the robot model at ``params (K,)`` and PSD poses ``psd_R (m, 3, 3)``, ``psd_c (m, 3)`` (m)."""
    R, _ = robot.fk_rt(q, params, check=False)
    i = laser.index(robot)
    p, w = laser_beams(robot, laser, q, params)
    Jq = robot.joint_jacobian(q, params, check=False)[:, i]  # (N, 6, dof)
    ro = R[:, i] @ laser.origin.to(R)
    v, om = Jq[:, :3], Jq[:, 3:]
    dp = v + torch.linalg.cross(om, ro[..., None].expand_as(om), dim=1)
    dw = torch.linalg.cross(om, w[..., None].expand_as(om), dim=1)
    zero = torch.zeros_like(p)
    Gp, Gw, _, _ = _spot_jac(p, w, zero, psd_c[loc], psd_R[loc])
    return Gp @ dp + Gw @ dw


def spot_covariance(robot, laser: Laser, q: Tensor, loc: Tensor, psd_R: Tensor, psd_c: Tensor, params: Tensor,
                    *, q_noise: float, uv_noise: float) -> Tensor:
    """``(N, 2, 2)`` expected covariance (m²) of each spot residual: encoder noise ``q_noise``
    (rad, std per joint, independent) carried through :func:`spot_sensitivity`, plus PSD noise
    ``uv_noise`` (m, std per axis)."""
    G = spot_sensitivity(robot, laser, q, loc, psd_R, psd_c, params)
    eye = torch.eye(2, dtype=G.dtype, device=G.device)
    return q_noise ** 2 * (G @ G.transpose(-1, -2)) + uv_noise ** 2 * eye


def spot_whitening(cov: Tensor) -> Tensor:
    """``(N, 2, 2)`` matrices ``W`` with ``W Σ Wᵀ = I`` (``W = L⁻¹`` for ``Σ = L Lᵀ``): a whitened
    residual ``W r`` has unit covariance, so least squares on it is generalised least squares."""
    L = torch.linalg.cholesky(cov)
    eye = torch.eye(2, dtype=cov.dtype, device=cov.device).expand_as(cov)
    return torch.linalg.solve_triangular(L, eye, upper=False)


# ------------------------------------------------------------------------------- residual blocks
class _Block:
    """Shared plumbing: robot parameters ``free`` (a ParamSet whose fixed entries keep their
    values) followed by the block's own unknowns; single-vector views for the solver."""

    def __init__(self, robot, laser: Laser, free: ParamSet):
        if free.names != robot.param_names:
            raise ValueError("free must be a ParamSet of this robot (robot.params())")
        self.robot, self.laser, self.free = robot, laser, free
        self.idx = free.free_index
        self.robot_names = free.free_names
        self.robot_units = [free.units[i] for i in self.idx.tolist()]

    def robot_params(self, X: Tensor) -> Tensor:
        """``(P, k)`` or ``(k,)`` block vectors -> full robot vectors ``(P, K)`` / ``(K,)``."""
        return self.free.expand(X[..., : self.idx.numel()])

    def problem(self, x0: Tensor | None = None) -> LeastSquaresProblem:
        """This block as an unbounded least-squares problem (start ``x0``, default :meth:`start`)."""
        x0 = self.start() if x0 is None else x0
        inf = torch.full_like(x0, math.inf)
        return LeastSquaresProblem(self.residuals, -inf, inf, x0=x0, jacobian_fn=self.jacobian, names=self.names)


class PointConstraint(_Block):
    """The seed's multi-point virtual constraint: all beams at one location meet in one point.

    Rows: for each pair of beams at a location (screened once, at ``params0``, to an angle of at
    least ``min_angle_deg``: near-parallel pairs put their point anywhere along the beams), the
    pair point (:func:`beam_pair_point`) minus the mean of the location's pair points, 3 rows (m);
    then, per known distance ``(a, b, D)``, ``weight · (‖mean_a − mean_b‖ − D)``.

    Args:
        robot, laser: the model; q: ``(N, dof)`` joint values (recorded or modified, rad);
        loc: ``(N,)`` location per row; free: which robot parameters are unknown.
        distances: known distances between location centres ``(a, b, D in m)``;
            distance_weight: their row weight (1: a metre of distance error counts like a metre
            of point residual).
        min_angle_deg: pairs closer to parallel are left out; params0: ``(K,)`` where the pair
            angles are judged (default ``free.values``).
    Attributes:
        names, units: of the unknowns (the free robot parameters).
        pairs: ``(n_pairs, 2)`` beam indices; n_rows: residual rows.
    """

    def __init__(self, robot, laser: Laser, q: Tensor, loc: Tensor, free: ParamSet, *,
                 distances: Sequence[tuple[int, int, float]] = (), distance_weight: float = _DIST_W,
                 min_angle_deg: float = 5.0, params0: Tensor | None = None):
        super().__init__(robot, laser, free)
        self.q, self.loc = q, loc.long()
        self.m = int(self.loc.max()) + 1
        p0 = free.values if params0 is None else params0
        _, w = laser_beams(robot, laser, q, p0)
        ia, ib = [], []
        cmin = math.cos(math.radians(min_angle_deg))
        for j in range(self.m):
            rows = torch.nonzero(self.loc == j).flatten()
            a, b = torch.triu_indices(rows.numel(), rows.numel(), 1, device=rows.device)
            a, b = rows[a], rows[b]
            keep = (w[a] * w[b]).sum(-1).abs() < cmin
            ia.append(a[keep]), ib.append(b[keep])
        self.ia, self.ib = torch.cat(ia), torch.cat(ib)
        self.pairs = torch.stack([self.ia, self.ib], 1)
        self.ploc = self.loc[self.ia]
        self.count = torch.bincount(self.ploc, minlength=self.m).to(q.dtype)
        if bool((self.count < 1).any()):
            raise ValueError(f"location(s) {torch.nonzero(self.count < 1).flatten().tolist()} have no pair of beams "
                             f"at {min_angle_deg}° or more apart; aim from more varied directions")
        self.distances = [(int(a), int(b), float(D)) for a, b, D in distances]
        for a, b, _ in self.distances:
            if not (0 <= a < self.m and 0 <= b < self.m and a != b):
                raise ValueError(f"a known distance needs two different locations in 0..{self.m - 1}, got ({a}, {b})")
        self.dw = float(distance_weight)
        self.names, self.units = list(self.robot_names), list(self.robot_units)
        self.n_rows = 3 * self.ia.numel() + len(self.distances)

    def start(self) -> Tensor:
        return self.free.values[self.idx].clone()

    def _means(self, M: Tensor) -> Tensor:
        """``(P, n_pairs, 3)`` -> per-location means ``(P, m, 3)``."""
        S = M.new_zeros(M.shape[0], self.m, 3).index_add_(1, self.ploc, M)
        return S / self.count[:, None]

    def points(self, X: Tensor) -> tuple[Tensor, Tensor]:
        """Pair points ``(P, n_pairs, 3)`` and location means ``(P, m, 3)`` (m)."""
        p, w = laser_beams(self.robot, self.laser, self.q, self.robot_params(X))
        M = _mid(p[:, self.ia], w[:, self.ia], p[:, self.ib], w[:, self.ib])
        return M, self._means(M)

    def residuals(self, X: Tensor) -> Tensor:
        """``(P, k) -> (P, n_rows)`` (m)."""
        M, C = self.points(X)
        r = [(M - C[:, self.ploc]).reshape(X.shape[0], -1)]
        for a, b, D in self.distances:
            r.append(self.dw * ((C[:, a] - C[:, b]).norm(dim=-1, keepdim=True) - D))
        return torch.cat(r, 1)

    def jacobian(self, x: Tensor) -> Tensor:
        """``(k,) -> (n_rows, k)``, analytic: beam derivatives from the robot's parameter
        Jacobian, chained with the closed-form pair-point derivatives."""
        th = self.robot_params(x)
        p, w, Jp, Jw = laser_beam_jacobian(self.robot, self.laser, self.q, th)
        Jp, Jw = Jp[..., self.idx], Jw[..., self.idx]
        ia, ib = self.ia, self.ib
        Ga, Gwa, Gb, Gwb = _mid_jac(p[ia], w[ia], p[ib], w[ib])  # (n_pairs, 3, 3) each
        dM = Ga @ Jp[ia] + Gwa @ Jw[ia] + Gb @ Jp[ib] + Gwb @ Jw[ib]  # (n_pairs, 3, k)
        k = dM.shape[-1]
        dC = dM.new_zeros(self.m, 3, k).index_add_(0, self.ploc, dM) / self.count[:, None, None]
        rows = [(dM - dC[self.ploc]).reshape(-1, k)]
        if self.distances:
            M = _mid(p[ia], w[ia], p[ib], w[ib])
            C = self._means(M[None])[0]
            for a, b, _ in self.distances:
                e = C[a] - C[b]
                rows.append(self.dw * (e / e.norm()) @ (dC[a] - dC[b]))
                rows[-1] = rows[-1][None]
        return torch.cat(rows, 0)


class SpotResidual(_Block):
    """Measured spots used directly: predicted minus measured ``(u, v)`` (m), with the PSD pose
    of every location among the unknowns.

    Unknowns: the free robot parameters, then per location ``psd{j}.rx/.ry/.rz`` (rad, a rotation
    vector applied on the left of the start rotation ``R0_j``: ``R_j = exp(r) R0_j``) and
    ``psd{j}.x/.y/.z`` (m, the centre). Per known distance ``(a, b, D)`` one more row
    ``weight · (‖c_a − c_b‖ − D)``.

    Args:
        robot, laser, data: the model and measurements; free: which robot parameters are unknown
            (none for a pure PSD-pose fit).
        R0, c0: ``(m, 3, 3)``, ``(m, 3)`` start PSD poses (:func:`fit_psd_poses`).
        whiten: optional ``(N, 2, 2)`` per-beam matrices ``W`` applied to each spot residual and
            its Jacobian rows (``W r``): beam weights, e.g. from the expected spot covariance
            (:func:`spot_whitening`); then the rows are unitless and a
            distance row should be weighted by one over its noise std (``distance_weight``).
    """

    def __init__(self, robot, laser: Laser, data: PSDData, free: ParamSet, R0: Tensor, c0: Tensor, *,
                 distances: Sequence[tuple[int, int, float]] = (), distance_weight: float = _DIST_W,
                 whiten: Tensor | None = None):
        super().__init__(robot, laser, free)
        if whiten is not None and whiten.shape != (data.q.shape[0], 2, 2):
            raise ValueError(f"whiten must have shape ({data.q.shape[0]}, 2, 2), got {tuple(whiten.shape)}")
        self.whiten = whiten
        self.data, self.m = data, data.n_locations
        self.R0, self.c0 = R0.to(data.q), c0.to(data.q)
        self.kr = self.idx.numel()
        self.names = list(self.robot_names) + [f"psd{j}.{s}" for j in range(self.m)
                                               for s in ("rx", "ry", "rz", "x", "y", "z")]
        self.units = list(self.robot_units) + ["rad", "rad", "rad", "m", "m", "m"] * self.m
        self.distances = [(int(a), int(b), float(D)) for a, b, D in distances]
        self.dw = float(distance_weight)
        self.n_rows = 2 * data.q.shape[0] + len(self.distances)

    def start(self) -> Tensor:
        z = torch.zeros(self.m, 6, dtype=self.data.q.dtype, device=self.data.q.device)
        z[:, 3:] = self.c0
        return torch.cat([self.free.values[self.idx], z.reshape(-1)])

    def psd_poses(self, x: Tensor) -> tuple[Tensor, Tensor]:
        """PSD rotations ``(m, 3, 3)`` and centres ``(m, 3)`` (m) of a block vector ``(k,)``."""
        e = x[self.kr:].reshape(self.m, 6)
        return so3_exp(e[:, :3]) @ self.R0, e[:, 3:]

    def residuals(self, X: Tensor) -> Tensor:
        """``(P, k) -> (P, n_rows)`` (m)."""
        P = X.shape[0]
        p, w = laser_beams(self.robot, self.laser, self.data.q, self.robot_params(X))  # (P, N, 3)
        e = X[:, self.kr:].reshape(P, self.m, 6)
        R = so3_exp(e[..., :3]) @ self.R0  # (P, m, 3, 3)
        c = e[..., 3:]
        L = self.data.loc
        _, uv = plane_intersection(p, w, c[:, L], R[:, L])
        d = uv - self.data.uv
        if self.whiten is not None:
            d = (self.whiten @ d[..., None])[..., 0]
        r = [d.reshape(P, -1)]
        for a, b, D in self.distances:
            r.append(self.dw * ((c[:, a] - c[:, b]).norm(dim=-1, keepdim=True) - D))
        return torch.cat(r, 1)

    def jacobian(self, x: Tensor) -> Tensor:
        """``(k,) -> (n_rows, k)``, analytic through the robot's parameter Jacobian and the
        closed-form spot."""
        N, L = self.data.q.shape[0], self.data.loc
        th = self.robot_params(x)
        e = x[self.kr:].reshape(self.m, 6)
        if self.kr:
            p, w, Jp, Jw = laser_beam_jacobian(self.robot, self.laser, self.data.q, th)
        else:
            p, w = laser_beams(self.robot, self.laser, self.data.q, th)
        Gp, Gw, Gr, Gc = _spot_jac(p, w, e[L, :3], e[L, 3:], self.R0[L])  # (N, 2, 3) each
        J = x.new_zeros(N, 2, x.numel())
        if self.kr:
            J[..., : self.kr] = Gp @ Jp[..., self.idx] + Gw @ Jw[..., self.idx]
        cols = self.kr + 6 * L[:, None] + torch.arange(6, device=x.device)  # (N, 6)
        J.scatter_(2, cols[:, None, :].expand(N, 2, 6), torch.cat([Gr, Gc], -1))
        if self.whiten is not None:
            J = self.whiten @ J
        rows = [J.reshape(2 * N, -1)]
        for a, b, _ in self.distances:
            d = x.new_zeros(1, x.numel())
            u = e[a, 3:] - e[b, 3:]
            u = u / u.norm()
            d[0, self.kr + 6 * a + 3: self.kr + 6 * a + 6] = self.dw * u
            d[0, self.kr + 6 * b + 3: self.kr + 6 * b + 6] = -self.dw * u
            rows.append(d)
        return torch.cat(rows, 0)


def analyse_block(block: "PointConstraint | SpotResidual", x: Tensor | None = None, *, rtol: float = 1e-9,
                  prefer=None):
    """Which unknowns of a residual block the data identify (:func:`~torchcal.problems.identifiability.analyse_jacobian`
    on the block's Jacobian at ``x``, default its start).

    Evaluate it on noise-free *design* data (simulated with the nominal model): on inconsistent
    data a point constraint seems to see the scale, because shrinking the robot shrinks every
    residual (``r → s·r``). PSD poses are kept first (they absorb the rigid-motion gauge).
    """
    from torchcal.problems.identifiability import analyse_jacobian

    x = block.start() if x is None else x
    pref = ([["psd*"]] if isinstance(block, SpotResidual) else []) + list(prefer or [])
    return analyse_jacobian(block.jacobian(x), block.names, block.units, rtol=rtol, prefer=pref or None)


# ------------------------------------------------------------------------------- PSD poses and pose modification
def _initial_psd_poses(p: Tensor, w: Tensor, uv: Tensor, loc: Tensor, m: int) -> tuple[Tensor, Tensor]:
    """Linear start: ``c + u r1 + v r2 − λ_i w_i = p_i`` for ``c, r1, r2`` and the ``λ_i``, then the
    nearest rotation with ``r1, r2`` as its first columns."""
    Rs, cs = [], []
    for j in range(m):
        i = torch.nonzero(loc == j).flatten()
        n = i.numel()
        if n < 5:
            raise ValueError(f"PSD location {j} has {n} samples; a PSD pose needs at least 5")
        A = p.new_zeros(3 * n, 9 + n)
        eye = torch.eye(3, dtype=p.dtype, device=p.device)
        for s in range(n):
            A[3 * s: 3 * s + 3, 0:3] = eye
            A[3 * s: 3 * s + 3, 3:6] = uv[i[s], 0] * eye
            A[3 * s: 3 * s + 3, 6:9] = uv[i[s], 1] * eye
            A[3 * s: 3 * s + 3, 9 + s] = -w[i[s]]
        sol = torch.linalg.lstsq(A, p[i].reshape(-1, 1)).solution[:, 0]
        c, B = sol[:3], torch.stack([sol[3:6], sol[6:9]], 1)
        U, _, Vh = torch.linalg.svd(B, full_matrices=False)
        Q = U @ Vh  # nearest matrix with orthonormal columns
        r3 = torch.linalg.cross(Q[:, 0], Q[:, 1])
        Rs.append(torch.stack([Q[:, 0], Q[:, 1], r3], 1))
        cs.append(c)
    return torch.stack(Rs), torch.stack(cs)


def fit_psd_poses(robot, laser: Laser, data: PSDData, params, *, R0: Tensor | None = None,
                  c0: Tensor | None = None) -> tuple[Tensor, Tensor, Tensor]:
    """PSD poses that best explain the spots with the robot model held at ``params``.

    A linear start (unless ``R0``, ``c0`` are given) refined by LM on :class:`SpotResidual` with
    no free robot parameter. Returns rotations ``(m, 3, 3)``, centres ``(m, 3)`` (m) and the RMS
    spot residual per location ``(m,)`` (m) — model errors show up there.
    """
    params = torch.as_tensor(params.values if isinstance(params, ParamSet) else params,
                             dtype=robot.dtype, device=robot.device)
    if R0 is None or c0 is None:
        p, w = laser_beams(robot, laser, data.q, params)
        R0, c0 = _initial_psd_poses(p, w, data.uv, data.loc, data.n_locations)
    none = robot.params(params)
    none.free[:] = False
    blk = SpotResidual(robot, laser, data, none, R0, c0)
    res = get_solver("lm", max_iter=100, gtol=1e-13, xtol=1e-15, ftol=1e-16).minimize(blk.problem())
    R, c = blk.psd_poses(res.x)
    r = blk.residuals(res.x[None])[0].reshape(-1, 2)
    ss = torch.zeros(data.n_locations, dtype=r.dtype, device=r.device).index_add_(0, data.loc, (r * r).sum(-1))
    rms = torch.sqrt(ss / torch.bincount(data.loc, minlength=data.n_locations).to(r.dtype))
    return R, c, rms


def modify_poses(robot, laser: Laser, data: PSDData, params, psd_R: Tensor, psd_c: Tensor, *,
                 tol: float = 1e-12) -> tuple[Tensor, dict]:
    """The seed's pose modification: joint values of virtual beams through the PSD centres.

    For each sample, with the model at ``params``: the beam ``(p, w)`` meets the estimated PSD
    surface at ``s``; the spot reading says the centre lies at ``h = s − R_j [u, v, 0]``. The
    laser frame is turned about ``p`` by the smallest rotation taking ``w`` to ``(h − p)/|h − p|``
    and IK (started at the recorded joints, so the nearest solution) gives the joints ``q′``.

    Returns ``q′ (N, dof)`` (rad) and ``info`` with ``angle`` ``(N,)`` (rad, the beam corrections),
    ``ik_converged`` ``(N,)`` bool and ``ik_pos_err`` ``(N,)`` (m).
    """
    params = torch.as_tensor(params.values if isinstance(params, ParamSet) else params,
                             dtype=robot.dtype, device=robot.device)
    L = data.loc
    R, t = robot.fk_rt(data.q, params, check=False)
    i = laser.index(robot)
    R, t = R[:, i], t[:, i]
    p, w = laser_beams(robot, laser, data.q, params)
    s, _ = plane_intersection(p, w, psd_c[L], psd_R[L])
    h = s - (psd_R[L][..., :2] @ data.uv[..., None])[..., 0]
    w2 = (h - p) / (h - p).norm(dim=-1, keepdim=True)
    ax = torch.linalg.cross(w, w2)
    ang = torch.atan2(ax.norm(dim=-1), (w * w2).sum(-1))
    n_ax = ax.norm(dim=-1, keepdim=True)
    rv = torch.where(n_ax > 0, ax / n_ax.clamp(min=1e-300), 0.0) * ang[:, None]  # no turn: no axis
    Q = so3_exp(rv)
    T = torch.zeros(p.shape[0], 4, 4, dtype=p.dtype, device=p.device)
    T[:, :3, :3] = Q @ R
    T[:, :3, 3] = p + (Q @ (t - p)[..., None])[..., 0]
    T[:, 3, 3] = 1.0
    ik = solve_ik(robot, params, T, q0=data.q, marker=robot.marker_names[i], tol_pos_m=tol, tol_rot=tol,
                  restarts=0, limits=False)
    return ik.q, {"angle": ang, "ik_converged": ik.converged, "ik_pos_err": ik.pos_err}


# ------------------------------------------------------------------------------- calibration
@dataclass
class PSDCalibration:
    """Outcome of :func:`calibrate_psd`.

    Attributes:
        params: ``(K,)`` identified robot errors (fixed entries as given).
        psd_R, psd_c: ``(m, 3, 3)``, ``(m, 3)`` PSD poses (m): estimated with the errors
            (``"spots"``), used by the last pose modification (``"pm"``), or fitted to the final
            model (``"raw"``).
        method: ``"pm"``, ``"raw"`` or ``"spots"``.
        results: the LM :class:`~torchcal.optim.Result` of every round.
        q_used: joints the last point constraint used (modified ones for ``"pm"``).
        rounds: per round ``{"params", "rms_m"}`` (``rms_m``: RMS residual row at the end, m),
            for the point constraint ``"max_change"`` (largest parameter change of the round);
            ``"psd_rms_m"`` (spot residual per location of the PSD-pose fit at the round's start
            model) for ``"pm"`` and ``"spots"``; for the point constraint also ``"n_pairs"``, and for
            ``"pm"`` ``"correction_max_rad"`` (largest beam correction) and ``"ik_all_converged"``.
    """

    params: Tensor
    psd_R: Tensor
    psd_c: Tensor
    method: str
    results: list[Result] = field(default_factory=list)
    q_used: Tensor | None = None
    rounds: list[dict] = field(default_factory=list)


def calibrate_psd(robot, laser: Laser, data: PSDData, free: ParamSet, *, method: str = "pm",
                  rounds: int = 1, round_tol: float = 0.0, distances: Sequence[tuple[int, int, float]] = (),
                  distance_weight: float = _DIST_W, min_angle_deg: float = 5.0,
                  lm: dict | None = None, noise: tuple[float, float, float] | None = None) -> PSDCalibration:
    """Identify robot errors from PSD data.

    Args:
        free: ``robot.params()`` with the unknowns free and everything else at its known value
            (start point = its values, Δs0 = 0 for zeros). Free only identifiable parameters: a
            point constraint cannot fix the gauge (see the module docstring).
        method: ``"pm"`` the seed: PSD poses from the spots (model at the current estimate),
            pose modification, then LM on the point constraint, ``rounds`` times; ``"raw"`` the
            point constraint on the recorded beams (right only when they hit the centre);
            ``"spots"`` LM on :class:`SpotResidual` (robot errors and PSD poses together).
        rounds: pose-modification rounds at most (``"pm"``); round_tol: stop earlier once no
            free parameter moved by more than this in a round (m or rad; 0 runs all rounds).
        distances: known distances between PSD centres ``(a, b, D in m)``.
        lm: LM options on top of :data:`SEED_LM` (the seed's μ0 = 0.1, ν = 2, identity damping).
        noise: ``(q_noise rad, uv_noise m, distance_noise m)`` stds; with ``"spots"``, weight each
            beam by its expected spot covariance (encoder noise through the arm, at the start
            model and PSD poses, plus PSD noise; :func:`spot_covariance`) and each known
            distance by one over its std: generalised least squares.
    """
    if method not in ("pm", "raw", "spots"):
        raise ValueError(f"method must be 'pm', 'raw' or 'spots', got {method!r}")
    if noise is not None and (method != "spots" or (distances and not noise[2] > 0)):
        raise ValueError("noise weights the spot residuals: it needs method='spots', and a positive distance "
                         "noise std when distances are given")
    cur = free.clone()
    out = PSDCalibration(params=cur.values.clone(), psd_R=torch.empty(0), psd_c=torch.empty(0), method=method)
    if method == "spots":
        R0, c0, rms0 = fit_psd_poses(robot, laser, data, cur.values)
        W = None
        if noise is not None:
            cov = spot_covariance(robot, laser, data.q, data.loc, R0, c0, cur.values, q_noise=noise[0],
                                  uv_noise=noise[1])
            W, distance_weight = spot_whitening(cov), 1.0 / noise[2]
        blk = SpotResidual(robot, laser, data, cur, R0, c0, distances=distances, distance_weight=distance_weight,
                           whiten=W)
        res = get_solver("lm", **{**SEED_LM, **(lm or {})}).minimize(blk.problem())
        out.params = blk.robot_params(res.x)
        out.psd_R, out.psd_c = blk.psd_poses(res.x)
        out.results.append(res)
        out.rounds.append({"params": out.params.detach().clone(), "psd_rms_m": rms0.tolist(),
                           "rms_m": float(torch.sqrt((res.extra["residuals"] ** 2).mean()))})
        return out
    opts = {**SEED_LM, **(lm or {})}
    n_rounds = 1 if method == "raw" else int(rounds)
    for _ in range(n_rounds):
        info: dict = {}
        q = data.q
        if method == "pm":
            R, c, rms = fit_psd_poses(robot, laser, data, cur.values)
            q, mi = modify_poses(robot, laser, data, cur.values, R, c)
            out.psd_R, out.psd_c = R, c
            info = {"psd_rms_m": rms.tolist(), "correction_max_rad": float(mi["angle"].max()),
                    "ik_all_converged": bool(mi["ik_converged"].all())}
        blk = PointConstraint(robot, laser, q, data.loc, cur, distances=distances, distance_weight=distance_weight,
                              min_angle_deg=min_angle_deg)
        res = get_solver("lm", **opts).minimize(blk.problem())
        step = float((blk.robot_params(res.x).detach() - cur.values).abs().max())
        cur.values = blk.robot_params(res.x).detach()
        info["rms_m"] = float(torch.sqrt((res.extra["residuals"] ** 2).mean()))
        info["n_pairs"] = int(blk.ia.numel())
        info["params"] = cur.values.clone()
        info["max_change"] = step
        out.results.append(res)
        out.rounds.append(info)
        out.q_used = q
        if step <= round_tol:
            break
    out.params = cur.values.clone()
    if method == "raw":
        out.psd_R, out.psd_c, _ = fit_psd_poses(robot, laser, data, cur.values)
    return out
