"""Robots documented by Denavit–Hartenberg tables.

A DH table becomes ordinary :class:`~torchcal.kinematics.tree.JointSpec` records whose origins remember their
DH values, so the error parameters are the textbook Δa, Δd, Δα, Δθ per row.

classic  (Craig's "standard", seed 000): ``A_i = Rz(θ_i + q_i) Tz(d_i) Tx(a_i) Rx(α_i)``
modified (Craig's):                      ``A_i = Rx(α_{i-1}) Tx(a_{i-1}) Rz(θ_i + q_i) Tz(d_i)``,
where, as in Craig's tables, row i lists α_{i-1} and a_{i-1} beside θ_i and d_i.

Prismatic rows move along z: ``d_i + q_i``. Their Δd is the joint zero offset, and their Δθ a
fixed rotation about z.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from torchcal.kinematics.tree import DHOrigin, JointSpec

__all__ = ["DHRow", "dh_joints"]


@dataclass
class DHRow:
    """One DH row (m, rad). ``theta`` is the constant added to the joint angle (revolute) or the
    fixed angle (prismatic); ``d`` likewise for prismatic rows."""

    a: float
    d: float
    alpha: float
    theta: float = 0.0
    type: str = "revolute"
    name: str | None = None
    lower: float | None = None
    upper: float | None = None
    velocity: float | None = None
    effort: float | None = None


def _rows(table) -> list[DHRow]:
    rows = []
    for i, r in enumerate(table):
        if isinstance(r, DHRow):
            rows.append(r)
        elif isinstance(r, dict):
            unknown = set(r) - set(DHRow.__dataclass_fields__)
            if unknown:
                raise ValueError(f"DH row {i + 1} has unknown keys {sorted(unknown)}; "
                                 f"use {sorted(DHRow.__dataclass_fields__)}")
            rows.append(DHRow(**r))
        else:
            vals = list(r)
            if len(vals) not in (3, 4):
                raise ValueError(f"DH row {i + 1} must be (a, d, alpha[, theta]) in m/rad or a dict, got {r!r}")
            rows.append(DHRow(*map(float, vals)))
        if rows[-1].type not in ("revolute", "prismatic", "continuous"):
            raise ValueError(f"DH row {i + 1}: type {rows[-1].type!r} is not revolute, continuous or prismatic")
    if not rows:
        raise ValueError("the DH table is empty")
    return rows


def dh_joints(table, convention: str = "classic", flange: str = "flange",
              tool: np.ndarray | None = None) -> list[JointSpec]:
    """Joint specs for a DH table. Links are ``link0`` (base) … ``link{n}``, then ``flange``
    after the last row's fixed transform (classic) or ``tool`` (either convention)."""
    if convention not in ("classic", "modified"):
        raise ValueError(f"convention must be 'classic' or 'modified', got {convention!r}")
    rows = _rows(table)
    n = len(rows)
    names = [r.name or f"joint_{i + 1}" for i, r in enumerate(rows)]
    joints: list[JointSpec] = []
    for i, r in enumerate(rows):
        prismatic = r.type == "prismatic"
        nm = names[i]
        if convention == "classic":
            prev = rows[i - 1] if i > 0 else None
            pn = names[i - 1] if i > 0 else None
            a, d, alpha = (prev.a, prev.d, prev.alpha) if prev else (0.0, 0.0, 0.0)
            slot_names = ({"a": f"{pn}.da", "d": f"{pn}.dd", "alpha": f"{pn}.dalpha"} if prev else {})
            if prev is not None and prev.type == "prismatic":  # its Δd is that joint's zero offset
                slot_names.pop("d")
        else:  # Craig's tables: row i holds alpha_{i-1}, a_{i-1}, theta_i, d_i
            a, d, alpha = r.a, r.d, r.alpha
            slot_names = {"a": f"{nm}.da", "d": f"{nm}.dd", "alpha": f"{nm}.dalpha"}
        if prismatic:
            slot_names["phi"] = f"{nm}.dtheta"
            if convention == "modified":  # Δd of a prismatic row is its zero offset
                slot_names.pop("d")
        origin = DHOrigin(convention, a, d, alpha, r.theta, slot_names)
        joints.append(JointSpec(
            name=nm, type="prismatic" if prismatic else r.type, parent=f"link{i}", child=f"link{i + 1}",
            origin=origin.matrix(), axis=np.array([0.0, 0.0, 1.0]), lower=r.lower, upper=r.upper,
            velocity=r.velocity, effort=r.effort, dh=origin,
            offset_name=(f"{nm}.dd" if prismatic else f"{nm}.dtheta")))
    if convention == "classic":
        last = rows[-1]
        fl = DHOrigin("classic", last.a, last.d, last.alpha, 0.0,
                      {"a": f"{names[-1]}.da", "d": f"{names[-1]}.dd", "alpha": f"{names[-1]}.dalpha"})
        if last.type == "prismatic":  # its Δd is already the joint offset
            fl.names.pop("d")
        joints.append(JointSpec(name=f"{flange}_joint", type="fixed", parent=f"link{n}", child=flange,
                                origin=fl.matrix(), dh=fl))
        end = flange
    else:
        end = f"link{n}"
    if tool is not None:
        joints.append(JointSpec(name="tool_joint", type="fixed", parent=end, child="tool",
                                origin=np.asarray(tool, dtype=float)))
    return joints
