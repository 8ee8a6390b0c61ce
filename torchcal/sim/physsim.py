"""An independent "physical" robot that generates test data for the calibration loop.

It parses the URDF itself (``xml.etree``) and does its own forward kinematics in numpy float64,
sharing no code with torchcal's kinematics, so that a bug there cannot hide behind the same bug
here.  Only :mod:`torchcal.measure.io` is used, to hand a :class:`Sample` over as ``Measurements``.

Units: m, rad, kg, N, N m, degC.  ``q: (N, dof)`` rad (m for prismatic joints), marker positions
``p: (N, M, 3)`` m in the instrument frame.  Base frame = URDF root link frame, gravity in it.
Compliance uses the gravity wrench of the rigid true robot at the commanded pose, with no
fixed-point iteration: the deflections are micro-radians and change the wrench only to second
order.  Gravity is not re-tilted with the base for the same reason.

A marker can also be measured as a full pose (a camera's or tracker's 6-D target): its frame is
its link frame times the marker's rotation, expressed in the instrument frame, as unit
quaternions ``(N, M, 4)`` (w, x, y, z).
"""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from torchcal.sim.base import Simulated
from torchcal.sim.covariates import warmup_temperature
from torchcal.sim.instrument import orientation_readings, outlier_shifts
from torchcal.sim.joint_terms import JointTerm, as_joint_terms
from torchcal.sim.physsim_drifts import apply_carriage, evaluate_drifts, instrument_motion, level_columns
from torchcal.sim.physsim_gravity import subtree_wrenches
from torchcal.sim.physsim_options import PhysicalOptions
from torchcal.sim.physsim_truth import error_support, robot_truth
from torchcal.sim.physsim_urdf import (MOVING_TYPES, homogeneous, joints_above, parse_marker, parse_urdf,
                                       rotation_exp, rpy_matrix, tree_order)
from torchcal.sim.sample import Sample

__all__ = ["JointTerm", "PhysicalOptions", "PhysicalRobot", "warmup_temperature"]


