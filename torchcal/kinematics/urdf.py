"""Read and write URDF files (kinematics only: meshes are never loaded).

The URDF is read with lxml, strictly (a truncated file is an error, not a robot with fewer joints),
into the few elements kinematics uses: joints, links, inertials and collision shapes. A parser
that builds scene graphs (yourdfpy) imports a mesh library (trimesh, and with it much of scipy:
about a second) that no command here uses; the tests compare with yourdfpy instead."""
from __future__ import annotations

import os
import re
from pathlib import Path

import numpy as np
import torch

from torchcal.kinematics.transforms import matrix_to_rpy, rpy_to_matrix
from torchcal.kinematics.tree import JointSpec
from torchcal.kinematics.urdf_check import is_urdf_text, parse_checked, strip_bom

__all__ = ["load_joints", "urdf_links", "write_urdf", "read_inertials", "read_collisions", "read_urdf_text"]


def read_urdf_text(path) -> str:
    """The text of a URDF file, refused with the file's name when it is not UTF-8 or is a xacro
    file (whose macros only ``xacro`` expands: read as URDF, their joints would be lost)."""
    p = Path(path)
    if p.is_dir():
        raise IsADirectoryError(f"URDF path {p} is a directory; give the .urdf file")
    try:
        text = p.read_bytes().decode("utf-8-sig")  # a byte-order mark is no part of the text
    except UnicodeDecodeError as e:
        raise ValueError(f"URDF file {p} is not UTF-8 text (byte 0x{e.object[e.start]:02x} at position {e.start}); "
                         "save it as UTF-8 (e.g. iconv -f latin1 -t utf-8 in.urdf > out.urdf)") from None
    _refuse_xacro(text, str(p))
    return text


def _refuse_xacro(text: str, where: str) -> None:
    # xacro's output may keep the namespace and mention the .xacro it came from, but holds no xacro element
    if "<xacro:" in re.sub(r"<!--.*?-->", "", text, flags=re.S) or where.endswith(".xacro"):
        raise ValueError(f"{where} is a xacro file: its macros and properties are not URDF. Run xacro first "
                         "(xacro robot.urdf.xacro > robot.urdf) and give the URDF it writes")


_FIX = ("Check that it is well-formed XML with a <robot> root and <link>/<joint> elements")


def _root(path_or_xml):
    """The ``<robot>`` element of a URDF given as a path or an XML string, parsed strictly and
    checked element by element (:mod:`torchcal.kinematics.urdf_check`); content is never taken for
    a path."""
    if is_urdf_text(path_or_xml):
        text, where = strip_bom(path_or_xml), "string"
        _refuse_xacro(text, "the URDF string")
    else:
        p = Path(path_or_xml)
        if not (p.is_file() or p.is_dir()):
            raise FileNotFoundError(f"URDF file not found: {p} (give the path to a .urdf file)")
        text, where = read_urdf_text(p), str(p)
    root = parse_checked(text, where)
    if root.tag != "robot":
        raise ValueError(f"could not parse URDF {where}: its root element is <{root.tag}>, not <robot>. {_FIX}")
    return root, where


def _floats(text: str | None, n: int | None = None) -> np.ndarray:
    v = np.array([float(x) for x in (text or "").split()], dtype=float)
    if n is not None and v.size != n:
        raise ValueError(f"{text!r} holds {v.size} numbers, not {n}")
    return v


def _float(text: str | None) -> float | None:
    return None if text is None else float(text)


def _or(value, default: float) -> float:
    """``value`` as a float, ``default`` only when it is absent (never when it is 0)."""
    return default if value is None else float(value)


def _origin(el) -> np.ndarray:
    """``(4, 4)`` transform of an ``<origin xyz rpy>`` (identity where absent; URDF's
    ``R = Rz(yaw) Ry(pitch) Rx(roll)``)."""
    T = np.eye(4)
    if el is not None:
        T[:3, :3] = rpy_to_matrix(torch.as_tensor(_floats(el.get("rpy", "0 0 0"), 3))).numpy()
        T[:3, 3] = _floats(el.get("xyz", "0 0 0"), 3)
    return T


def _link_of(el, tag: str) -> str:
    ref = el.find(tag)
    if ref is None or not ref.get("link"):
        raise ValueError(f"joint {el.get('name')!r} has no <{tag} link=\"...\"/>")
    return ref.get("link")


def _joint(el) -> JointSpec:
    lim, mimic, axis = el.find("limit"), el.find("mimic"), el.find("axis")
    get = (lambda k: None) if lim is None else (lambda k: _float(lim.get(k)))
    return JointSpec(
        name=el.get("name"), type=el.get("type"), parent=_link_of(el, "parent"), child=_link_of(el, "child"),
        origin=_origin(el.find("origin")),
        axis=np.array([1.0, 0.0, 0.0]) if axis is None else _floats(axis.get("xyz", "1 0 0"), 3),
        mimic=None if mimic is None else (mimic.get("joint"), float(mimic.get("multiplier", 1.0)),
                                          float(mimic.get("offset", 0.0))),
        lower=get("lower"), upper=get("upper"), velocity=get("velocity"), effort=get("effort"))


def _read(path_or_xml, what):
    """``what(root)`` on a parsed URDF; a malformed element is refused with the file and the fix."""
    root, where = _root(path_or_xml)
    try:
        return what(root)
    except (ValueError, TypeError, AttributeError) as e:  # a missing element or attribute, a bad number
        raise ValueError(f"could not parse URDF {where[:200]!r}: {e}. {_FIX}") from None


