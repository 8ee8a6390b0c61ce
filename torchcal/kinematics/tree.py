"""Plain description of a kinematic tree: joints, links and measured frames (markers).

Nothing here is a tensor: loaders (:mod:`torchcal.kinematics.urdf`, :mod:`torchcal.kinematics.dh`) produce these
records and :class:`torchcal.kinematics.robot.Robot` turns them into batched tensors.
"""
from __future__ import annotations

import math
import re
from dataclasses import dataclass, field

import numpy as np

__all__ = ["JointSpec", "DHOrigin", "Marker", "parse_marker", "select_subtree", "MOVABLE", "JOINT_TYPES"]

MOVABLE = ("revolute", "continuous", "prismatic")
JOINT_TYPES = MOVABLE + ("fixed",)


@dataclass
class DHOrigin:
    """A joint origin written as DH values (m, rad) rather than xyz/rpy.

    classic:  origin = Tz(d) Tx(a) Rx(alpha) Rz(phi)   (a, d, alpha of the previous DH row)
    modified: origin = Rx(alpha) Tx(a) Tz(d) Rz(phi)   (alpha, a of the previous row, d of this one)

    ``names`` maps each slot ("a", "d", "alpha", "phi") to the name of the error parameter that
    moves it (e.g. ``"joint_2.da"``), or ``None`` when no parameter moves that slot.
    """

    convention: str
    a: float
    d: float
    alpha: float
    phi: float
    names: dict = field(default_factory=dict)

    def matrix(self) -> np.ndarray:
        ca, sa, cp, sp = np.cos(self.alpha), np.sin(self.alpha), np.cos(self.phi), np.sin(self.phi)
        T = np.eye(4)
        T[:3, :3] = [[cp, -sp, 0.0], [ca * sp, ca * cp, -sa], [sa * sp, sa * cp, ca]]
        if self.convention == "classic":
            T[:3, 3] = [self.a, 0.0, self.d]
        else:
            T[:3, 3] = [self.a, -self.d * sa, self.d * ca]
        return T


@dataclass
class JointSpec:
    """One joint. ``origin`` is the (4, 4) nominal transform parent link -> joint frame (m);
    ``axis`` the unit motion axis in the joint frame; ``mimic`` = (source joint, multiplier,
    offset) for coupled joints; limits in rad or m."""

    name: str
    type: str
    parent: str
    child: str
    origin: np.ndarray
    axis: np.ndarray = field(default_factory=lambda: np.array([0.0, 0.0, 1.0]))
    mimic: tuple[str, float, float] | None = None
    lower: float | None = None
    upper: float | None = None
    velocity: float | None = None
    effort: float | None = None
    dh: DHOrigin | None = None
    offset_name: str | None = None  # name of the zero-offset parameter (None: "<name>.offset")

    def __post_init__(self):
        if self.type not in JOINT_TYPES:
            raise ValueError(f"joint {self.name!r} has type {self.type!r}; torchcal supports "
                             f"{', '.join(JOINT_TYPES)} (planar and floating joints are not calibrated: "
                             "replace them by fixed joints or a chain of revolute/prismatic joints)")
        self.origin = np.asarray(self.origin, dtype=float)
        axis = np.asarray(self.axis, dtype=float)
        n = np.linalg.norm(axis)
        if self.type != "fixed" and n < 1e-12:
            raise ValueError(f"joint {self.name!r} has a zero axis; give a unit axis like '0 0 1'")
        self.axis = axis / n if n > 0 else np.array([0.0, 0.0, 1.0])

    @property
    def movable(self) -> bool:
        return self.type in MOVABLE


