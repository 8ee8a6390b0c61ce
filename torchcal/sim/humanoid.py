"""Humanoid robots as URDF text for the independent simulator, link inertials from boxes of given
size and mass (m, kg): a 19-joint upper body (torso, head, two seven-joint arms) and a 9-joint arm
(two torso joints and a seven-joint arm with a gripper)."""
from __future__ import annotations

import math

__all__ = ["ARM", "ARM7", "HEAD", "TORSO", "TORSO2", "arm9_urdf", "humanoid_urdf"]


# Chains of (joint, child link, origin xyz m, axis, limits rad, child mass kg, COM m, inertia box m); each
# joint's parent is the previous child.  The arm is the left one (y > 0); the right one mirrors it in x-z.
TORSO = [("torso_yaw", "torso_yaw_link", (0, 0, .12), "z", (-1, 1), 2.0, (0, 0, .03), (.15, .15, .06)),
          ("torso_pitch", "torso_pitch_link", (0, 0, .06), "y", (-.3, .8), 2.0, (0, 0, .02), (.15, .15, .05)),
          ("torso_roll", "chest_link", (0, 0, .05), "x", (-.4, .4), 15.0, (.02, 0, .22), (.25, .38, .45))]


HEAD = [("head_yaw", "neck_link", (0, 0, .45), "z", (-1.3, 1.3), 0.5, (0, 0, .03), (.06, .06, .08)),
         ("head_pitch", "head_link", (0, 0, .08), "y", (-.5, .8), 3.0, (.02, 0, .1), (.2, .16, .24))]


ARM = [("shoulder_pitch", "shoulder_pitch_link", (0, .2, .38), "y", (-2.8, 1.2), 1.0, (0, .03, 0), (.1, .08, .1)),
        ("shoulder_roll", "shoulder_roll_link", (0, .06, 0), "x", (-.3, 2.6), .8, (0, 0, -.02), (.08, .08, .08)),
        ("shoulder_yaw", "upper_arm_link", (0, 0, -.05), "z", (-2, 2), 2.5, (0, 0, -.14), (.09, .09, .28)),
        ("elbow", "forearm_link", (.02, 0, -.28), "y", (-2.4, .05), 1.5, (.01, 0, -.12), (.07, .07, .25)),
        ("wrist_yaw", "wrist_yaw_link", (0, 0, -.25), "z", (-2, 2), .4, (0, 0, -.015), (.06, .06, .04)),
        ("wrist_pitch", "wrist_pitch_link", (0, 0, -.03), "y", (-1.2, 1.2), .3, (0, 0, -.015), (.05, .05, .04)),
        ("wrist_roll", "wrist_roll_link", (0, 0, -.03), "x", (-1.2, 1.2), .8, (0, 0, -.06), (.04, .09, .15))]

# The 9-joint arm: torso yaw and pitch carry the chest; the arm's last joint turns the hand about
# its own long axis (z), so the gripper's origin lies on that axis.
TORSO2 = [TORSO[0], ("torso_pitch", "chest_link", (0, 0, .06), "y", (-.3, .8), 15.0, (.02, 0, .22), (.25, .38, .45))]
ARM7 = ARM[:6] + [("wrist_roll", "wrist_roll_link", (0, 0, -.03), "z", (-2.5, 2.5), .3, (0, 0, -.02),
                   (.05, .05, .04))]

_HEADER = ['<?xml version="1.0"?>', '<robot name="{name}">', '<link name="base_link"><inertial><origin xyz="0 0 0.05"/>'
           '<mass value="8"/><inertia ixx="0.1" ixy="0" ixz="0" iyy="0.075" iyz="0" izz="0.14"/></inertial></link>']


def _v(t) -> str:
    return " ".join(f"{x:g}" for x in t)


