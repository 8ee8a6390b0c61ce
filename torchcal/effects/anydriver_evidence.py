"""What a finding of :class:`~torchcal.effects.anydriver.ParameterDrivers` is drawn from (its
evidence plot, :mod:`torchcal.pipelines.loop.evidence`): a parameter's change per row against its
driver, or for a rigid thing per level (a marker point, the instrument frame) the markers'
displacement."""
from __future__ import annotations

from torch import Tensor

from torchcal.effects import anydriver_words as words
from torchcal.effects.base import Prepared

__all__ = ["signature", "parameter_change"]


def parameter_change(eff, theta: Tensor, prep: Prepared, label: str) -> tuple[str, Tensor]:
    """(parameter, ``(N,)`` its change per row) from the terms of mode ``label``."""
    idx = dict(eff.modes())[label]
    return eff.terms[idx[0]][0], prep.features["F"][:, idx] @ theta[idx]


def _rigid(eff, prep: Prepared, label: str, theta: Tensor) -> dict:
    """A marker point or the instrument frame per level: the markers' displacement ``(N, M, 3)`` m
    per row; its largest length over the markers is drawn, ``G`` its direction."""
    idx = dict(eff.modes())[label]
    pos = prep.features["pos"].tolist()
    F, G = prep.features["F"], prep.features["G"]
    disp = 0
    for i in idx:
        disp = disp + G[..., pos.index(i)] * (F[:, i] * theta[i])[:, None, None]
    size = disp.norm(dim=-1).amax(-1)
    d = eff.terms[idx[0]][1]
    return {"x": prep.features["X"][d], "xlabel": words.axis_label(eff.robot, d), "fitted": size,
            "ylabel": f"{label.split('~')[0]} offset [m]", "G": disp / size.clamp(min=1e-300)[:, None, None]}


def signature(eff, prep: Prepared, label: str, theta: Tensor) -> dict:
    """The evidence of mode ``label`` (:meth:`~torchcal.effects.base.Effect.signature`): ``x (N,)``
    the driver, ``fitted (N,)`` the parameter's change (or a rigid thing's displacement, m), and
    ``dof`` (a zero offset's joint) or ``G (N, M, 3)`` (displacement per unit of the change)."""
    if label.split("~")[0].endswith((".point", ".frame")):
        return _rigid(eff, prep, label, theta)
    p, change = parameter_change(eff, theta, prep, label)
    i = dict(eff.modes())[label][0]
    d = eff.terms[i][1]
    offs = eff._offset_params()
    sig = {"x": prep.features["X"][d], "xlabel": words.axis_label(eff.robot, d), "fitted": change,
           "ylabel": f"{p} [{dict(zip(eff.robot.param_names, eff.robot.param_units))[p]}]"}
    if p in offs:
        sig["dof"] = eff.robot.joint_names.index(offs[p])
    else:
        k = int((prep.features["pos"] == i).nonzero()[0, 0])
        sig["G"] = prep.features["G"][..., k]
    return sig
