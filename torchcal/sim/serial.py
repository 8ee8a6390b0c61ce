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

from torchcal.kinematics.bounds import config_bounds
from torchcal.measure.data import Measurements
from torchcal.measure.io import save_measurements
from torchcal.outputs import atomic_write_text
from torchcal.params import ParamSet
from torchcal.sim.base import Simulated, expected_noise_norm
from torchcal.sim.effect_truth import apply_effects, directions_of, draw_effects

__all__ = ["SimConfig", "random_configs", "random_errors", "simulate", "write_dataset",
           "simulate_fleet", "SimulatedRobot", "simulated_robot", "hide_axes"]


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
    """``(n, dof)`` uniform joint values inside :func:`~torchcal.kinematics.bounds.config_bounds`."""
    lo, hi = config_bounds(robot, margin)
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
        atomic_write_text(tp, json.dumps({"names": truth.names, "units": truth.units, "values": truth.values.tolist(),
                                          "meta": meta or {}}, indent=1) + "\n")


def simulate_fleet(robot, n_robots: int, cfg: SimConfig | None = None, *, spread: float = 1.0, n_test: int = 0,
                   moved: dict | None = None) -> tuple[list[Measurements], list[Measurements] | None, list[ParamSet]]:
    """``n_robots`` robots of one model, as a factory makes them: every robot's geometric errors are
    a fleet-wide mean (drawn from ``cfg``'s error sizes) plus its own deviation (``spread`` times
    those sizes); each has its own instrument placement, ``cfg.n`` random poses and noise.

    Args:
        spread: per-robot deviation relative to the mean's size (1: as large as the mean).
        n_test: held-out poses per robot (noisy, like real ones), or 0.
        moved: ``{robot index: {parameter: added value}}``, e.g. a re-mastered axis
            ``{3: {"joint_a3.offset": 8e-3}}`` (rad).
    Returns:
        (training measurements, held-out measurements or None, true parameters) per robot. Seeded
        by ``cfg.seed``; only the measurements should reach a solver.
    """
    cfg = cfg or SimConfig()
    g = torch.Generator().manual_seed(cfg.seed)
    still = SimConfig(**{**cfg.__dict__, "base_distance": 0.0})
    mean = random_errors(robot, robot.params(), still, g).values
    own = SimConfig(**{**cfg.__dict__, "length_error": spread * cfg.length_error,
                       "angle_error": spread * cfg.angle_error})
    train, test, truths = [], [] if n_test else None, []
    for r in range(n_robots):
        gr = torch.Generator().manual_seed(cfg.seed * 1_000_003 + r + 1)
        truth = random_errors(robot, robot.params(), own, gr)
        truth.values = truth.values + mean
        for name, dv in (moved or {}).get(r, {}).items():
            truth[name] = truth[name] + dv
        for n, q in ((cfg.n, train), (n_test, test)):
            if n:
                d, _ = simulate(robot, SimConfig(**{**cfg.__dict__, "n": n, "seed": int(torch.randint(
                    0, 2 ** 31 - 1, (1,), generator=gr))}), true_params=truth)
                q.append(d)
        truths.append(truth)
    return train, test, truths


