"""Measurements from a ROS bag: ROS 1 (a ``.bag`` file) or ROS 2 (a bag directory, sqlite3 or
MCAP storage, or its ``.db3`` / ``.mcap`` file), read with the pure-Python ``rosbags`` package
(``pip install 'torchcal[ros]'``; no ROS install needed).

What is read:

* joint values from a ``sensor_msgs/JointState`` topic (rad / m, as ROS publishes them). A message
  counts when it names every actuated joint of the URDF; other names on the topic (a gripper's) are
  ignored and listed; a message naming only some of the robot's joints is skipped and counted.
* each marker either from a ``geometry_msgs`` topic: ``Point``, ``PointStamped``, ``Pose``,
  ``PoseStamped``, ``PoseWithCovarianceStamped``, ``Transform`` or ``TransformStamped`` (the
  position, and the orientation where the message has one); or from ``/tf`` and ``/tf_static``:
  the pose of frame CHILD in frame PARENT (the instrument's frame), along any chain of tf edges
  (:mod:`torchcal.measure.tfchain`). It must come from the instrument: ``robot_state_publisher``'s
  tf is the nominal model applied to the joint states, not a measurement.

Rows: the robot stood still where every joint stayed within ``still_tol`` (rad or m, max − min)
for at least ``still_s`` seconds (windows are maximal and do not overlap; a gap in the joint
states longer than ``still_s`` ends one). Each window is one row: the mean joint values and, per
marker, the mean of its samples stamped inside the window (from ``settle_s`` after its start).
Covariates: ``t_start_robot``, ``t_end_robot`` (s: the window's first and last joint sample, in
the chosen time base), ``marker_std_mm`` (the RMS over the window's samples of their 3-D distance
from the window mean, in mm; pooled over the markers seen when there are several) and
``marker_samples`` (samples averaged; the fewest of any marker seen).

Time: each message's header stamp (``stamps="header"``; the bag's receive time for a message
without a header or with a zero stamp) or the bag's receive time for every message
(``stamps="bag"``). Marker samples stamped in no kept window (taken while the robot moved) are
not used and are reported; a window in which no marker has ``min_samples`` samples is skipped and
reported; a marker with too few samples in a kept window is left empty (not seen) in that row.
"""
from __future__ import annotations

import re
from collections import defaultdict
from dataclasses import dataclass, field
from functools import reduce
from pathlib import Path

import numpy as np
import torch
from tqdm.auto import tqdm

from torchcal.measure.bag_files import INSTALL_HINT, BagReadOptions, joint_renamer
from torchcal.measure.bag_files import check_options as _check_options, open_bag as _open
from torchcal.measure.data import Measurements
from torchcal.measure.still import mean_quaternion, still_windows
from torchcal.measure.tfchain import chain_samples

__all__ = ["MarkerSource", "BagImport", "read_bag", "bag_to_measurements", "GEOMETRY_TYPES", "INSTALL_HINT"]

_JOINT_STATE = "sensor_msgs/msg/JointState"
_TF_TYPES = ("tf2_msgs/msg/TFMessage", "tf/msg/tfMessage")
_TF_TOPICS = ("/tf", "/tf_static")
# message type -> (fields leading to the position, to the orientation or None)
GEOMETRY_TYPES = {
    "geometry_msgs/msg/Point": ((), None),
    "geometry_msgs/msg/PointStamped": (("point",), None),
    "geometry_msgs/msg/Pose": (("position",), ("orientation",)),
    "geometry_msgs/msg/PoseStamped": (("pose", "position"), ("pose", "orientation")),
    "geometry_msgs/msg/PoseWithCovarianceStamped": (("pose", "pose", "position"), ("pose", "pose", "orientation")),
    "geometry_msgs/msg/Transform": (("translation",), ("rotation",)),
    "geometry_msgs/msg/TransformStamped": (("transform", "translation"), ("transform", "rotation")),
}
_NAME = re.compile(r"^[A-Za-z0-9_\-]+$")
_SOURCE_SYNTAX = ("write NAME=/topic (a geometry_msgs Point, Pose or Transform topic, stamped or not) or "
                  "NAME=tf:PARENT,CHILD (the pose of frame CHILD in frame PARENT, from /tf and /tf_static)")


