"""An independent "physical" robot that generates test data for the calibration loop.

It parses the URDF itself (``xml.etree``) and does its own forward kinematics in numpy float64,
sharing no code with torchcal's kinematics, so that a bug there cannot hide behind the same bug
here.  Only :mod:`torchcal.measure.io` is used, to hand a :class:`Sample` over as ``Measurements``.

Units: m, rad, kg, N, N m, degC.  ``q: (N, dof)`` rad (m for prismatic joints), marker positions
``p: (N, M, 3)`` m in the instrument frame.  Base frame = URDF root link frame, gravity in it.
Compliance uses the gravity wrench of the rigid true robot at the commanded pose, with no
fixed-point iteration: the deflections are micro-radians and change the wrench only to second
order.  Gravity is not re-tilted with the base for the same reason.
"""
from __future__ import annotations

import math
import re
from pathlib import Path

import numpy as np

from torchcal.sim.base import Simulated
from torchcal.sim.physsim_urdf import (MOVING_TYPES, UrdfJoint, homogeneous, parse_floats, parse_urdf,
                                       rotation_exp, rpy_matrix)
from torchcal.sim.sample import Sample

__all__ = ["PhysicalRobot", "warmup_temperature"]

_MARKER_RE = re.compile(r"^\s*([^@=\s]+)\s*(?:@\s*([^=\s]+))?\s*(?:=\s*(.+?))?\s*$")
def warmup_temperature(n: int, span_k: float = 8.0, seed: int = 0, *, start_c: float = 20.0,
                       noise_k: float = 0.1) -> np.ndarray:
    """``(n,)`` degC, rows in visiting order: ``start_c + span_k (1 - exp(-i / (n/4)))`` plus
    Gaussian noise of ``noise_k``: a robot warming up over the campaign."""
    warm = span_k * (1 - np.exp(-np.arange(n) / max(n / 4, 1.0)))
    return start_c + warm + np.random.default_rng(seed).normal(0, noise_k, n)


