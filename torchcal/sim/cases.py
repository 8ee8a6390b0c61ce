"""Data sets for the loop nobody here declared: each a failure seen on held-back data, made by the
independent simulator :mod:`torchcal.sim.physsim` (its own URDF parser, kinematics and gravity; no
torchcal effect class is involved).

Set-ups follow the issue that describes them: a 6R arm with link inertials (the UR5e), 300
training and 150 held-out poses, tracker noise 0.02 mm per axis, the instrument 3 m away at a
random rotation, geometric errors of 0.5 mm and 1 mrad on every joint origin; the humanoid upper
body has 19 joints, three motion-capture markers, 500 + 150 poses and 0.3 mm noise. The effects
nobody catalogued (issue 24) run on a 7-joint arm (the KUKA iiwa 14) with the UR5e cases'
tracker, errors and pose counts, and a reflector on a tool 6 cm off the flange axis. The noise
floor is the mean Euclidean norm of the simulated noise on the held-out rows.

:data:`GEOMETRY_CASES` (issue 23) are small geometric data sets with no other effect: a 9-joint
humanoid arm under motion capture, its marker declared on the last joint's axis, and a UR10-class
arm measured in full 6-D pose by a camera. :func:`make_case` makes both kinds.

Effect sizes in the comments ("size"): the displacement each effect causes at the marker on the
150 held-out poses, RMS of the per-point norm in µm, in total / beyond what a geometric fit on
the training poses absorbs (first order), seed 0 [range over seeds 1-6]; ``effect_sizes(name,
seed)`` recomputes them.  The noise floor of every 7-joint case is 32.9 µm at seed 0 [30.2-32.4].
In ``named``, the effect to be named first comes first: the larger one beyond geometry, but a
catalogued physical effect before the general joint-space family (``joint_terms``).
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from torchcal.sim.covariates import covariate_columns
from torchcal.sim.drift_cases import DRIFT_CASES, level_series, track_urdf
from torchcal.sim.effect_size import EFFECT_KEYS, displacement_um
from torchcal.sim.humanoid import arm9_urdf, humanoid_urdf
from torchcal.sim.physsim import PhysicalRobot, warmup_temperature
from torchcal.sim.physsim_drifts import Drift
from torchcal.sim.sample import Sample
from torchcal.sim.ur10 import ur10_urdf

__all__ = ["CASES", "GEOMETRY_CASES", "Case", "effect_sizes", "make_case", "TORSION"]

def _knocked_at_240(rows):
    return (rows >= 240).astype(float)[:, None] * np.array([0.15e-3, 0.0, -0.1e-3, 0.0, 0.25e-3, 0.0])


TORSION = {"shoulder_lift_joint": 6e-6, "elbow_joint": 9e-6, "wrist_1_joint": 20e-6}  # rad/(N·m), joints 2-4

_UR5E = dict(robot="ur5e", markers=["tool@flange"], n_train=300, n_test=150, noise_m=0.02e-3)
_HUMANOID = dict(robot="humanoid", n_train=500, n_test=150, noise_m=0.3e-3, length_error_m=1e-3,
                 angle_error_rad=2e-3, markers=["lh@l_hand=0.0,0.0,0.08", "rh@r_hand=0.0,0.0,0.08",
                                                "hd@head_link=0.08,0,0.1"],
                 declared=["lh@l_hand", "rh@r_hand", "hd@head_link"])

_IIWA = dict(robot="kuka_iiwa14", markers=["tool@flange=0.06,0.0,0.08"], declared=["tool@flange=0.06,0.0,0.08"],
             marker_error_m=1e-3, n_train=300, n_test=150, noise_m=0.02e-3)
BACKLASH_J1 = 5e-5  # rad, half play of the base axis
TORSION_7DOF = {"iiwa_joint_2": 1e-6, "iiwa_joint_4": 1.5e-6, "iiwa_joint_6": 6e-6}  # rad/(N·m)
SEAT_7DOF = {"iiwa_joint_2": (1e-6, 1e-6, 0.0), "iiwa_joint_4": (2e-6, 2e-6, 0.0)}  # rad/(N·m), seat x/y
TORSION_SOFT_7DOF = {k: 2 * v for k, v in TORSION_7DOF.items()}  # no tool: twice as soft, rad/(N·m)
HARMONICS_J4 = [(1, 1.2e-4, 0.3), (2, 8e-5, -1.0)]  # (harmonic, rad, phase rad)

CASES: dict[str, dict] = {
    # an undeclared tool, position unknown, on an arm whose joints 2-4 give under gravity
    "payload_12kg": {**_UR5E, "named": ["joint_compliance"],
                     "physics": dict(payload_kg=12.0, payload_com_m=(0.04, -0.03, 0.12), torsion=TORSION)},
    # the cell measured with four payloads, swapped every 25 poses and logged (kg): the joints twist by
    # what each row carries (issue 32's load-dependent stiffness, seen through a logged load)
    "logged_loads": {**_UR5E, "named": ["load_compliance"],
                     "covariates": {"payload_kg": ("payloads", {"masses": (0.0, 3.0, 6.0, 10.0)})},
                     "physics": dict(payload_column="payload_kg", payload_com_m=(0.03, 0.0, 0.12), torsion=TORSION)},
    # the same, each load logged by name in a text column (the empty gripper, a box, a pallet)
    "named_loads": {**_UR5E, "named": ["load_compliance"], "levels": {"load": ["empty", "box", "pallet"]},
                    "physics": dict(payload_column="level:load", payload_levels={"empty": 0.5, "box": 4.0, "pallet": 9.0},
                                    payload_com_m=(0.0, 0.04, 0.08), torsion=TORSION)},
    # the payload swapped once, 8 kg from row 225 on, and nothing logged: the simulator reads a column
    # the loop never sees ("hidden")
    "payload_swap": {**_UR5E, "named": ["joint_compliance", "load_compliance"],
                     "covariates": {"carried_kg": ("payload_swap", {"before": 0.0, "after": 8.0, "at": 0.5})},
                     "hidden": ["carried_kg"],
                     "physics": dict(payload_column="carried_kg", payload_com_m=(0.0, 0.03, 0.1), torsion=TORSION)},
    # the payload swapped (6 kg from row 150 on) and the tracker knocked at row 240, nothing logged: two
    # set-up changes in one session, the knock's step the easier to see
    "swap_and_knock": {**_UR5E, "named": ["joint_compliance", "load_compliance", "parameter_drivers"],
                       "covariates": {"carried_kg": ("payload_swap", {"before": 0.0, "after": 6.0, "at": 1 / 3})},
                       "hidden": ["carried_kg"],
                       "physics": dict(payload_column="carried_kg", payload_com_m=(0.02, 0.0, 0.09), torsion=TORSION,
                                       drifts=[Drift("instrument", "row", _knocked_at_240,
                                                     "the tracker knocked at row 240: 0.15 mm, 0.1 mm, 0.25 mrad")])},
    # clean, with logs that drive nothing: a payload column the robot never carries and an operator's name
    "clean_logs": {**_UR5E, "named": [], "levels": {"operator": ["ann", "bob", "cem"]},
                   "covariates": {"payload_kg": ("payloads", {"masses": (0.0, 5.0)})}, "physics": {}},
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
    # ---- issue 24: effects nobody catalogued, on a 7-joint arm
    # a wrist whose last axis turns with the one before (gear coupling), and play in the base axis.
    # size: coupling 113 / 100 µm [112-121 / 94-113]; backlash 32 / 32 µm [33 / 33-34] (the
    # loop's physical effects come before the general family, hence backlash first)
    "wrist_coupling": {**_IIWA, "named": ["backlash", "joint_terms"],
                       "physics": dict(joint_terms={"iiwa_joint_7": [("iiwa_joint_6", "linear", 2e-3)]},
                                       backlash={"iiwa_joint_1": BACKLASH_J1})},
    # a link that grows with its motor's temperature, logged in the second of two temperature
    # columns; the first (the hall's air) drives nothing.  The motor warms from 22 degC to 37-46
    # degC and swings with its duty (blocks of 30 rows); the air cycles by ±0.6 K (|correlation|
    # with the motor < 0.4 over 40 seeds).
    # size: 142 / 33 µm [136-196 / 28-64]: most of the growth is a mean length a geometric fit takes
    "thermal_second_column": {**_IIWA, "named": ["thermal_drift"],
                              "covariates": {"temp_ambient": ("ambient", {}),
                                             "temp_motor_a4": ("motor", {"rise_k": 25.0})},
                              "physics": dict(thermal={"iiwa_joint_4": (2.3e-5, "temp_motor_a4")})},
    # joints that twist, and two bearing seats that give way sideways, under an undeclared tool.
    # size: twist 104 / 59 µm [103-110 / 56-62]; seats 58 / 39 µm [58-65 / 37-40]; both 146 / 73 µm
    "twist_seat_7dof": {**_IIWA, "named": ["joint_compliance", "elastic_deformation"],
                        "physics": dict(payload_kg=8.0, payload_com_m=(0.0, 0.03, 0.12), torsion=TORSION_7DOF,
                                        lateral_frame="parent", lateral=SEAT_7DOF)},
    # transmission error of one joint (1st and 2nd harmonics of its own angle) on a twisting arm.
    # size: twist 94 / 54 µm [94-103 / 52-57]; harmonics 66 / 32 µm [60-66 / 31-35]; both 125 / 69 µm
    "harmonics_twist": {**_IIWA, "named": ["joint_compliance", "cyclic_joint_error"],
                        "physics": dict(torsion=TORSION_SOFT_7DOF, cyclic={"iiwa_joint_4": HARMONICS_J4})},
    # geometry only, with the logs of a real cell that drive nothing: air, a motor, the arm's
    # cover (degC) and the campaign's time (s, with a 10 min break every 50 poses)
    **DRIFT_CASES,
    "clean_covariates": {**_IIWA, "named": [], "physics": {},
                         "covariates": {"temp_ambient": ("ambient", {}), "temp_motor_a2": ("motor", {}),
                                        "temp_skin": ("skin", {}), "time": ("time", {})}},
}

GEOMETRY_CASES: dict[str, dict] = {
    # issue 23: motion capture of one point on the gripper of a 9-joint humanoid arm, declared at
    # the gripper's origin (on the last joint's axis) while the real point is 5.8 cm off it
    "arm9_mocap": dict(robot="arm9", n_train=45, n_test=16, noise_m=0.3e-3, length_error_m=2e-3, angle_error_rad=3e-3,
                       markers=["grip@gripper_link"], marker_true_m={"grip": (0.05, 0.03, -0.02)}, named=[],
                       physics={}),
    # issue 23: a camera 1.5 m away sees a 6-D target on the flange of a UR10-class arm (0.5 mm
    # and 2 mrad per axis); the tool frame is unknown: declared at the flange, the target sits on a
    # 45 mm standoff, 12 and 8 mm aside, turned by a few mrad (drawn, 5 mrad per axis)
    "pose6d": dict(robot="ur10", n_train=17, n_test=6, noise_m=0.5e-3, length_error_m=2e-3, angle_error_rad=3e-3,
                   markers=["target@flange"], marker_true_m={"target": (0.012, -0.008, 0.045)}, named=[], physics={},
                   base_distance_m=1.5, pose_markers=True, rot_noise_rad=2e-3, marker_rotation_error_rad=5e-3),
}
# the same with orientation on half the rows (a camera that lost the target's orientation)
GEOMETRY_CASES["pose6d_partial"] = {**GEOMETRY_CASES["pose6d"], "orientation_fraction": 0.5}


_ROBOT_KEYS = ("length_error_m", "angle_error_rad", "marker_error_m", "marker_true_m", "marker_rotation_error_rad",
               "base_distance_m", "pose_markers", "rot_noise_rad")


@dataclass
class Case:
    """One simulated data set: the "real" robot (its truth), training and held-out samples, the
    noise floor (mm; for pose data also ``rot_floor_mrad``, the mean angle of the orientation
    noise on the held-out rows that have one), the URDF text, the markers to declare (unknown
    points on their links) and the effects a loop should name."""

    name: str
    real: PhysicalRobot
    train: Sample
    test: Sample
    floor_mm: float
    urdf: str
    markers: list[str]
    named: list[str]
    rot_floor_mrad: float | None = None

    @property
    def error_support(self) -> dict:
        """Where the true geometry differs from the URDF (see :meth:`PhysicalRobot.error_support`);
        for scoring only, a solver never reads it."""
        return self.real.error_support()

    def true_parameters(self, marker_names: list[str], turns: bool = False) -> list[str]:
        """Glob patterns of torchcal's parameters for exactly the errors the simulator drew (and the
        instrument frame; with ``turns`` the markers' rotations too): the parameter set of "the true
        model", for scoring a calibration against its least-squares fit. Truth: never a solver's input."""
        sup = self.error_support
        out = (["base.*"] + [f"{j}.d*" for j in sup["joint_origins"]] + [f"{j}.offset" for j in sup["zero_offsets"]]
               + [f"{m}.d{a}" for m in sup["marker_offsets"] for a in "xyz"])
        return out + ([f"{m}.d{a}" for m in marker_names for a in ("roll", "pitch", "yaw")] if turns else [])