@dataclass(frozen=True)
class MarkerSource:
    """Where a marker's samples come from: a ``geometry_msgs`` ``topic``, or the tf pose of frame
    ``child`` in frame ``parent``."""

    name: str
    topic: str | None = None
    parent: str | None = None
    child: str | None = None

    @classmethod
    def parse(cls, spec: str) -> "MarkerSource":
        """``NAME=/topic`` or ``NAME=tf:PARENT,CHILD`` (``tf:PARENT->CHILD`` too, quoted in a shell)."""
        name, sep, src = (s.strip() for s in str(spec).partition("="))
        if not sep or not src:
            raise ValueError(f"marker {spec!r}: {_SOURCE_SYNTAX}")
        if not _NAME.match(name):
            raise ValueError(f"marker {spec!r}: the name {name!r} may hold only letters, digits, '_' and '-' (it "
                             "names the CSV columns NAME.x, NAME.y, NAME.z)")
        if src.startswith("tf:"):
            frames = [f.strip().strip("/") for f in re.split(r",|->", src[3:])]
            if len(frames) != 2 or not all(frames) or frames[0] == frames[1]:
                raise ValueError(f"marker {spec!r}: give two different frames, e.g. {name}=tf:tracker,{name}; "
                                 f"{_SOURCE_SYNTAX}")
            return cls(name, parent=frames[0], child=frames[1])
        return cls(name, topic="/" + src.lstrip("/"))

    def __str__(self) -> str:
        return self.topic if self.topic else f"tf {self.parent} -> {self.child}"


@dataclass
class BagImport:
    """What :func:`read_bag` made of a bag (times in s, in the time base chosen).

    Attributes:
        data: one row per kept still window (see the module docstring).
        windows: ``(W, 2)`` start and end of every still window found, kept or not.
        skipped: ``(t_start, t_end, reason)`` of the windows left out.
        unused: marker -> ``(first, last, count)`` of each run of its samples not used (taken
            while the robot moved or settled, or in a skipped window).
        n_samples: marker -> samples read.
        stamps: topic -> the time used for its messages.
        notes: what else was noticed (ignored joint names, skipped messages).
        t0: the bag's first message time; the summary gives times from it.
    """

    data: Measurements
    windows: np.ndarray
    skipped: list[tuple[float, float, str]]
    unused: dict[str, list[tuple[float, float, int]]]
    n_samples: dict[str, int]
    stamps: dict[str, str]
    notes: list[str] = field(default_factory=list)
    t0: float = 0.0

    def summary(self) -> list[str]:
        """Lines for a person: rows, windows skipped and why, marker samples not used."""
        rel = lambda t: f"{t - self.t0:.2f}"  # noqa: E731
        out = [f"{len(self.data)} rows from {len(self.windows)} still windows (times below: s from the bag's start)"]
        if self.skipped:
            out.append(f"{len(self.skipped)} still window(s) skipped: " + "; ".join(
                f"{rel(a)}-{rel(b)} s ({why})" for a, b, why in self.skipped[:10]) + " ..." * (len(self.skipped) > 10))
        for m, runs in self.unused.items():
            n, k = self.n_samples[m], sum(r[2] for r in runs)
            out.append(f"marker {m}: {n - k} of {n} samples used" + (f"; {k} not used (taken in motion or settling, "
                       "or in a skipped window), at " + ", ".join(f"{rel(a)}-{rel(b)} s ({c})" if c > 1 else
                       f"{rel(a)} s" for a, b, c in runs[:8]) + " ..." * (len(runs) > 8) if k else ""))
        out.append("times: " + "; ".join(f"{k}: {v}" for k, v in self.stamps.items()))
        return out + self.notes


def _runs(t: np.ndarray, used: np.ndarray) -> list[tuple[float, float, int]]:
    """``(first, last, count)`` of each run of consecutive unused samples (times ``t``, sorted)."""
    idx = np.flatnonzero(~used)
    return [(float(t[g[0]]), float(t[g[-1]]), len(g)) for g in np.split(idx, np.flatnonzero(np.diff(idx) > 1) + 1)
            if len(g)]


