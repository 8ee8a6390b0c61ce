"""A URDF checked as strictly as a measurement CSV, before anything is built from it.

yourdfpy reads what it can: a vector with four numbers keeps three, ``nan`` in an axis becomes
another axis further on, a link named twice is one link. A calibration built on such a robot is
wrong without a word. Here every number the kinematics, inertials or collisions read must be a
finite number, every vector must hold exactly its three numbers, link and joint names must be
unique, every joint must have one parent and one child that are links of the file, every link at
most one parent joint, and every moving joint a non-zero finite axis. A refusal names the element,
its line and the fix.

Text handling lives here too: a UTF-8 byte-order mark is accepted (editors on Windows write one),
and file content is never taken for a path (:func:`is_urdf_text`).
"""
from __future__ import annotations

import math

from lxml import etree

__all__ = ["check_urdf_tree", "parse_checked", "strip_bom", "is_urdf_text"]

_BOM = "\ufeff"

# attribute -> how many numbers it holds, per element tag (the URDF specification's numeric attributes)
_VECTORS = {"origin": {"xyz": 3, "rpy": 3}, "axis": {"xyz": 3}, "box": {"size": 3}, "mesh": {"scale": 3}}
_SCALARS = {"mass": ("value",), "inertia": ("ixx", "ixy", "ixz", "iyy", "iyz", "izz"), "cylinder": ("radius", "length"),
            "sphere": ("radius",), "capsule": ("radius", "length"), "limit": ("lower", "upper", "effort", "velocity"),
            "mimic": ("multiplier", "offset"), "dynamics": ("damping", "friction"),
            "calibration": ("rising", "falling"),
            "safety_controller": ("soft_lower_limit", "soft_upper_limit", "k_position", "k_velocity")}
_REQUIRED = {"mass": ("value",), "cylinder": ("radius", "length"), "sphere": ("radius",)}


def strip_bom(text: str) -> str:
    """``text`` without a leading UTF-8 byte-order mark."""
    return text[1:] if text.startswith(_BOM) else text


def is_urdf_text(obj) -> bool:
    """Whether ``obj`` is URDF text rather than a path: a string whose first character (after a
    byte-order mark and white space) is ``<``, or one that no file system takes for a path (a line
    break in it). Content is never opened as a file name."""
    if not isinstance(obj, str):
        return False
    s = strip_bom(obj).lstrip()
    return s.startswith("<") or "\n" in s


class _Where:
    def __init__(self, source: str):
        self.source = source

    def refuse(self, el, problem: str, fix: str) -> None:
        owner = el
        while owner is not None and owner.tag not in ("joint", "link"):
            owner = owner.getparent()
        of = "" if owner is None or owner is el else f" of {owner.tag} {owner.get('name')!r}"
        name = f" {el.get('name')!r}" if el.tag in ("joint", "link") and el.get("name") else ""
        raise ValueError(f"URDF {self.source}, line {el.sourceline}: <{el.tag}>{name}{of}: {problem}; {fix}")


def _numbers(text: str) -> list[float] | None:
    try:
        return [float(t) for t in text.split()]
    except ValueError:
        return None


def _check_numbers(el, w: _Where) -> None:
    for attr, n in _VECTORS.get(el.tag, {}).items():
        text = el.get(attr)
        if text is None:
            continue
        vals = _numbers(text)
        if vals is None or len(vals) != n or not all(math.isfinite(v) for v in vals):
            w.refuse(el, f'{attr}="{text}" must be {n} finite numbers separated by spaces',
                     f'write e.g. {attr}="{"0 0 1" if el.tag == "axis" else " ".join(["0"] * n)}"')
    for attr in _SCALARS.get(el.tag, ()):
        text = el.get(attr)
        if text is None:
            if attr in _REQUIRED.get(el.tag, ()):
                w.refuse(el, f"the attribute {attr!r} is missing", f"give {attr}=\"…\" (a finite number)")
            continue
        vals = _numbers(text)
        if vals is None or len(vals) != 1 or not math.isfinite(vals[0]):
            w.refuse(el, f'{attr}="{text}" is not one finite number', f"write one number, e.g. {attr}=\"0\"")
    if el.tag == "box" and el.get("size") is None:
        w.refuse(el, "the attribute 'size' is missing", 'give size="x y z" in metres')


def _one(joint, tag: str, w: _Where) -> str:
    found = joint.findall(tag)
    if len(found) != 1:
        w.refuse(joint, f"has {len(found)} <{tag}> elements", f"give exactly one <{tag} link=\"…\"/>")
    link = found[0].get("link")
    if not link:
        w.refuse(found[0], "has no link attribute", f"write <{tag} link=\"LINK_NAME\"/>")
    return link


