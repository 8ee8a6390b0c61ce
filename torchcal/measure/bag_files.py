"""A ROS bag on disk: what a path must be to be a bag, the reader that opens it, the import's
options checked, and a bag's joint names as the URDF's."""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from torchcal.options import Options

__all__ = ["BagReadOptions", "check_bag_path", "open_bag", "check_options", "joint_renamer", "BAG_SHAPES"]

INSTALL_HINT = "pip install 'torchcal[ros]'"
BAG_SHAPES = ("a bag is a ROS 1 .bag file, a ROS 2 bag directory (metadata.yaml beside its .db3 or .mcap files), "
              "or one ROS 2 .db3 / .mcap file")


@dataclass(frozen=True)
class BagReadOptions(Options):
    """The settings of :func:`~torchcal.measure.rosbag.read_bag`.

    Attributes:
        joints: the ``sensor_msgs/JointState`` topic.
        still_s: least time (s) the joints stand still for a row. ``still_tol``: how far (rad or m,
            max − min per joint) they may move then. ``settle_s``: marker samples in the first
            ``settle_s`` seconds of a window are left out (vibration after a stop).
        min_samples: least marker samples in a window for the marker to count as seen there.
        stamps: ``"header"`` or ``"bag"`` (see :mod:`torchcal.measure.rosbag`).
        progress: a progress bar over the messages.
        joint_map: the bag's joint names as the URDF's: a prefix to take off (``"ur_"``) or a
            dict ``{bag name: URDF name}``; None: as they are.
    """
    joints: str = "/joint_states"
    still_s: float = 0.5
    still_tol: float = 5e-5
    settle_s: float = 0.0
    min_samples: int = 3
    stamps: str = "header"
    progress: bool = False
    joint_map: object = None


def check_bag_path(bag: Path) -> None:
    """Refuse a path that is no bag, saying what a bag looks like (the reading library would
    only say that a metadata file is missing)."""
    if not bag.exists():
        raise FileNotFoundError(f"bag not found: {bag}; {BAG_SHAPES}")
    if bag.is_file() and bag.suffix in (".bag", ".db3", ".mcap"):
        return
    if bag.is_dir():
        if (bag / "metadata.yaml").is_file():
            return
        inside = sorted(p.name for p in bag.iterdir() if p.suffix in (".bag", ".db3", ".mcap"))[:3]
        raise ValueError(f"{bag} is a directory but not a ROS 2 bag: it has no metadata.yaml; {BAG_SHAPES}"
                         + (f" (it holds {inside}: give one of them)" if inside else ""))
    raise ValueError(f"{bag} is not a bag (a {bag.suffix or 'suffix-less'} file); {BAG_SHAPES}")


def open_bag(bag: Path):
    """A ``rosbags`` AnyReader (not yet opened) and its error type, or the reason why not."""
    try:
        from rosbags.highlevel import AnyReader, AnyReaderError
        from rosbags.typesys import Stores, get_typestore
    except ImportError:
        raise ModuleNotFoundError(f"reading ROS bags needs the rosbags package: {INSTALL_HINT}") from None
    check_bag_path(bag)
    store = get_typestore(Stores.ROS1_NOETIC if bag.suffix == ".bag" else Stores.ROS2_HUMBLE)
    try:
        return AnyReader([bag], default_typestore=store), AnyReaderError
    except AnyReaderError as e:
        raise ValueError(f"{bag}: rosbags cannot read it: {e}") from None


def check_options(still_s, still_tol, settle_s, min_samples, stamps) -> None:
    if not (still_s > 0 and still_tol > 0 and settle_s >= 0 and min_samples >= 1):
        raise ValueError(f"still_s ({still_s}) and still_tol ({still_tol}) must be positive, settle_s ({settle_s}) "
                         f"zero or more, min_samples ({min_samples}) at least 1")
    if stamps not in ("header", "bag"):
        raise ValueError(f"stamps must be 'header' (the messages' header stamps) or 'bag' (receive time), got {stamps!r}")


def joint_renamer(joint_map: dict | str | None):
    """A bag's joint name -> the URDF's: ``joint_map`` a prefix to take off (``"ur_"``), a dict
    ``{bag name: URDF name}``, or None (names as they are)."""
    if not joint_map:
        return lambda n: n
    if isinstance(joint_map, str):
        return lambda n: n[len(joint_map):] if n.startswith(joint_map) else n
    if not isinstance(joint_map, dict):
        raise TypeError("joint_map must be a prefix (str) or a dict {bag name: URDF name}, got "
                        f"{type(joint_map).__name__}")
    return lambda n: joint_map.get(n, n)
