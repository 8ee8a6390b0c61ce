"""The candidate parameters of a calibration: which of a robot's parameters a fit may identify,
before the data judge which of them it can.

One builder for every driver (a single calibration, the loop, a fleet): the ``free`` patterns
(default the ParamSet's own flags), the points of markers the data never see fixed (nothing can
see them), and, for position data, every marker's orientation fixed (a point has none). The
instrument frame (``base.*``) stays a candidate; registering it to the data is the driver's step
(:func:`geometric_start` does it for the loop).
"""
from __future__ import annotations

import torch

from torchcal.measure.registration import register_base, register_marker_rotations
from torchcal.measure.setup import Setup
from torchcal.params import ParamSet

__all__ = ["candidate_template", "geometric_start"]


def candidate_template(robot, marker_names, params: ParamSet | None = None, free=None,
                       kind: str = "position") -> ParamSet:
    """A copy of ``params`` (default ``robot.params()``) with the candidate parameters free.

    Args:
        robot: the model (its ``marker_names``, ``params()``).
        marker_names: the markers the data measure.
        free: glob pattern(s) of the parameters to identify (None: the ParamSet's free flags).
        kind: ``"position"`` (marker orientations fixed) or ``"pose"`` (left as they are).
    """
    p = (params if params is not None else robot.params()).clone()
    if free is not None:
        p.only(*([free] if isinstance(free, str) else list(free)))
    for m in robot.marker_names:
        if m not in marker_names:
            p.fix(f"{m}.*")
        if kind == "position":
            p.fix(f"{m}.droll", f"{m}.dpitch", f"{m}.dyaw")
    return p


def geometric_start(robot, data, patterns, setup: Setup | None = None, turns: bool = False) -> ParamSet:
    """The loop's start: :func:`candidate_template` (markers' points free, their orientations fixed)
    narrowed to the errors matching ``patterns`` (None: the robot's default free set; the data's
    marker points stay free), registered to the instrument (and, with ``turns``, the rotations of
    markers whose orientation was measured started from the mean measured one and freed); then the
    set-up's unknowns.

    Without three full positions there is nothing to register: with no position at all (planes,
    distances) the instrument frame is fixed at the robot base, since the planes and fixed points
    absorb where it stands; with partial positions only it starts there and is fitted."""
    p = candidate_template(robot, data.marker_names)
    if patterns is not None:
        keep = set(p.free_names)
        p.free[:] = False
        for pat in patterns:
            try:
                p.unfix(pat)
            except KeyError:
                pass
        for m in data.marker_names:
            p.unfix(f"{m}.dx", f"{m}.dy", f"{m}.dz")
        p.free &= torch.tensor([n in keep for n in p.names], device=p.free.device)
    if int(data.seen.sum()) >= 3:
        p = register_base(robot, data, p)
    elif not bool(data.observed.any()):
        p.fix("base.*")
    if turns and data.quaternions is not None and bool(torch.isfinite(data.quaternions).all(-1).any()):
        p = register_marker_rotations(robot, data, p)
    return p if setup is None else ParamSet.concat(p, setup.params())