class PhysicalRobot:
    """A "real" robot built from a URDF plus drawn errors and physical effects.

    Args:
        urdf: path or URDF XML text.
        markers: ``"link"`` (its origin) or ``"name@link=x,y,z"`` (m, link frame).
        settings: a :class:`~torchcal.sim.physsim_options.PhysicalOptions` (the drawn errors, the
            effects, the instrument); its fields may also be given as keywords.

    Joints not on a path to a marker are not columns; they stay "parked" at 0 (clipped into
    their limits) and their bodies still weigh on the joints they hang from.
    """

    def __init__(self, urdf, markers, settings: PhysicalOptions | None = None, /, **kw):
        o = PhysicalOptions.build(settings, **kw)
        seed, length_error_m, angle_error_rad, marker_error_m = o.seed, o.length_error_m, o.angle_error_rad, \
            o.marker_error_m
        base_distance_m, instrument_frame, payload_kg, payload_com_m = o.base_distance_m, o.instrument_frame, \
            o.payload_kg, o.payload_com_m
        payload_link, torsion, lateral, lateral_frame, base_tilt = o.payload_link, o.torsion, o.lateral, \
            o.lateral_frame, o.base_tilt
        thermal, t_ref_c, backlash, cyclic, noise_m, gravity = o.thermal, o.t_ref_c, o.backlash, o.cyclic, \
            o.noise_m, o.gravity
        geometric_errors, joint_terms, marker_rpy, marker_rotation_error_rad = o.geometric_errors, o.joint_terms, \
            o.marker_rpy, o.marker_rotation_error_rad
        pose_markers, rot_noise_rad, marker_true_m, drifts = o.pose_markers, o.rot_noise_rad, o.marker_true_m, \
            o.drifts
        self.settings = o
        text = str(urdf) if str(urdf).lstrip("\ufeff \t\r\n").startswith("<") else Path(urdf).read_text("utf-8-sig")
        text = text.lstrip("\ufeff")  # a byte-order mark is no part of the text
        self.name, joints, self._bodies = parse_urdf(text)
        self._j = {j.name: j for j in joints}
        self.root, self._order, self._below = tree_order(joints)

        self.markers = [parse_marker(spec, self._below) for spec in markers]  # (name, link, declared offset (3,) m)
        self.marker_names = [m[0] for m in self.markers]
        needed = joints_above(joints, [m[1] for m in self.markers])
        self.joint_names = [j.name for j in joints if j.name in needed and j.type in MOVING_TYPES and not j.mimic]
        self.dof = len(self.joint_names)
        act = [self._j[n] for n in self.joint_names]
        self.joint_limits = (np.array([j.lower for j in act]), np.array([j.upper for j in act]))
        self._parked = {j.name: float(np.clip(0.0, j.lower, j.upper)) for j in joints
                        if j.type in MOVING_TYPES and not j.mimic and j.name not in needed}

        self.torsion = dict(torsion or {})
        self.lateral = {k: np.asarray(v, dtype=float) for k, v in (lateral or {}).items()}
        if lateral_frame not in ("child", "parent"):
            raise ValueError(f"lateral_frame must be 'child' or 'parent', got {lateral_frame!r}")
        self.lateral_frame = lateral_frame
        self.base_tilt = None if base_tilt is None else np.asarray(base_tilt, dtype=float)
        self.thermal = {k: float(v[0] if isinstance(v, (tuple, list)) else v) for k, v in (thermal or {}).items()}
        self.thermal_column = {k: str(v[1]) if isinstance(v, (tuple, list)) else "temperature"
                               for k, v in (thermal or {}).items()}
        self.t_ref_c = float(t_ref_c)
        self.backlash = dict(backlash or {})
        self.cyclic = {k: [tuple(map(float, h)) for h in v] for k, v in (cyclic or {}).items()}
        for what, d, ok in (("torsion", self.torsion, ("revolute", "continuous")),
                            ("lateral", self.lateral, MOVING_TYPES + ("fixed",)),
                            ("thermal", self.thermal, MOVING_TYPES + ("fixed",)), ("cyclic", self.cyclic, MOVING_TYPES),
                            ("backlash", self.backlash, self.joint_names)):
            bad = [k for k in d if k not in self._j or (self._j[k].type not in ok and k not in ok)]
            if bad:
                raise ValueError(f"{what}: {bad} are not suitable joints of this URDF")
        self.joint_terms = as_joint_terms(joint_terms, self.joint_names)
        self.pose_markers = list(self.marker_names) if pose_markers is True else list(pose_markers or [])
        unknown = [m for m in self.pose_markers + list(marker_rpy or {}) + list(marker_true_m or {})
                   if m not in self.marker_names]
        if unknown:
            raise ValueError(f"pose_markers / marker_rpy / marker_true_m: {unknown} are not markers "
                             f"({self.marker_names})")
        self.rot_noise_rad = float(rot_noise_rad)
        self.drifts = list(drifts or [])  # parameters changing with a driver (physsim_drifts)
        self._first_row = 0  # the measuring order of the rows reach() is asked for
        self.noise_m, self.gravity = float(noise_m), np.asarray(gravity, dtype=float)
        self.payload_kg, self.payload_com_m = float(payload_kg), np.asarray(payload_com_m, dtype=float)
        self.payload_column = o.payload_column  # the payload's mass per row, logged in this covariate (kg)
        self.payload_levels = dict(o.payload_levels or {})  # or its level -> kg, for a text column
        self.payload_link = payload_link or self.markers[0][1]
        if self.payload_link not in self._below:
            raise ValueError(f"payload_link {self.payload_link!r} is not a link of the URDF")

        # Draw everything in a fixed order whatever the flags, so the same seed always gives the
        # same instrument frame and data stream.
        self.seed, self._rng = seed, np.random.default_rng(seed)
        rng = self._rng  # the same generator then serves sample_q and measure
        ge = 1.0 if geometric_errors else 0.0
        self._err, self._origin = {}, {}
        for j in joints:
            e = np.concatenate([rng.normal(0, length_error_m, 3), rng.normal(0, angle_error_rad, 3)]) * ge
            self._err[j.name] = e
            self._origin[j.name] = j.origin @ homogeneous(rpy_matrix(e[5], e[4], e[3]), e[:3])  # Rz(dyaw) Ry(dpitch) Rx(droll)
        self._offset = {j.name: ge * rng.normal(0, length_error_m if j.type == "prismatic" else angle_error_rad)
                        for j in act}
        drawn = [m[2] + ge * rng.normal(0, marker_error_m, 3) for m in self.markers]  # also where set: same stream
        self._marker_true = [np.asarray((marker_true_m or {}).get(m[0], x), dtype=float)
                             for m, x in zip(self.markers, drawn)]
        ax, d = rng.normal(size=3), rng.normal(size=3)
        T_bi = homogeneous(rotation_exp(ax / np.linalg.norm(ax) * rng.uniform(0, 0.9 * math.pi)),
                     d / np.linalg.norm(d) * base_distance_m)
        self.instrument_in_base = T_bi if instrument_frame is None else np.asarray(instrument_frame, dtype=float)
        self._first_dir = np.where(rng.random(self.dof) < 0.5, -1.0, 1.0)
        rng2 = np.random.default_rng([seed, 1])
        self._marker_rpy = {m: tuple(map(float, (marker_rpy or {}).get(m, (0, 0, 0)))) for m in self.marker_names}
        self._marker_rot = [rpy_matrix(*self._marker_rpy[m]) @ rotation_exp(
            ge * rng2.normal(0, marker_rotation_error_rad, 3)) for m in self.marker_names]

    # ------------------------------------------------------------------ kinematics
    def directions(self, q: np.ndarray) -> np.ndarray:
        """``(N, dof)`` +-1: sign of the last motion of each joint along the visiting order (no
        motion: the previous direction; first pose: the drawn ``first_direction``)."""
        q = self._check_q(q)
        d = np.vstack([self._first_dir[None], np.sign(np.diff(q, axis=0))])
        idx = np.maximum.accumulate(np.where(d != 0, np.arange(len(q))[:, None], 0), axis=0)
        return np.take_along_axis(d, idx, 0)

    def _check_q(self, q) -> np.ndarray:
        q = np.atleast_2d(np.asarray(q, dtype=float))
        if q.shape[1] != self.dof:
            raise ValueError(f"q must be (N, {self.dof}) in the order {self.joint_names}, got {q.shape}")
        return q

    def _angles(self, q: np.ndarray, dirs: np.ndarray, cov: dict) -> dict[str, np.ndarray]:
        """Real joint values before compliance: name -> ``(N,)`` rad (m).  A mimic joint follows
        its source's true angle (command + zero offset), like the linkage it models; the source's
        backlash, cyclic error, joint terms and compliance stay in the source's drive and are not
        passed on."""
        cmd = {n: q[:, k] for k, n in enumerate(self.joint_names)}
        cmd.update({n: np.full(len(q), v) for n, v in self._parked.items()})
        true = {n: v + self._offset.get(n, 0.0) for n, v in cmd.items()}

        def value(n: str) -> np.ndarray:
            if n not in true:
                src, mul, off = self._j[n].mimic
                true[n] = mul * value(src) + off
            return true[n]

        out = {}
        for j in (j for j in self._order if j.type in MOVING_TYPES):
            th = value(j.name)
            for h, a, ph in self.cyclic.get(j.name, []):  # a function of the motor (commanded) angle
                th = th + a * np.sin(h * cmd.get(j.name, th) + ph)
            if j.name in self.backlash:
                th = th + self.backlash[j.name] * dirs[:, self.joint_names.index(j.name)]
            for t in self.joint_terms.get(j.name, []):  # commands, as the drive sees them, or logged columns
                th = th + t.coef * t.basis(cmd[t.source] if t.source in cmd else cov[t.source])
            out[j.name] = th
        return out

    def _fk(self, th: dict, cov: dict, N: int, bend: dict | None = None, carriage: dict | None = None
            ) -> dict[str, np.ndarray]:
        """Link poses in the base frame: link -> ``(N, 4, 4)``; ``cov``: column -> ``(N,)``."""
        T = {self.root: np.broadcast_to(np.eye(4), (N, 4, 4))}
        for j in self._order:
            O = self._origin[j.name]
            if j.name in self.thermal:
                O = np.repeat(O[None], N, 0)
                O[:, :3, 3] *= (1 + self.thermal[j.name] * (cov[self.thermal_column[j.name]] - self.t_ref_c))[:, None]
            A = T[j.parent] @ O
            seat = bend is not None and j.name in bend and self.lateral_frame == "parent"
            if seat:  # a bearing seat in the parent link: bent before the joint turns
                A[:, :3, :3] = A[:, :3, :3] @ bend[j.name]
            if j.type == "prismatic":
                A[:, :3, 3] += A[:, :3, :3] @ j.axis * th[j.name][:, None]
            elif j.type != "fixed":
                A[:, :3, :3] = A[:, :3, :3] @ rotation_exp(j.axis * th[j.name][:, None])
            if bend is not None and j.name in bend and not seat:
                A[:, :3, :3] = A[:, :3, :3] @ bend[j.name]
            if carriage and j.name in carriage:  # the guide's straightness and pitch along the travel
                A = apply_carriage(A, carriage[j.name])
            T[j.child] = A
        return T

    def _wrenches(self, T: dict, cov: dict) -> dict:
        """Gravity wrenches, see :meth:`gravity_wrenches`; ``cov``: the covariate columns (a payload
        logged per row)."""
        bodies = dict(self._bodies)
        mass = self.payload_kg
        if self.payload_column:
            col = cov[self.payload_column]
            mass = np.array([self.payload_levels[x] for x in col]) if self.payload_column.startswith("level:") else col
        if self.payload_column or self.payload_kg:
            bodies[self.payload_link] = bodies.get(self.payload_link, []) + [(mass, self.payload_com_m)]
        return subtree_wrenches(T, self._order, self._below, self.root, bodies, self.gravity)

    def _columns_read(self) -> dict[str, float]:
        """Covariate columns the effects read -> the value meaning "no effect" (``t_ref_c`` for
        thermal growth, ``ref`` for a joint term, no payload), used where a column is not given."""
        cols = {t.source: t.ref for ts in self.joint_terms.values() for t in ts if t.source not in self.joint_names}
        cols.update({c: self.t_ref_c for c in self.thermal_column.values()})
        if self.payload_column and not self.payload_column.startswith("level:"):
            cols[self.payload_column] = 0.0
        return cols

    def _columns(self, N: int, temperature, covariates) -> dict[str, np.ndarray]:
        """Covariate columns as ``(N,)`` arrays, see :meth:`_columns_read` for those not given."""
        cov = {**self._columns_read(), "temperature": self.t_ref_c if temperature is None else temperature}
        cov.update(covariates or {})
        return {k: np.broadcast_to(np.asarray(v, dtype=str if k.startswith("level:") else float), (N,))
                for k, v in cov.items()}

    def _state(self, q, temperature, directions, covariates=None):
        q = self._check_q(q)
        cov = self._columns(len(q), temperature, covariates)
        th = self._angles(q, self.directions(q) if directions is None else np.asarray(directions, dtype=float), cov)
        return th, cov, self._fk(th, cov, len(q))

    def gravity_wrenches(self, q, *, temperature=None, directions=None, covariates=None) -> dict:
        """Gravity wrenches of the rigid true robot at the commanded ``q (N, dof)``, base frame:
        ``{"joints": {name: {"F_N": (N, 3), "M_Nm": (N, 3) about the joint's child frame origin,
        "tau_Nm": (N,) M . axis (revolute joints)}}, "base": {"F_N", "M_Nm" about the base origin}}``,
        each on everything downstream (the base: every body, payload included)."""
        _, cov, T = self._state(q, temperature, directions, covariates)
        return self._wrenches(T, cov)

    def reach(self, q, *, temperature=None, directions=None, covariates=None) -> np.ndarray:
        """Noise-free marker positions ``(N, M, 3)`` m in the instrument frame for commanded
        ``q (N, dof)``; ``temperature`` degC (scalar or ``(N,)``, default ``t_ref_c``);
        ``directions (N, dof)`` +-1 (default :meth:`directions`); ``covariates``: column ->
        scalar or ``(N,)`` read by thermal growth and joint terms."""
        return self.reach_pose(q, temperature=temperature, directions=directions, covariates=covariates)[0]

    def reach_pose(self, q, *, temperature=None, directions=None, covariates=None) -> tuple[np.ndarray, np.ndarray]:
        """Noise-free marker frames in the instrument frame: positions ``(N, M, 3)`` m and
        rotations ``(N, M, 3, 3)`` (link frame times the marker's true rotation); arguments as
        :meth:`reach`."""
        th, cov, T = self._state(q, temperature, directions, covariates)
        tilt, dr = None, self._drifts(q, th, cov, T)
        if dr["offset"] or dr["carriage"]:
            th = {n: v + dr["offset"].get(n, 0.0) for n, v in th.items()}
            T = self._fk(th, cov, len(q), carriage=dr["carriage"])
        if self.torsion or self.lateral or self.base_tilt is not None:
            W = self._wrenches(T, cov)

            def frame(n):  # the joint frame after its motion (child), or before it (parent)
                R = T[self._j[n].child][:, :3, :3]
                jt = self._j[n]
                if self.lateral_frame == "parent" and jt.type in ("revolute", "continuous"):
                    R = R @ rotation_exp(-jt.axis * th[n][:, None])
                return R
            bend = {n: rotation_exp(c * np.einsum("nji,nj->ni", frame(n), W["joints"][n]["M_Nm"]))
                    for n, c in self.lateral.items()}  # the moment in that frame's axes
            for n, k in self.torsion.items():
                th[n] = th[n] + k * W["joints"][n]["tau_Nm"]
            T = self._fk(th, cov, len(T[self.root]), bend, dr["carriage"])
            if self.base_tilt is not None:
                M = W["base"]["M_Nm"]
                tilt = rotation_exp(np.stack([self.base_tilt[0] * M[:, 0], self.base_tilt[1] * M[:, 1], 0 * M[:, 0]], -1))
        p = np.stack([(T[ln][:, :3, :3] @ x if m not in dr["marker"] else
                       np.einsum("nij,nj->ni", T[ln][:, :3, :3], x + dr["marker"][m])) + T[ln][:, :3, 3]
                      for (m, ln, _), x in zip(self.markers, self._marker_true)], 1)
        Rm = np.stack([T[ln][:, :3, :3] @ Rk for (_, ln, _), Rk in zip(self.markers, self._marker_rot)], 1)
        if tilt is not None:
            p = np.einsum("nij,nmj->nmi", tilt, p)
            Rm = np.einsum("nij,nmjk->nmik", tilt, Rm)
        Ti = self.instrument_in_base if dr["instrument"] is None else instrument_motion(dr["instrument"]) @ \
            self.instrument_in_base
        R, t = Ti[..., :3, :3], Ti[..., :3, 3]
        if Ti.ndim == 3:  # an instrument frame that moves from row to row
            return np.einsum("nji,nmj->nmi", R, p - t[:, None]), np.einsum("nji,nmjk->nmik", R, Rm)
        return (p - t) @ R, np.einsum("ji,nmjk->nmik", R, Rm)

    def _drifts(self, q, th: dict, cov: dict, T: dict) -> dict:
        """The drifts' values at these rows (:func:`~torchcal.sim.physsim_drifts.evaluate_drifts`)."""
        rows = self._first_row + np.arange(len(q))
        torque = None
        if any(d.driver.startswith("torque:") for d in self.drifts):
            W = self._wrenches(T, cov)
            torque = {n: W["joints"][n]["tau_Nm"] for n in self.joint_names if n in W["joints"]}
        cmd = {n: q[:, k] for k, n in enumerate(self.joint_names)}
        return evaluate_drifts(self.drifts, cmd, cov, rows, torque, len(q))

    def measure(self, q, *, temperature=None, covariates=None, outlier_fraction: float = 0.0,
                outlier_mm=(5.0, 20.0), orientation_fraction: float = 1.0, first_row: int = 0,
                levels: dict | None = None) -> Sample:
        """Simulated measurement of ``q (N, dof)`` visited in row order: :meth:`reach` + noise
        ``noise_m`` per axis + outliers on ``round(outlier_fraction N)`` rows, each marker moved
        by a length uniform in ``outlier_mm`` (mm) in a random direction (per row, at random:
        one vector for all markers, or one per marker; orientations are not moved).

        Covariates recorded, in this order: ``temperature`` (degC, when given or thermal growth
        reads it), every column of ``covariates`` (name -> ``(N,)``: the logs of the cell, e.g.
        several temperatures; those that thermal growth or joint terms read must be among them),
        and ``dir.<joint>`` for every joint when backlash is simulated.  Pose markers carry
        quaternions on ``round(orientation_fraction N)`` rows drawn at random (NaN elsewhere)."""
        q = self._check_q(q)
        N, M = len(q), len(self.markers)
        covariates = {k: np.broadcast_to(np.asarray(v, dtype=float), (N,)).copy()
                      for k, v in (covariates or {}).items()}
        missing = [c for c in self._columns_read() if c != "temperature" and c not in covariates]
        if missing:
            raise ValueError(f"measure: the robot's thermal growth or joint terms read the covariate(s) {missing}; "
                             "pass them in covariates={name: (N,) values}")
        dirs = self.directions(q)
        self._first_row = int(first_row)  # rows are measured in order from first_row (drifts read it)
        lv = {k: np.asarray(v).astype(str) for k, v in (levels or {}).items()}
        try:
            true, true_R = self.reach_pose(q, temperature=temperature, directions=dirs,
                                           covariates={**covariates, **{f"level:{k}": v for k, v in lv.items()}})
        finally:
            self._first_row = 0
        pos = true + self._rng.normal(0, self.noise_m, true.shape)
        rows, v, per_marker = outlier_shifts(self._rng, N, M, outlier_fraction, outlier_mm)
        pos[rows] += v
        cov = {}
        if temperature is not None or "temperature" in self.thermal_column.values():
            cov["temperature"] = np.broadcast_to(np.asarray(self.t_ref_c if temperature is None else temperature,
                                                            dtype=float), (N,)).copy()
        cov.update(covariates)
        cov.update(level_columns(lv))  # a text column, as a file's reader holds it: one 0/1 column per level
        if self.backlash:
            cov.update({f"dir.{n}": dirs[:, k] for k, n in enumerate(self.joint_names)})
        quat = true_quat = None  # drawn last: without pose markers the position data stay what they were
        if self.pose_markers:
            quat, true_quat = orientation_readings(self._rng, true_R, self.rot_noise_rad, orientation_fraction,
                                                   np.array([m in self.pose_markers for m in self.marker_names]))
        return Sample(q.copy(), pos, list(self.joint_names), list(self.marker_names), cov, true, rows, v, per_marker,
                      quat, true_quat)

    def sample_q(self, n: int, margin: float = 0.1) -> np.ndarray:
        """``(n, dof)`` uniform in the limits shrunk by ``margin`` x range at each end (+-pi
        where a joint has none)."""
        lo, hi = (np.where(np.isfinite(x), x, s * math.pi) for x, s in zip(self.joint_limits, (-1, 1)))
        w = hi - lo
        return self._rng.uniform(lo + margin * w, hi - margin * w, size=(n, self.dof))

    def simulate(self, n: int, *, seed: int = 0, margin: float = 0.1) -> Simulated:
        """The :class:`~torchcal.sim.base.Simulator` interface: ``n`` poses drawn inside the joint
        limits and measured. ``seed`` seeds this data set alone; the robot's errors stay what
        they are. ``noise_floor``: the mean Euclidean norm of the noise actually added (m)."""
        saved, self._rng = self._rng, np.random.default_rng(seed)
        try:
            s = self.measure(self.sample_q(n, margin))
        finally:
            self._rng = saved
        noise = np.linalg.norm(s.positions - s.true_positions, axis=-1)
        return Simulated(s.to_measurements(), {"robot": self.truth(), "sample": s}, noise_floor=float(noise.mean()))

    def truth(self) -> dict:
        """Every drawn value and effect setting, JSON-able, units in the key names."""
        return robot_truth(self)

    def error_support(self) -> dict:
        """Where the true geometry differs from the URDF, see :func:`~torchcal.sim.physsim_truth.error_support`."""
        return error_support(self)
