"""Nominal robot descriptions (pure data, with citations).

Four robots are described as plain Python dicts in ``ROBOTS``:

* ``"kuka_kr5_arc"`` -- KUKA KR 5 arc, 6R industrial arm (seed 000, geometric calibration).
* ``"scara"``        -- Adept (Omron) Cobra s600, 4-axis SCARA R-R-P-R (seed 001, dynamics).
* ``"ur5e"``         -- Universal Robots UR5e, 6R collaborative arm.
* ``"kuka_iiwa14"``  -- KUKA LBR iiwa 14 R820, 7R collaborative arm.

Nothing here imports torch or numpy; the numbers are meant to be converted by the
kinematics / dynamics modules.

Units
-----
Lengths in metres, angles in radians, masses in kg, inertias in kg m^2, joint velocity
limits in rad/s (m/s for prismatic joints), joint effort limits in N m (N for prismatic
joints).  ``None`` means "not published / not known".

Kinematic convention (``"convention": "classic"``)
---------------------------------------------------
Classic (distal, standard) Denavit-Hartenberg.  For joint ``i`` (1-based) with joint
variable ``q_i``::

    revolute :  A_i = Rz(theta_i + q_i) . Tz(d_i)       . Tx(a_i) . Rx(alpha_i)
    prismatic:  A_i = Rz(theta_i)       . Tz(d_i + q_i) . Tx(a_i) . Rx(alpha_i)

    T_flange(q) = A_1 A_2 ... A_n . T_tool

Frame 0 is the robot base frame (described in ``"base_frame"``).  Frame ``i`` is the frame
after ``A_i``; it is rigidly attached to link ``i`` (the body moved by joint ``i``).
``theta`` (revolute) and ``d`` (prismatic) are the constant joint offsets, so ``q = 0``
is the configuration described in ``"zero_pose"``.

``"tool"`` is ``None`` (identity: frame n already is the flange) or a fixed transform
``{"xyz": [x, y, z], "rpy": [roll, pitch, yaw]}`` of the tool/flange frame expressed in
frame n, with ``R = Rz(yaw) Ry(pitch) Rx(roll)`` (URDF convention).

``"joint_sign"`` relates the DH joint variables to the joint values used by the cited
controller / URDF: ``q_dh[i] = joint_sign[i] * q_source[i]`` (no extra offsets for any of
the four robots: the zero poses coincide).  Joint limits in the joint dicts are already
expressed in the DH variables ``q_dh``.

Joint dict keys
---------------
``name, type ("revolute" | "prismatic"), a, d, alpha, theta, lower, upper, velocity,
effort``.

Inertials
---------
``"inertials"`` is ``None`` (no credible per-link data) or a list with one dict per
moving link ``i = 1..n``::

    {"mass": m,                                  # kg
     "com": [x, y, z],                           # m, centre of mass in DH frame i
     "inertia": [ixx, ixy, ixz, iyy, iyz, izz]}  # kg m^2, about the COM, axes of DH frame i

(products of inertia with the usual sign convention, ``ixy = -int(x y dm)``, as in URDF).
Where the source gives the data in other frames (URDF link frames) it has been converted
numerically into the DH frames; each robot's comment block says how.

Other keys: ``name`` (human-readable), ``urdf_name`` (name of the public URDF/package the
numbers were cross-checked against), ``dof``, ``source`` (short citation string),
``approximate`` (what is approximate or illustrative), ``zero_pose`` (flange position at
``q = 0`` from the DH product, m, in frame 0).
"""

from copy import deepcopy
from math import pi, radians

__all__ = ["ROBOTS", "get_robot", "robot_names"]


def _joint(name, kind, a, d, alpha, theta, lower, upper, velocity, effort):
    """One row of a robot's DH table as a joint dict (the keys above, in that order)."""
    return {"name": name, "type": kind, "a": a, "d": d, "alpha": alpha, "theta": theta, "lower": lower,
            "upper": upper, "velocity": velocity, "effort": effort}


