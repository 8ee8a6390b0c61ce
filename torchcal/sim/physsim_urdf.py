"""The independent simulator's own URDF reading and rigid-body maths (numpy only; shares no code
with torchcal's kinematics): joints, link inertials, rotations (rad) and homogeneous transforms (m)."""
from __future__ import annotations

import math
import xml.etree.ElementTree as ET
from dataclasses import dataclass

import numpy as np

__all__ = ["MOVING_TYPES", "UrdfJoint", "homogeneous", "parse_floats", "parse_urdf", "rotation_exp",
           "rpy_matrix", "skew"]


MOVING_TYPES = ("revolute", "continuous", "prismatic")


def skew(v: np.ndarray) -> np.ndarray:
    """``(..., 3) -> (..., 3, 3)`` cross-product matrices."""
    z = np.zeros(v.shape[:-1])
    x, y, w = v[..., 0], v[..., 1], v[..., 2]
    return np.stack([np.stack([z, -w, y], -1), np.stack([w, z, -x], -1), np.stack([-y, x, z], -1)], -2)


def rotation_exp(v) -> np.ndarray:
    """Rodrigues: rotation vectors ``(..., 3)`` rad -> rotation matrices ``(..., 3, 3)``."""
    v = np.asarray(v, dtype=float)
    th = np.linalg.norm(v, axis=-1)[..., None, None]
    K = skew(v)
    small = th < 1e-4  # Taylor below 1e-4 rad: (1 - cos)/th^2 loses digits there
    ts = np.where(small, 1.0, th)
    a = np.where(small, 1 - th ** 2 / 6, np.sin(ts) / ts)
    b = np.where(small, 0.5 - th ** 2 / 24, (1 - np.cos(ts)) / ts ** 2)
    return np.eye(3) + a * K + b * (K @ K)


def rpy_matrix(r: float, p: float, y: float) -> np.ndarray:
    """URDF fixed-axis roll-pitch-yaw (rad): ``Rz(y) Ry(p) Rx(r)``, (3, 3)."""
    return rotation_exp([0, 0, y]) @ rotation_exp([0, p, 0]) @ rotation_exp([r, 0, 0])


def homogeneous(R: np.ndarray, t) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, t
    return T


def parse_floats(s: str | None, default, sep: str | None = None) -> np.ndarray:
    return np.array([float(v) for v in s.split(sep)] if s else default, dtype=float)


@dataclass
class UrdfJoint:
    name: str
    type: str
    parent: str
    child: str
    origin: np.ndarray  # (4, 4) nominal pose of the joint frame in the parent link frame
    axis: np.ndarray  # (3,) unit, joint frame
    lower: float
    upper: float
    mimic: tuple[str, float, float] | None  # (source, multiplier, offset)


def parse_urdf(text: str) -> tuple[str, list[UrdfJoint], dict[str, list[tuple[float, np.ndarray]]]]:
    """-> (robot name, joints in file order, link -> [(mass kg, COM (3,) m in the link frame)])."""
    root = ET.fromstring(text)
    bodies: dict[str, list] = {}
    for ln in root.findall("link"):
        bodies[ln.get("name")] = []
        inert = ln.find("inertial")
        if inert is not None and inert.find("mass") is not None:
            o = inert.find("origin")
            com = parse_floats(None if o is None else o.get("xyz"), [0, 0, 0])
            bodies[ln.get("name")].append((float(inert.find("mass").get("value")), com))
    joints = []
    for j in root.findall("joint"):
        typ = j.get("type")
        if typ not in MOVING_TYPES + ("fixed",):
            raise ValueError(f"joint {j.get('name')!r}: type {typ!r} is not supported")
        o, ax, lim, mim = j.find("origin"), j.find("axis"), j.find("limit"), j.find("mimic")
        xyz = parse_floats(None if o is None else o.get("xyz"), [0, 0, 0])
        rpy = parse_floats(None if o is None else o.get("rpy"), [0, 0, 0])
        axis = parse_floats(None if ax is None else ax.get("xyz"), [1, 0, 0])
        lo, hi = -math.inf, math.inf
        if typ != "continuous" and lim is not None and lim.get("lower") is not None:
            lo, hi = float(lim.get("lower")), float(lim.get("upper", 0.0))
        mimic = None
        if mim is not None:
            mimic = (mim.get("joint"), float(mim.get("multiplier", 1.0)), float(mim.get("offset", 0.0)))
        joints.append(UrdfJoint(j.get("name"), typ, j.find("parent").get("link"), j.find("child").get("link"),
                             homogeneous(rpy_matrix(*rpy), xyz), axis / np.linalg.norm(axis), lo, hi, mimic))
    return root.get("name", "robot"), joints, bodies
