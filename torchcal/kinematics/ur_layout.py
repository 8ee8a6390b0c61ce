"""A Universal Robots arm's own calibration layout: ``ur_description``'s ``default_kinematics.yaml``,
which the UR macro (``ur_macro.xacro``) reads with ``xacro.load_yaml``::

    kinematics:
      shoulder:  {x: …, y: …, z: …, roll: …, pitch: …, yaw: …}   # origin of shoulder_pan_joint
      upper_arm: {…}                                              # shoulder_lift_joint
      forearm:   {…}                                              # elbow_joint
      wrist_1:   {…}                                              # wrist_1_joint
      wrist_2:   {…}                                              # wrist_2_joint
      wrist_3:   {…}                                              # wrist_3_joint
      hash: calib_…

Every key is present (an unchanged joint too: the macro reads all six), metres and radians,
``R = Rz(yaw) Ry(pitch) Rx(roll)``, each the joint's whole origin (not a correction).
"""
from __future__ import annotations

from typing import Sequence

__all__ = ["UR_KEYS", "ur_joints"]

# the layout's key -> the UR joint whose <origin> it holds, in the chain's order
UR_KEYS = {"shoulder": "shoulder_pan_joint", "upper_arm": "shoulder_lift_joint", "forearm": "elbow_joint",
           "wrist_1": "wrist_1_joint", "wrist_2": "wrist_2_joint", "wrist_3": "wrist_3_joint"}


def ur_joints(joints: Sequence) -> dict[str, str] | None:
    """The layout's key -> the robot's joint name when ``joints`` (JointSpecs) hold a UR arm: the
    six UR joint names under one common prefix (``ur_`` for ``ur_shoulder_pan_joint`` …), all
    revolute, each the child of the one before (a serial chain in the UR order). None otherwise."""
    by_name = {j.name: j for j in joints}
    for j in joints:
        if not j.name.endswith(UR_KEYS["shoulder"]):
            continue
        prefix = j.name[: -len(UR_KEYS["shoulder"])]
        chain = [by_name.get(prefix + name) for name in UR_KEYS.values()]
        if any(c is None or c.type not in ("revolute", "continuous") for c in chain):
            continue
        if all(b.parent == a.child for a, b in zip(chain, chain[1:])):
            return {key: c.name for key, c in zip(UR_KEYS, chain)}
    return None