def load_joints(path_or_xml) -> tuple[str, list[JointSpec], None]:
    """Parse a URDF (path or XML string). Returns (robot name, joints in file order, None: the
    place of a parser object that nothing reads). Meshes referenced with ``package://`` need not
    exist."""
    name, joints = _read(path_or_xml, lambda r: (r.get("name"), [_joint(j) for j in r.findall("joint")]))
    if not joints:
        raise ValueError("the URDF has no joints; torchcal needs at least one joint")
    return name, joints, None


def urdf_links(path_or_xml) -> list[str]:
    """Names of all links in a URDF."""
    return _read(path_or_xml, lambda r: [l.get("name") for l in r.findall("link")])


def _fmt(v) -> str:
    return " ".join(repr(float(x)) for x in v)


def write_urdf(name: str, joints: list[JointSpec], path: str | os.PathLike | None = None,
               inertials: dict | None = None, comment: str | None = None) -> str:
    """Write a kinematic URDF from joint specs (origins as xyz/rpy with 17 significant digits).

    ``inertials`` maps link name -> dict(mass kg, com (3,) m, inertia (ixx, ixy, ixz, iyy, iyz, izz)
    kg m^2 about the COM). Returns the XML text and writes it to ``path`` when given.
    """

    links = []
    for j in joints:
        for l in (j.parent, j.child):
            if l not in links:
                links.append(l)
    out = ['<?xml version="1.0"?>']
    if comment:
        out.append("<!--\n" + comment.replace("--", "- -") + "\n-->")
    out.append(f'<robot name="{name}">')
    for l in links:
        inert = (inertials or {}).get(l)
        if inert is None:
            out.append(f'  <link name="{l}"/>')
            continue
        I = inert["inertia"]
        out += [f'  <link name="{l}">', "    <inertial>",
                f'      <origin xyz="{_fmt(inert["com"])}" rpy="0 0 0"/>',
                f'      <mass value="{float(inert["mass"])!r}"/>',
                f'      <inertia ixx="{I[0]!r}" ixy="{I[1]!r}" ixz="{I[2]!r}" iyy="{I[3]!r}" iyz="{I[4]!r}" izz="{I[5]!r}"/>',
                "    </inertial>", "  </link>"]
    for j in joints:
        T = np.asarray(j.origin, dtype=float)
        rpy = matrix_to_rpy(torch.as_tensor(T[:3, :3])).numpy()
        out.append(f'  <joint name="{j.name}" type="{j.type}">')
        out.append(f'    <parent link="{j.parent}"/>')
        out.append(f'    <child link="{j.child}"/>')
        out.append(f'    <origin xyz="{_fmt(T[:3, 3])}" rpy="{_fmt(rpy)}"/>')
        if j.type != "fixed":
            out.append(f'    <axis xyz="{_fmt(j.axis)}"/>')
        if j.type in ("revolute", "prismatic"):
            lo = -np.pi if j.lower is None else j.lower
            hi = np.pi if j.upper is None else j.upper
            out.append(f'    <limit lower="{lo!r}" upper="{hi!r}" effort="{_or(j.effort, 0.0)!r}" '
                       f'velocity="{_or(j.velocity, 0.0)!r}"/>')
        if j.mimic is not None:
            out.append(f'    <mimic joint="{j.mimic[0]}" multiplier="{j.mimic[1]!r}" offset="{j.mimic[2]!r}"/>')
        out.append("  </joint>")
    out.append("</robot>")
    xml = "\n".join(out) + "\n"
    if path is not None:
        Path(path).write_text(xml)
    return xml


def read_inertials(path_or_xml) -> dict[str, dict]:
    """Link inertials of a URDF: link name -> dict(mass kg, com (3,) m in the link frame).
    Links without an ``<inertial>`` or with zero mass are left out."""

    def inertials(root) -> dict[str, dict]:
        out = {}
        for link in root.findall("link"):
            inert = link.find("inertial")
            mass = None if inert is None or inert.find("mass") is None else _float(inert.find("mass").get("value"))
            if mass is not None and mass > 0:
                out[link.get("name")] = {"mass": mass, "com": _origin(inert.find("origin"))[:3, 3].copy()}
        return out

    return _read(path_or_xml, inertials)


def _shape(c) -> dict | None:
    g = c.find("geometry")
    s = {"origin": _origin(c.find("origin"))}
    box, cyl, sph, mesh = (None if g is None else g.find(k) for k in ("box", "cylinder", "sphere", "mesh"))
    if box is not None:
        s.update(kind="box", size=_floats(box.get("size"), 3))
    elif cyl is not None:
        s.update(kind="cylinder", radius=float(cyl.get("radius")), length=float(cyl.get("length")))
    elif sph is not None:
        s.update(kind="sphere", radius=float(sph.get("radius")))
    elif mesh is not None:
        sc = mesh.get("scale")
        s.update(kind="mesh", filename=str(mesh.get("filename")),
                 scale=np.ones(3) if sc is None else np.broadcast_to(_floats(sc), (3,)).copy())
    else:
        return None
    return s


def read_collisions(path_or_xml) -> dict[str, list[dict]]:
    """Link collision shapes of a URDF: link name -> list of dicts with ``kind`` (``"box"``,
    ``"cylinder"``, ``"sphere"`` or ``"mesh"``), ``origin`` (4, 4) in the link frame (m), and
    ``size`` (3,) m, ``radius`` / ``length`` m, or ``filename`` and ``scale`` (3,). Mesh files
    are not opened here. Links without ``<collision>`` are left out."""

    def collisions(root) -> dict[str, list[dict]]:
        out: dict[str, list[dict]] = {}
        for link in root.findall("link"):
            for c in link.findall("collision"):
                s = _shape(c)
                if s is not None:
                    out.setdefault(link.get("name"), []).append(s)
        return out

    return _read(path_or_xml, collisions)
