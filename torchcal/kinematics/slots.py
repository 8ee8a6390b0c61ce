"""The error parameters of a robot and the slots they move, laid out once from its structure.

A *slot* is one scalar of the model a parameter may move: a base coordinate, an entry of a joint
origin (six per URDF joint, four per DH row), a joint's zero offset, an entry of a marker's pose.
Parameters are the named errors the user sees (:attr:`Robot.param_names`); most move one slot,
a DH joint's zero offset is both its ``dtheta`` and its offset, and a DH row's ``phi`` slot is
moved by no parameter of its own (its slot gathers the padding index).
"""
from __future__ import annotations

from dataclasses import dataclass

from torchcal.kinematics.tree import JointSpec, Marker

__all__ = ["SlotLayout", "slot_layout", "BASE_NAMES"]

_ORIGIN_SLOTS = ("dx", "dy", "dz", "droll", "dpitch", "dyaw")
_DH_SLOTS = ("a", "d", "alpha", "phi")
# the instrument (base) frame's parameters of every robot, in their order: shifts (m), rotation vector (rad)
BASE_NAMES = ("base.x", "base.y", "base.z", "base.rx", "base.ry", "base.rz")
# DH errors read best grouped by row: a, d, alpha, theta
_DH_ORDER = {"da": 0, "dd": 1, "dalpha": 2, "dtheta": 3}


@dataclass(frozen=True)
class SlotLayout:
    """Parameters and slots of one robot.

    Attributes:
        param_names, param_units (``"m"``/``"rad"``), default_free: per parameter, in the order of
            a parameter vector: base, URDF origins (or DH rows, grouped by row), offsets, markers.
        slot_param: per slot, the name of the parameter that moves it (``None``: none does), in
            slot order: base (6), URDF origins (6 each), DH rows (4 each), offsets (one per
            actuated joint), markers (6 each).
        urdf_idx, dh_idx: the joints with a URDF origin and those with a DH row.
    """

    param_names: list[str]
    param_units: list[str]
    default_free: list[bool]
    slot_param: list[str | None]
    urdf_idx: list[int]
    dh_idx: list[int]


def _unit(slot: str, lengths: tuple[str, ...]) -> str:
    return "m" if slot in lengths else "rad"


def slot_layout(joints: list[JointSpec], joint_names: list[str], markers: list[Marker]) -> SlotLayout:
    """The layout of a robot with ``joints`` (kept, in chain order), actuated ``joint_names`` and
    ``markers``."""
    entries: list[tuple[str, str, bool]] = []  # (name, unit, free by default)
    slot_param: list[str | None] = []
    for n in BASE_NAMES:
        slot_param.append(n)
        entries.append((n, "m" if n[-1] in "xyz" and "r" not in n[5:] else "rad", True))
    urdf_idx = [j for j, jt in enumerate(joints) if jt.dh is None]
    dh_idx = [j for j, jt in enumerate(joints) if jt.dh is not None]
    for j in urdf_idx:
        for s in _ORIGIN_SLOTS:
            n = f"{joints[j].name}.{s}"
            slot_param.append(n)
            entries.append((n, _unit(s, ("dx", "dy", "dz")), True))
    dh_entries = {}
    for j in dh_idx:
        for s in _DH_SLOTS:
            n = joints[j].dh.names.get(s)
            slot_param.append(n)
            if n is not None:
                dh_entries[n] = (n, _unit(s, ("a", "d")), True)
    by_name = {jt.name: jt for jt in joints}
    for n in joint_names:
        jt = by_name[n]
        on = jt.offset_name or f"{n}.offset"
        slot_param.append(on)
        entry = (on, "m" if jt.type == "prismatic" else "rad", True)
        if jt.dh is not None:
            dh_entries.setdefault(on, entry)
        else:
            entries.append(entry)
    for mk in markers:
        for s in _ORIGIN_SLOTS:
            n = f"{mk.name}.{s}"
            slot_param.append(n)
            entries.append((n, _unit(s, ("dx", "dy", "dz")), s in ("dx", "dy", "dz")))
    if dh_entries:
        row = {jt.name: i for i, jt in enumerate(joints)}

        def key(e):
            joint, slot = e[0].rsplit(".", 1)
            return row.get(joint, len(row)), _DH_ORDER.get(slot, 9)

        entries = entries[:6] + sorted(dh_entries.values(), key=key) + entries[6:]
    return SlotLayout([e[0] for e in entries], [e[1] for e in entries], [e[2] for e in entries], slot_param,
                      urdf_idx, dh_idx)