class _Collector:
    """Samples gathered from the bag's messages, with the time each one is given."""

    def __init__(self, joint_names: list[str], header: bool, rename=None):
        self.joint_names, self.header = joint_names, header
        self.rename = rename or (lambda n: n)  # a bag's joint name -> the URDF's
        self.jt, self.jq = [], []  # joint sample times (s), values (dof,)
        self.geo = defaultdict(lambda: ([], [], []))  # topic -> times, positions, quaternions
        self.tf = defaultdict(lambda: ([], [], []))  # (parent, child) -> times, positions, quaternions
        self.tf_static: dict[tuple[str, str], tuple[np.ndarray, np.ndarray]] = {}
        self.n_stamp = defaultdict(lambda: [0, 0])  # topic -> [header stamps, bag times]
        self._index: dict[tuple, list[int]] = {}
        self.extra, self.seen, self.partial = set(), set(), 0  # joint names: not the URDF's, all; partial messages

    def time(self, topic: str, hdr, t_ns: int) -> float:
        if self.header and hdr is not None and (hdr.stamp.sec or hdr.stamp.nanosec):
            self.n_stamp[topic][0] += 1
            return hdr.stamp.sec + hdr.stamp.nanosec * 1e-9
        self.n_stamp[topic][1] += 1
        return t_ns * 1e-9

    def joints(self, topic: str, msg, t_ns: int) -> None:
        names = tuple(self.rename(n) for n in msg.name)
        idx = self._index.get(names)
        if idx is None:
            idx = self._index[names] = [names.index(j) if j in names else -1 for j in self.joint_names]
            self.extra.update(set(names) - set(self.joint_names))
            self.seen.update(names)
        if min(idx) < 0 or len(msg.position) != len(names):
            self.partial += 1
            return
        self.jt.append(self.time(topic, getattr(msg, "header", None), t_ns))
        self.jq.append(np.asarray(msg.position, dtype=np.float64)[idx])

    def geometry(self, topic: str, msgtype: str, msg, t_ns: int) -> None:
        pos, rot = GEOMETRY_TYPES[msgtype]
        t, p, r = self.geo[topic]
        t.append(self.time(topic, getattr(msg, "header", None), t_ns))
        p.append(_vec(reduce(getattr, pos, msg)))
        r.append(None if rot is None else _quat(reduce(getattr, rot, msg)))

    def transforms(self, topic: str, msg, t_ns: int) -> None:
        for tr in msg.transforms:
            key = (tr.header.frame_id.strip("/"), tr.child_frame_id.strip("/"))
            p, r = _vec(tr.transform.translation), _quat(tr.transform.rotation)
            if topic == "/tf_static":
                self.tf_static[key] = (p, r)
            else:
                t, ps, rs = self.tf[key]
                t.append(self.time(topic, tr.header, t_ns))
                ps.append(p)
                rs.append(r)


def _vec(v) -> np.ndarray:
    return np.array([v.x, v.y, v.z], dtype=np.float64)


def _quat(r) -> np.ndarray:
    return np.array([r.w, r.x, r.y, r.z], dtype=np.float64)


def _check_topics(bag: Path, topics: dict, joints: str, sources: list[MarkerSource]) -> None:
    """Refuse a missing topic or one of the wrong type, saying what the bag holds."""
    def of(types) -> list[str]:
        return [k for k, v in sorted(topics.items()) if v.msgtype in types]
    held = ", ".join(f"{k} ({v.msgtype})" for k, v in sorted(topics.items()))
    if topics.get(joints) is None or topics[joints].msgtype != _JOINT_STATE:
        what = f"has no topic {joints!r}" if joints not in topics else \
            f"topic {joints!r} carries {topics[joints].msgtype}, not {_JOINT_STATE}"
        raise ValueError(f"{bag} {what}; name the joint state topic with --joints (JointState topics in the bag: "
                         f"{of([_JOINT_STATE]) or 'none'}; its topics: {held})")
    for s in sources:
        if s.topic is None:
            if not of(_TF_TYPES):
                raise ValueError(f"{bag} has no /tf or /tf_static topic for marker {s.name} ({s}); its topics: {held}")
        elif s.topic not in topics or topics[s.topic].msgtype not in GEOMETRY_TYPES:
            what = "has no topic" if s.topic not in topics else f"carries {topics[s.topic].msgtype} on"
            raise ValueError(f"{bag} {what} {s.topic!r} (marker {s.name}); a marker topic must carry one of "
                             f"{[k.split('/')[-1] for k in GEOMETRY_TYPES]} (geometry_msgs); such topics in the bag: "
                             f"{of(GEOMETRY_TYPES) or 'none'}, or use NAME=tf:PARENT,CHILD")