def _chain(out: list[str], parent: str, rows, side: str = "", y: int = 1, rpy=(0, 0, 0)) -> None:
    """Append links and revolute joints of ``rows`` to ``out``; ``y = -1`` mirrors them in x-z."""
    for joint, child, xyz, axis, lim, mass, com, box in rows:
        child = side + child
        a, b, c = (x * x for x in box)
        lim = lim if y > 0 or axis == "y" else (-lim[1], -lim[0])  # mirroring flips x and z rotations
        out.append(f'<link name="{child}"><inertial><origin xyz="{_v((com[0], y * com[1], com[2]))}"/><mass '
                   f'value="{mass}"/><inertia ixx="{mass * (b + c) / 12:.6g}" ixy="0" ixz="0" '
                   f'iyy="{mass * (a + c) / 12:.6g}" iyz="0" izz="{mass * (a + b) / 12:.6g}"/></inertial></link>')
        out.append(f'<joint name="{side}{joint}_joint" type="revolute"><parent link="{parent}"/><child '
                   f'link="{child}"/><origin xyz="{_v((xyz[0], y * xyz[1], xyz[2]))}" rpy="{_v(rpy)}"/><axis '
                   f'xyz="{_v([float(axis == k) for k in "xyz"])}"/><limit lower="{lim[0]}" upper="{lim[1]}" '
                   'effort="100" velocity="2"/></joint>')
        parent, rpy = child, (0, 0, 0)


def humanoid_urdf() -> str:
    """A synthetic humanoid upper body; a test robot, not a real one.  Fixed ``base_link``
    (pelvis, 8 kg), torso yaw/pitch/roll, two 7-joint arms (shoulder pitch/roll/yaw, elbow,
    wrist yaw/pitch/roll) on ``chest_link`` (15 kg), head yaw/pitch: 19 revolute joints.  Tool
    links ``l_hand``/``r_hand`` 0.1 m beyond the wrists, and ``head_link`` (3 kg).  Adult-size
    lengths (upper arm 0.28 m, forearm 0.25 m) and masses (upper arm 2.5, forearm 1.5, hand 0.8
    kg); box inertias about the COM; shoulders mounted with a 0.15 rad outward roll."""
    out = [h.format(name="humanoid_upper_body") for h in _HEADER]
    _chain(out, "base_link", TORSO)
    for side, y in (("l_", 1), ("r_", -1)):
        _chain(out, "chest_link", ARM, side, y, (y * 0.15, 0, 0))
        out.append(f'<link name="{side}hand"/><joint name="{side}hand_joint" type="fixed"><parent link="{side}'
                   f'wrist_roll_link"/><child link="{side}hand"/><origin xyz="0 0 -0.1" rpy="0 {math.pi / 2} 0"/>'
                   '</joint>')
    _chain(out, "chest_link", HEAD)
    return "\n".join(out + ["</robot>"]) + "\n"


def arm9_urdf() -> str:
    """A synthetic 9-joint humanoid arm; a test robot, not a real one.  Fixed ``base_link`` (8 kg),
    torso yaw and pitch (the chest, 15 kg), then a 7-joint arm as in :func:`humanoid_urdf`
    (shoulder pitch/roll/yaw, elbow, wrist yaw/pitch) whose last joint, ``wrist_roll_joint``,
    turns about the hand's long axis (z).  ``gripper_link`` (0.6 kg) sits 0.12 m beyond the wrist
    on that axis: a point declared at its origin lies on the last joint's axis."""
    out = [h.format(name="humanoid_arm9") for h in _HEADER]
    _chain(out, "base_link", TORSO2)
    _chain(out, "chest_link", ARM7, rpy=(0.15, 0, 0))
    out.append('<link name="gripper_link"><inertial><origin xyz="0 0 -0.05"/><mass value="0.6"/><inertia '
               'ixx="0.0012" ixy="0" ixz="0" iyy="0.001" iyz="0" izz="0.0008"/></inertial></link>')
    out.append('<joint name="gripper_joint" type="fixed"><parent link="wrist_roll_link"/><child link="gripper_link"/>'
               '<origin xyz="0 0 -0.12" rpy="0 0 0"/></joint>')
    return "\n".join(out + ["</robot>"]) + "\n"
