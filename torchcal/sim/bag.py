"""A simulated calibration run recorded as a ROS bag, written with ``rosbags`` (``pip install
'torchcal[ros]'``): the robot visits still poses with straight-line motion in between, its joint
states at ``joint_hz``, an instrument's marker at ``marker_hz`` with Gaussian noise. ROS 1
(``.bag``) or ROS 2 (sqlite3 or MCAP storage). For tests and examples of
:mod:`torchcal.measure.rosbag`; the truth is returned apart from the bag."""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from torchcal.options import Options

__all__ = ["BagTruth", "BagOptions", "write_bag", "STORAGES", "MARKER_KINDS"]

STORAGES = ("ros1", "sqlite3", "mcap")
# how the marker is published: a topic of PointStamped / PoseStamped / TransformStamped, or /tf
MARKER_KINDS = {"point": "geometry_msgs/msg/PointStamped", "pose": "geometry_msgs/msg/PoseStamped",
                "transform": "geometry_msgs/msg/TransformStamped", "tf": "tf2_msgs/msg/TFMessage"}
_LATENCY_S = 0.002  # bag receive time after the header stamp


@dataclass
class BagTruth:
    """What the simulated bag holds, for checking an import (times in s, header stamps).

    Attributes:
        q: ``(K, dof)`` joint values at the still poses (rad / m).
        p: ``(K, 3)`` marker position at each still pose (m, in the instrument frame).
        quat: ``(K, 4)`` marker orientation (w, x, y, z) in the same frame.
        still: ``(K, 2)`` start and end of each still pose.
        stray: times of the marker samples injected while the robot moved.
        noise_m: marker noise, std per axis (m).
    """

    q: np.ndarray
    p: np.ndarray
    quat: np.ndarray
    still: np.ndarray
    stray: np.ndarray
    noise_m: float


def _profile(t: np.ndarray, stops: np.ndarray, still_s: float, move_s: float) -> np.ndarray:
    """``(n, d)`` values at times ``t``: ``stops[k]`` while still, straight lines while moving."""
    period = still_s + move_s
    k = np.clip(np.floor(t / period).astype(int), 0, len(stops) - 1)
    alpha = np.clip((t - k * period - still_s) / move_s, 0.0, 1.0)[:, None]
    nxt = np.minimum(k + 1, len(stops) - 1)
    return stops[k] + alpha * (stops[nxt] - stops[k])


def _inside(t: np.ndarray, spans: np.ndarray) -> np.ndarray:
    """Which times ``t (n,)`` fall in any of the ``spans (k, 2)``."""
    return ((t[:, None] >= spans[:, 0]) & (t[:, None] <= spans[:, 1])).any(1)


def _typestore(ros1: bool):
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    ts = get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.ROS2_HUMBLE)
    if "tf2_msgs/msg/TFMessage" not in ts.types:  # ROS 1's store lacks it
        ts.register(get_types_from_msg("geometry_msgs/TransformStamped[] transforms", "tf2_msgs/msg/TFMessage"))
    return ts