# =====================================================================================
# KUKA KR 5 arc
# -------------------------------------------------------------------------------------
# Sources
#   [K1] Seed 000 (LDPSO-BT, 2022), digest in shared/docs/seeds.md: nominal DH
#        a = 180, 600, 120, 0, 0, 0 mm; d = 400, 0, 0, 620, 0, 115 mm;
#        alpha = -90, 0, -90, 90, -90, 0 deg.  (Values from the public KUKA data sheet.)
#   [K2] ros-industrial/kuka_experimental, kuka_kr5_support/urdf/kr5_arc_macro.xacro
#        (joint origins 0.4 / 0.18 / 0.6 / 0.12 / 0.62 / 0.115 m; joint limits and
#        velocities transcribed from the KUKA KR 5 arc specification).
#   [K3] ARTE toolbox (A. Gil, 2012) data/ARTE/KUKA/KR5_arc/parameters.m, as shipped in
#        petercorke/robotics-toolbox-matlab: same limits and the same max joint speeds
#        (154, 154, 228, 343, 384, 721 deg/s), i.e. two independent transcriptions of the
#        KUKA specification agree.
#   [K4] kuka_experimental kuka_kr5_support/config/opw_kinematics_kr5.yaml: joint sign
#        corrections [-1, 1, 1, -1, 1, -1] (KUKA A1, A4, A6 turn negatively about the
#        upward / outward axes of a right-handed z-up model).
#   [K5] Total mass ~127 kg, reach 1412 mm: KUKA KR 5 arc data sheet (as catalogued in
#        public robot-viewer catalogue code); KUKA publishes no per-link masses.
# Offsets chosen
#   theta = [0, 0, -pi/2, 0, 0, 0].  With these, q_dh = 0 is KUKA's mechanical zero
#   (A1..A6 = 0): upper arm horizontal pointing forward, forearm horizontal (its axis
#   120 mm above the A2/A3 line), flange facing forward at (1.515, 0, 0.52) m.  This was
#   checked numerically against the full kinematic chain of [K2] at random
#   configurations, with q_dh = joint_sign * A_kuka, joint_sign = [-1, 1, 1, -1, 1, -1]
#   (position and orientation agree to 1e-15).  KUKA's HOME {0, -90, 90, 0, 0, 0} deg
#   puts the flange at (0.915, 0, 1.12) m.  Other public KR5 DH tables differ: ARTE uses
#   theta2 = q2 - pi/2 with different alpha/d signs, the Python Robotics Toolbox "KR5"
#   model uses yet another (non-KUKA-zero) table; neither reproduces KUKA's zero with the
#   seed's alpha signs, hence the choice above.
# Frames
#   Frame 0 = KUKA $ROBROOT (robot foot, z up, x forward).  Frame 6 origin = flange centre
#   (115 mm beyond the wrist centre), z6 along A6 pointing out of the flange.  The ROS-I
#   REP-199 "flange" frame of [K2] has the same origin with axes (x_f, y_f, z_f) =
#   (z6, -y6, x6); for position-only calibration (seed 000) the tool is identity.
# Approximate
#   Nominal geometry only (no per-robot calibration).  No per-link inertials are published;
#   the CAD-export inertials in [K2] sum to only ~17 kg for the six moving links (robot
#   weighs ~127 kg) and are not used.  Joint efforts are not published -> None.
# =====================================================================================
_KR5_ARC = {
    "name": "KUKA KR 5 arc",
    "urdf_name": "kuka_kr5_arc",
    "dof": 6,
    "convention": "classic",
    "source": (
        "DH a/d/alpha: seed 000 digest (KUKA data sheet values); zero offsets, joint "
        "signs, limits, speeds: ros-industrial/kuka_experimental "
        "kuka_kr5_support/urdf/kr5_arc_macro.xacro and opw_kinematics_kr5.yaml, "
        "cross-checked with ARTE KUKA/KR5_arc/parameters.m"
    ),
    "base_frame": "KUKA $ROBROOT at the robot foot, z up, x forward",
    "joint_sign": [-1, 1, 1, -1, 1, -1],  # q_dh = joint_sign * (KUKA axis value A1..A6)
    "joints": [
        _joint("joint_a1", "revolute", 0.180, 0.400, -pi / 2, 0.0, radians(-155), radians(155), radians(154), None),
        _joint("joint_a2", "revolute", 0.600, 0.0, 0.0, 0.0, radians(-180), radians(65), radians(154), None),
        _joint("joint_a3", "revolute", 0.120, 0.0, -pi / 2, -pi / 2, radians(-15), radians(158), radians(228), None),
        _joint("joint_a4", "revolute", 0.0, 0.620, pi / 2, 0.0, radians(-350), radians(350), radians(343), None),
        _joint("joint_a5", "revolute", 0.0, 0.0, -pi / 2, 0.0, radians(-130), radians(130), radians(384), None),
        _joint("joint_a6", "revolute", 0.0, 0.115, 0.0, 0.0, radians(-350), radians(350), radians(721), None),
    ],
    "tool": None,
    "inertials": None,
    "total_mass": 127.0,   # kg, whole robot incl. base (data sheet); no per-link split
    "zero_pose": [1.515, 0.0, 0.520],
    "approximate": (
        "nominal data-sheet geometry; theta offsets chosen here so that q=0 is KUKA's "
        "mechanical zero; no per-link inertials published (None); efforts unknown (None)"
    ),
}