def _collect(bag: Path, joints: str, sources: list[MarkerSource], joint_names: list[str], header: bool,
             progress: bool, rename=None) -> tuple[_Collector, float]:
    reader, reader_error = _open(bag)
    c = _Collector(joint_names, header, rename)
    try:
        with reader:
            topics = reader.topics
            _check_topics(bag, topics, joints, sources)
            want = {joints} | {s.topic for s in sources if s.topic}
            if any(s.topic is None for s in sources):
                want |= {k for k in _TF_TOPICS if k in topics and topics[k].msgtype in _TF_TYPES}
            conns = [x for x in reader.connections if x.topic in want]
            for conn, t_ns, raw in tqdm(reader.messages(connections=conns), total=sum(x.msgcount for x in conns),
                                        disable=not progress, unit="msg", desc="reading bag"):
                msg = reader.deserialize(raw, conn.msgtype)
                if conn.topic == joints:
                    c.joints(conn.topic, msg, t_ns)
                elif conn.msgtype in _TF_TYPES:
                    c.transforms(conn.topic, msg, t_ns)
                else:
                    c.geometry(conn.topic, conn.msgtype, msg, t_ns)
            return c, reader.start_time * 1e-9
    except reader_error as e:
        raise ValueError(f"{bag}: rosbags cannot read it: {e}") from None


def _marker_samples(s: MarkerSource, c: _Collector) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    if s.topic is None:
        t, p, r = chain_samples(c.tf, c.tf_static, s.parent, s.child, f"marker {s.name}")
    else:
        t, p, r = c.geo[s.topic]
        t, p, r = np.asarray(t), np.asarray(p), None if not r or r[0] is None else np.asarray(r)
    o = np.argsort(t, kind="stable")
    return t[o], p[o].reshape(-1, 3), None if r is None else r[o]


def read_bag(bag, robot, markers, settings: BagReadOptions | None = None, **kw) -> BagImport:
    """Still poses of a ROS bag as measurement rows (see the module docstring).

    Args:
        bag: ROS 1 ``.bag`` file, ROS 2 bag directory, or a ROS 2 ``.db3`` / ``.mcap`` file.
        robot: the :class:`~torchcal.kinematics.robot.Robot`; its joint names (the URDF's) name the
            joint columns.
        markers: :class:`MarkerSource` or strings ``NAME=/topic`` / ``NAME=tf:PARENT,CHILD``.
        settings: a :class:`~torchcal.measure.bag_files.BagReadOptions` (the topic of the joints, what
            counts as still, the time base, the joint names' map); ``kw``: any of its fields
            (``read_bag(bag, robot, markers, still_s=1.0)``).
    Returns a :class:`BagImport`; ``.data`` holds ``q (K, dof)`` rad / m and ``positions (K, M, 3)``
    m. Raises ``ValueError`` saying what is wrong and how to fix it; ``ModuleNotFoundError``
    without rosbags.
    """
    o = BagReadOptions.build(settings, **kw)
    joints, still_s, still_tol, settle_s, min_samples = o.joints, o.still_s, o.still_tol, o.settle_s, o.min_samples
    _check_options(still_s, still_tol, settle_s, min_samples, o.stamps)
    sources = [s if isinstance(s, MarkerSource) else MarkerSource.parse(s) for s in markers]
    names = [s.name for s in sources]
    if not sources or len(set(names)) != len(names):
        raise ValueError(f"give each marker once, with a distinct name (got {names})")
    bag = Path(bag)
    joint_names = list(robot.joint_names)
    c, t0 = _collect(bag, joints, sources, joint_names, o.stamps == "header", o.progress, joint_renamer(o.joint_map))
    if len(c.jt) < 2:
        raise ValueError(f"{bag}: no message on {joints} names all of the URDF's joints {joint_names} (it names "
                         f"{sorted(c.seen)}); the JointState names must be the URDF's joint names: map them with "
                         "joint_map (--strip-prefix PREFIX or --joint-map BAG_NAME=URDF_NAME)")
    order = np.argsort(c.jt, kind="stable")
    tj, qj = np.asarray(c.jt)[order], np.stack(c.jq)[order]
    samples = {s.name: _marker_samples(s, c) for s in sources}
    for s in sources:
        t = samples[s.name][0]
        if not len(t) or t[-1] < tj[0] or t[0] > tj[-1]:
            raise ValueError(f"marker {s.name} ({s}): {len(t)} samples, none between the first and last joint state "
                             f"({tj[0]:.3f}-{tj[-1]:.3f} s); if their clocks differ, try stamps='bag' (--stamps bag)")
    wins = still_windows(tj, qj, still_s, still_tol)
    skipped, used, rows = _rows(tj, qj, wins, samples, settle_s, min_samples)
    if not rows:
        raise ValueError(f"{bag}: no row: {len(wins)} still windows (joints within {still_tol:g} rad or m for "
                         f"{still_s:g} s or more), {len(skipped)} without marker samples; try a shorter still_s "
                         "(--still-s) or a larger still_tol (--still-tol)")
    data = _measurements(rows, sources, samples, joint_names, robot)
    stamp_words = {k: "header stamps" if b == 0 else "bag time" if h == 0 else f"header stamps ({b} by bag time)"
                   for k, (h, b) in c.n_stamp.items()}
    notes = []
    if c.extra:
        notes.append(f"{joints}: names not among the URDF's joints, ignored: {sorted(c.extra)}")
    if c.partial:
        notes.append(f"{joints}: {c.partial} message(s) without all of the robot's joints skipped")
    return BagImport(data, np.array([(tj[i], tj[j - 1]) for i, j in wins]).reshape(-1, 2), skipped,
                     {m: _runs(samples[m][0], u) for m, u in used.items()}, {m: len(samples[m][0]) for m in samples},
                     stamp_words, notes, t0)


