"""The robots shipped with torchcal, ready to use.

Four nominal robot descriptions live in :mod:`torchcal.kinematics.robot_data` (pure data with citations);
this module turns them into :class:`~torchcal.kinematics.robot.Robot` objects, either

* from the shipped URDF files ``urdf/<name>.urdf`` (``source="urdf"``, the default): error
  parameters per joint origin (``dx, dy, dz, droll, dpitch, dyaw``), or
* from the classic DH table (``source="dh"``): error parameters Δa, Δd, Δα, Δθ per row (what a
  DH calibration such as seed 000 identifies).

Both describe the same kinematics: the URDF files are generated from the DH tables by
``scripts/make_urdfs.py``.

Units: metres, radians, kg, kg m^2; joint limits in rad (m for prismatic joints), velocities in
rad/s (m/s), efforts in N m (N).

Frames of a DH-built robot (classic convention): link ``link{i}`` (child of joint ``i``) is *not*
DH frame ``i``.  Its frame is DH frame ``i-1`` followed by ``Rz(theta_i + q_i)`` (``Rz(theta_i)
Tz(q_i)`` for a prismatic row), and DH frame ``i = link{i} . F_i`` with ``F_i = Tz(d_i) Tx(a_i)
Rx(alpha_i)``.  The fixed link ``flange`` is DH frame ``n`` (and ``tool`` the tool frame, when the
robot has one).  :func:`link_inertials` maps the DH-frame inertials of ``robot_data`` into these
link frames.
"""
from __future__ import annotations

import math
from pathlib import Path
from typing import Literal

import numpy as np

from torchcal.kinematics.robot import Robot
from torchcal.kinematics.robot_data import get_robot

__all__ = ["SHIPPED", "shipped", "urdf_path", "dh_table", "link_inertials", "tool_matrix"]

SHIPPED: tuple[str, ...] = ("kuka_kr5_arc", "scara", "ur5e", "kuka_iiwa14")
"""Names accepted by :func:`shipped` (keys of :data:`torchcal.kinematics.robot_data.ROBOTS`)."""

_DH_KEYS = ("a", "d", "alpha", "theta", "type", "name", "lower", "upper", "velocity", "effort")


def _data(name: str) -> dict:
    if name not in SHIPPED:
        raise KeyError(f"unknown robot {name!r}; shipped robots: {list(SHIPPED)}")
    return get_robot(name)


def urdf_path(name: str) -> Path:
    """Path of the shipped URDF ``urdf/<name>.urdf`` (in the source tree, next to the package).

    Raises:
        KeyError: ``name`` is not one of :data:`SHIPPED`.
        FileNotFoundError: the file is absent, e.g. when torchcal was installed from a wheel
            (the ``urdf/`` folder is not part of the package); use ``shipped(name, source="dh")``.
    """
    _data(name)
    p = Path(__file__).resolve().parents[2] / "urdf" / f"{name}.urdf"
    if not p.is_file():
        raise FileNotFoundError(
            f"shipped URDF {p} not found (installed without the source tree's urdf/ folder?); "
            f"build the same robot from its DH table with shipped({name!r}, source='dh'), or "
            f"regenerate the files with scripts/make_urdfs.py")
    return p


def dh_table(name: str) -> list[dict]:
    """Classic DH rows of robot ``name``, ready for :meth:`Robot.from_dh`.

    Each row is a dict with ``a, d`` (m), ``alpha, theta`` (rad), ``type``, ``name`` (the joint
    name from :mod:`torchcal.kinematics.robot_data`, e.g. ``joint_a1`` or ``shoulder_pan_joint``), and
    ``lower, upper`` (rad or m), ``velocity`` (rad/s or m/s), ``effort`` (N m or N; ``None``
    where not published).
    """
    return [{k: j[k] for k in _DH_KEYS} for j in _data(name)["joints"]]