# =====================================================================================
# SCARA: Adept (Omron) Cobra s600
# -------------------------------------------------------------------------------------
# Seed 001 lost its DH table, so a documented commercial SCARA is used instead.
# Sources
#   [S1] P. Corke, Robotics Toolbox for Python, roboticstoolbox/models/DH/Cobra600.py
#        (standard DH: d1 = 0.387, a1 = 0.325, a2 = 0.275, alpha2 = pi, prismatic
#        joint 3 with range 0..0.210 m).
#   [S2] ROS-Industrial adept_experimental, adept_cobra_s600_support/urdf/cobra_s600.urdf
#        (fork BenjaminSchellenbeck/adept_experimental): J1 at z = 0.342, J2 at x = 0.325,
#        quill at x = 0.275, z = +0.045 (so the flange is at 0.387 m with the quill up,
#        consistent with [S1]); limits J1 +-1.8326 rad (+-105 deg), J2 +-2.618 rad
#        (+-150 deg), J3 0.210 m stroke, J4 +-2 pi; speeds 6.737 rad/s (386 deg/s),
#        12.566 rad/s (720 deg/s), 1.1 m/s, 20.944 rad/s (1200 deg/s).
# Convention notes
#   alpha2 = pi turns z2 downwards, so q3 > 0 moves the quill DOWN and q4 turns about the
#   downward axis (the URDF [S2] also uses axis -z for J4).  Checked numerically: DH frame
#   4 coincides with the [S2] "tool0" frame for all q with q_dh = [q1, q2, -q3_urdf, q4]
#   (the URDF prismatic variable runs from -0.210 to 0).  q = 0 is the arm stretched
#   along +x, quill fully up: flange at (0.600, 0, 0.387) m.
# Dynamics (seed 001 uses a horizontal 2-link model with m1, m2, I1, I2, a1, a2, x1, x2)
#   Adept/Omron publish no link masses or inertias.  The values below are ILLUSTRATIVE,
#   NOT PUBLISHED: plausible magnitudes for a 600 mm SCARA (robot weight ~41 kg, mostly
#   in the base).  As in seed 001 the quill (joints 3-4) is lumped into link 2 as a
#   payload, so links 3 and 4 carry zero mass.  Inertials in DH frames:
#   link 1 COM at distance x1 from the J1 axis along the link -> (x1 - a1, 0, 0) in frame
#   1 (origin on the J2 axis); link 2 COM at x2 from the J2 axis -> (x2 - a2, 0, 0) in
#   frame 2 (origin on the quill axis).  izz = I1 / I2 (about the vertical axis through
#   the COM; the sign of z2 does not matter for a diagonal tensor).
# =====================================================================================
_SCARA_PLANAR = {
    # ILLUSTRATIVE, NOT PUBLISHED (plausible values; see comment above)
    "a1": 0.325, "a2": 0.275,   # m, link lengths (published, [S1]/[S2])
    "m1": 7.0, "m2": 4.5,       # kg (m2 includes the lumped quill / joints 3-4)
    "x1": 0.17, "x2": 0.15,     # m, COM distance from the proximal joint axis
    "I1": 0.07, "I2": 0.04,     # kg m^2, about the COM, vertical axis
    "note": "a1, a2 published; m1, m2, x1, x2, I1, I2 illustrative, not published",
}

