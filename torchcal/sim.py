"""Simulated measurements for any robot: geometric errors, an instrument frame far from the
base, instrument noise. The truth goes to a separate JSON file that the solver never reads.
"""
from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path

import torch
from torch import Tensor

from .io import Measurements, save_measurements
from .params import ParamSet

__all__ = ["SimConfig", "random_configs", "random_errors", "simulate", "write_dataset"]


@dataclass
class SimConfig:
    """What to simulate.

    Attributes:
        n: number of poses.
        length_error: std of length errors (m); ``angle_error``: std of angle errors (rad).
        noise: instrument noise, std per axis (m) (a laser tracker: ~10–20 µm).
        base_distance: distance of the instrument from the robot base (m); its rotation is
            random (any orientation).
        joint_margin: fraction of each joint range left out at both ends.
    """

    n: int = 100
    length_error: float = 0.5e-3
    angle_error: float = 1e-3
    noise: float = 0.02e-3
    base_distance: float = 3.0
    joint_margin: float = 0.1
    seed: int = 0


def random_configs(robot, n: int, generator: torch.Generator, margin: float = 0.1) -> Tensor:
    """``(n, dof)`` uniform joint values inside the limits (±π where a joint has none)."""
    lo, hi = (x.cpu() for x in robot.joint_limits)
    lo, hi = lo.clamp(min=-math.pi), hi.clamp(max=math.pi)
    span = hi - lo
    lo, hi = lo + margin * span, hi - margin * span
    u = torch.rand(n, robot.dof, generator=generator, dtype=torch.float64)
    return (lo + (hi - lo) * u).to(device=robot.device, dtype=robot.dtype)


def random_errors(robot, params: ParamSet, cfg: SimConfig, generator: torch.Generator) -> ParamSet:
    """A true parameter vector: Gaussian errors on every free non-base entry, and a base frame
    ``cfg.base_distance`` away at a random rotation."""
    p = params.clone()
    std = torch.tensor([cfg.length_error if u == "m" else cfg.angle_error for u in p.units], dtype=torch.float64)
    e = torch.randn(len(p), generator=generator, dtype=torch.float64) * std
    is_base = torch.tensor([n.startswith("base.") for n in p.names])
    v = torch.where(p.free.cpu() & ~is_base, e, torch.zeros_like(e)).to(p.values)
    p.values = p.values + v
    if cfg.base_distance > 0:
        d = torch.randn(3, generator=generator, dtype=torch.float64)
        d = d / d.norm() * cfg.base_distance
        axis = torch.randn(3, generator=generator, dtype=torch.float64)
        rv = axis / axis.norm() * (torch.rand(1, generator=generator, dtype=torch.float64) * 0.9 * math.pi)
        for n, val in zip(("base.x", "base.y", "base.z", "base.rx", "base.ry", "base.rz"), torch.cat([d, rv]).tolist()):
            p[n] = val
    return p


def simulate(robot, cfg: SimConfig | None = None, *, true_params: ParamSet | None = None,
             q: Tensor | None = None) -> tuple[Measurements, ParamSet]:
    """Measurements a laser tracker would give of ``robot`` with errors ``true_params``
    (random ones from ``cfg`` when omitted). Returns (measurements, truth). Only the
    measurements should ever reach a solver."""
    cfg = cfg or SimConfig()
    g = torch.Generator().manual_seed(cfg.seed)
    truth = true_params if true_params is not None else random_errors(robot, robot.params(), cfg, g)
    if q is None:
        q = random_configs(robot, cfg.n, g, cfg.joint_margin)
    p = robot.positions(q, truth.values)  # (N, M, 3)
    noise = torch.randn(p.shape, generator=g, dtype=torch.float64).to(p) * cfg.noise
    return Measurements(q.clone(), p + noise, list(robot.marker_names), list(robot.joint_names)), truth


def write_dataset(path_csv, data: Measurements, truth: ParamSet | None = None, truth_path=None,
                  meta: dict | None = None) -> None:
    """Write the measurements (CSV) and, separately, the truth (JSON) for later evaluation."""
    save_measurements(path_csv, data)
    if truth is not None:
        tp = Path(truth_path or Path(path_csv).with_suffix(".truth.json"))
        tp.write_text(json.dumps({"names": truth.names, "units": truth.units, "values": truth.values.tolist(),
                                  "meta": meta or {}}, indent=1) + "\n")


# ---------------------------------------------------------------------------- effects
EFFECT_DEFAULTS = {
    # joint deflection per N·m; a 2.5 kg tool 8 cm beyond the tool link origin that the URDF lacks
    "joint_compliance": {"compliance": 2e-5, "payload_kg": 2.5, "payload_com": (0.0, 0.0, 0.08)},
    "backlash": {"half_play": 3e-4},                       # rad, on every joint
    "cyclic_joint_error": {"amp1": 4e-4, "amp2": 2e-4},    # rad, first and second harmonic
    "joint_scale": {"scale": 3e-4},                        # relative gear-ratio error
    "thermal_drift": {"alpha": 1.2e-5, "dT": 30.0},        # 1/K (steel), K span of the run
}


