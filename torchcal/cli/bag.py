"""``torchcal import-bag``: a measurement CSV from a ROS 1 or ROS 2 bag (sqlite3 or MCAP), one
row per still pose (:mod:`torchcal.measure.rosbag`; needs ``pip install 'torchcal[ros]'``).

Writes joint columns named as in the URDF (rad / m), ``<marker>.x/.y/.z`` (m), orientation
columns where the marker's messages carry one, and the covariates ``t_start_robot``,
``t_end_robot`` (s), ``marker_std_mm`` and ``marker_samples``; prints rows written, still windows
skipped and why, and the marker samples not used. Never overwrites a file (``--force``).
"""
from __future__ import annotations

import argparse
import sys

import torch

from torchcal.cli.conventions import add_progress, progress_on
from torchcal.cli.common import add_common, int_at_least, nonnegative_float, positive_float
from torchcal.kinematics.robot import Robot
from torchcal.measure.instrument import parse_column_map
from torchcal.measure.io import save_measurements
from torchcal.measure.rosbag import MarkerSource, read_bag
from torchcal.outputs import check_out_file

__all__ = ["add_bag_parser", "bag_main"]


def _source(text: str) -> MarkerSource:
    try:
        return MarkerSource.parse(text)
    except ValueError as e:
        raise argparse.ArgumentTypeError(str(e)) from None


def add_bag_parser(sub) -> argparse.ArgumentParser:
    """Add the ``import-bag`` sub-command to an ``argparse`` sub-parser set."""
    p = sub.add_parser("import-bag", help="measurement CSV from a ROS 1 / ROS 2 bag: one row per still pose",
                       description="Read joint states and a marker from a ROS bag (ROS 1 .bag, ROS 2 sqlite3 or "
                                   "MCAP; no ROS install needed), find where the robot stood still, and write one "
                                   "averaged row per still pose.")
    p.add_argument("bag", help="ROS 1 .bag file, ROS 2 bag directory, or a ROS 2 .db3 / .mcap file")
    p.add_argument("--robot", required=True, help="URDF; the joint columns take its joint names")
    p.add_argument("--joints", default="/joint_states", help="sensor_msgs/JointState topic")
    p.add_argument("--marker", action="append", required=True, type=_source,
                   metavar="NAME=/topic | NAME=tf:PARENT,CHILD",
                   help="a marker and where it is measured: a geometry_msgs Point, Pose or Transform topic "
                        "(stamped or not), or the pose of tf frame CHILD in frame PARENT (the instrument's frame; "
                        "any chain of /tf and /tf_static edges). Repeatable")
    p.add_argument("--out", required=True, help="measurement CSV to write (refused if it exists; see --force)")
    p.add_argument("--still-s", type=positive_float, default=0.5,
                   help="least time the joints stand still for a row (s)")
    p.add_argument("--still-tol", type=positive_float, default=5e-5,
                   help="how far each joint may move (max - min) and still count as still (rad or m)")
    p.add_argument("--settle-s", type=nonnegative_float, default=0.0,
                   help="leave out marker samples in the first SETTLE_S seconds of each still window (vibration "
                        "after a stop)")
    p.add_argument("--min-samples", type=int_at_least(1), default=3,
                   help="least marker samples in a still window for the marker to count as seen")
    p.add_argument("--stamps", choices=("header", "bag"), default="header",
                   help="time of each message: its header stamp (bag time where it has none) or the bag's receive "
                        "time")
    add_progress(p, "the bag's messages")
    names = p.add_mutually_exclusive_group()
    names.add_argument("--strip-prefix", metavar="PREFIX",
                       help="take PREFIX off the bag's joint names (ur_shoulder_pan_joint -> shoulder_pan_joint with "
                            "--strip-prefix ur_)")
    names.add_argument("--joint-map", action="append", metavar="BAG_NAME=URDF_NAME",
                       help="the URDF's name of a joint the bag names otherwise (repeatable)")
    add_common(p, units=False)
    p.set_defaults(func=bag_main)
    return p


def bag_main(a: argparse.Namespace, argv: list[str] | None = None) -> int:
    """Run ``torchcal import-bag`` with parsed arguments (see :func:`add_bag_parser`)."""
    out = check_out_file(a.out, a.force, inputs=(a.bag,))
    torch.set_num_threads(a.threads)
    robot = Robot.from_urdf(a.robot)
    progress = progress_on(a)
    try:
        res = read_bag(a.bag, robot, a.marker, joints=a.joints, still_s=a.still_s, still_tol=a.still_tol,
                       settle_s=a.settle_s, min_samples=a.min_samples, stamps=a.stamps, progress=progress,
                       joint_map=a.strip_prefix or parse_column_map(a.joint_map) or None)
    except ModuleNotFoundError as e:
        print(f"torchcal import-bag: error: {e}", file=sys.stderr)
        return 2
    save_measurements(out, res.data)
    print(f"{robot.name}: " + "\n".join(res.summary()))
    print(f"wrote {len(res.data)} rows to {out}")
    return 0