def tool_matrix(name: str) -> np.ndarray | None:
    """The fixed tool transform (4, 4) in DH frame n (m), or ``None`` when the flange is the
    last DH frame (``tool`` is ``None`` in :mod:`torchcal.kinematics.robot_data`)."""
    tool = _data(name)["tool"]
    if tool is None:
        return None
    r, p, y = tool.get("rpy", (0.0, 0.0, 0.0))
    cr, sr, cp, sp, cy, sy = (math.cos(r), math.sin(r), math.cos(p), math.sin(p), math.cos(y),
                              math.sin(y))
    T = np.eye(4)
    T[:3, :3] = [[cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
                 [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
                 [-sp, cp * sr, cp * cr]]  # R = Rz(yaw) Ry(pitch) Rx(roll)
    T[:3, 3] = tool.get("xyz", (0.0, 0.0, 0.0))
    return T


def _F(a: float, d: float, alpha: float) -> np.ndarray:
    """Tz(d) Tx(a) Rx(alpha): link{i} frame -> DH frame i."""
    ca, sa = math.cos(alpha), math.sin(alpha)
    # exact zeros for multiples of pi/2, so that cos(pi/2) = 6e-17 does not leak into the files
    ca, sa = (0.0 if abs(ca) < 1e-15 else ca), (0.0 if abs(sa) < 1e-15 else sa)
    return np.array([[1.0, 0.0, 0.0, a], [0.0, ca, -sa, 0.0], [0.0, sa, ca, d], [0.0, 0.0, 0.0, 1.0]])


def link_inertials(name: str) -> dict[str, dict]:
    """Per-link inertials of robot ``name`` in the link frames of its DH-built robot.

    Returns ``{"link1": {"mass": kg, "com": (3,) m, "inertia": (ixx, ixy, ixz, iyy, iyz, izz)
    kg m^2}, ...}`` (about the COM, axes of the link frame), or ``{}`` when
    :mod:`torchcal.kinematics.robot_data` has no inertials for the robot.  The data there are given in DH
    frame ``i``; with DH frame ``i = link{i} . F_i``, ``F_i = Tz(d_i) Tx(a_i) Rx(alpha_i)``:
    ``com_link = F_i . com_dh`` and ``I_link = Rx(alpha_i) I_dh Rx(alpha_i)^T``.  Links with zero
    mass are kept (they carry a zero inertial).
    """
    data = _data(name)
    if data["inertials"] is None:
        return {}
    if data["convention"] != "classic":
        raise NotImplementedError("inertial conversion is written for classic DH tables")
    out = {}
    for i, (row, inert) in enumerate(zip(data["joints"], data["inertials"]), start=1):
        F = _F(row["a"], row["d"], row["alpha"])
        com = F[:3, :3] @ np.asarray(inert["com"], dtype=float) + F[:3, 3]
        ixx, ixy, ixz, iyy, iyz, izz = (float(v) for v in inert["inertia"])
        I = np.array([[ixx, ixy, ixz], [ixy, iyy, iyz], [ixz, iyz, izz]])
        Il = F[:3, :3] @ I @ F[:3, :3].T
        out[f"link{i}"] = {"mass": float(inert["mass"]), "com": tuple(float(v) for v in com),
                           "inertia": tuple(float(x) for x in (Il[0, 0], Il[0, 1], Il[0, 2], Il[1, 1],
                                                               Il[1, 2], Il[2, 2]))}
    return out


def shipped(name: str, source: Literal["urdf", "dh"] = "urdf", markers=None, **kw) -> Robot:
    """One of the shipped robots (:data:`SHIPPED`) as a :class:`Robot`.

    Args:
        name: ``"kuka_kr5_arc"``, ``"scara"``, ``"ur5e"`` or ``"kuka_iiwa14"``.
        source: ``"urdf"`` loads ``urdf/<name>.urdf`` (joint-origin error parameters);
            ``"dh"`` builds the robot from its classic DH table (Δa, Δd, Δα, Δθ per row).
            Both have the same links (``link0`` .. ``link{n}``, ``flange``) and joint names.
        markers: measured frames (link names or ``"name@link=x,y,z"`` strings, m); default
            ``["tool"]`` when the robot has a tool frame, else ``["flange"]``.
        **kw: passed on to :meth:`Robot.from_urdf` / :meth:`Robot.from_dh` (``dtype``,
            ``device``).
    """
    data = _data(name)
    tool = tool_matrix(name)
    if markers is None:
        markers = ["tool" if tool is not None else "flange"]
    if source == "urdf":
        return Robot.from_urdf(urdf_path(name), markers=markers, **kw)
    if source == "dh":
        return Robot.from_dh(dh_table(name), data["convention"], markers=markers,
                             name=data["urdf_name"], tool=tool, **kw)
    raise ValueError(f"source must be 'urdf' or 'dh', got {source!r}")

