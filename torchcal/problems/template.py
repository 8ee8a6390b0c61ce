"""The candidate parameters of a calibration: which of a robot's parameters a fit may identify,
before the data judge which of them it can.

One builder for every driver (a single calibration, the loop, a fleet): the ``free`` patterns
(default the ParamSet's own flags), the points of markers the data never see fixed (nothing can
see them), and, for position data, every marker's orientation fixed (a point has none). The
instrument frame (``base.*``) stays a candidate; registering it to the data is the driver's step.
"""
from __future__ import annotations

from torchcal.params import ParamSet

__all__ = ["candidate_template"]


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
