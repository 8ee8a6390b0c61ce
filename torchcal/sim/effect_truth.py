"""The hidden truth of the physical effects a simulated robot has: their true sizes, drawn, and
the joint deflections and position scale they cause.

Written independently of the fitted effect classes (:mod:`torchcal.effects`) where that is cheap
(random phases, true masses plus a payload), so that the loop is not shown its own model: each
effect the simulator can make has its own truth functions here, in tables keyed by the effect's
registered name; a name the tables lack is refused, saying whether torchcal fits it at all.
"""
from __future__ import annotations

import math

import torch
from torch import Tensor

from torchcal.effects.gravity import gravity_features
from torchcal.effects.registry import EFFECTS
from torchcal.kinematics.urdf import read_inertials

__all__ = ["EFFECT_DEFAULTS", "draw_effects", "apply_effects", "directions_of"]

EFFECT_DEFAULTS = {
    # joint deflection per N·m; a 2.5 kg tool 8 cm beyond the tool link origin that the URDF lacks
    "joint_compliance": {"compliance": 2e-5, "payload_kg": 2.5, "payload_com": (0.0, 0.0, 0.08)},
    "backlash": {"half_play": 3e-4},                       # rad, on every joint
    "cyclic_joint_error": {"amp1": 4e-4, "amp2": 2e-4},    # rad, first and second harmonic
    "joint_scale": {"scale": 3e-4},                        # relative gear-ratio error
    "thermal_drift": {"alpha": 1.2e-5, "dT": 30.0},        # 1/K (steel), K span of the run
}


def _uniform(generator: torch.Generator, *shape: int) -> Tensor:
    return torch.rand(*shape, generator=generator, dtype=torch.float64)


def _draw_compliance(robot, o: dict, g: torch.Generator) -> dict:
    inert = read_inertials(robot.urdf_text) if robot.urdf_text else {}
    links = [l for l in inert if l in {jt.child for jt in robot.joints}]
    m = o["payload_kg"]
    mm = [[inert[l]["mass"], *(inert[l]["mass"] * inert[l]["com"]).tolist()] for l in links]
    mm.append([m, *(m * torch.tensor(o["payload_com"], dtype=torch.float64)).tolist()])
    return {"compliance_rad_per_Nm": (o["compliance"] * (0.5 + _uniform(g, robot.dof))).tolist(),
            "payload_kg": m, "payload_com_m": list(o["payload_com"]),
            "links": links + [robot.markers[0].link], "mass_moments": mm}


def _draw_cyclic(robot, o: dict, g: torch.Generator) -> dict:
    dof = robot.dof
    return {"phase_rad": (2 * math.pi * _uniform(g, 2, dof)).tolist(),
            "amp1_rad": (o["amp1"] * (0.5 + _uniform(g, dof))).tolist(),
            "amp2_rad": (o["amp2"] * (0.5 + _uniform(g, dof))).tolist()}


_DRAW = {
    "joint_compliance": _draw_compliance,
    "backlash": lambda robot, o, g: {"half_play_rad": (o["half_play"] * (0.5 + _uniform(g, robot.dof))).tolist()},
    "cyclic_joint_error": _draw_cyclic,
    "joint_scale": lambda robot, o, g: {
        "scale": (o["scale"] * torch.randn(robot.dof, generator=g, dtype=torch.float64)).tolist()},
    "thermal_drift": lambda robot, o, g: {"alpha_per_K": o["alpha"], "span_K": o["dT"], "t_ref_C": 20.0 + o["dT"] / 2},
}


def _simulated(name: str) -> None:
    """Refuse an effect the simulator has no truth for, saying whether torchcal can fit it at all."""
    if name in _DRAW:
        return
    if name in EFFECTS:
        what = f"the simulator cannot make effect {name!r} (torchcal fits it, but the simulator has no truth of its own)"
    else:
        what = f"unknown effect {name!r}"
    raise ValueError(f"{what}; simulate one of {sorted(EFFECT_DEFAULTS)}")


def draw_effects(robot, names: list[str], generator: torch.Generator, options: dict | None = None) -> dict:
    """Draw the true size of each named physical effect (the hidden truth of a simulated robot)."""
    opts = {k: dict(v) for k, v in EFFECT_DEFAULTS.items()}
    for k, v in (options or {}).items():
        opts.setdefault(k, {}).update(v)
    truth: dict = {}
    for name in names:
        _simulated(name)
        truth[name] = _DRAW[name](robot, opts.get(name, {}), generator)
    return truth


def _compliance_dq(robot, q: Tensor, t: dict, state: dict) -> Tensor:
    T = lambda v: torch.as_tensor(v, dtype=q.dtype, device=q.device)  # noqa: E731
    F = gravity_features(robot, q, t["links"])  # (N, L, dof, 4)
    tau = torch.einsum("nljf,lf->nj", F, T(t["mass_moments"]))
    return T(t["compliance_rad_per_Nm"]) * tau * state["revolute"]


def _cyclic_dq(robot, q: Tensor, t: dict, state: dict) -> Tensor:
    T = lambda v: torch.as_tensor(v, dtype=q.dtype, device=q.device)  # noqa: E731
    ph = T(t["phase_rad"])
    return (T(t["amp1_rad"]) * torch.sin(q + ph[0]) + T(t["amp2_rad"]) * torch.sin(2 * q + ph[1])) * state["revolute"]


# name -> Δq (N, dof) of the commands q, given the truth and the state (directions, temperature)
_JOINT_DELTA = {
    "joint_compliance": _compliance_dq,
    "backlash": lambda robot, q, t, state: torch.as_tensor(t["half_play_rad"], dtype=q.dtype, device=q.device)
    * state["directions"],
    "cyclic_joint_error": _cyclic_dq,
    "joint_scale": lambda robot, q, t, state: torch.as_tensor(t["scale"], dtype=q.dtype, device=q.device) * q,
}
# name -> (N,) scale of robot-base positions
_POSITION_SCALE = {
    "thermal_drift": lambda t, state: 1 + t["alpha_per_K"] * (state["temperature"] - t["t_ref_C"]),
}


def apply_effects(robot, q: Tensor, truth: dict, *, directions: Tensor | None = None,
                  temperature: Tensor | None = None) -> tuple[Tensor, Tensor | None]:
    """Joint deflections ``Δq (N, dof)`` and the row scale of robot-base positions (thermal, or
    None) of the effects in ``truth`` at commands ``q``. ``directions (N, dof)`` (+1/-1) and
    ``temperature (N,)`` °C are the states backlash and thermal drift need."""
    dq = torch.zeros_like(q)
    scale = None
    state = {"directions": directions, "temperature": temperature,
             "revolute": torch.tensor([u == "rad" for u in robot.joint_units], device=q.device)}
    for name, t in truth.items():
        _simulated(name)
        if name in _JOINT_DELTA:
            dq = dq + _JOINT_DELTA[name](robot, q, t, state)
        else:
            scale = _POSITION_SCALE[name](t, state)
    return dq, scale


def directions_of(q: Tensor, generator: torch.Generator | None = None) -> Tensor:
    """Direction (+1/-1) from which each joint reaches each pose when the poses are visited in
    order; the first pose's direction is drawn (or +1)."""
    first = (torch.sign(torch.randn(1, q.shape[1], generator=generator, dtype=torch.float64)).to(q)
             if generator is not None else torch.ones(1, q.shape[1], dtype=q.dtype, device=q.device))
    steps = torch.diff(q, dim=0, prepend=q[:1] - 1e-3 * first)
    return torch.where(steps >= 0, torch.ones_like(q), -torch.ones_like(q))