def _urdf(name: str) -> str:
    made = {"humanoid": humanoid_urdf, "arm9": arm9_urdf, "ur10": ur10_urdf, "ur5e_track": track_urdf}
    if name in made:
        return made[name]()
    return (Path(__file__).resolve().parents[2] / "urdf" / f"{name}.urdf").read_text()


def _spec(name: str) -> dict:
    if name not in CASES and name not in GEOMETRY_CASES:
        raise ValueError(f"unknown case {name!r}; cases: {sorted(CASES) + sorted(GEOMETRY_CASES)}")
    return CASES.get(name) or GEOMETRY_CASES[name]


def _robot(c: dict, text: str, seed: int, physics: dict) -> PhysicalRobot:
    extra = {k: c[k] for k in _ROBOT_KEYS if k in c}
    return PhysicalRobot(text, c["markers"], seed=seed, noise_m=c["noise_m"], **extra, **physics)


def _angle_mrad(qa: np.ndarray, qb: np.ndarray) -> np.ndarray:
    """Angles (mrad) between unit quaternions ``(..., 4)``."""
    return 2e3 * np.arccos(np.clip(np.abs(np.sum(qa * qb, -1)), 0.0, 1.0))


def make_case(name: str, seed: int = 0, outliers: float | None = None, urdf: str | None = None) -> Case:
    """The data set ``name`` of :data:`CASES` or :data:`GEOMETRY_CASES` drawn with ``seed``;
    ``outliers`` overrides the fraction of training rows moved by 5-20 mm; ``urdf`` replaces the
    robot's description.  Covariate logs are drawn over the whole campaign (training rows
    first) and split like the poses."""
    c = _spec(name)
    text = urdf or _urdf(c["robot"])
    real = _robot(c, text, seed, c["physics"])
    n, m = c["n_train"], c["n_test"]
    q = real.sample_q(n + m)
    temp = warmup_temperature(n + m, span_k=c["warmup_k"], seed=seed) if "warmup_k" in c else None
    logs = covariate_columns(c.get("covariates", {}), n + m, seed)
    frac = c.get("outliers", 0.0) if outliers is None else outliers
    levels = {k: level_series(v, n + m, [seed, 200 + i]) for i, (k, v) in enumerate(c.get("levels", {}).items())}
    # held-out rows from the same session (issue 32's time drift), else after the training rows
    order = np.random.default_rng([seed, 300]).permutation(n + m) if c.get("interleave") else np.arange(n + m)
    tr, te = np.sort(order[:n]), np.sort(order[n:])

    def rows(sl) -> dict:
        return dict(temperature=None if temp is None else temp[sl], covariates={k: v[sl] for k, v in logs.items()},
                    orientation_fraction=c.get("orientation_fraction", 1.0), levels={k: v[sl] for k, v in levels.items()})

    if c.get("interleave"):  # one session: every row measured in its order, then split
        full = real.measure(q, **rows(slice(None)))
        train, test = full.subset(tr), full.subset(te)
    else:
        train = real.measure(q[:n], outlier_fraction=frac, **rows(slice(0, n)))
        test = real.measure(q[n:], first_row=n, **rows(slice(n, None)))
    for k in c.get("hidden", ()):  # what the physics read but no log holds
        train.covariates.pop(k)
        test.covariates.pop(k)
    for k, col in c.get("coded", {}).items():  # a text column logged by number: level i -> i + 1
        for smp in (train, test):
            code = np.zeros(len(smp.q))
            for lv in [x for x in list(smp.covariates) if x.startswith(f"{k}=")]:
                code += (c["levels"][k].index(lv.split("=", 1)[1]) + 1) * smp.covariates.pop(lv)
            smp.covariates[col] = code
    floor = float(np.linalg.norm(test.true_positions - test.positions, axis=-1).mean()) * 1e3
    rot_floor = None
    if test.quaternions is not None:
        seen = ~np.isnan(test.quaternions).any(-1)
        rot_floor = float(_angle_mrad(test.quaternions[seen], test.true_quaternions[seen]).mean())
    declared = c.get("declared", [mk.split("=")[0] for mk in c["markers"]])
    return Case(name, real, train, test, floor, text, declared, list(c["named"]), rot_floor)


def effect_sizes(name: str, seed: int = 0) -> dict[str, dict]:
    """Each effect of case ``name`` at its markers on the held-out poses: the same robot with
    and without it (``"all"``: without every effect), in total and beyond a geometric fit on the
    training poses, see :func:`~torchcal.sim.effect_size.displacement_um` (µm);
    ``"floor_um"``: the noise floor."""
    c, case = _spec(name), make_case(name, seed)

    def state(s: Sample) -> dict:  # what made the sample's rows, outliers and noise aside
        return dict(directions=case.real.directions(s.q), temperature=s.covariates.get("temperature"),
                    covariates={k: v for k, v in s.covariates.items()
                                if not k.startswith("dir.") and k != "temperature"})

    keys = [k for k in EFFECT_KEYS if k in c["physics"]]
    out = {}
    for k in keys + (["all"] if len(keys) > 1 else []):
        without = {p: v for p, v in c["physics"].items() if p != k and (k != "all" or p not in EFFECT_KEYS)}
        out[k] = displacement_um(case.real, _robot(c, case.urdf, seed, without), case.test.q, state(case.test),
                                 case.train.q, state(case.train))
    out["floor_um"] = {"mean_um": case.floor_mm * 1e3}
    return out