_SCARA = {
    "name": "Adept (Omron) Cobra s600 SCARA",
    "urdf_name": "adept_cobra_s600",
    "dof": 4,
    "convention": "classic",
    "source": (
        "geometry: Corke Robotics Toolbox models/DH/Cobra600.py; limits/speeds/zero: "
        "ROS-Industrial adept_experimental adept_cobra_s600_support/urdf/cobra_s600.urdf; "
        "masses/inertias: illustrative, not published"
    ),
    "base_frame": "robot base mounting surface, z up, x along the stretched arm at q=0",
    # q_dh = joint_sign * q_urdf ([S2] quill axis is +z, range -0.21..0)
    "joint_sign": [1, 1, -1, 1],
    "joints": [
        _joint("joint_1", "revolute", 0.325, 0.387, 0.0, 0.0, radians(-105), radians(105), radians(386), None),
        _joint("joint_2", "revolute", 0.275, 0.0, pi, 0.0, radians(-150), radians(150), radians(720), None),
        _joint("joint_3", "prismatic", 0.0, 0.0, 0.0, 0.0, 0.0, 0.210, 1.1, None),
        _joint("joint_4", "revolute", 0.0, 0.0, 0.0, 0.0, -2 * pi, 2 * pi, radians(1200), None),
    ],
    "tool": None,
    # ILLUSTRATIVE, NOT PUBLISHED -- consistent with _SCARA_PLANAR (quill lumped into link 2)
    "inertials": [
        {"mass": 7.0, "com": [0.17 - 0.325, 0.0, 0.0], "inertia": [0.007, 0.0, 0.0, 0.07, 0.0, 0.07]},
        {"mass": 4.5, "com": [0.15 - 0.275, 0.0, 0.0], "inertia": [0.004, 0.0, 0.0, 0.04, 0.0, 0.04]},
        {"mass": 0.0, "com": [0.0, 0.0, 0.0], "inertia": [0.0, 0.0, 0.0, 0.0, 0.0, 0.0]},
        {"mass": 0.0, "com": [0.0, 0.0, 0.0], "inertia": [0.0, 0.0, 0.0, 0.0, 0.0, 0.0]},
    ],
    "planar_dynamics": _SCARA_PLANAR,
    "zero_pose": [0.600, 0.0, 0.387],
    "approximate": (
        "kinematics nominal (public model / URDF, not an official DH table); ALL masses, "
        "COMs and inertias are illustrative, not published; efforts unknown (None)"
    ),
}