class SimulatedRobot:
    """A "real" robot for simulation: geometric errors, physical effects and an instrument.

    Only :meth:`measure` output should reach a solver; :meth:`reach` (noise-free) is for scoring
    what commands actually do, e.g. after correction."""

    def __init__(self, robot, truth: ParamSet, effects: dict, noise: float, generator: torch.Generator):
        self.robot, self.truth, self.effects, self.noise, self.g = robot, truth, effects, noise, generator

    def reach(self, q: Tensor, *, directions: Tensor | None = None, temperature: Tensor | None = None) -> Tensor:
        """``(N, M, 3)`` where the markers really go for commands ``q`` (m, instrument frame)."""
        if directions is None and "backlash" in self.effects:
            directions = directions_of(q)
        if temperature is None and "thermal_drift" in self.effects:
            temperature = torch.full((q.shape[0],), self.effects["thermal_drift"]["t_ref_C"], dtype=q.dtype)
        dq, scale = apply_effects(self.robot, q, self.effects, directions=directions, temperature=temperature)
        geo = self.truth.values
        p = self.robot.positions(q + dq, geo, base=False)
        if scale is not None:
            p = p * scale[:, None, None]
        Rb, tb = self.robot.base_transform(geo)
        return tb + (Rb @ p[..., None])[..., 0]

    def measure(self, q: Tensor) -> Measurements:
        """Measure poses visited in the order given: covariates for the effects present."""
        cov: dict[str, Tensor] = {}
        d = temp = None
        if "backlash" in self.effects:
            d = directions_of(q, self.g)
            cov.update({f"dir.{n}": d[:, j] for j, n in enumerate(self.robot.joint_names)})
        if "thermal_drift" in self.effects:
            t = self.effects["thermal_drift"]
            walk = torch.cumsum(torch.randn(q.shape[0], generator=self.g, dtype=torch.float64), 0).to(q)
            walk = (walk - walk.min()) / (walk.max() - walk.min() + 1e-12) * t["span_K"]
            temp = 20.0 + walk
            cov["temperature"] = temp
        p = self.reach(q, directions=d, temperature=temp)
        p = p + torch.randn(p.shape, generator=self.g, dtype=torch.float64).to(p) * self.noise
        return Measurements(q.clone(), p, list(self.robot.marker_names), list(self.robot.joint_names), covariates=cov)


    def simulate(self, n: int, *, seed: int = 0, margin: float = 0.1) -> Simulated:
        """The :class:`~torchcal.sim.base.Simulator` interface: ``n`` poses drawn inside the joint
        limits (``margin`` of each range kept clear) and measured. ``seed`` seeds this data set
        alone (poses, noise, covariates); the robot's errors stay what they are. ``noise_floor``: the
        expected Euclidean norm of the isotropic per-axis noise (m)."""
        g = torch.Generator(device=self.robot.device).manual_seed(int(seed))
        saved, self.g = self.g, g
        try:
            data = self.measure(random_configs(self.robot, n, g, margin))
        finally:
            self.g = saved
        return Simulated(data, {"params": self.truth, "effects": self.effects, "noise_m": self.noise},
                         noise_floor=expected_noise_norm(self.noise))


    # ------------------------------------------------------------------ partial measurements
    def _marker(self, marker: str | None) -> int:
        name = marker or self.robot.marker_names[0]
        if name not in self.robot.marker_names:
            raise ValueError(f"unknown marker {name!r}; the robot has {self.robot.marker_names}")
        if "backlash" in self.effects or "thermal_drift" in self.effects:
            raise ValueError("contacts and distances are simulated for geometry and configuration effects only "
                             "(backlash and thermal drift depend on the visiting order and time)")
        return self.robot.marker_names.index(name)

    def touch(self, planes: dict, n: int, *, marker: str | None = None, margin: float = 0.1) -> Measurements:
        """Probe contacts: ``n`` poses per plane at which ``marker`` touches it. ``planes``: label ->
        ``(unit normal (3,), offset d)`` with the plane ``nᵀp = d`` (instrument frame, m). Random
        commands are moved onto each plane through the real robot (Newton steps along the
        gradient of the signed distance); each contact triggers at a signed distance drawn from
        the instrument noise. Only commands and plane labels are returned."""
        m = self._marker(marker)
        lo, hi = (x.to(self.robot.dtype) for x in config_bounds(self.robot, 0.0))
        qs, idx = [], []
        for k, (label, (nrm, d)) in enumerate(planes.items()):
            nrm = torch.as_tensor(nrm, dtype=self.robot.dtype)
            nrm = nrm / nrm.norm()
            got = torch.zeros(0, self.robot.dof, dtype=self.robot.dtype)
            for _ in range(20):
                if got.shape[0] >= n:
                    break
                q = random_configs(self.robot, 4 * n, self.g, margin)
                eps = torch.randn(q.shape[0], generator=self.g, dtype=torch.float64).to(q) * self.noise
                f = None
                for _ in range(40):
                    f = self.reach(q)[:, m] @ nrm - float(d) - eps
                    grad = self._gradient(q, m, nrm)
                    step = f[:, None] * grad / (grad * grad).sum(-1, keepdim=True).clamp(min=1e-12)
                    step = step * (0.3 / step.norm(dim=-1, keepdim=True).clamp(min=0.3))
                    q = q - step
                f = self.reach(q)[:, m] @ nrm - float(d) - eps
                ok = (f.abs() < 1e-11) & ((q >= lo) & (q <= hi)).all(-1)
                got = torch.cat([got, q[ok]])
            if got.shape[0] < n:
                raise ValueError(f"plane {label!r}: only {got.shape[0]} of {n} contacts reachable within the joint "
                                 "limits; move the plane into the robot's workspace")
            qs.append(got[:n])
            idx.append(torch.full((n,), k, dtype=torch.long))
        q = torch.cat(qs)
        N = q.shape[0]
        return Measurements(q, torch.full((N, 1, 3), float("nan"), dtype=q.dtype), [self.robot.marker_names[m]],
                            list(self.robot.joint_names), planes=torch.cat(idx)[:, None], plane_names=list(planes))

    def _gradient(self, q: Tensor, m: int, nrm: Tensor, h: float = 1e-6) -> Tensor:
        dof = q.shape[1]
        E = torch.eye(dof, dtype=q.dtype) * h
        qq = torch.cat([q[:, None] + E, q[:, None] - E], 1).reshape(-1, dof)
        f = (self.reach(qq)[:, m] @ nrm).reshape(q.shape[0], 2, dof)
        return (f[:, 0] - f[:, 1]) / (2 * h)

    def measure_distances(self, point, name: str, q: Tensor, *, marker: str | None = None) -> Measurements:
        """Distances from ``marker`` to a fixed point (the pivot of a ball bar, m, instrument frame)
        at commands ``q``, with the instrument noise; the point's position is not returned."""
        m = self._marker(marker)
        c = torch.as_tensor(point, dtype=q.dtype)
        d = (self.reach(q)[:, m] - c).norm(dim=-1)
        d = d + torch.randn(d.shape, generator=self.g, dtype=torch.float64).to(d) * self.noise
        mk = self.robot.marker_names[m]
        return Measurements(q.clone(), torch.full((q.shape[0], 1, 3), float("nan"), dtype=q.dtype), [mk],
                            list(self.robot.joint_names), distances={(mk, name): d})


