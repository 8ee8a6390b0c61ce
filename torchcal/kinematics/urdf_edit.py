"""Surgical edits of URDF text: new ``<origin>`` values for a few joints and a few appended
elements, everything else left byte for byte as it was (comments, meshes, inertials,
transmissions, gazebo blocks, number formats, indentation).

Positions in the text come from expat (the byte index of each start tag), so a ``<joint>`` inside
a comment, a ``<transmission>`` or a ``<gazebo>`` block is never mistaken for a robot joint.
"""
from __future__ import annotations

import math
import re
import xml.parsers.expat
from dataclasses import dataclass

import numpy as np

__all__ = ["rpy_near", "format_values", "format_number", "edit_origins", "origin_text", "OriginEdit", "ZERO"]

_TAG = re.compile(rb"<(?P<name>[\w:.-]+)(?P<attrs>(?:\s+[\w:.-]+\s*=\s*(?:\"[^\"]*\"|'[^']*'))*)\s*(?P<end>/?)>")
_ATTR = re.compile(rb"([\w:.-]+)\s*=\s*(?:\"([^\"]*)\"|'([^']*)')")
# a number below this (m or rad) is float64 rounding of zero (a sum of products of cosines and sines
# that cancel): written 0, never as -2.198e-20
ZERO = 1e-15
# |cos pitch| below this: the rotation is at gimbal lock to within what float64 rpy can say
_LOCK = 1e-12


@dataclass
class OriginEdit:
    """New values for one joint's ``<origin>``: ``xyz`` (3,) m and ``rpy`` (3,) rad, or None to
    keep that attribute as it is."""

    xyz: np.ndarray | None
    rpy: np.ndarray | None


def _wrap_near(a: float, ref: float) -> float:
    """``a`` shifted by a multiple of 2π to lie within π of ``ref``."""
    return a + 2 * math.pi * round((ref - a) / (2 * math.pi))


def rpy_near(R: np.ndarray, rpy0) -> np.ndarray:
    """Roll, pitch, yaw (rad) of ``R (3, 3)`` (``R = Rz(yaw) Ry(pitch) Rx(roll)``), of all the
    triples that give ``R`` the one closest to ``rpy0 (3,)``.

    Away from pitch = ±π/2 there are two solutions, ``(r, p, y)`` and ``(r + π, π − p, y + π)``,
    each up to multiples of 2π: the closer one is taken. At the lock only ``r − y`` (pitch π/2) or
    ``r + y`` (pitch −π/2) is defined: yaw keeps its old value and roll takes the change, which
    is what a correction applied after the origin (``O · Rx(δ)``, about the axis that lies along
    the lock) does. Close to the lock but not at it, roll and yaw individually are ill-conditioned
    functions of ``R``: a tilt of δ rad that leaves the lock moves them by up to π/2 (only their
    sum or difference stays near), and no exact triple avoids that; the closer of the two
    solutions is still taken.
    """
    R = np.asarray(R, dtype=float)
    r0, p0, y0 = (float(v) for v in rpy0)
    cp = math.hypot(R[0, 0], R[1, 0])
    if cp < _LOCK:
        up = -R[2, 0] > 0  # pitch +π/2
        p = _wrap_near(math.pi / 2 if up else -math.pi / 2, p0)
        if up:  # R01 = sin(r − y), R11 = cos(r − y)
            return np.array([_wrap_near(math.atan2(R[0, 1], R[1, 1]) + y0, r0), p, y0]) + 0.0
        return np.array([_wrap_near(math.atan2(-R[0, 1], R[1, 1]) - y0, r0), p, y0]) + 0.0  # R01 = −sin(r + y)
    sols = [(math.atan2(R[2, 1], R[2, 2]), math.atan2(-R[2, 0], cp), math.atan2(R[1, 0], R[0, 0])),
            (math.atan2(-R[2, 1], -R[2, 2]), math.atan2(-R[2, 0], -cp), math.atan2(-R[1, 0], -R[0, 0]))]
    best = None
    for sol in sols:
        v = np.array([_wrap_near(a, ref) for a, ref in zip(sol, (r0, p0, y0))])
        dist = float(np.abs(v - (r0, p0, y0)).sum())
        if best is None or dist < best[0]:
            best = (dist, v)
    return best[1] + 0.0  # + 0.0: no -0.0 in the text


def format_number(v) -> float:
    """``v`` as a float, with rounding noise about zero (``|v| <`` :data:`ZERO`) and ``-0.0`` as ``0.0``."""
    v = float(v)
    return 0.0 if abs(v) < ZERO else v + 0.0


def format_values(new, old_text: str | None) -> str:
    """Space-separated values for an attribute: each number the old text already states exactly
    keeps its old spelling (``0`` stays ``0``); the others are written with the shortest repr
    that reads back to the same float, rounding noise about zero as ``0``
    (:func:`format_number`)."""
    old = old_text.split() if old_text else []
    out = []
    for i, v in enumerate(new):
        v = format_number(v)
        tok = old[i] if i < len(old) else None
        try:
            same = tok is not None and float(tok) == v
        except ValueError:
            same = False
        out.append(tok if same else "0" if v == 0.0 else repr(v))
    return " ".join(out)