class _Msgs:
    """Messages of one typestore (ROS 1 headers carry a ``seq``, ROS 2 headers do not)."""

    def __init__(self, ts):
        self.T = ts.types

    def header(self, t: float, frame: str = ""):
        ns = int(round(t * 1e9))
        stamp = self.T["builtin_interfaces/msg/Time"](sec=ns // 10**9, nanosec=ns % 10**9)
        H = self.T["std_msgs/msg/Header"]
        return H(seq=0, stamp=stamp, frame_id=frame) if "seq" in H.__dataclass_fields__ else H(stamp=stamp,
                                                                                                frame_id=frame)

    def vec(self, kind: str, v):
        return self.T[f"geometry_msgs/msg/{kind}"](x=float(v[0]), y=float(v[1]), z=float(v[2]))

    def quat(self, r):
        return self.T["geometry_msgs/msg/Quaternion"](w=float(r[0]), x=float(r[1]), y=float(r[2]), z=float(r[3]))

    def transform(self, t: float, parent: str, child: str, p, r):
        tr = self.T["geometry_msgs/msg/Transform"](translation=self.vec("Vector3", p), rotation=self.quat(r))
        return self.T["geometry_msgs/msg/TransformStamped"](header=self.header(t, parent), child_frame_id=child,
                                                            transform=tr)

    def marker(self, kind: str, t: float, parent: str, child: str, p, r):
        G = "geometry_msgs/msg/"
        if kind == "point":
            return self.T[G + "PointStamped"](header=self.header(t, parent), point=self.vec("Point", p))
        if kind == "pose":
            pose = self.T[G + "Pose"](position=self.vec("Point", p), orientation=self.quat(r))
            return self.T[G + "PoseStamped"](header=self.header(t, parent), pose=pose)
        tr = self.transform(t, parent, child, p, r)
        return tr if kind == "transform" else self.T["tf2_msgs/msg/TFMessage"](transforms=[tr])


@dataclass(frozen=True)
class BagOptions(Options):
    """How :func:`write_bag` records the run (times in s).

    Attributes:
        storage: ``"ros1"``, ``"sqlite3"`` or ``"mcap"``.
        marker: ``"point"``, ``"pose"``, ``"transform"`` (on ``topic``) or ``"tf"`` (on ``/tf``: the
            pose of ``frames[1]`` in ``frames[0]``, beside a ``base_link -> tool0`` transform that is
            not the marker).
        static: ``(translation (3,), quaternion (4,))`` of ``frames[0]`` in a frame ``world``, sent
            on ``/tf_static`` (the returned truth stays in ``frames[0]``).
        still_s, move_s: how long the robot stays at each pose and moves between two.
        joint_hz, marker_hz: sample rates of the joint states and the marker (Hz).
        noise_m: marker noise, std per axis (m); joint_noise: joint-state noise (rad / m).
        in_motion: the instrument also samples while the robot moves (otherwise only when still).
        stray: times (s from the start) of extra marker samples (meant to fall in motion).
        extra_joints: names also published on ``/joint_states`` (a gripper), not in ``joint_names``.
        lost: still poses (indices) at which the instrument sees nothing.
        t0: header stamps are ``t0 + t``; the bag's receive time is 2 ms later.
        seed: seeds the noise.
    """

    storage: str = "ros1"
    marker: str = "point"
    topic: str = "/tracker/point"
    frames: tuple[str, str] = ("tracker", "smr")
    static: tuple | None = None
    still_s: float = 1.5
    move_s: float = 1.0
    joint_hz: float = 100.0
    marker_hz: float = 50.0
    noise_m: float = 5e-5
    joint_noise: float = 1e-6
    in_motion: bool = True
    stray: tuple[float, ...] = ()
    extra_joints: tuple[str, ...] = ()
    lost: tuple[int, ...] = ()
    t0: float = 1.7e9
    seed: int = 0


@dataclass
class _Samples:
    """The run as sampled: joint-state times ``tj`` and values ``qj``, marker times ``tm``,
    positions ``pm`` and orientations ``rm``, the still spans (s from the start)."""

    tj: np.ndarray
    qj: np.ndarray
    tm: np.ndarray
    pm: np.ndarray
    rm: np.ndarray
    still: np.ndarray


def _sample(q: np.ndarray, p: np.ndarray, quat: np.ndarray, o: BagOptions) -> _Samples:
    g = np.random.default_rng(o.seed)
    K = len(q)
    span = K * o.still_s + (K - 1) * o.move_s
    tj = np.arange(int(span * o.joint_hz) + 1) / o.joint_hz
    qj = _profile(tj, q, o.still_s, o.move_s) + g.normal(0.0, o.joint_noise, (len(tj), q.shape[1]))
    period = o.still_s + o.move_s
    still = np.stack([np.arange(K) * period, np.arange(K) * period + o.still_s], 1)
    tm = (np.arange(int(span * o.marker_hz)) + 0.37) / o.marker_hz
    if not o.in_motion:
        tm = tm[_inside(tm, still)]
    if o.lost:
        tm = tm[~_inside(tm, still[list(o.lost)])]
    tm = np.sort(np.r_[tm, np.asarray(o.stray, dtype=np.float64)])
    pm = _profile(tm, p, o.still_s, o.move_s) + g.normal(0.0, o.noise_m, (len(tm), 3))
    rm = quat[np.clip(np.floor(tm / period).astype(int), 0, K - 1)]
    return _Samples(tj, qj, tm, pm, rm, still)


def _record(path, joint_names: list[str], s: _Samples, o: BagOptions) -> None:
    """Write the sampled run's messages, in time order, to a bag at ``path``."""
    from rosbags.rosbag1 import Writer as Writer1
    from rosbags.rosbag2 import StoragePlugin, Writer as Writer2

    ros1 = o.storage == "ros1"
    ts = _typestore(ros1)
    m = _Msgs(ts)
    ser = ts.serialize_ros1 if ros1 else ts.serialize_cdr
    plugin = StoragePlugin.MCAP if o.storage == "mcap" else StoragePlugin.SQLITE3
    writer = Writer1(Path(path)) if ros1 else Writer2(Path(path), version=Writer2.VERSION_LATEST, storage_plugin=plugin)
    events = []
    t0, frames = o.t0, o.frames
    with writer:
        def add(topic_name: str, msgtype: str, items):
            conn = writer.add_connection(topic_name, msgtype, typestore=ts)
            events.extend((t, conn, msgtype, msg) for t, msg in items)

        names = list(joint_names) + list(o.extra_joints)
        add("/joint_states", "sensor_msgs/msg/JointState",
            ((t, ts.types["sensor_msgs/msg/JointState"](
                header=m.header(t0 + t), name=names, position=np.r_[v, np.zeros(len(o.extra_joints))],
                velocity=np.zeros(0), effort=np.zeros(0))) for t, v in zip(s.tj, s.qj)))
        items = [(t, m.marker(o.marker, t0 + t, frames[0], frames[1], v, r)) for t, v, r in zip(s.tm, s.pm, s.rm)]
        if o.marker == "tf":  # what robot_state_publisher would add beside it: not the marker
            items += [(t, ts.types["tf2_msgs/msg/TFMessage"](transforms=[m.transform(
                t0 + t, "base_link", "tool0", [0.0, 0.0, 0.5], [1.0, 0.0, 0.0, 0.0])])) for t in s.tj[::5]]
        add("/tf" if o.marker == "tf" else o.topic, MARKER_KINDS[o.marker], items)
        if o.static is not None:
            add("/tf_static", "tf2_msgs/msg/TFMessage", [(0.0, ts.types["tf2_msgs/msg/TFMessage"](
                transforms=[m.transform(t0, "world", frames[0], o.static[0], o.static[1])]))])
        for t, conn, msgtype, msg in sorted(events, key=lambda e: e[0]):
            writer.write(conn, int(round((t0 + t + _LATENCY_S) * 1e9)), ser(msg, msgtype))


def write_bag(path, q: np.ndarray, p: np.ndarray, joint_names: list[str], *, quat: np.ndarray | None = None,
              settings: BagOptions | None = None, **kw) -> BagTruth:
    """Write a bag at ``path`` (a ``.bag`` file for ROS 1, a new directory for ROS 2).

    Args:
        q: ``(K, dof)`` still joint values (rad / m), visited in order; ``p``: ``(K, 3)`` marker
            positions there (m, instrument frame); ``quat``: ``(K, 4)`` orientations (w, x, y, z;
            default identity).
        settings, kw: a :class:`BagOptions` and/or its fields as keywords (``storage``, ``marker``,
            ``noise_m``, ``lost``, …).
    Times: header stamps ``t0 + t``; the bag's receive time is 2 ms later.
    """
    o = BagOptions.build(settings, **kw)
    if o.storage not in STORAGES or o.marker not in MARKER_KINDS:
        raise ValueError(f"storage must be one of {STORAGES} and marker one of {list(MARKER_KINDS)}")
    q, p = np.asarray(q, dtype=np.float64), np.asarray(p, dtype=np.float64)
    quat = np.tile([1.0, 0.0, 0.0, 0.0], (len(q), 1)) if quat is None else np.asarray(quat, dtype=np.float64)
    s = _sample(q, p, quat, o)
    _record(path, joint_names, s, o)
    return BagTruth(q, p, quat, s.still + o.t0, np.asarray(o.stray, dtype=np.float64) + o.t0, o.noise_m)