# =====================================================================================
# Universal Robots UR5e
# -------------------------------------------------------------------------------------
# Sources
#   [U1] Universal Robots, "DH Parameters for calculations of kinematics and dynamics"
#        (universal-robots.com/articles/ur/application-installation/
#        dh-parameters-for-calculations-of-kinematics-and-dynamics/): UR5e
#        a = [0, -0.425, -0.3922, 0, 0, 0] m, d = [0.1625, 0, 0, 0.1333, 0.0997, 0.0996] m,
#        alpha = [pi/2, 0, 0, pi/2, -pi/2, 0], theta = 0; link masses
#        [3.761, 8.058, 2.846, 1.37, 1.3, 0.365] kg and COMs (in the DH frames):
#        [0, -0.02561, 0.00193], [0.2125, 0, 0.11336], [0.15, 0, 0.0265],
#        [0, -0.0018, 0.01634], [0, 0.0018, 0.01634], [0, 0, -0.001159] m.
#   [U2] UniversalRobots/Universal_Robots_ROS2_Description config/ur5e/
#        physical_parameters.yaml: inertia tensors ("tensor") and the rpy "rotation" used
#        for each inertial in urdf/ur_macro.xacro; config/ur5e/joint_limits.yaml (from
#        the UR5e user manual and UR's max-joint-torque article): all joints +-360 deg,
#        180 deg/s, efforts 150, 150, 150, 28, 28, 28 N m.
# Conversion
#   The URDF link frames of [U2] (nominal default_kinematics: shoulder z=d1; upper_arm
#   rpy (pi/2,0,0); forearm x=a2; wrist_1 (a3, 0, d4); wrist_2 y=-d5, rpy (pi/2,0,0);
#   wrist_3 y=d6, rpy (pi/2,pi,pi)) relate to the DH frames by constant transforms
#   (checked numerically at random q): link1 = DH1 . Rx(-pi/2); upper_arm = DH2 . Tx(-a2);
#   forearm = DH3 . Tx(-a3); wrist_1 = DH4 . Rx(-pi/2); wrist_2 = DH5 . Rx(pi/2);
#   wrist_3 = DH6.  The rpy rotation attached to each inertial in [U2] is exactly the
#   DH->URDF rotation, i.e. the [U2] tensors are already expressed in DH-frame axes, and
#   the [U2] COMs map back exactly onto the [U1] COMs.  So the tensors below are the
#   [U2] numbers unchanged and the COMs are the [U1] numbers.
# Zero pose
#   q = 0: arm stretched horizontally along -x: flange at
#   (a2 + a3, -(d4 + d6), d1 - d5) = (-0.8172, -0.2329, 0.0628) m, which is what the UR
#   DH description implies and what the [U2] URDF gives for wrist_3 (= UR tool flange,
#   ROS "tool0" orientation aside).
# Approximate
#   Nominal (uncalibrated) geometry; every real UR5e ships with a factory calibration.
#   UR notes the UR5e inertia values are small; tensors are from the ROS description, not
#   the UR article.  Elbow limits: the manual states +-360 deg but the forearm collides
#   with the upper arm beyond about +-180 deg (ROS description note) -> +-pi here.
# =====================================================================================
_UR5E = {
    "name": "Universal Robots UR5e",
    "urdf_name": "ur5e",
    "dof": 6,
    "convention": "classic",
    "source": (
        "DH, masses, COMs: Universal Robots 'DH Parameters for calculations of kinematics "
        "and dynamics'; inertia tensors and limits: UniversalRobots/"
        "Universal_Robots_ROS2_Description config/ur5e/physical_parameters.yaml, "
        "joint_limits.yaml"
    ),
    "base_frame": "UR 'Base' frame at the base mounting surface (ROS base_link_inertia)",
    "joint_sign": [1, 1, 1, 1, 1, 1],  # DH variables = UR controller joint values
    "joints": [
        _joint("shoulder_pan_joint", "revolute", 0.0, 0.1625, pi / 2, 0.0, -2 * pi, 2 * pi, pi, 150.0),
        _joint("shoulder_lift_joint", "revolute", -0.425, 0.0, 0.0, 0.0, -2 * pi, 2 * pi, pi, 150.0),
        _joint("elbow_joint", "revolute", -0.3922, 0.0, 0.0, 0.0, -pi, pi, pi, 150.0),
        _joint("wrist_1_joint", "revolute", 0.0, 0.1333, pi / 2, 0.0, -2 * pi, 2 * pi, pi, 28.0),
        _joint("wrist_2_joint", "revolute", 0.0, 0.0997, -pi / 2, 0.0, -2 * pi, 2 * pi, pi, 28.0),
        _joint("wrist_3_joint", "revolute", 0.0, 0.0996, 0.0, 0.0, -2 * pi, 2 * pi, pi, 28.0),
    ],
    "tool": None,
    "inertials": [
        {"mass": 3.761, "com": [0.0, -0.02561, 0.00193],
         "inertia": [0.00700210, 0.00000073, -0.00001053, 0.00648091, 0.00049994, 0.00657286]},
        {"mass": 8.058, "com": [0.2125, 0.0, 0.11336],
         "inertia": [0.01505885, -0.00005400, 0.00000563, 0.33388086, -0.00000181, 0.33247207]},
        {"mass": 2.846, "com": [0.15, 0.0, 0.0265],
         "inertia": [0.00399632, -0.00001365, 0.00137272, 0.07879254, -0.00000660, 0.07848510]},
        {"mass": 1.37, "com": [0.0, -0.0018, 0.01634],
         "inertia": [0.00165491, -0.00000282, -0.00000438, 0.00135962, 0.00010157, 0.00126279]},
        {"mass": 1.3, "com": [0.0, 0.0018, 0.01634],
         "inertia": [0.00135617, -0.00000274, 0.00000444, 0.00127827, -0.00005048, 0.00096614]},
        {"mass": 0.365, "com": [0.0, 0.0, -0.001159],
         "inertia": [0.00018694, 0.00000006, -0.00000017, 0.00018908, -0.00000092, 0.00025756]},
    ],
    "zero_pose": [-0.8172, -0.2329, 0.0628],
    "approximate": (
        "nominal UR geometry (real robots carry a per-unit calibration); inertia tensors "
        "from the ROS description (UR calls them negligible for the UR5e); elbow limit "
        "reduced to +-pi (physical self-collision limit)"
    ),
}


