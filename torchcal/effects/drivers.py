"""Drivers: what a model parameter may vary with, as one value per row.

A driver is named by a string a saved model carries:

* ``q:<joint>``: the joint's commanded position (rad, or m along a prismatic axis);
* ``torque:<joint>``: the gravity torque on the joint (N·m; N along a prismatic axis), from the
  URDF's inertials at the commanded pose;
* ``time:<column>``: a time column (s, :data:`~torchcal.effects.base.TIME_COVARIATES`);
* ``row``: the row order, where the data has no time column (the loop adds the ``row`` column);
* ``cov:<column>``: any other numeric covariate (a temperature, a load, a counter);
* ``level:<column>``: a text column (a tool, an operator, a fixture, a day) as its levels; it is
  held as one 0/1 covariate per level, ``<column>=<level>`` (:mod:`torchcal.measure.levels`).
"""
from __future__ import annotations

import torch
from torch import Tensor

from torchcal.effects.base import TIME_COVARIATES
from torchcal.measure.data import is_quality_column
from torchcal.measure.levels import factor_levels, is_level_column

__all__ = ["ROW", "list_drivers", "driver_values", "driver_kind", "driver_unit", "driver_words", "gravity_torques"]

ROW = "row"  # the covariate holding the row order (0, 1, …) when the data has no time column


def driver_kind(driver: str) -> str:
    return "row" if driver == ROW else driver.split(":", 1)[0]


def _numeric(covariates: dict) -> list[str]:
    out = []
    for k, v in covariates.items():
        if k.startswith("dir.") or is_quality_column(k) or is_level_column(k) or k == ROW:
            continue
        v = v[torch.isfinite(v)]
        if v.numel() > 1 and float(v.max() - v.min()) > 0:
            out.append(k)
    return out


def list_drivers(robot, joints: list[str], covariates: dict, torques: bool) -> list[str]:
    """Every driver the data offers: the positions of ``joints``, their gravity torques (with
    ``torques``: the URDF has inertials), time (else the row order), the numeric covariates and
    the text columns with at least two levels."""
    out = [f"q:{j}" for j in joints]
    if torques:
        out += [f"torque:{j}" for j in joints]
    num = _numeric(covariates)
    times = [c for c in num if c in TIME_COVARIATES]
    out += [f"time:{c}" for c in times]
    if not times and ROW in covariates:
        out.append(ROW)
    out += [f"cov:{c}" for c in num if c not in TIME_COVARIATES]
    out += [f"level:{f}" for f, lv in factor_levels(covariates).items() if len(lv) >= 2]
    return out


def gravity_torques(robot, q: Tensor, geometry: Tensor | None = None, payload=None,
                    payload_link: str | None = None) -> Tensor:
    """``(N, dof)`` gravity torque on each actuated joint (N·m; force along the axis, N, for a
    prismatic joint) from the URDF's inertials at commands ``q (N, dof)``, plus a payload the loop
    fitted: ``payload`` its mass moments ``(m kg, m·sx, m·sy, m·sz kg·m)`` on ``payload_link``, ``(4,)``
    or ``(N, 4)`` per row (a load logged row by row: :func:`~torchcal.effects.gravity.row_payload`)."""
    from torchcal.effects.gravity import gravity_wrenches  # gravity imports the kinematics: only when asked

    w = gravity_wrenches(robot, q, geometry, payload_link=payload_link)
    wrench = w.urdf
    if payload is not None:
        mu = torch.as_tensor(payload, dtype=q.dtype, device=q.device)
        wrench = wrench + (w.payload @ mu if mu.ndim == 1 else torch.einsum("nfsk,nk->nfs", w.payload, mu))
    out = q.new_zeros(q.shape[0], robot.dof)
    for k, name in enumerate(robot.joint_names):
        f = w.names.index(name)
        jt = robot.joints[f - 1]
        ax = torch.as_tensor(jt.axis, dtype=q.dtype, device=q.device)
        part = wrench[:, f, :3] if jt.type == "prismatic" else wrench[:, f, 3:]
        out[:, k] = part @ ax
    return out


def driver_values(robot, driver: str, q: Tensor, covariates: dict, torques: Tensor | None = None) -> Tensor:
    """``(N,)`` the driver's value per row (``torques``: :func:`gravity_torques`, needed for a
    torque driver). For a level driver: the level index (the baseline level 0)."""
    kind = driver_kind(driver)
    name = driver.split(":", 1)[1] if ":" in driver else driver
    if kind == "q":
        return q[:, robot.joint_names.index(name)]
    if kind == "torque":
        if torques is None:
            raise ValueError(f"driver {driver}: no gravity torques (the URDF has no inertials)")
        return torques[:, robot.joint_names.index(name)]
    col = ROW if kind == "row" else name
    if kind == "level":
        raise ValueError("a level driver has one column per level: read them with level_column")
    if col not in covariates:
        raise ValueError(f"driver {driver} needs the column {col!r}; the data has {sorted(covariates)}")
    return covariates[col].to(q)


def driver_unit(robot, driver: str) -> str:
    kind = driver_kind(driver)
    name = driver.split(":", 1)[-1]
    if kind == "q":
        return robot.joint_units[robot.joint_names.index(name)]
    if kind == "torque":
        return "N" if robot.joint_units[robot.joint_names.index(name)] == "m" else "N·m"
    if kind == "time":
        return "s"
    return "row" if kind == "row" else "unit"


def driver_words(driver: str) -> str:
    kind = driver_kind(driver)
    name = driver.split(":", 1)[-1]
    return {"q": f"{name}'s position", "torque": f"the gravity torque at {name}", "time": f"time ({name})",
            "row": "the row order", "cov": name, "level": name}[kind]