class PhysicalRobot:
    """A "real" robot built from a URDF plus drawn errors and physical effects.

    Args:
        urdf: path or URDF XML text.
        markers: ``"link"`` (its origin) or ``"name@link=x,y,z"`` (m, link frame).
        seed: one ``numpy.random.Generator`` draws the robot, then every ``sample_q``/``measure``.
        length_error_m, angle_error_rad: std of the joint origin errors and zero offsets.
        marker_error_m: std per axis of the true marker offset around the declared one.
        base_distance_m: distance instrument origin <-> base origin.
        instrument_frame: ``(4, 4)`` pose of the instrument frame in the base frame, replacing
            the drawn one (``np.eye(4)``: measure in the base frame).
        payload_kg, payload_com_m, payload_link: undeclared point mass (COM m in the link frame;
            default link: the first marker's).
        torsion: joint -> k rad/(N m); lateral: joint -> (cx, cy, cz) rad/(N m) about the child
            frame axes (``lateral_frame="parent"``: about the joint frame's axes before the joint
            turns, applied before the motion, as a bearing seat in the parent link); base_tilt: (cx, cy) rad/(N m); thermal: joint -> alpha 1/K on that joint
            origin's translation; backlash: joint -> half play rad (m); cyclic: joint ->
            [(harmonic, amplitude rad, phase rad), ...]; noise_m: instrument noise std per axis.
        geometric_errors: False: nominal geometry (the random draws still happen, so the
            instrument frame and later data are the same as with errors).

    Joints not on a path to a marker are not columns; they stay "parked" at 0 (clipped into
    their limits) and their bodies still weigh on the joints they hang from.
    """

    def __init__(self, urdf, markers, *, seed: int = 0, length_error_m: float = 0.5e-3,
                 angle_error_rad: float = 1e-3, marker_error_m: float = 0.0, base_distance_m: float = 3.0,
                 instrument_frame=None, payload_kg: float = 0.0, payload_com_m=(0.0, 0.0, 0.0),
                 payload_link: str | None = None, torsion=None, lateral=None, lateral_frame: str = "child",
                 base_tilt=None, thermal=None,
                 t_ref_c: float = 20.0, backlash=None, cyclic=None, noise_m: float = 0.02e-3,
                 gravity=(0.0, 0.0, -9.81), geometric_errors: bool = True):
        text = str(urdf) if str(urdf).lstrip().startswith("<") else Path(urdf).read_text()
        self.name, joints, self._bodies = parse_urdf(text)
        self._j = {j.name: j for j in joints}
        by_child = {j.child: j for j in joints}
        roots = sorted({j.parent for j in joints} - set(by_child))
        if len(roots) != 1:
            raise ValueError(f"the URDF needs exactly one root link, found {roots}")
        self.root = roots[0]
        kids: dict[str, list[UrdfJoint]] = {}
        for j in joints:
            kids.setdefault(j.parent, []).append(j)
        self._order, stack = [], [self.root]  # parent before child
        while stack:
            for j in kids.get(stack.pop(0), []):
                self._order.append(j)
                stack.append(j.child)
        self._below: dict[str, list[str]] = {}  # link -> links of its subtree
        for j in reversed(self._order):
            self._below.setdefault(j.child, [j.child])
            self._below.setdefault(j.parent, [j.parent]).extend(self._below[j.child])
        self._below.setdefault(self.root, [self.root])

        self.markers = []  # (name, link, declared offset (3,) m)
        for spec in markers:
            m = _MARKER_RE.match(spec)
            if not m or (m.group(2) or m.group(1)) not in self._below:
                raise ValueError(f"marker {spec!r}: write 'link' or 'name@link=x,y,z' with a link of the URDF")
            self.markers.append((m.group(1), m.group(2) or m.group(1), parse_floats(m.group(3), [0, 0, 0], ",")))
        self.marker_names = [m[0] for m in self.markers]
        needed: set[str] = set()

        def climb(link: str) -> None:
            while link in by_child:
                j = by_child[link]
                needed.add(j.name)
                if j.mimic and j.mimic[0] not in needed:
                    climb(self._j[j.mimic[0]].child)
                link = j.parent

        for m in self.markers:
            climb(m[1])
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
        self.thermal, self.t_ref_c = dict(thermal or {}), float(t_ref_c)
        self.backlash = dict(backlash or {})
        self.cyclic = {k: [tuple(map(float, h)) for h in v] for k, v in (cyclic or {}).items()}
        for what, d, ok in (("torsion", self.torsion, ("revolute", "continuous")),
                            ("lateral", self.lateral, MOVING_TYPES + ("fixed",)),
                            ("thermal", self.thermal, MOVING_TYPES + ("fixed",)), ("cyclic", self.cyclic, MOVING_TYPES),
                            ("backlash", self.backlash, self.joint_names)):
            bad = [k for k in d if k not in self._j or (self._j[k].type not in ok and k not in ok)]
            if bad:
                raise ValueError(f"{what}: {bad} are not suitable joints of this URDF")
        self.noise_m, self.gravity = float(noise_m), np.asarray(gravity, dtype=float)
        self.payload_kg, self.payload_com_m = float(payload_kg), np.asarray(payload_com_m, dtype=float)
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
        self._marker_true = [m[2] + ge * rng.normal(0, marker_error_m, 3) for m in self.markers]
        ax, d = rng.normal(size=3), rng.normal(size=3)
        T_bi = homogeneous(rotation_exp(ax / np.linalg.norm(ax) * rng.uniform(0, 0.9 * math.pi)),
                     d / np.linalg.norm(d) * base_distance_m)
        self.instrument_in_base = T_bi if instrument_frame is None else np.asarray(instrument_frame, dtype=float)
        self._first_dir = np.where(rng.random(self.dof) < 0.5, -1.0, 1.0)

    # ------------------------------------------------------------------ kinematics
    def _unit(self, name: str) -> str:
        return "m" if self._j[name].type == "prismatic" else "rad"

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

    def _angles(self, q: np.ndarray, dirs: np.ndarray) -> dict[str, np.ndarray]:
        """Real joint values before compliance: name -> ``(N,)`` rad (m).  A mimic joint follows
        its source's true angle (command + zero offset), like the linkage it models; the source's
        backlash, cyclic error and compliance stay in the source's drive and are not passed on."""
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
            out[j.name] = th
        return out

    def _fk(self, th: dict, temp: np.ndarray, bend: dict | None = None) -> dict[str, np.ndarray]:
        """Link poses in the base frame: link -> ``(N, 4, 4)``."""
        N = len(temp)
        T = {self.root: np.broadcast_to(np.eye(4), (N, 4, 4))}
        for j in self._order:
            O = self._origin[j.name]
            if j.name in self.thermal:
                O = np.repeat(O[None], N, 0)
                O[:, :3, 3] *= (1 + self.thermal[j.name] * (temp - self.t_ref_c))[:, None]
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
            T[j.child] = A
        return T

    def _wrenches(self, T: dict) -> dict:
        """Gravity wrenches, see :meth:`gravity_wrenches`."""
        N = len(T[self.root])
        m_link, s_link = {}, {}  # mass and first mass moment sum(m c) per link
        for link, bodies in self._bodies.items():
            if link == self.payload_link and self.payload_kg:
                bodies = bodies + [(self.payload_kg, self.payload_com_m)]
            if link in T and bodies:
                R, p = T[link][:, :3, :3], T[link][:, :3, 3]
                m_link[link] = sum(b[0] for b in bodies)
                s_link[link] = sum(b[0] * (R @ b[1] + p) for b in bodies)
        out: dict = {"joints": {}}
        for j in self._order + [None]:
            sub = self._below[j.child if j else self.root]
            m = sum(m_link.get(ln, 0.0) for ln in sub)
            s = sum((s_link[ln] for ln in sub if ln in s_link), np.zeros((N, 3)))
            o = T[j.child][:, :3, 3] if j else np.zeros((N, 3))
            # sum (c - o) x m g = (sum m c - m_tot o) x g
            w = {"F_N": np.tile(m * self.gravity, (N, 1)), "M_Nm": np.cross(s - m * o, self.gravity)}
            if j is None:
                out["base"] = w
                continue
            if j.type in ("revolute", "continuous"):
                w["tau_Nm"] = np.einsum("ni,ni->n", w["M_Nm"], T[j.child][:, :3, :3] @ j.axis)
            out["joints"][j.name] = w
        return out

    def _state(self, q, temperature, directions):
        q = self._check_q(q)
        temp = np.broadcast_to(np.asarray(self.t_ref_c if temperature is None else temperature, dtype=float),
                               (len(q),))
        th = self._angles(q, self.directions(q) if directions is None else np.asarray(directions, dtype=float))
        return th, temp, self._fk(th, temp)

    def gravity_wrenches(self, q, *, temperature=None, directions=None) -> dict:
        """Gravity wrenches of the rigid true robot at the commanded ``q (N, dof)``, base frame:
        ``{"joints": {name: {"F_N": (N, 3), "M_Nm": (N, 3) about the joint's child frame origin,
        "tau_Nm": (N,) M . axis (revolute joints)}}, "base": {"F_N", "M_Nm" about the base origin}}``,
        each on everything downstream (the base: every body, payload included)."""
        return self._wrenches(self._state(q, temperature, directions)[2])

    def reach(self, q, *, temperature=None, directions=None) -> np.ndarray:
        """Noise-free marker positions ``(N, M, 3)`` m in the instrument frame for commanded
        ``q (N, dof)``; ``temperature`` degC (scalar or ``(N,)``, default ``t_ref_c``);
        ``directions (N, dof)`` +-1 (default :meth:`directions`)."""
        th, temp, T = self._state(q, temperature, directions)
        tilt = None
        if self.torsion or self.lateral or self.base_tilt is not None:
            W = self._wrenches(T)

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
            T = self._fk(th, temp, bend)
            if self.base_tilt is not None:
                M = W["base"]["M_Nm"]
                tilt = rotation_exp(np.stack([self.base_tilt[0] * M[:, 0], self.base_tilt[1] * M[:, 1], 0 * M[:, 0]], -1))
        p = np.stack([T[ln][:, :3, :3] @ x + T[ln][:, :3, 3] for (_, ln, _), x in zip(self.markers, self._marker_true)],
                     1)
        if tilt is not None:
            p = np.einsum("nij,nmj->nmi", tilt, p)
        R, t = self.instrument_in_base[:3, :3], self.instrument_in_base[:3, 3]
        return (p - t) @ R

    def measure(self, q, *, temperature=None, outlier_fraction: float = 0.0, outlier_mm=(5.0, 20.0)) -> Sample:
        """Simulated measurement of ``q (N, dof)`` visited in row order: :meth:`reach` + noise
        ``noise_m`` per axis + outliers on ``round(outlier_fraction N)`` rows, each marker moved
        by a length uniform in ``outlier_mm`` (mm) in a random direction (per row, at random:
        one vector for all markers, or one per marker).  Covariates: ``temperature`` (degC, when
        given or thermal growth is simulated) and ``dir.<joint>`` for every joint when backlash is."""
        q = self._check_q(q)
        N, M = len(q), len(self.markers)
        dirs = self.directions(q)
        true = self.reach(q, temperature=temperature, directions=dirs)
        pos = true + self._rng.normal(0, self.noise_m, true.shape)
        K = int(round(outlier_fraction * N))
        rows = np.sort(self._rng.choice(N, K, replace=False)).astype(int)
        per_marker = self._rng.random(K) < 0.5
        v = self._rng.normal(size=(K, M, 3))
        v *= self._rng.uniform(*outlier_mm, size=(K, M, 1)) * 1e-3 / np.linalg.norm(v, axis=-1, keepdims=True)
        v[~per_marker] = v[~per_marker][:, :1]
        pos[rows] += v
        cov = {}
        if temperature is not None or self.thermal:
            cov["temperature"] = np.broadcast_to(np.asarray(self.t_ref_c if temperature is None else temperature,
                                                            dtype=float), (N,)).copy()
        if self.backlash:
            cov.update({f"dir.{n}": dirs[:, k] for k, n in enumerate(self.joint_names)})
        return Sample(q.copy(), pos, list(self.joint_names), list(self.marker_names), cov, true, rows, v, per_marker)

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
        f = lambda a: np.asarray(a, dtype=float).tolist()  # noqa: E731
        err = {n: dict(zip(("dx_m", "dy_m", "dz_m", "dyaw_rad", "dpitch_rad", "droll_rad"), f(e)))
               for n, e in self._err.items()}
        return {
            "robot": self.name, "seed": self.seed, "root_link": self.root, "joint_names": list(self.joint_names),
            "joint_origin_error": err,
            "zero_offset_rad": {n: float(v) for n, v in self._offset.items() if self._unit(n) == "rad"},
            "zero_offset_m": {n: float(v) for n, v in self._offset.items() if self._unit(n) == "m"},
            "parked_joints_rad_or_m": dict(self._parked),
            "marker_link": {m[0]: m[1] for m in self.markers},
            "marker_offset_declared_m": {m[0]: f(m[2]) for m in self.markers},
            "marker_offset_true_m": {m[0]: f(x) for m, x in zip(self.markers, self._marker_true)},
            "instrument_in_base_4x4_m": f(self.instrument_in_base),
            "base_in_instrument_4x4_m": f(np.linalg.inv(self.instrument_in_base)),
            "payload_kg": self.payload_kg, "payload_com_m": f(self.payload_com_m), "payload_link": self.payload_link,
            "gravity_m_per_s2": f(self.gravity),
            "torsion_rad_per_Nm": {k: float(v) for k, v in self.torsion.items()},
            "lateral_rad_per_Nm": {k: f(v) for k, v in self.lateral.items()},
            "base_tilt_rad_per_Nm": None if self.base_tilt is None else f(self.base_tilt),
            "thermal_per_K": {k: float(v) for k, v in self.thermal.items()}, "t_ref_c": self.t_ref_c,
            "backlash_half_play": {k: {f"half_play_{self._unit(k)}": float(v)} for k, v in self.backlash.items()},
            "backlash_first_direction": dict(zip(self.joint_names, f(self._first_dir))),
            "cyclic": {k: [{"harmonic": h[0], f"amplitude_{self._unit(k)}": h[1], "phase_rad": h[2]} for h in v]
                       for k, v in self.cyclic.items()},
            "noise_m": self.noise_m,
        }


