"""Simulated PSD data (seed 003): beams from a flange laser aimed at a PSD at several locations, with
encoder and PSD noise; the true joint values are kept apart from what the PSD reports."""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from torchcal.kinematics.ik import solve_ik
from torchcal.measure.laser import Laser, laser_beams, plane_intersection, psd_frame
from torchcal.measure.psd import PSDData
from torchcal.options import Options
from torchcal.sim.base import Simulated

__all__ = ["simulate_psd", "measure_psd", "PSDNoise", "AimOptions", "PSDSimulator"]


@dataclass(frozen=True)
class PSDNoise(Options):
    """What the recorded readings carry.

    Attributes:
        q_noise: encoder noise, std per joint (rad), added to the recorded joints.
        uv_noise: PSD noise, std per axis (m), added to the spots.
        psd_half: half the side of the PSD's active area (m); spots outside it are not recorded.
    """

    q_noise: float = 0.0
    uv_noise: float = 0.0
    psd_half: float = 10e-3


@dataclass(frozen=True)
class AimOptions(PSDNoise):
    """How :func:`simulate_psd` aims the laser, beyond :class:`PSDNoise`.

    Attributes:
        cone_deg: aims come from a random direction within this angle of the PSD normal (deg).
        standoff: ``(min, max)`` distance of the laser from the spot (m).
        spot_half: aims at a random point with ``|u|, |v| <=`` this (m; 0: the centre).
        roll_deg: random roll about the beam within ``±`` this (deg).
        q0: ``(dof,)`` start of the aiming IK (the arm branch); ik_tol: its tolerance (m, rad).
            The spots are computed from the joints IK found, so they are exact whatever the
            tolerance; it matters only for aims at the centre (``spot_half=0``).
    """

    cone_deg: float = 35.0
    standoff: tuple[float, float] = (0.25, 0.45)
    spot_half: float = 8e-3
    roll_deg: float = 90.0
    q0: Tensor | None = None
    ik_tol: float = 1e-13


def simulate_psd(robot, params, laser: Laser, psd_R: Tensor, psd_c: Tensor, k: int, *,
                 generator: torch.Generator, settings: AimOptions | None = None, **kw) -> tuple[PSDData, Tensor]:
    """What the PSD procedure would record on a robot with errors ``params``.

    Per location the robot aims its laser at a random point of the surface (``|u|, |v| <=
    spot_half``) from a random direction within ``cone_deg`` of the normal, ``standoff`` m away,
    at a random roll about the beam (``±roll_deg``); IK on the *true* model gives the joints (the
    operator jogs until the spot is on the PSD). Unreachable aims, and spots off the active area,
    are redrawn.

    Args:
        params: ``(K,)`` true errors. psd_R, psd_c: ``(m, 3, 3)``, ``(m, 3)`` true PSD poses.
        settings, kw: an :class:`AimOptions` and/or its fields as keywords (``q_noise`` rad,
            ``uv_noise`` m, ``cone_deg``, ``q0``, …).
    Returns:
        ``(data, q_true)``: :class:`PSDData` with ``k`` samples per location (location-major)
        and the true joints ``(m*k, dof)``.
    """
    o = AimOptions.build(settings, **kw)
    cone_deg, standoff, spot_half, roll_deg = o.cone_deg, o.standoff, o.spot_half, o.roll_deg
    q_noise, uv_noise, psd_half, q0, ik_tol = o.q_noise, o.uv_noise, o.psd_half, o.q0, o.ik_tol
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


def measure_psd(robot, params: Tensor, laser: Laser, q: Tensor, loc: Tensor, psd_R: Tensor, psd_c: Tensor, *,
                generator: torch.Generator, settings: PSDNoise | None = None, **kw) -> tuple[PSDData, Tensor]:
    """What the PSD records when the robot with errors ``params (K,)`` goes to commanded joints
    ``q (N, dof)`` (rad) aimed at locations ``loc (N,)`` with true poses ``psd_R``, ``psd_c``.

    The encoders read the joints with ``q_noise`` (rad std) error; the spots carry ``uv_noise``
    (m std). Aims whose spot misses the active area (``psd_half``, m) or hits it from behind are
    dropped. ``settings``, ``kw``: a :class:`PSDNoise` and/or its fields as keywords. Returns the
    data and the ``(N,)`` bool mask of the aims kept.
    """
    o = PSDNoise.build(settings, **kw)
    p, w = laser_beams(robot, laser, q, params)
    R, c = psd_R[loc], psd_c[loc]
    _, uv = plane_intersection(p, w, c, R)
    keep = (uv.abs() <= o.psd_half).all(-1) & ((w * R[..., 2]).sum(-1) < 0)
    dt = dict(dtype=q.dtype, device=q.device)
    qn = o.q_noise * torch.randn(q.shape, generator=generator, dtype=torch.float64).to(**dt)
    un = o.uv_noise * torch.randn(uv.shape, generator=generator, dtype=torch.float64).to(**dt)
    data = PSDData((q + qn)[keep], (uv + un)[keep], loc[keep], int(psd_R.shape[0]))
    return data, keep


class PSDSimulator:
    """Seed 003's set-up behind :class:`~torchcal.sim.base.Simulator`.

    Args:
        robot: the robot model; params: ``(K,)`` its true error values.
        laser: the flange laser; psd_R, psd_c: ``(m, 3, 3)``, ``(m, 3)`` true PSD poses (m).
        **options: fields of :class:`AimOptions` for :func:`simulate_psd` (aim cone, stand-off,
            noise ``q_noise`` rad and ``uv_noise`` m, ...).
    """

    def __init__(self, robot, params: Tensor, laser: Laser, psd_R: Tensor, psd_c: Tensor, **options):
        self.robot, self.params, self.laser, self.psd_R, self.psd_c = robot, params, laser, psd_R, psd_c
        self.options = options

    def simulate(self, n: int, *, seed: int = 0) -> Simulated:
        """``n`` samples at each PSD location. ``data`` is the :class:`PSDData` a PSD and the
        encoders give; ``truth`` holds the true errors, PSD poses and joint values."""
        g = torch.Generator(device=self.robot.device).manual_seed(int(seed))
        data, q_true = simulate_psd(self.robot, self.params, self.laser, self.psd_R, self.psd_c, n, generator=g,
                                    **self.options)
        return Simulated(data, {"params": self.params, "psd_R": self.psd_R, "psd_c": self.psd_c, "q_true": q_true})
