"""The settings of the independent simulator's "real" robot (:class:`~torchcal.sim.physsim.PhysicalRobot`),
as one record: what is drawn (geometric errors, the instrument), what physics acts (gravity,
compliance, thermal growth, backlash, cyclic errors, joint terms, drifting parameters) and how the
instrument measures.

Fields (units in the names: m, rad, kg, N, degC):

* seed: one ``numpy.random.Generator`` draws the robot, then every ``sample_q``/``measure``.
* length_error_m, angle_error_rad: std of the joint origin errors and zero offsets.
* marker_error_m: std per axis of the true marker offset around the declared one;
  marker_true_m: marker -> its true offset (m, link frame) instead, set apart from the
  declared guess (e.g. a guess on a joint axis, the real point cm off it).
* marker_rpy: marker -> declared rotation (roll, pitch, yaw) rad of its frame in the link
  frame (default identity); marker_rotation_error_rad: std per axis of the true frame's
  rotation around it (drawn from a second generator, so the data stream is unchanged).
* base_distance_m: distance instrument origin <-> base origin.
* instrument_frame: ``(4, 4)`` pose of the instrument frame in the base frame, replacing
  the drawn one (``np.eye(4)``: measure in the base frame).
* payload_kg, payload_com_m, payload_link: undeclared point mass (COM m in the link frame;
  default link: the first marker's); payload_column: its mass per row (kg) is that covariate's
  value instead (the robot measured with several loads, logged), or for ``"level:<column>"`` a text
  column's, each level's mass in payload_levels (level -> kg).
* torsion: joint -> k rad/(N m); lateral: joint -> (cx, cy, cz) rad/(N m) about the child
  frame axes (``lateral_frame="parent"``: about the joint frame's axes before the joint
  turns, applied before the motion, as a bearing seat in the parent link); base_tilt:
  (cx, cy) rad/(N m); thermal: joint -> alpha 1/K on that joint origin's translation,
  driven by the covariate ``temperature``, or -> (alpha, column) driven by the named
  covariate column (degC); backlash: joint -> half play rad (m); cyclic: joint ->
  [(harmonic, amplitude rad, phase rad), ...] of its own commanded angle; joint_terms:
  joint -> [:class:`JointTerm` or (source, kind, coef[, harmonic[, phase[, ref]]]), ...]
  added to its true value, the source another joint's command or a covariate column;
  noise_m: instrument noise std per axis.
* pose_markers: markers also measured in orientation (names, or True: all), with
  ``rot_noise_rad`` std per axis of a small random rotation (in the marker frame).
* geometric_errors: False: nominal geometry (the random draws still happen, so the
  instrument frame and later data are the same as with errors).
* drifts: parameters changing with a driver (:class:`~torchcal.sim.physsim_drifts.Drift`): a zero
  that steps, an instrument that settles, a guide's straightness, a tool point per level.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from torchcal.options import Options

__all__ = ["PhysicalOptions"]


@dataclass(frozen=True)
class PhysicalOptions(Options):
    """Settings of a :class:`~torchcal.sim.physsim.PhysicalRobot` (module docstring)."""

    seed: int = 0
    length_error_m: float = 0.5e-3
    angle_error_rad: float = 1e-3
    marker_error_m: float = 0.0
    base_distance_m: float = 3.0
    instrument_frame: Any = None
    payload_kg: float = 0.0
    payload_com_m: tuple = (0.0, 0.0, 0.0)
    payload_link: str | None = None
    payload_column: str | None = None
    payload_levels: dict | None = None
    torsion: dict | None = None
    lateral: dict | None = None
    lateral_frame: str = "child"
    base_tilt: Any = None
    thermal: dict | None = None
    t_ref_c: float = 20.0
    backlash: dict | None = None
    cyclic: dict | None = None
    noise_m: float = 0.02e-3
    gravity: tuple = (0.0, 0.0, -9.81)
    geometric_errors: bool = True
    joint_terms: dict | None = None
    marker_rpy: dict | None = None
    marker_rotation_error_rad: float = 0.0
    pose_markers: Any = None
    rot_noise_rad: float = 0.0
    marker_true_m: dict | None = None
    drifts: tuple | list | None = None
