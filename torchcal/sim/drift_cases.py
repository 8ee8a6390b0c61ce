"""Cases of issue 32 for the independent simulator: a parameter of the robot changes with a driver,
in a shape nobody declared (:mod:`torchcal.sim.physsim_drifts`; no torchcal effect code).

On the UR5e cases' set-up (300 training + 150 held-out poses, 0.02 mm tracker noise 3 m away):

* ``zero_step``: the elbow's zero shifts by 1.9 mrad at row 210 (a joint re-mastered) and stays;
  no time column, so only the row order tells;
* ``instrument_drift``: the tracker settles: its frame turns 0.8 mrad per hour about its y axis
  and creeps 0.1 mm per hour along x, over an hour's campaign (``time`` column, s); held-out
  rows are drawn from the same session;
* ``instrument_settle``: the tracker warms up after it is switched on: its frame turns 0.5 mrad about
  its x axis and rises 0.06 mm, settling with a time constant of 15 min (``time`` column, s);
  held-out rows from the same session;
* ``instrument_cycle``: the tracker's frame swings with the air conditioning, a 33-minute cycle of
  a phase nobody logged: it turns 0.15 mrad about z and 0.08 mrad about y and moves 0.04 mm along x
  (``time`` column, s; held-out rows from the same session);
* ``wandering_frame``: the tracker's stand creeps through the session in no shape: its frame follows a
  random walk of 12 steps over the session (a fixed draw, each step a steady creep), 0.08 mm and
  0.25 mrad per axis over the whole walk (``time`` column, s; held-out rows from the same session);
* ``tool_levels``: two tools are used, logged in a text column ``tool``; the probe's point sits
  12 mm and 4 mm off the gripper's;
* ``tool_set``: three tools logged in a text column ``tool``: a probe 75 mm longer than the
  gripper and a spindle 25 mm aside and 40 mm longer (centimetres: the geometric stage sees only
  the tools' scatter);
* ``tool_codes``: four tools logged by number in a numeric column ``tool_id`` (1 to 4), not by
  name: their points sit up to 60 mm apart with no order in the number (the number is a code, and
  no line or curve in it fits the tools);
* ``tool_for_a_while``: a tool 40 mm longer and 10 mm aside used for rows 100 to 199, then the
  first one back, nothing logged (the held-out rows come after, with the first tool);
* ``tool_and_station``: the three tools of ``tool_set`` and two tracker stations at once, in two text
  columns; station B's registration leaves the frame 1.5 mm, 1 mm and 0.5 mm off and turned 2, 1 and
  2.5 mrad (what the tools leave must still be told from the stations);
* ``station_levels``: the tracker is set up twice, logged in a text column ``station``; the second
  set-up's registration leaves the instrument frame 0.3 mm along y and 0.1 mm down and turned
  0.25 mrad about y and 0.1 mrad about z from the first's (one rigid motion);
* ``setup_change``: the tracker knocked and registered again 50 min into the session: its frame
  moves 0.2 mm along x and 0.15 mm up and turns 0.2 mrad about x and 0.15 mrad about z, and stays
  (``time`` column, s; held-out rows from the same session);
* ``station_far``: the tracker at two stations, logged in a text column ``station``: B stands 0.9 m
  back, 1.4 m aside and 0.1 m higher than A, turned 0.8 rad about z and 40 and 20 mrad about x and y
  (metres: the geometric stage, one registration for both, sees nothing of the robot);
* ``tracker_moved``: the tracker carried to another place at row 180 and the session carried on,
  with no column to say so: 0.3 m, 0.5 m and 40 mm away, turned 0.45 rad about z and 30 mrad about x;
* ``tracker_carried``: the same kind at row 150: 0.4 m, 0.3 m and 20 mm away, turned 0.35 rad about z
  and 20 mrad about y (the screening's linear view of a turn that large can place the step a row
  late);
* ``torque_stiffness``: the shoulder lift twists 20 µrad/(N·m) up to ±15 N·m and half that
  beyond (a gear whose backlash region is soft);
* ``loaded_stiffness``: the gear of ``torque_stiffness`` (twice as stiff beyond ±15 N·m) under
  payloads logged row by row (0, 3, 6 and 10 kg in a ``payload_kg`` column, runs of them): the
  torque the gear carries, and so its stiffness, changes with what each row holds; the other joints
  twist linearly (the ``logged_loads`` torsion);
* ``swapped_stiffness``: the same gear with an 8 kg payload swapped in halfway through the session and
  nothing logged (the simulator reads a column the loop never sees), the other joints twisting
  linearly: the load changes at a step the loop must find itself;
* ``stiffening_elbow``: the elbow under a fixed 4 kg tool twists ``c τ / (1 + |τ| / τ₀)``, 30 µrad/(N·m)
  near zero torque and stiffer with the load (τ₀ = 10 N·m), a smooth curve no piecewise-linear knee
  matches exactly;
* ``prismatic_guide``: the UR5e on a 1.5 m linear track whose carriage wanders 40 µm sideways
  in a bow and pitches 0.3 mrad along its travel.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from torchcal.sim.physsim_drifts import Drift

__all__ = ["DRIFT_CASES", "track_urdf", "level_series"]

TRACK_M = 1.5  # travel of the linear track (m)

_UR5E = dict(robot="ur5e", markers=["tool@flange"], n_train=300, n_test=150, noise_m=0.02e-3)


def track_urdf() -> str:
    """The UR5e on a linear track: a prismatic joint ``track`` (x, 0 to :data:`TRACK_M` m) under its base."""
    text = (Path(__file__).resolve().parents[2] / "urdf" / "ur5e.urdf").read_text()
    rail = (f'<link name="rail"/>\n  <joint name="track" type="prismatic">\n    <parent link="rail"/>\n'
            f'    <child link="link0"/>\n    <origin xyz="0 0 0" rpy="0 0 0"/>\n    <axis xyz="1 0 0"/>\n'
            f'    <limit lower="0" upper="{TRACK_M}" effort="1000" velocity="1"/>\n  </joint>\n  ')
    return text.replace('<robot name="ur5e">', '<robot name="ur5e_track">', 1).replace(
        '<link name="link0"/>', rail + '<link name="link0"/>', 1)


def level_series(levels: list[str], n: int, seed) -> np.ndarray:
    """``(n,)`` a text column: each row one of ``levels`` at random."""
    return np.asarray(levels)[np.random.default_rng(seed).integers(0, len(levels), n)]


def _step(rows):
    return 1.9e-3 * (rows >= 210)


def _settle(t):
    h = (t - t[0] if t.ndim else t) / 3600.0
    return np.stack([0.1e-3 * h, 0 * h, 0 * h, 0 * h, 0.8e-3 * h, 0 * h], -1)


def _warm_up(t):
    h = (t - t[0] if t.ndim else t) / 3600.0
    f = 1.0 - np.exp(-h / 0.25)
    z = 0 * h
    return np.stack([z, z, 0.06e-3 * f, 0.5e-3 * f, z, z], -1)


def _air_conditioning(t):
    h = (t - t[0] if t.ndim else t) / 3600.0
    w = np.sin(2 * np.pi * h / (33.0 / 60.0) + 1.1)
    z = 0 * h
    return np.stack([0.04e-3 * w, z, z, z, 0.08e-3 * w, 0.15e-3 * w], -1)


# wandering_frame's walk: a fixed draw (the path is the case's, the noise and the poses the seed's),
# 12 knots over the campaign's span (campaign_time: 450 poses, 7 pauses), a steady creep between them
_WALK_T = np.linspace(0.0, 8400.0, 12)
_WALK = np.cumsum(np.random.default_rng(20261128).normal(size=(12, 6))
                  * np.array([80e-6] * 3 + [0.25e-3] * 3) / np.sqrt(12.0), 0)
_WALK -= _WALK[0]


def _wander(t):
    t = np.asarray(t, dtype=float)
    return np.stack([np.interp(t, _WALK_T, _WALK[:, k]) for k in range(6)], -1)


def _probe(tool):
    return np.where((tool == "probe")[:, None], np.array([0.0, 0.012, 0.004]), 0.0)


def _tool_set(tool):
    tips = {"gripper": (0.0, 0.0, 0.0), "probe": (0.0, 0.0, 0.075), "spindle": (0.025, 0.0, 0.040)}
    return np.array([tips[t] for t in tool])


def _four_tools(tool):
    tips = {"t1": (0.0, 0.0, 0.0), "t2": (0.010, 0.0, 0.060), "t3": (-0.008, 0.012, 0.015),
            "t4": (0.004, -0.006, 0.045)}
    return np.array([tips[t] for t in tool])


def _tool_for_a_while(rows):
    return ((rows >= 100) & (rows < 200)).astype(float)[:, None] * np.array([0.0, 0.010, 0.040])


def _station_b(station):
    moved = (station == "B").astype(float)[:, None]
    return moved * np.array([1.5e-3, -1e-3, 0.5e-3, 2e-3, -1e-3, 2.5e-3])


def _station(station):
    moved = (station == "B").astype(float)[:, None]
    return moved * np.array([0.0, 0.3e-3, -0.1e-3, 0.0, 0.25e-3, 0.1e-3])


def _far_station(station):
    moved = (station == "B").astype(float)[:, None]
    return moved * np.array([-0.9, 1.4, 0.1, 0.04, 0.02, -0.8])


def _carried(rows):
    return (rows >= 180).astype(float)[:, None] * np.array([0.3, -0.5, 0.04, -0.03, 0.0, 0.45])


def _carried_at_150(rows):
    return (rows >= 150).astype(float)[:, None] * np.array([0.4, 0.3, -0.02, 0.0, 0.02, -0.35])


def _knocked(t):
    moved = ((t - t[0] if t.ndim else t) >= 3000.0).astype(float)[..., None]
    return moved * np.array([0.2e-3, 0.0, 0.15e-3, 0.2e-3, 0.0, 0.15e-3])


def _soft_gear(tau, c_soft=2e-5, c_stiff=1e-5, knee=15.0):
    return c_stiff * tau + (c_soft - c_stiff) * np.clip(tau, -knee, knee)


def _stiffening(tau, c=3e-5, tau0=10.0):
    return c * tau / (1.0 + np.abs(tau) / tau0)


def _guide(x):
    u = x / TRACK_M
    z = 0 * u
    return np.stack([z, 40e-6 * 4 * u * (1 - u), z, z, 0.3e-3 * np.sin(np.pi * u), z], -1)


DRIFT_CASES: dict[str, dict] = {
    "zero_step": {**_UR5E, "named": ["parameter_drivers"],
                  "physics": dict(drifts=[Drift("offset:elbow_joint", "row", _step,
                                                "the elbow's zero shifts by 1.9 mrad at row 210")])},
    "instrument_drift": {**_UR5E, "named": ["parameter_drivers"], "interleave": True,
                         "covariates": {"time": ("time", {})},
                         "physics": dict(drifts=[Drift("instrument", "cov:time", _settle,
                                                       "the instrument turns 0.8 mrad/h and creeps 0.1 mm/h")])},
    "instrument_settle": {**_UR5E, "named": ["parameter_drivers"], "interleave": True,
                          "covariates": {"time": ("time", {})},
                          "physics": dict(drifts=[Drift("instrument", "cov:time", _warm_up,
                                                        "the instrument turns 0.5 mrad and rises 0.06 mm, "
                                                        "settling in 15 min")])},
    "instrument_cycle": {**_UR5E, "named": ["parameter_drivers"], "interleave": True,
                         "covariates": {"time": ("time", {})},
                         "physics": dict(drifts=[Drift("instrument", "cov:time", _air_conditioning,
                                                       "the instrument turns 0.15 mrad about z and 0.08 mrad about y "
                                                       "and moves 0.04 mm in a 33-minute cycle")])},
    "wandering_frame": {**_UR5E, "named": ["frame_path"], "interleave": True,
                        "covariates": {"time": ("time", {})},
                        "physics": dict(drifts=[Drift("instrument", "cov:time", _wander,
                                                      "the frame wanders 0.08 mm and 0.25 mrad per axis")])},
    "tool_levels": {**_UR5E, "named": ["parameter_drivers"], "levels": {"tool": ["gripper", "probe"]},
                    "physics": dict(drifts=[Drift("marker:tool", "level:tool", _probe,
                                                  "the probe's point is 12 mm, 4 mm off the gripper's")])},
    "tool_set": {**_UR5E, "named": ["parameter_drivers"], "levels": {"tool": ["gripper", "probe", "spindle"]},
                 "physics": dict(drifts=[Drift("marker:tool", "level:tool", _tool_set,
                                               "a probe 75 mm longer, a spindle 25 mm aside and 40 mm longer")])},
    "tool_codes": {**_UR5E, "named": ["parameter_drivers"], "levels": {"tool": ["t1", "t2", "t3", "t4"]},
                   "coded": {"tool": "tool_id"},
                   "physics": dict(drifts=[Drift("marker:tool", "level:tool", _four_tools,
                                                 "four tools by number, up to 60 mm apart")])},
    "tool_for_a_while": {**_UR5E, "named": ["parameter_drivers"],
                         "physics": dict(drifts=[Drift("marker:tool", "row", _tool_for_a_while,
                                                       "a 40 mm longer tool for rows 100-199")])},
    "tool_and_station": {**_UR5E, "named": ["parameter_drivers"],
                         "levels": {"tool": ["gripper", "probe", "spindle"], "station": ["A", "B"]},
                         "physics": dict(drifts=[Drift("marker:tool", "level:tool", _tool_set, "three tools"),
                                                 Drift("instrument", "level:station", _station_b, "two stations")])},
    "station_levels": {**_UR5E, "named": ["parameter_drivers"], "levels": {"station": ["A", "B"]},
                       "physics": dict(drifts=[Drift("instrument", "level:station", _station,
                                                     "set-up B moves the frame 0.3 mm, 0.1 mm, turns 0.25 mrad, 0.1 mrad")])},
    "setup_change": {**_UR5E, "named": ["parameter_drivers"], "interleave": True, "covariates": {"time": ("time", {})},
                     "physics": dict(drifts=[Drift("instrument", "cov:time", _knocked,
                                                   "the frame moves 0.2 mm, 0.15 mm and turns 0.2, 0.15 mrad at 50 min")])},
    "station_far": {**_UR5E, "named": ["parameter_drivers"], "levels": {"station": ["A", "B"]},
                    "physics": dict(drifts=[Drift("instrument", "level:station", _far_station,
                                                  "station B 0.9 m, 1.4 m, 0.1 m away, turned 0.8 rad")])},
    "tracker_moved": {**_UR5E, "named": ["parameter_drivers"],
                      "physics": dict(drifts=[Drift("instrument", "row", _carried,
                                                    "the tracker carried 0.3 m, 0.5 m away and turned 0.45 rad "
                                                    "at row 180")])},
    "tracker_carried": {**_UR5E, "named": ["parameter_drivers"],
                        "physics": dict(drifts=[Drift("instrument", "row", _carried_at_150,
                                                      "the tracker carried 0.4 m, 0.3 m away and turned 0.35 rad "
                                                      "at row 150")])},
    "torque_stiffness": {**_UR5E, "named": ["joint_compliance", "parameter_drivers"],
                         "physics": dict(payload_kg=5.0, payload_com_m=(0.0, 0.0, 0.1),
                                         drifts=[Drift("offset:shoulder_lift_joint", "torque:shoulder_lift_joint",
                                                       _soft_gear, "20 µrad/N·m up to 15 N·m, half beyond")])},
    "loaded_stiffness": {**_UR5E, "named": ["load_compliance", "parameter_drivers"],
                         "covariates": {"payload_kg": ("payloads", {"masses": (0.0, 3.0, 6.0, 10.0)})},
                         "physics": dict(payload_column="payload_kg", payload_com_m=(0.03, 0.0, 0.12),
                                         torsion={"elbow_joint": 9e-6, "wrist_1_joint": 20e-6},
                                         drifts=[Drift("offset:shoulder_lift_joint", "torque:shoulder_lift_joint",
                                                       _soft_gear, "20 µrad/N·m up to 15 N·m, half beyond, "
                                                       "under the logged loads")])},
    "swapped_stiffness": {**_UR5E, "named": ["joint_compliance", "load_compliance", "parameter_drivers"],
                          "covariates": {"carried_kg": ("payload_swap", {"before": 0.0, "after": 8.0, "at": 0.5})},
                          "hidden": ["carried_kg"],
                          "physics": dict(payload_column="carried_kg", payload_com_m=(0.0, 0.03, 0.1),
                                          torsion={"elbow_joint": 9e-6, "wrist_1_joint": 20e-6},
                                          drifts=[Drift("offset:shoulder_lift_joint", "torque:shoulder_lift_joint",
                                                        _soft_gear, "20 µrad/N·m up to 15 N·m, half beyond, "
                                                        "an 8 kg payload swapped in halfway, nothing logged")])},
    "stiffening_elbow": {**_UR5E, "named": ["joint_compliance", "parameter_drivers"],
                         "physics": dict(payload_kg=4.0, payload_com_m=(0.0, 0.0, 0.1),
                                         drifts=[Drift("offset:elbow_joint", "torque:elbow_joint", _stiffening,
                                                       "30 µrad/N·m near zero torque, stiffer with the load")])},
    "prismatic_guide": {**_UR5E, "robot": "ur5e_track", "named": ["parameter_drivers"],
                        "physics": dict(drifts=[Drift("carriage:track", "q:track", _guide,
                                                      "the carriage bows 40 µm and pitches 0.3 mrad")])},
}