def simulate_effects(robot, q: Tensor, names: list[str], generator: torch.Generator,
                     options: dict | None = None) -> tuple[Tensor, dict, dict, Tensor | None]:
    """Joint deflections and covariates of physical effects for commands ``q (N, dof)``.

    Written independently of the fitted effect classes where that is cheap (random phases,
    a motion sequence for directions), so that the loop is not shown its own model.

    Returns (Δq (N, dof), covariates, truth, row scale of robot-base positions or None).
    """
    from .effects.gravity import gravity_features
    from .urdf import read_inertials

    opts = {k: dict(v) for k, v in EFFECT_DEFAULTS.items()}
    for k, v in (options or {}).items():
        opts.setdefault(k, {}).update(v)
    N, dof = q.shape
    dq = torch.zeros_like(q)
    cov: dict[str, Tensor] = {}
    truth: dict = {}
    scale = None
    rev = torch.tensor([u == "rad" for u in robot.joint_units], device=q.device)
    for name in names:
        o = opts.get(name, {})
        if name == "joint_compliance":
            inert = read_inertials(robot._urdf_text) if robot._urdf_text else {}
            links = [l for l in inert if l in {jt.child for jt in robot.joints}]
            tool = robot.markers[0].link
            F = gravity_features(robot, q, links + [tool])  # (N, L+1, dof, 4)
            mm = [[inert[l]["mass"], *(inert[l]["mass"] * inert[l]["com"]).tolist()] for l in links]
            m = o["payload_kg"]
            mm.append([m, *(m * torch.tensor(o["payload_com"], dtype=torch.float64)).tolist()])
            tau = torch.einsum("nljf,lf->nj", F, torch.tensor(mm, dtype=q.dtype, device=q.device))
            c = o["compliance"] * (0.5 + torch.rand(dof, generator=generator, dtype=torch.float64)).to(q)
            dq = dq + c * tau * rev
            truth[name] = {"compliance_rad_per_Nm": c.tolist(), "payload_kg": m, "payload_com_m": list(o["payload_com"])}
        elif name == "backlash":
            # the poses are visited in the order given: each joint's direction of approach
            steps = torch.diff(q, dim=0, prepend=q[:1] - 1e-3 * torch.sign(torch.randn(1, dof, generator=generator,
                                                                                         dtype=torch.float64)).to(q))
            d = torch.where(steps >= 0, torch.ones_like(q), -torch.ones_like(q))
            b = o["half_play"] * (0.5 + torch.rand(dof, generator=generator, dtype=torch.float64)).to(q)
            dq = dq + b * d
            for j, n in enumerate(robot.joint_names):
                cov[f"dir.{n}"] = d[:, j]
            truth[name] = {"half_play_rad": b.tolist()}
        elif name == "cyclic_joint_error":
            ph = 2 * math.pi * torch.rand(2, dof, generator=generator, dtype=torch.float64).to(q)
            a1 = o["amp1"] * (0.5 + torch.rand(dof, generator=generator, dtype=torch.float64)).to(q)
            a2 = o["amp2"] * (0.5 + torch.rand(dof, generator=generator, dtype=torch.float64)).to(q)
            dq = dq + (a1 * torch.sin(q + ph[0]) + a2 * torch.sin(2 * q + ph[1])) * rev
            truth[name] = {"amp1_rad": a1.tolist(), "amp2_rad": a2.tolist(), "phase_rad": ph.tolist()}
        elif name == "joint_scale":
            s = o["scale"] * torch.randn(dof, generator=generator, dtype=torch.float64).to(q)
            dq = dq + s * q
            truth[name] = {"scale": s.tolist()}
        elif name == "thermal_drift":
            walk = torch.cumsum(torch.randn(N, generator=generator, dtype=torch.float64), 0).to(q)
            walk = (walk - walk.min()) / (walk.max() - walk.min() + 1e-12) * o["dT"]
            temp = 20.0 + walk
            cov["temperature"] = temp
            scale = 1 + o["alpha"] * (temp - temp.mean())
            truth[name] = {"alpha_per_K": o["alpha"], "t_ref_C": float(temp.mean())}
        else:
            raise ValueError(f"unknown effect {name!r}; simulate one of {sorted(EFFECT_DEFAULTS)}")
    return dq, cov, truth, scale


def simulate_with_effects(robot, cfg: SimConfig | None = None, effects: list[str] = (), *,
                          options: dict | None = None, true_params: ParamSet | None = None,
                          q: Tensor | None = None) -> tuple[Measurements, ParamSet, dict]:
    """Like :func:`simulate`, plus physical effects the geometric model lacks.

    Returns (measurements with covariates, geometric truth, effect truth)."""
    cfg = cfg or SimConfig()
    g = torch.Generator().manual_seed(cfg.seed)
    truth = true_params if true_params is not None else random_errors(robot, robot.params(), cfg, g)
    if q is None:
        q = random_configs(robot, cfg.n, g, cfg.joint_margin)
    dq, cov, etruth, scale = simulate_effects(robot, q, list(effects), g, options)
    geo = truth.values
    p = robot.positions(q + dq, geo, base=False)
    if scale is not None:
        p = p * scale[:, None, None]
    Rb, tb = robot.base_transform(geo)
    p = tb + (Rb @ p[..., None])[..., 0]
    noise = torch.randn(p.shape, generator=g, dtype=torch.float64).to(p) * cfg.noise
    data = Measurements(q.clone(), p + noise, list(robot.marker_names), list(robot.joint_names), covariates=cov)
    return data, truth, etruth
