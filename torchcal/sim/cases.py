"""Data sets for the loop nobody here declared: each a failure seen on held-back data, made by the
independent simulator :mod:`torchcal.sim.physsim` (its own URDF parser, kinematics and gravity; no
torchcal effect class is involved).

Set-ups follow the issue that describes them: a 6R arm with link inertials (the UR5e), 300
training and 150 held-out poses, tracker noise 0.02 mm per axis, the instrument 3 m away at a
random rotation, geometric errors of 0.5 mm and 1 mrad on every joint origin; the humanoid upper
body has 19 joints, three motion-capture markers, 500 + 150 poses and 0.3 mm noise. The noise
floor is the mean Euclidean norm of the simulated noise on the held-out rows.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from torchcal.sim.humanoid import humanoid_urdf
from torchcal.sim.physsim import PhysicalRobot, warmup_temperature
from torchcal.sim.sample import Sample

__all__ = ["CASES", "Case", "make_case", "TORSION"]

TORSION = {"shoulder_lift_joint": 6e-6, "elbow_joint": 9e-6, "wrist_1_joint": 20e-6}  # rad/(N·m), joints 2-4

_UR5E = dict(robot="ur5e", markers=["tool@flange"], n_train=300, n_test=150, noise_m=0.02e-3)
_HUMANOID = dict(robot="humanoid", n_train=500, n_test=150, noise_m=0.3e-3, length_error_m=1e-3,
                 angle_error_rad=2e-3, markers=["lh@l_hand=0.0,0.0,0.08", "rh@r_hand=0.0,0.0,0.08",
                                                "hd@head_link=0.08,0,0.1"],
                 declared=["lh@l_hand", "rh@r_hand", "hd@head_link"])

CASES: dict[str, dict] = {
    # an undeclared tool, position unknown, on an arm whose joints 2-4 give under gravity
    "payload_12kg": {**_UR5E, "named": ["joint_compliance"],
                     "physics": dict(payload_kg=12.0, payload_com_m=(0.04, -0.03, 0.12), torsion=TORSION)},
    "payload_0kg": {**_UR5E, "named": ["joint_compliance"], "physics": dict(payload_kg=0.0, torsion=TORSION)},
    "payload_20kg": {**_UR5E, "named": ["joint_compliance"],
                     "physics": dict(payload_kg=20.0, payload_com_m=(-0.05, 0.02, 0.2), torsion=TORSION)},
    # an aluminium segment next to a warm motor: one link grows over a 15 K warm-up
    "one_warm_link": {**_UR5E, "named": ["thermal_drift"], "warmup_k": 15.0,
                      "physics": dict(thermal={"elbow_joint": 2.3e-5})},
    # gravity bends joints sideways
    "lateral": {**_UR5E, "named": ["elastic_deformation"],
                "physics": dict(payload_kg=5.0, payload_com_m=(0.0, 0.0, 0.1),
                                lateral={"shoulder_lift_joint": (10e-6, 0.0, 0.0), "elbow_joint": (0.0, 8e-6, 0.0)})},
    # the same, but the bearings' seats in the parent links give way: bent before the joints turn
    "lateral_seat": {**_UR5E, "named": ["elastic_deformation"],
                     "physics": dict(payload_kg=5.0, payload_com_m=(0.0, 0.0, 0.1), lateral_frame="parent",
                                     lateral={"shoulder_lift_joint": (10e-6, 0.0, 0.0),
                                              "elbow_joint": (0.0, 8e-6, 0.0)})},
    # a base on a compliant floor, tilting towards the overturning moment
    "tilting_base": {**_UR5E, "named": ["elastic_deformation"],
                     "physics": dict(payload_kg=5.0, payload_com_m=(0.0, 0.0, 0.1), base_tilt=(3e-6, 3e-6))},
    "clean": {**_UR5E, "named": [], "physics": {}},
    # a compliant arm with 5 % of the training rows moved by 5-20 mm (a bumped reflector)
    "outliers": {**_UR5E, "named": ["joint_compliance"], "outliers": 0.05,
                 "physics": dict(payload_kg=3.0, payload_com_m=(0.0, 0.0, 0.08),
                                 torsion={"shoulder_lift_joint": 2e-5, "elbow_joint": 2e-5, "wrist_1_joint": 3e-5})},
    # a humanoid upper body whose joints twist and whose torso bends sideways
    "humanoid": {**_HUMANOID, "named": ["joint_compliance", "elastic_deformation"],
                 "physics": dict(payload_kg=1.0, payload_com_m=(0, 0, 0.05),
                                 torsion={"torso_pitch_joint": 3e-5, "l_shoulder_pitch_joint": 2e-4,
                                          "r_shoulder_pitch_joint": 2e-4, "l_elbow_joint": 3e-4,
                                          "r_elbow_joint": 3e-4},
                                 lateral={"torso_yaw_joint": (4e-5, 4e-5, 0.0), "l_shoulder_roll_joint": (2e-4, 0, 0),
                                          "r_shoulder_roll_joint": (2e-4, 0, 0)})},
}


@dataclass
class Case:
    """One simulated data set: the "real" robot (its truth), training and held-out samples, the
    noise floor (mm), the URDF text and the markers to declare (unknown points on their links)."""

    name: str
    real: PhysicalRobot
    train: Sample
    test: Sample
    floor_mm: float
    urdf: str
    markers: list[str]
    named: list[str]


def _urdf(name: str) -> str:
    if name == "humanoid":
        return humanoid_urdf()
    return (Path(__file__).resolve().parents[2] / "urdf" / f"{name}.urdf").read_text()


def make_case(name: str, seed: int = 0, outliers: float | None = None, urdf: str | None = None) -> Case:
    """The data set ``name`` of :data:`CASES` drawn with ``seed``; ``outliers`` overrides the
    fraction of training rows moved by 5-20 mm; ``urdf`` replaces the robot's description."""
    if name not in CASES:
        raise ValueError(f"unknown case {name!r}; cases: {sorted(CASES)}")
    c = CASES[name]
    text = urdf or _urdf(c["robot"])
    extra = {k: c[k] for k in ("length_error_m", "angle_error_rad") if k in c}
    real = PhysicalRobot(text, c["markers"], seed=seed, noise_m=c["noise_m"], **extra, **c["physics"])
    n, m = c["n_train"], c["n_test"]
    q = real.sample_q(n + m)
    temp = warmup_temperature(n + m, span_k=c["warmup_k"], seed=seed) if "warmup_k" in c else None
    frac = c.get("outliers", 0.0) if outliers is None else outliers
    train = real.measure(q[:n], temperature=None if temp is None else temp[:n], outlier_fraction=frac)
    test = real.measure(q[n:], temperature=None if temp is None else temp[n:])
    floor = float(np.linalg.norm(test.true_positions - test.positions, axis=-1).mean()) * 1e3
    declared = c.get("declared", [mk.split("=")[0] for mk in c["markers"]])
    return Case(name, real, train, test, floor, text, declared, list(c["named"]))