def hide_axes(data: Measurements, fraction: float, generator: torch.Generator) -> Measurements:
    """A copy of ``data`` in which a ``fraction`` of the observations lose one or two of their
    axes at random (a motion-capture marker seen by too few cameras, a dial gauge per axis)."""
    pos = data.positions.clone()
    N, M, _ = pos.shape
    hit = torch.rand(N, M, generator=generator, dtype=torch.float64) < fraction
    keep = torch.randint(0, 6, (N, M), generator=generator)  # one of 6 non-empty proper axis subsets
    subsets = torch.tensor([[1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 0], [1, 0, 1], [0, 1, 1]], dtype=torch.bool)
    drop = hit[..., None] & ~subsets[keep]
    pos[drop.to(pos.device)] = float("nan")
    return Measurements(data.q.clone(), pos, list(data.marker_names), list(data.joint_names), data.quaternions,
                        dict(data.covariates), data.source, data.planes, list(data.plane_names), dict(data.distances))


def simulated_robot(robot, cfg: SimConfig | None = None, effects: list[str] = (), *, options: dict | None = None,
                    true_params: ParamSet | None = None) -> SimulatedRobot:
    """Draw a "real" robot: geometric errors from ``cfg`` (or ``true_params``) and effects."""
    cfg = cfg or SimConfig()
    g = torch.Generator().manual_seed(cfg.seed)
    truth = true_params if true_params is not None else random_errors(robot, robot.params(), cfg, g)
    return SimulatedRobot(robot, truth, draw_effects(robot, list(effects), g, options), cfg.noise, g)


def simulate_with_effects(robot, cfg: SimConfig | None = None, effects: list[str] = (), *,
                          options: dict | None = None, true_params: ParamSet | None = None,
                          q: Tensor | None = None) -> tuple[Measurements, ParamSet, dict]:
    """Like :func:`simulate`, plus physical effects the geometric model lacks.

    Returns (measurements with covariates, geometric truth, effect truth)."""
    cfg = cfg or SimConfig()
    sim = simulated_robot(robot, cfg, effects, options=options, true_params=true_params)
    if q is None:
        q = random_configs(robot, cfg.n, sim.g, cfg.joint_margin)
    return sim.measure(q), sim.truth, sim.effects