def _names(elements, kind: str, w: _Where) -> dict:
    seen: dict = {}
    for el in elements:
        name = el.get("name")
        if not name:
            w.refuse(el, f"a {kind} without a name", f"give every <{kind}> a unique name=\"…\"")
        if name in seen:
            w.refuse(el, f"the {kind} name {name!r} is used again (first on line {seen[name].sourceline})",
                     f"give every {kind} a unique name")
        seen[name] = el
    return seen


_URDF_TYPES = ("revolute", "continuous", "prismatic", "fixed", "floating", "planar")


def _check_joint(j, links: dict, joints: dict, parent_of: dict, w: _Where) -> None:
    if j.get("type") not in _URDF_TYPES:
        w.refuse(j, f"type {j.get('type')!r} is not a URDF joint type" if j.get("type") else "has no type attribute",
                 f"give type=\"…\", one of {', '.join(_URDF_TYPES)}")
    parent, child = _one(j, "parent", w), _one(j, "child", w)
    for role, link in (("parent", parent), ("child", child)):
        if link not in links:
            w.refuse(j.find(role), f"names link {link!r}, which no <link> defines",
                     f"add <link name=\"{link}\"/> or correct the name")
    if child in parent_of:
        w.refuse(j, f"link {child!r} already has the parent joint {parent_of[child].get('name')!r} (line "
                    f"{parent_of[child].sourceline})", "a link has at most one parent joint: remove one")
    parent_of[child] = j
    for tag in ("origin", "axis", "limit", "mimic"):
        if len(j.findall(tag)) > 1:
            w.refuse(j, f"has {len(j.findall(tag))} <{tag}> elements", f"keep one <{tag}>")
    axis = j.find("axis")
    if j.get("type") in ("revolute", "continuous", "prismatic") and axis is not None and axis.get("xyz") is not None:
        vals = _numbers(axis.get("xyz"))
        if vals is not None and math.sqrt(sum(v * v for v in vals)) < 1e-12:
            w.refuse(axis, f'xyz="{axis.get("xyz")}" is a zero axis', 'give the unit axis of motion, e.g. xyz="0 0 1"')
    lim = j.find("limit")
    if lim is not None and lim.get("lower") is not None and lim.get("upper") is not None \
            and float(lim.get("lower")) > float(lim.get("upper")):
        w.refuse(lim, f'lower="{lim.get("lower")}" is above upper="{lim.get("upper")}"', "swap them")
    mimic = j.find("mimic")
    if mimic is not None and mimic.get("joint") not in joints:
        w.refuse(mimic, f"joint {j.get('name')!r} mimics {mimic.get('joint')!r}, which is not in the URDF",
                 "name a <joint> of the file")


def check_urdf_tree(root, source: str) -> None:
    """Refuse (``ValueError``, naming ``source``, the element and its line) a parsed URDF whose
    numbers, vectors, names or tree are malformed; see the module docstring."""
    w = _Where(source)
    if root.tag != "robot":
        w.refuse(root, "the root element is not <robot>", "a URDF's root element is <robot name=\"…\">")
    if not root.get("name"):
        w.refuse(root, "has no name attribute", "give the robot a name: <robot name=\"my_robot\">")
    links = _names(root.findall("link"), "link", w)
    joints = _names(root.findall("joint"), "joint", w)
    for el in list(links.values()) + list(joints.values()):
        for sub in el.iter():
            if isinstance(sub.tag, str):
                _check_numbers(sub, w)
    parent_of: dict = {}
    for j in joints.values():
        _check_joint(j, links, joints, parent_of, w)
    _check_tree(root, links, parent_of, w)


def _check_tree(root, links: dict, parent_of: dict, w: _Where) -> None:
    """One root, and no link its own ancestor."""
    for link in links:
        seen, at = {link}, link
        while at in parent_of:
            at = parent_of[at].find("parent").get("link")
            if at in seen:
                w.refuse(parent_of[link], f"link {link!r} is its own ancestor (the joints form a loop)",
                         "a URDF is a tree: remove the joint that closes the loop")
            seen.add(at)
    roots = [n for n in links if n not in parent_of]
    if len(roots) > 1:
        w.refuse(root, f"the links {roots[:4]} have no parent joint: the URDF is {len(roots)} trees, not one",
                 "join each to the robot with a joint, or delete the links that belong to nothing")


def parse_checked(text: str, source: str):
    """Parse ``text`` strictly (lxml, no recovery) and check it; return the root element."""
    try:
        root = etree.fromstring(strip_bom(text).encode())
    except etree.XMLSyntaxError as e:
        raise ValueError(f"could not parse URDF {source}: {e}. It must be well-formed XML (every tag closed, quotes "
                         "matched) and load it again") from None
    check_urdf_tree(root, source)
    return root
