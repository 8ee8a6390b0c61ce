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
