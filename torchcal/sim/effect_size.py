"""How large a simulated effect is at the markers, measured with the independent simulator alone:
the displacement it causes on given poses (the same robot with and without it), in total and
beyond what a geometric calibration could absorb to first order (the least-squares residual of
that displacement against finite-difference derivatives of the simulator's own geometric
errors: joint origins, zero offsets, marker points and the instrument frame)."""
from __future__ import annotations

import copy

import numpy as np

from torchcal.sim.physsim import PhysicalRobot
from torchcal.sim.physsim_urdf import homogeneous, rotation_exp

__all__ = ["EFFECT_KEYS", "displacement_um", "geometric_jacobian"]

#: PhysicalRobot arguments that each switch on one non-geometric effect
EFFECT_KEYS = ("torsion", "lateral", "base_tilt", "thermal", "backlash", "cyclic", "joint_terms")


def _moved(real: PhysicalRobot, k: int, h: float) -> PhysicalRobot:
    """A copy of ``real`` with geometric parameter ``k`` moved by ``h`` (m or rad), parameters
    in the order of :func:`geometric_jacobian`."""
    r = copy.copy(real)
    r._origin, r._offset, r._marker_true = dict(real._origin), dict(real._offset), list(real._marker_true)
    names = [j.name for j in real._order]
    if k < 6 * len(names):
        n, i = names[k // 6], k % 6
        d = np.zeros(6)
        d[i] = h
        r._origin[n] = real._origin[n] @ homogeneous(rotation_exp(d[3:]), d[:3])
        return r
    k -= 6 * len(names)
    if k < len(real.joint_names):
        r._offset[real.joint_names[k]] = real._offset[real.joint_names[k]] + h
        return r
    k -= len(real.joint_names)
    if k < 3 * len(real.markers):
        r._marker_true[k // 3] = real._marker_true[k // 3] + h * np.eye(3)[k % 3]
        return r
    d = np.zeros(6)
    d[k - 3 * len(real.markers)] = h
    r.instrument_in_base = real.instrument_in_base @ homogeneous(rotation_exp(d[3:]), d[:3])
    return r


def geometric_jacobian(real: PhysicalRobot, q: np.ndarray, h: float = 1e-6, **state) -> np.ndarray:
    """``(N·M·3, P)``: central differences of :meth:`PhysicalRobot.reach` (m) at ``q (N, dof)``
    with respect to every geometric error the simulator draws (6 per joint origin, a zero
    offset per commanded joint, 3 per marker point, 6 for the instrument frame); ``state``:
    ``temperature``, ``directions``, ``covariates`` as for ``reach``."""
    P = 6 * len(real._order) + len(real.joint_names) + 3 * len(real.markers) + 6
    cols = [(_moved(real, k, h).reach(q, **state) - _moved(real, k, -h).reach(q, **state)).ravel() / (2 * h)
            for k in range(P)]
    return np.stack(cols, 1)


def displacement_um(with_effect: PhysicalRobot, without: PhysicalRobot, q: np.ndarray, state: dict,
                    q_fit: np.ndarray, state_fit: dict) -> dict:
    """The effect's displacement of the markers at ``q (N, dof)`` (the held-out poses):
    ``{"rms_um": RMS of the per-point displacement norm, "mean_um": its mean,
    "beyond_geometry_rms_um": RMS of what is left of it at ``q`` after the geometric errors of
    ``without`` were fitted to it, least squares to first order, at ``q_fit`` (the training
    poses)}``, µm.  ``state``/``state_fit``: ``temperature``, ``directions``, ``covariates`` of
    each set, as for ``reach``."""
    effect = lambda qq, st: (with_effect.reach(qq, **st) - without.reach(qq, **st)).ravel()  # noqa: E731
    d = effect(q, state)
    x = np.linalg.lstsq(geometric_jacobian(without, q_fit, **state_fit), effect(q_fit, state_fit), rcond=1e-10)[0]
    rest = d - geometric_jacobian(without, q, **state) @ x
    norm = lambda v: np.linalg.norm(v.reshape(-1, 3), axis=1)  # noqa: E731
    return {"rms_um": float(np.sqrt(np.mean(norm(d) ** 2)) * 1e6), "mean_um": float(norm(d).mean() * 1e6),
            "beyond_geometry_rms_um": float(np.sqrt(np.mean(norm(rest) ** 2)) * 1e6)}
