"""The truth behind a :class:`~torchcal.sim.physsim.PhysicalRobot`, for scoring only: every drawn
value and effect setting as JSON-able dicts, units in the key names.  A solver never reads it."""
from __future__ import annotations

import numpy as np

from torchcal.sim.physsim_urdf import rpy_matrix

__all__ = ["error_support", "robot_truth"]


def _unit(r, name: str) -> str:
    if name not in r._j:  # a covariate column
        return "K" if "temp" in name.lower() else "unit"
    return "m" if r._j[name].type == "prismatic" else "rad"


def robot_truth(r) -> dict:
    """Every drawn value and effect setting of the robot ``r``."""
    f = lambda a: np.asarray(a, dtype=float).tolist()  # noqa: E731
    err = {n: dict(zip(("dx_m", "dy_m", "dz_m", "dyaw_rad", "dpitch_rad", "droll_rad"), f(e)))
           for n, e in r._err.items()}
    return {
        "robot": r.name, "seed": r.seed, "root_link": r.root, "joint_names": list(r.joint_names),
        "joint_origin_error": err,
        "zero_offset_rad": {n: float(v) for n, v in r._offset.items() if _unit(r, n) == "rad"},
        "zero_offset_m": {n: float(v) for n, v in r._offset.items() if _unit(r, n) == "m"},
        "parked_joints_rad_or_m": dict(r._parked),
        "marker_link": {m[0]: m[1] for m in r.markers},
        "marker_offset_declared_m": {m[0]: f(m[2]) for m in r.markers},
        "marker_offset_true_m": {m[0]: f(x) for m, x in zip(r.markers, r._marker_true)},
        "instrument_in_base_4x4_m": f(r.instrument_in_base),
        "base_in_instrument_4x4_m": f(np.linalg.inv(r.instrument_in_base)),
        "payload_kg": r.payload_kg, "payload_com_m": f(r.payload_com_m), "payload_link": r.payload_link,
        "gravity_m_per_s2": f(r.gravity),
        "torsion_rad_per_Nm": {k: float(v) for k, v in r.torsion.items()},
        "lateral_rad_per_Nm": {k: f(v) for k, v in r.lateral.items()},
        "base_tilt_rad_per_Nm": None if r.base_tilt is None else f(r.base_tilt),
        "thermal_per_K": {k: float(v) for k, v in r.thermal.items()}, "t_ref_c": r.t_ref_c,
        "backlash_half_play": {k: {f"half_play_{_unit(r, k)}": float(v)} for k, v in r.backlash.items()},
        "backlash_first_direction": dict(zip(r.joint_names, f(r._first_dir))),
        "cyclic": {k: [{"harmonic": h[0], f"amplitude_{_unit(r, k)}": h[1], "phase_rad": h[2]} for h in v]
                   for k, v in r.cyclic.items()},
        "noise_m": r.noise_m,
        "thermal_column": dict(r.thermal_column),
        "joint_terms": {k: [t.as_dict() for t in v] for k, v in r.joint_terms.items()},
        "joint_terms_in_words": [t.words(k, _unit(r, k), _unit(r, t.source))
                                 for k, v in r.joint_terms.items() for t in v],
        "marker_rpy_declared_rad": {m: list(r._marker_rpy[m]) for m in r.marker_names},
        "marker_rotation_true_3x3": {m: f(R) for m, R in zip(r.marker_names, r._marker_rot)},
        "pose_markers": list(r.pose_markers), "rot_noise_rad": r.rot_noise_rad,
        "geometric_error_support": error_support(r),
    }


def error_support(r) -> dict:
    """Where the true geometry of ``r`` differs from the URDF and the declared markers:
    ``{"joint_origins": [joints with a nonzero origin error], "zero_offsets": [commanded joints
    with a nonzero zero offset], "marker_offsets": [markers whose true point differs from the
    declared one], "marker_rotations": [markers whose true frame is rotated from the declared
    one]}``, e.g. the parameters of the true model's least-squares fit."""
    return {"joint_origins": [n for n, e in r._err.items() if np.any(e != 0)],
            "zero_offsets": [n for n, v in r._offset.items() if v != 0],
            "marker_offsets": [m[0] for m, x in zip(r.markers, r._marker_true) if np.any(x != m[2])],
            "marker_rotations": [m for m, R in zip(r.marker_names, r._marker_rot)
                                 if np.any(R != rpy_matrix(*r._marker_rpy[m]))]}
