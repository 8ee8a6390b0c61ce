"""Parameters that change with a driver, for the independent simulator (numpy only; no torchcal
effect code): a joint zero re-mastered mid-session, an instrument frame that settles with time, a
linear guide whose carriage pitches and wanders along its travel, a tool point that depends on
which tool is mounted, a joint whose stiffness changes with the load.

A :class:`Drift` adds ``fn(driver values)`` to one target:

* ``offset:<joint>``: the joint's true value (rad, m), ``fn -> (N,)``;
* ``carriage:<joint>``: a small motion of the joint's child frame after the joint moves (a guide's
  straightness and pitch), ``fn -> (N, 6)`` (dx, dy, dz m, then a rotation vector rad, in that frame);
* ``instrument``: a small motion of the instrument frame, ``fn -> (N, 6)`` (as above, base frame);
* ``marker:<name>``: the marker's point in its link frame, ``fn -> (N, 3)`` m.

Drivers: ``q:<joint>`` (the command), ``torque:<joint>`` (gravity torque of the rigid robot,
N·m), ``row`` (the row's index in the measuring order), ``cov:<column>`` and ``level:<column>``
(the level's name per row, ``fn`` gets an array of strings).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

__all__ = ["Drift", "driver_array", "apply_carriage", "instrument_motion"]


@dataclass(frozen=True)
class Drift:
    """``fn(driver) `` added to ``target`` (module docstring); ``words`` says it for a report."""

    target: str
    driver: str
    fn: Callable
    words: str = ""

    def as_dict(self) -> dict:
        return {"target": self.target, "driver": self.driver, "words": self.words}


def driver_array(d: Drift, cmd: dict, cov: dict, rows: np.ndarray, torque: dict | None) -> np.ndarray:
    """``(N,)`` the drift's driver per row."""
    kind, _, name = d.driver.partition(":")
    if kind == "q":
        return cmd[name]
    if kind == "torque":
        if torque is None:
            raise ValueError(f"drift {d.target}: a torque driver needs the wrenches")
        return torque[name]
    if kind == "row":
        return rows.astype(float)
    if kind == "level":
        return np.asarray(cov[f"level:{name}"])
    return np.asarray(cov[name], dtype=float)


def _rotation(v: np.ndarray) -> np.ndarray:
    """``(N, 3, 3)`` rotations of rotation vectors ``v (N, 3)`` (Rodrigues)."""
    th = np.linalg.norm(v, axis=-1)[:, None, None]
    k = v / np.where(th[..., 0] > 0, th[..., 0], 1.0)
    K = np.zeros((len(v), 3, 3))
    K[:, 0, 1], K[:, 0, 2], K[:, 1, 2] = -k[:, 2], k[:, 1], -k[:, 0]
    K = K - K.transpose(0, 2, 1)
    return np.eye(3) + np.sin(th) * K + (1 - np.cos(th)) * K @ K


def _motion(v: np.ndarray) -> np.ndarray:
    T = np.repeat(np.eye(4)[None], len(v), 0)
    T[:, :3, :3] = _rotation(v[:, 3:])
    T[:, :3, 3] = v[:, :3]
    return T


def apply_carriage(A: np.ndarray, v: np.ndarray) -> np.ndarray:
    """A child frame ``A (N, 4, 4)`` moved by ``v (N, 6)`` in its own axes."""
    return A @ _motion(v)


def instrument_motion(v: np.ndarray) -> np.ndarray:
    """``(N, 4, 4)`` the instrument frame's motion ``v (N, 6)`` (base frame, applied on the left)."""
    return _motion(v)


def evaluate_drifts(drifts: list[Drift], cmd: dict, cov: dict, rows: np.ndarray, torque: dict | None,
                    n: int) -> dict:
    """Every drift's value per row, summed by target: ``{"offset": {joint: (N,)}, "carriage":
    {joint: (N, 6)}, "instrument": (N, 6) or None, "marker": {name: (N, 3)}}``."""
    out: dict = {"offset": {}, "carriage": {}, "instrument": None, "marker": {}}
    for d in drifts:
        v = np.asarray(d.fn(driver_array(d, cmd, cov, rows, torque)), dtype=float)
        kind, _, name = d.target.partition(":")
        if kind == "instrument":
            out["instrument"] = v.reshape(n, 6) + (0 if out["instrument"] is None else out["instrument"])
        elif kind in ("offset", "carriage", "marker"):
            shape = {"offset": (n,), "carriage": (n, 6), "marker": (n, 3)}[kind]
            out[kind][name] = out[kind].get(name, 0) + v.reshape(shape)
        else:
            raise ValueError(f"drift target {d.target!r}: use offset:<joint>, carriage:<joint>, instrument or "
                             "marker:<name>")
    return out


def level_columns(levels: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """Text columns as the 0/1 covariates a measurement file's reader makes of them
    (``<column>=<level>``), for a :class:`~torchcal.sim.sample.Sample`."""
    out = {}
    for name, vals in levels.items():
        for lv in sorted(set(vals.tolist())):
            out[f"{name}={lv}"] = (vals == lv).astype(float)
    return out