# =====================================================================================
# KUKA LBR iiwa 14 R820
# -------------------------------------------------------------------------------------
# KUKA publishes no DH table.  Sources
#   [I1] RobotLocomotion/drake manipulation/models/iiwa_description/urdf/
#        iiwa14_no_collision.urdf: joint origins (0.1575 + 0.2025 = 0.36 base->J2;
#        0.2045 + 0.2155 = 0.42 J2->J4; 0.1845 + 0.2155 = 0.40 J4->J6; 0.081 + 0.045 =
#        0.126 J6->flange), joint limits (+-170, +-120, +-170, +-120, +-170, +-120,
#        +-175 deg), velocities (85, 85, 100, 75, 130, 135, 135 deg/s), efforts
#        (320, 320, 176, 176, 110, 40, 40 N m), link masses / COMs / inertias.
#   [I2] Modi1987/KST-Kuka-Sunrise-Toolbox constDhDataOf14R820.m: d = 0.36, 0.42, 0.40,
#        0.126 m "taken from KUKA manuals (Medien-Flansch)"; same lengths.  Some public
#        code uses 0.152 m for J6->flange with a taller media flange; not used here.
# DH table
#   a = 0, d = [0.36, 0, 0.42, 0, 0.40, 0, 0.126], alpha = [-90, 90, 90, -90, -90, 90,
#   0] deg, theta = 0.  Of all 64 sign choices for alpha this is the only one that
#   reproduces the [I1] chain (joint directions included: q_dh = q_urdf, J2/J6 about +y,
#   J4 about -y at q = 0) -- checked numerically at random configurations.  q = 0 is the
#   arm straight up: flange at (0, 0, 1.306) m.
# Inertials (converted from [I1] link frames; URDF inertials have rpy = 0)
#   URDF iiwa_link_i expressed in DH frame i (constant, checked at random q):
#     link1: R = [[1,0,0],[0,0,-1],[0,1,0]],  p = (0, 0.2025, 0)
#     link2: R = [[-1,0,0],[0,0,1],[0,1,0]],  p = 0
#     link3: R = [[1,0,0],[0,0,1],[0,-1,0]],  p = (0, -0.2155, 0)
#     link4: R = [[1,0,0],[0,0,-1],[0,1,0]],  p = 0
#     link5: R = [[-1,0,0],[0,0,-1],[0,-1,0]], p = (0, 0.2155, 0)
#     link6: R = [[-1,0,0],[0,0,1],[0,1,0]],  p = 0
#     link7: R = I,                           p = (0, 0, -0.045)
#   com_dh = R com_urdf + p, I_dh = R I_urdf R^T.  (All [I1] tensors are diagonal, so the
#   conversion only permutes ixx/iyy/izz.)
# Approximate
#   Geometry nominal.  Masses are Drake's tuned values (6.35, 3.5, 3.5, 3.5 kg for links
#   2-5); the Drake file's comments give KUKA CAD values 3.95, 3.18, 2.74, 1.69, 1.8,
#   0.31 kg for links 2-7.  Inertias are Drake's rounded diagonal approximations.  Treat
#   all inertials as approximate.
# =====================================================================================
_IIWA14 = {
    "name": "KUKA LBR iiwa 14 R820",
    "urdf_name": "iiwa14",
    "dof": 7,
    "convention": "classic",
    "source": (
        "geometry, limits, inertials: RobotLocomotion/drake manipulation/models/"
        "iiwa_description/urdf/iiwa14_no_collision.urdf; link lengths cross-checked with "
        "KST-Kuka-Sunrise-Toolbox constDhDataOf14R820.m"
    ),
    "base_frame": "robot mounting flange (bottom of link 0), z up",
    "joint_sign": [1, 1, 1, 1, 1, 1, 1],  # DH variables = URDF / KUKA Sunrise joint values
    "joints": [
        _joint("iiwa_joint_1", "revolute", 0.0, 0.36, -pi / 2, 0.0, radians(-170), radians(170), radians(85), 320.0),
        _joint("iiwa_joint_2", "revolute", 0.0, 0.0, pi / 2, 0.0, radians(-120), radians(120), radians(85), 320.0),
        _joint("iiwa_joint_3", "revolute", 0.0, 0.42, pi / 2, 0.0, radians(-170), radians(170), radians(100), 176.0),
        _joint("iiwa_joint_4", "revolute", 0.0, 0.0, -pi / 2, 0.0, radians(-120), radians(120), radians(75), 176.0),
        _joint("iiwa_joint_5", "revolute", 0.0, 0.40, -pi / 2, 0.0, radians(-170), radians(170), radians(130), 110.0),
        _joint("iiwa_joint_6", "revolute", 0.0, 0.0, pi / 2, 0.0, radians(-120), radians(120), radians(135), 40.0),
        _joint("iiwa_joint_7", "revolute", 0.0, 0.126, 0.0, 0.0, radians(-175), radians(175), radians(135), 40.0),
    ],
    "tool": None,
    "inertials": [
        {"mass": 5.76, "com": [0.0, 0.0825, -0.03], "inertia": [0.033, 0.0, 0.0, 0.0123, 0.0, 0.0333]},
        {"mass": 6.35, "com": [-0.0003, 0.042, 0.059], "inertia": [0.0305, 0.0, 0.0, 0.011, 0.0, 0.0304]},
        {"mass": 3.5, "com": [0.0, -0.0855, -0.03], "inertia": [0.025, 0.0, 0.0, 0.0076, 0.0, 0.0238]},
        {"mass": 3.5, "com": [0.0, -0.034, 0.067], "inertia": [0.017, 0.0, 0.0, 0.006, 0.0, 0.0164]},
        {"mass": 3.5, "com": [-0.0001, 0.1395, -0.021], "inertia": [0.01, 0.0, 0.0, 0.00449, 0.0, 0.0087]},
        {"mass": 1.8, "com": [0.0, 0.0004, 0.0006], "inertia": [0.0049, 0.0, 0.0, 0.0036, 0.0, 0.0047]},
        {"mass": 1.2, "com": [0.0, 0.0, -0.025], "inertia": [0.001, 0.0, 0.0, 0.001, 0.0, 0.001]},
    ],
    "zero_pose": [0.0, 0.0, 1.306],
    "approximate": (
        "no official KUKA DH (lengths from public URDF / KUKA manual dimensions); "
        "inertials are Drake's tuned approximations, not KUKA data"
    ),
}


ROBOTS = {"kuka_kr5_arc": _KR5_ARC, "scara": _SCARA, "ur5e": _UR5E, "kuka_iiwa14": _IIWA14}


def robot_names():
    """Names of the available robot descriptions."""
    return list(ROBOTS)


def get_robot(name):
    """Return a deep copy of ``ROBOTS[name]`` (safe to modify)."""
    try:
        return deepcopy(ROBOTS[name])
    except KeyError:
        raise KeyError(f"unknown robot {name!r}; available: {robot_names()}") from None
