"""A ROS bag of a simulated UR5e calibration run, to try ``torchcal import-bag`` on.

The robot (with random geometric errors, a laser tracker 3 m away) visits ``--poses`` still poses,
1.5 s each, moving 1 s between them. The bag holds ``/joint_states`` (100 Hz) and the tracker's
``/tracker/point`` (``geometry_msgs/PointStamped``, 50 Hz, ``--noise-mm`` per axis and sample,
also while the robot moves). The reflector sits 5 cm beyond the flange
(``--marker tcp@flange=0,0,0.05`` for the other commands).

    python scripts/make_example_bag.py --out run_bag [--storage mcap|sqlite3|ros1]
"""
from __future__ import annotations

import argparse
import shutil
import sys
from pathlib import Path

import torch

from torchcal.kinematics.robot import Robot
from torchcal.sim.bag import STORAGES, write_bag
from torchcal.sim.serial import SimConfig, simulate

URDF = Path(__file__).resolve().parents[1] / "urdf" / "ur5e.urdf"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", default="run_bag", help="bag to write: a directory (ROS 2) or a .bag file (ROS 1)")
    ap.add_argument("--storage", choices=STORAGES, default="mcap", help="ROS 2 MCAP (default), ROS 2 sqlite3, ROS 1")
    ap.add_argument("--poses", type=int, default=20, help="still poses (default 20)")
    ap.add_argument("--noise-mm", type=float, default=0.02, help="tracker noise per axis and sample (mm)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--force", action="store_true", help="replace an existing bag")
    a = ap.parse_args()
    torch.set_num_threads(1)
    out = Path(a.out)
    if a.storage == "ros1" and out.suffix != ".bag":
        out = out.with_suffix(".bag")
    if out.exists():
        if not a.force:
            print(f"{out} exists; choose another --out or pass --force", file=sys.stderr)
            return 2
        shutil.rmtree(out) if out.is_dir() else out.unlink()
    robot = Robot.from_urdf(URDF, markers=["tcp@flange=0,0,0.05"])
    # noise-free marker positions at the still poses; the bag adds the noise to every sample
    data, _ = simulate(robot, SimConfig(n=a.poses, noise=0.0, seed=a.seed))
    write_bag(out, data.q.numpy(), data.positions[:, 0].numpy(), robot.joint_names, storage=a.storage,
              noise_m=a.noise_mm / 1000, seed=a.seed)
    print(f"wrote {out}: {a.poses} still poses of a simulated UR5e, /joint_states and /tracker/point "
          f"({a.storage})")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