def _rows(tj, qj, wins, samples, settle_s, min_samples):
    """Per kept window: ``(t_start, t_end, q mean, {marker: (a, b)})``; the windows skipped; and
    marker -> which of its samples were used."""
    rows, skipped = [], []
    used = {m: np.zeros(len(s[0]), dtype=bool) for m, s in samples.items()}
    for i, j in wins:
        ts, te = float(tj[i]), float(tj[j - 1])
        span = {m: (int(np.searchsorted(t, ts + settle_s, "left")), int(np.searchsorted(t, te, "right")))
                for m, (t, _, _) in samples.items()}
        seen = {m: ab for m, ab in span.items() if ab[1] - ab[0] >= min_samples}
        if not seen:
            most = max(b - a for a, b in span.values())
            skipped.append((ts, te, "no marker sample" if most == 0 else f"{most} marker sample(s), fewer than "
                            f"min_samples = {min_samples}"))
            continue
        for m, (a, b) in seen.items():
            used[m][a:b] = True
        rows.append((ts, te, qj[i:j].mean(0), seen))
    return skipped, used, rows


def _measurements(rows, sources, samples, joint_names, robot) -> Measurements:
    K, M = len(rows), len(sources)
    P, R = np.full((K, M, 3), np.nan), np.full((K, M, 4), np.nan)
    std, count = np.zeros(K), np.zeros(K)
    for k, (_, _, _, seen) in enumerate(rows):
        ms = []
        for n, s in enumerate(sources):
            if s.name not in seen:
                continue
            a, b = seen[s.name]
            _, p, r = samples[s.name]
            P[k, n] = p[a:b].mean(0)
            if b - a > 1:  # one sample shows no spread
                ms.append(float(((p[a:b] - P[k, n]) ** 2).sum(1).mean()))
            if r is not None:
                R[k, n] = mean_quaternion(r[a:b])
        std[k] = 1000.0 * np.sqrt(np.mean(ms)) if ms else np.nan
        count[k] = min(b - a for a, b in seen.values())
    has_rot = any(samples[s.name][2] is not None for s in sources)
    cov = {"t_start_robot": [r[0] for r in rows], "t_end_robot": [r[1] for r in rows], "marker_std_mm": std,
           "marker_samples": count}
    as_t = lambda x: torch.as_tensor(np.asarray(x, dtype=np.float64), dtype=robot.dtype, device=robot.device)  # noqa
    return Measurements(as_t([r[2] for r in rows]), as_t(P), [s.name for s in sources], list(joint_names),
                        as_t(R) if has_rot else None, {k: as_t(v) for k, v in cov.items()})


def bag_to_measurements(bag, robot, markers, **options) -> Measurements:
    """The rows of :func:`read_bag` alone (options as there). Write them with
    :func:`torchcal.measure.io.save_measurements`."""
    return read_bag(bag, robot, markers, **options).data
