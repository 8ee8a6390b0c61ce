"""What partial observations (planes, distances, single axes) cannot see, with the reason in words:
the identifiability of the marker points through the observations, parameter by parameter."""
from __future__ import annotations

import torch
from torch import Tensor

from torchcal.measure.data import Measurements
from torchcal.measure.observations import KIND_NAMES, Observations
from torchcal.measure.setup import Setup, needs_setup
from torchcal.params import ParamSet
from torchcal.problems.identifiability import analyse_jacobian

__all__ = ["blind_reasons", "unseen"]


def blind_reasons(obs: Observations, names: list[str], J_marker: Tensor, J_obs: Tensor,
                  fraction: float = 0.02) -> dict[str, str]:
    """Words for parameters the observations barely see although they move the markers: for each
    of ``names``, its column of marker displacements ``J_marker (n, 3, k)`` (the observed markers,
    all three axes) against its column of the observation Jacobian ``J_obs (n, 3, k)``
    (:meth:`Observations.project`). A parameter gets a sentence when less than ``fraction`` of its
    displacement reaches a measured component."""
    kinds = [KIND_NAMES[int(k)] for k in torch.unique(obs.kind).tolist()]
    out = {}
    for j, n in enumerate(names):
        moved = float(J_marker[..., j].norm())
        seen = float(J_obs[..., j].norm())
        if moved > 0 and seen < fraction * moved:
            out[n] = (f"{n} moves the markers, but only in directions none of these measurements sees "
                      f"({', '.join(kinds)}; {100 * seen / moved:.2g} % of its displacement reaches a measured "
                      "component): a plane contact sees only the displacement along the plane's normal, a distance "
                      "only along the line between its two points, a partial position only its measured axes")
    return out


def unseen(robot, data: Measurements, params: ParamSet | None = None, setup: Setup | None = None) -> dict[str, str]:
    """The robot's geometric parameters (its default free set) that these observations cannot
    see, each with the reason in words, and ``"scale"`` when the robot's size is invisible.

    Args:
        params: where to judge (the robot's parameters, optionally followed by the set-up's
            unknowns); default: nominal.
        setup: the planes and fixed points (default: located from ``data`` at ``params``).
    """
    K = robot.n_params
    p = robot.params() if params is None else params
    geo = p.values[:K]
    if setup is None and needs_setup(data):
        setup = Setup.from_data(robot, data, geo)
    S = 0 if setup is None else setup.n_params
    s = p.values[K:K + S] if len(p) >= K + S and S and p.names[K:K + S] == setup.names else (
        setup.start if S else geo.new_zeros(0))
    default = set(robot.params().free_names)
    names = [n for n in robot.param_names if n in default and not n.endswith(("droll", "dpitch", "dyaw"))
             and not any(n.startswith(f"{m}.") for m in robot.marker_names if m not in data.marker_names)]
    out: dict[str, str] = {}
    if not bool(data.observed.any()):
        for n in [n for n in names if n.startswith("base.")]:
            out[n] = (f"{n}: no position is measured, and plane contacts and distances do not change when the robot "
                      "and every plane and fixed point move together, so nothing says where the robot stands; the "
                      "planes and fixed points are expressed in the robot's base frame")
        names = [n for n in names if n not in out]
    cand = [robot.param_names.index(n) for n in names]
    obs = Observations(robot, data, setup)
    J, pos = robot.param_jacobian(data.q, geo, kind="position", check=False, return_positions=True)
    Jm = J[..., cand]
    Jo = obs.project(pos, Jm, s if S else None)
    Js = obs.setup_jacobian(pos, s)
    units = [robot.param_units[i] for i in cand] + (list(setup.units) if S else [])
    rep = analyse_jacobian(torch.cat([Jo, Js], -1).reshape(3 * obs.n, -1), names + (setup.names if S else []),
                           units, markers=robot.marker_names)
    blind = blind_reasons(obs, names, Jm[obs.rows, obs.marker], Jo)
    for n in rep.dropped:
        out[n] = blind[n] + "; what does reach them, " + rep.reasons[n] if n in blind else rep.reasons[n]
    if setup is not None and setup.scale_gauge is not None:
        out["scale"] = ("the robot's size: a robot scaled about its base touches planes whose offsets scale with it "
                        "at the same commands, so plane contacts alone cannot tell how large the robot is; the fit "
                        "holds it at the nominal size. One known length (a distance between two points, a few "
                        "positions) makes it measurable")
    return out