@dataclass
class Marker:
    """A measured frame: a point (and orientation) fixed on ``link``.

    ``xyz`` (m) and ``rpy`` (rad) give its nominal pose in the link frame; for a reflector glued
    somewhere on the hand they are only an initial guess, identified with the rest.
    """

    name: str
    link: str
    xyz: tuple[float, float, float] = (0.0, 0.0, 0.0)
    rpy: tuple[float, float, float] = (0.0, 0.0, 0.0)

    def matrix(self) -> np.ndarray:
        r, p, y = self.rpy
        cr, sr, cp, sp, cy, sy = np.cos(r), np.sin(r), np.cos(p), np.sin(p), np.cos(y), np.sin(y)
        T = np.eye(4)
        T[:3, :3] = [[cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
                     [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
                     [-sp, cp * sr, cp * cr]]
        T[:3, 3] = self.xyz
        return T


_MARKER_RE = re.compile(r"^\s*([^@=\s]+)\s*(?:@\s*([^=\s]+))?\s*(?:=\s*(.*))?$")


def parse_marker(spec) -> Marker:
    """Accept a :class:`Marker`, a link name (``"tool0"``), or ``"name@link=x,y,z"`` (m; the
    ``=x,y,z`` initial guess is optional: ``"m1@arm_7_link"`` starts at the link origin)."""
    if isinstance(spec, Marker):
        return spec
    if not isinstance(spec, str):
        raise TypeError(f"a marker is a link name, 'name@link=x,y,z' or a Marker, got {type(spec).__name__}")
    m = _MARKER_RE.match(spec)
    if not m:
        name = spec.split("=")[0].split("@")[0].strip()
        if any(c.isspace() for c in name):
            fixed = "_".join(name.split())
            raise ValueError(f"marker name {name!r} has a space; a marker's name names its CSV columns "
                             f"({name}.x, …) and parameters, which take no spaces: rename it {fixed!r} in the marker "
                             f"and in the CSV header ({fixed}.x, {fixed}.y, {fixed}.z)")
        raise ValueError(f"cannot read marker {spec!r}; write 'link' or 'name@link=x,y,z' (metres)")
    name, link, guess = m.groups()
    xyz = (0.0, 0.0, 0.0)
    if guess:
        try:
            vals = [float(v) for v in guess.split(",")]
        except ValueError:
            raise ValueError(f"marker {spec!r}: the initial guess must be three numbers in metres, "
                             "like 'm1@arm_7_link=0.05,0,0.1'") from None
        if len(vals) != 3:
            raise ValueError(f"marker {spec!r}: the initial guess has {len(vals)} numbers, expected 3 (x,y,z in m)")
        if not all(math.isfinite(v) for v in vals):
            raise ValueError(f"marker {spec!r}: the initial guess must be three finite numbers in metres, like "
                             f"'{name}@{link or name}=0.05,0,0.1' (give 0,0,0 when it is unknown)")
        xyz = tuple(vals)
    return Marker(name=name, link=link or name, xyz=xyz)


def select_subtree(joints: list[JointSpec], markers: list[Marker]) -> tuple[str, list[JointSpec]]:
    """Root link and the joints on the paths from the root to the markers' links, in topological
    (parent before child) order, mimic sources included. Raises on unknown links and cycles."""
    by_child = {}
    for j in joints:
        if j.child in by_child:
            raise ValueError(f"link {j.child!r} is the child of two joints ({by_child[j.child].name!r} and "
                             f"{j.name!r}); a URDF must be a tree")
        by_child[j.child] = j
    links = {j.parent for j in joints} | {j.child for j in joints}
    roots = sorted({j.parent for j in joints} - set(by_child))
    if len(roots) != 1:
        raise ValueError(f"the URDF must have exactly one root link, found {roots or 'none (a cycle)'}")
    root = roots[0]
    by_name = {j.name: j for j in joints}
    needed: set[str] = set()

    def climb(link: str) -> None:
        seen = set()
        while link in by_child:
            if link in seen:
                raise ValueError(f"the joints form a cycle through link {link!r}")
            seen.add(link)
            j = by_child[link]
            needed.add(j.name)
            if j.mimic is not None:
                src = by_name.get(j.mimic[0])
                if src is None:
                    raise ValueError(f"joint {j.name!r} mimics {j.mimic[0]!r}, which is not in the URDF")
                if src.name not in needed:
                    climb(src.child)
            link = j.parent

    for mk in markers:
        if mk.link not in links:
            close = [l for l in sorted(links) if mk.link.lower() in l.lower() or l.lower() in mk.link.lower()][:5]
            listed = sorted(links)
            more = f" and {len(listed) - 12} more" if len(listed) > 12 else ""
            hint = f"; did you mean {', '.join(close)}?" if close else f"; its links are {listed[:12]}{more}"
            raise ValueError(f"marker {mk.name!r} is on link {mk.link!r}, which is not in the URDF{hint}")
        climb(mk.link)
    order, frontier = [], [root]
    children: dict[str, list[JointSpec]] = {}
    for j in joints:  # file order among siblings keeps the result deterministic
        if j.name in needed:
            children.setdefault(j.parent, []).append(j)
    while frontier:
        link = frontier.pop(0)
        for j in children.get(link, []):
            order.append(j)
            frontier.append(j.child)
    return root, order
