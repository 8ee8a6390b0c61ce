"""Read and write URDF files (kinematics only: meshes are never loaded).

yourdfpy (and with it trimesh, a third of a second) is imported when a URDF is first parsed, not
when torchcal is: ``--help`` and a refusal at the door never parse one."""
from __future__ import annotations

import io
import os
import re
from pathlib import Path

import numpy as np
import torch
from lxml import etree

from torchcal.kinematics.transforms import matrix_to_rpy
from torchcal.kinematics.tree import JointSpec

__all__ = ["load_joints", "urdf_links", "write_urdf", "read_inertials", "read_collisions", "read_urdf_text"]


def _strict_parse(text: str, where: str) -> None:
    """yourdfpy parses in lxml's recover mode, which silently drops whatever follows an XML
    error (a truncated file loses its last joints): parse strictly first to say where it broke."""

    try:
        etree.fromstring(text.encode())
    except etree.XMLSyntaxError as e:
        raise ValueError(f"could not parse URDF {where}: {e}. It must be well-formed XML (every tag closed, quotes "
                         "matched) and load it again") from None


def read_urdf_text(path) -> str:
    """The text of a URDF file, refused with the file's name when it is not UTF-8 or is a xacro
    file (whose macros only ``xacro`` expands: read as URDF, their joints would be lost)."""
    p = Path(path)
    if p.is_dir():
        raise IsADirectoryError(f"URDF path {p} is a directory; give the .urdf file")
    try:
        text = p.read_bytes().decode("utf-8")
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


def _load(path_or_xml):
    import yourdfpy

    kw = dict(build_scene_graph=False, load_meshes=False, build_collision_scene_graph=False,
              load_collision_meshes=False)
    is_xml = isinstance(path_or_xml, str) and path_or_xml.lstrip().startswith("<")
    if is_xml:
        _refuse_xacro(path_or_xml, "the URDF string")
        _strict_parse(path_or_xml, "string")
    elif Path(path_or_xml).is_file() or Path(path_or_xml).is_dir():
        _strict_parse(read_urdf_text(path_or_xml), str(path_or_xml))
    try:
        if isinstance(path_or_xml, (str, os.PathLike)) and not str(path_or_xml).lstrip().startswith("<"):
            p = Path(path_or_xml)
            if not p.is_file():
                raise FileNotFoundError(f"URDF file not found: {p} (give the path to a .urdf file)")
            return yourdfpy.URDF.load(str(p), **kw)

        return yourdfpy.URDF.load(io.BytesIO(str(path_or_xml).encode()), **kw)
    except FileNotFoundError:
        raise
    except Exception as e:  # yourdfpy/lxml raise many types; say what the user can fix
        raise ValueError(f"could not parse URDF {str(path_or_xml)[:200]!r}: {e}. Check that it is "
                         "well-formed XML with a <robot> root and <link>/<joint> elements") from e


def load_joints(path_or_xml) -> tuple[str, list[JointSpec], object]:
    """Parse a URDF (path or XML string). Returns (robot name, joints in file order, the
    yourdfpy object for writing back). Meshes referenced with ``package://`` need not exist."""
    u = _load(path_or_xml)
    joints = []
    for j in u.robot.joints:
        lim = j.limit
        joints.append(JointSpec(
            name=j.name, type=j.type, parent=j.parent, child=j.child,
            origin=np.eye(4) if j.origin is None else np.asarray(j.origin, dtype=float),
            axis=np.array([1.0, 0.0, 0.0]) if j.axis is None else np.asarray(j.axis, dtype=float),
            mimic=None if j.mimic is None else (j.mimic.joint, float(j.mimic.multiplier or 1.0),
                                                float(j.mimic.offset or 0.0)),
            lower=None if lim is None or lim.lower is None else float(lim.lower),
            upper=None if lim is None or lim.upper is None else float(lim.upper),
            velocity=None if lim is None or lim.velocity is None else float(lim.velocity),
            effort=None if lim is None or lim.effort is None else float(lim.effort)))
    if not joints:
        raise ValueError("the URDF has no joints; torchcal needs at least one joint")
    return u.robot.name, joints, u


def urdf_links(path_or_xml) -> list[str]:
    """Names of all links in a URDF."""
    return [l.name for l in _load(path_or_xml).robot.links]


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
            out.append(f'    <limit lower="{lo!r}" upper="{hi!r}" effort="{float(j.effort or 0.0)!r}" '
                       f'velocity="{float(j.velocity or 0.0)!r}"/>')
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
    u = _load(path_or_xml)
    out = {}
    for l in u.robot.links:
        inert = l.inertial
        if inert is None or inert.mass is None or float(inert.mass) <= 0:
            continue
        T = np.eye(4) if inert.origin is None else np.asarray(inert.origin, dtype=float)
        out[l.name] = {"mass": float(inert.mass), "com": T[:3, 3].copy()}
    return out


def read_collisions(path_or_xml) -> dict[str, list[dict]]:
    """Link collision shapes of a URDF: link name -> list of dicts with ``kind`` (``"box"``,
    ``"cylinder"``, ``"sphere"`` or ``"mesh"``), ``origin`` (4, 4) in the link frame (m), and
    ``size`` (3,) m, ``radius`` / ``length`` m, or ``filename`` and ``scale`` (3,). Mesh files
    are not opened here. Links without ``<collision>`` are left out."""
    u = _load(path_or_xml)
    out: dict[str, list[dict]] = {}
    for l in u.robot.links:
        for c in l.collisions:
            g = c.geometry
            s = {"origin": np.eye(4) if c.origin is None else np.asarray(c.origin, dtype=float)}
            if g.box is not None:
                s.update(kind="box", size=np.asarray(g.box.size, dtype=float))
            elif g.cylinder is not None:
                s.update(kind="cylinder", radius=float(g.cylinder.radius), length=float(g.cylinder.length))
            elif g.sphere is not None:
                s.update(kind="sphere", radius=float(g.sphere.radius))
            elif g.mesh is not None:
                sc = g.mesh.scale
                s.update(kind="mesh", filename=str(g.mesh.filename),
                         scale=np.ones(3) if sc is None else np.broadcast_to(np.asarray(sc, dtype=float), (3,)).copy())
            else:
                continue
            out.setdefault(l.name, []).append(s)
    return out
