"""The per-observation errors of a model on measured data (:class:`ErrorDetails`): what a
stage's statistics summarise and its figures plot."""
from __future__ import annotations

import torch
from torch import Tensor

from torchcal.measure.records import ErrorDetails

__all__ = ["error_details"]


def error_details(robot, params: Tensor, data, errors_xyz: Tensor | None = None, obs=None) -> ErrorDetails:
    """Per observation of ``data``: the error vector ``xyz (n, 3)`` (model − measured, m,
    instrument frame; computed from ``params (K,)`` unless given; NaN in axes not measured), its
    norm ``e (n,)``, the marker's distance from the robot base ``dist (n,)`` (m), and where it
    came from: ``row (n,)`` (0-based row of ``data``), ``marker (n,)`` (index into
    ``robot.marker_names``), ``dims (n,)`` (how many components it measured).

    With ``obs`` (:class:`~torchcal.measure.observations.Observations`, ``errors_xyz`` its residual
    vectors) every observation counts in ``e`` and ``dist`` (a plane contact's error is its signed
    distance), and ``xyz`` holds the position observations only."""
    mk = [robot.marker_names.index(m) for m in data.marker_names]
    base_free = robot.positions(data.q, params, check=False, base=False)[:, mk]
    robot_marker = torch.tensor(mk, device=base_free.device)
    if obs is not None:
        pos = obs.kind == 0
        xyz = errors_xyz[pos].masked_fill(~obs.mask[pos], float("nan"))
        return ErrorDetails(e=errors_xyz.norm(dim=-1), xyz=xyz, dist=base_free[obs.rows, obs.data_marker].norm(dim=-1),
                            row=obs.rows, marker=robot_marker[obs.data_marker], dims=obs.dims)
    seen = data.observed
    if errors_xyz is None:
        p = robot.positions(data.q, params, check=False)[:, mk][seen]
        errors_xyz = p - data.positions[seen]
    rows, cols = torch.nonzero(seen, as_tuple=True)
    return ErrorDetails(e=torch.nan_to_num(errors_xyz).norm(dim=-1), xyz=errors_xyz, dist=base_free[seen].norm(dim=-1),
                        row=rows, marker=robot_marker[cols], dims=torch.isfinite(errors_xyz).sum(-1))
