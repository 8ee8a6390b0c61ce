"""The independent simulator's own URDF reading and rigid-body maths (numpy only; shares no code
with torchcal's kinematics): joints, link inertials, rotations (rad) and homogeneous transforms (m)."""
from __future__ import annotations

import math
import re
import xml.etree.ElementTree as ET
from dataclasses import dataclass

import numpy as np

__all__ = ["MOVING_TYPES", "UrdfJoint", "homogeneous", "joints_above", "matrix_to_quat", "parse_floats",
           "parse_marker", "parse_urdf", "rotation_exp", "rpy_matrix", "skew", "tree_order"]


MOVING_TYPES = ("revolute", "continuous", "prismatic")
_MARKER_RE = re.compile(r"^\s*([^@=\s]+)\s*(?:@\s*([^=\s]+))?\s*(?:=\s*(.+?))?\s*$")


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


def matrix_to_quat(R: np.ndarray) -> np.ndarray:
    """Rotation matrices ``(..., 3, 3)`` -> unit quaternions ``(..., 4)`` (w, x, y, z), ``w >= 0``.
    Shepperd's method: the largest of w, x, y, z is taken from the diagonal, the others from
    the off-diagonal sums, so no branch divides by a small number."""
    R = np.asarray(R, dtype=float)
    d = np.stack([1 + R[..., 0, 0] + R[..., 1, 1] + R[..., 2, 2], 1 + R[..., 0, 0] - R[..., 1, 1] - R[..., 2, 2],
                  1 - R[..., 0, 0] + R[..., 1, 1] - R[..., 2, 2], 1 - R[..., 0, 0] - R[..., 1, 1] + R[..., 2, 2]], -1)
    a, b = R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0]
    c, e = R[..., 1, 0] - R[..., 0, 1], R[..., 0, 1] + R[..., 1, 0]
    f, g = R[..., 0, 2] + R[..., 2, 0], R[..., 1, 2] + R[..., 2, 1]
    # row k: 4 q_k times (w, x, y, z) when q_k is the largest component
    cand = np.stack([np.stack([d[..., 0], a, b, c], -1), np.stack([a, d[..., 1], e, f], -1),
                     np.stack([b, e, d[..., 2], g], -1), np.stack([c, f, g, d[..., 3]], -1)], -2)
    k = np.argmax(d, -1)[..., None, None]
    qt = np.take_along_axis(cand, np.broadcast_to(k, k.shape[:-2] + (1, 4)), -2)[..., 0, :]
    qt = qt / np.linalg.norm(qt, axis=-1, keepdims=True)
    return np.where(qt[..., :1] < 0, -qt, qt)


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


def tree_order(joints: list[UrdfJoint]) -> tuple[str, list[UrdfJoint], dict[str, list[str]]]:
    """-> (root link, joints parent before child (breadth first), link -> links of its subtree)."""
    by_child = {j.child: j for j in joints}
    roots = sorted({j.parent for j in joints} - set(by_child))
    if len(roots) != 1:
        raise ValueError(f"the URDF needs exactly one root link, found {roots}")
    root = roots[0]
    kids: dict[str, list[UrdfJoint]] = {}
    for j in joints:
        kids.setdefault(j.parent, []).append(j)
    order, stack = [], [root]
    while stack:
        for j in kids.get(stack.pop(0), []):
            order.append(j)
            stack.append(j.child)
    below: dict[str, list[str]] = {}
    for j in reversed(order):
        below.setdefault(j.child, [j.child])
        below.setdefault(j.parent, [j.parent]).extend(below[j.child])
    below.setdefault(root, [root])
    return root, order, below


def joints_above(joints: list[UrdfJoint], links: list[str]) -> set[str]:
    """Names of the joints on the paths from the root to ``links``, mimic sources included."""
    by_child, by_name = {j.child: j for j in joints}, {j.name: j for j in joints}
    needed: set[str] = set()

    def climb(link: str) -> None:
        while link in by_child:
            j = by_child[link]
            needed.add(j.name)
            if j.mimic and j.mimic[0] not in needed:
                climb(by_name[j.mimic[0]].child)
            link = j.parent

    for link in links:
        climb(link)
    return needed


def parse_marker(spec: str, links) -> tuple[str, str, np.ndarray]:
    """``"link"`` or ``"name@link=x,y,z"`` (m, link frame) -> (name, link, offset (3,) m)."""
    m = _MARKER_RE.match(spec)
    if not m or (m.group(2) or m.group(1)) not in links:
        raise ValueError(f"marker {spec!r}: write 'link' or 'name@link=x,y,z' with a link of the URDF")
    return m.group(1), m.group(2) or m.group(1), parse_floats(m.group(3), [0, 0, 0], ",")