def origin_text(text: str) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Per robot joint of a URDF text, its ``<origin>``'s ``xyz`` and ``rpy`` as written (zeros
    where absent)."""
    data = text.encode()
    out = {}
    for name, (_, o_at) in _locate(data)[0].items():
        old = {} if o_at is None else _attrs(_tag(data, o_at).group(0))
        out[name] = tuple(np.array([float(v) for v in old[k].split()]) if old.get(k) else np.zeros(3)
                          for k in ("xyz", "rpy"))
    return out


def _attrs(tag: bytes) -> dict[str, str]:
    return {a.group(1).decode(): (a.group(2) if a.group(2) is not None else a.group(3)).decode()
            for a in _ATTR.finditer(tag)}


def _locate(data: bytes) -> tuple[dict, int, int]:
    """Byte offsets in ``data``: per robot joint (a ``<joint>`` child of ``<robot>``), its start
    tag and its direct ``<origin>`` child's start tag (or None); the ``<robot>`` start tag and its
    end tag."""
    p = xml.parsers.expat.ParserCreate()
    stack: list[str] = []
    joints: dict[str, list] = {}
    where = {"robot": None, "robot_end": None}
    current: list = [None]

    def start(name, attrs):
        at = p.CurrentByteIndex
        if not stack and name == "robot":
            where["robot"] = at
        elif len(stack) == 1 and name == "joint" and "name" in attrs:
            current[0] = joints.setdefault(attrs["name"], [at, None])
        elif len(stack) == 2 and stack[1] == "joint" and name == "origin" and current[0] is not None:
            if current[0][1] is None:
                current[0][1] = at
        stack.append(name)

    def end(name):
        stack.pop()
        if not stack:
            where["robot_end"] = p.CurrentByteIndex
        elif len(stack) == 1:
            current[0] = None

    p.StartElementHandler, p.EndElementHandler = start, end
    p.Parse(data, True)
    if where["robot"] is None:
        raise ValueError("cannot export: the URDF text has no <robot> root element")
    return joints, where["robot"], where["robot_end"]


def _tag(data: bytes, at: int) -> re.Match:
    m = _TAG.match(data, at)
    if m is None:
        raise ValueError(f"cannot read the tag at byte {at} of the URDF text")
    return m


def _set_attrs(tag: bytes, values: dict[str, str]) -> bytes:
    """``tag`` (a whole start tag) with the given attributes' values replaced, or appended before
    its end when absent."""
    for key, val in values.items():
        k = key.encode()
        m = next((a for a in _ATTR.finditer(tag) if a.group(1) == k), None)
        v = val.encode()
        if m is not None:
            g = 2 if m.group(2) is not None else 3
            tag = tag[:m.start(g)] + v + tag[m.end(g):]
        else:
            cut = len(tag) - (2 if tag.endswith(b"/>") else 1)
            tag = tag[:cut].rstrip() + b" " + k + b'="' + v + b'"' + tag[cut:]
    return tag


def _indent_at(data: bytes, at: int) -> bytes:
    line = data.rfind(b"\n", 0, at) + 1
    lead = data[line:at]
    return lead if not lead.strip() else b""


def edit_origins(text: str, edits: dict[str, OriginEdit], append: list[str], note: str | None = None) -> str:
    """``text`` with the ``<origin>`` of each joint in ``edits`` rewritten (an origin is added to
    a joint that has none), the XML fragments in ``append`` added before ``</robot>`` and ``note``
    as a comment after ``<robot>``; every other byte unchanged."""
    data = text.encode()
    joints, robot_at, robot_end = _locate(data)
    patches: list[tuple[int, int, bytes]] = []  # (start, end, replacement), non-overlapping
    for name, e in edits.items():
        if name not in joints:
            raise ValueError(f"cannot export: joint {name!r} is not a <joint> of the URDF's <robot>")
        j_at, o_at = joints[name]
        if o_at is not None:
            m = _tag(data, o_at)
            old = _attrs(m.group(0))
            vals = {}
            if e.xyz is not None:
                vals["xyz"] = format_values(e.xyz, old.get("xyz"))
            if e.rpy is not None:
                vals["rpy"] = format_values(e.rpy, old.get("rpy"))
            new = _set_attrs(m.group(0), vals)
            if new != m.group(0):
                patches.append((m.start(), m.end(), new))
            continue
        jm = _tag(data, j_at)
        pad = _indent_at(data, j_at)
        xyz = format_values(np.zeros(3) if e.xyz is None else e.xyz, None)
        rpy = format_values(np.zeros(3) if e.rpy is None else e.rpy, None)
        frag = b"\n" + pad + b"  " + f'<origin xyz="{xyz}" rpy="{rpy}"/>'.encode()
        if jm.group("end"):  # <joint .../>: open it to hold the origin
            patches.append((jm.start(), jm.end(), jm.group(0)[:-2].rstrip() + b">" + frag + b"\n" + pad + b"</joint>"))
        else:
            patches.append((jm.end(), jm.end(), frag))
    pad = _indent_at(data, robot_end) + b"  " if append else b""
    if append:
        block = b"".join(pad + a.encode() + b"\n" for a in append)
        line = data.rfind(b"\n", 0, robot_end) + 1
        at = line if not data[line:robot_end].strip() else robot_end
        patches.append((at, at, block if at == line else b"\n" + block))
    if note:
        rm = _tag(data, robot_at)
        patches.append((rm.end(), rm.end(), b"\n" + _indent_at(data, robot_end) + b"  <!-- "
                        + note.replace("--", "\u2014").encode() + b" -->"))
    for s, e, new in sorted(patches, key=lambda t: t[0], reverse=True):
        data = data[:s] + new + data[e:]
    return data.decode()
