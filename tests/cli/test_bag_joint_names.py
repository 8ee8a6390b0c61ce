"""``torchcal import-bag`` with a bag whose joint names carry a prefix (``ur_shoulder_pan_joint``
against the URDF's ``shoulder_pan_joint``), and with a path that is no bag."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("rosbags", reason="the ROS bag tests need rosbags: pip install 'torchcal[ros]'")

from torchcal.cli.app import main  # noqa: E402
from torchcal.kinematics.robot import Robot  # noqa: E402
from torchcal.measure.io import load_measurements  # noqa: E402
from torchcal.sim.bag import write_bag  # noqa: E402

URDF = str(Path(__file__).resolve().parents[2] / "urdf" / "ur5e.urdf")
K = 4


@pytest.fixture(scope="module")
def prefixed_bag(tmp_path_factory):
    """A ROS 1 bag whose JointState names are the URDF's with ``ur_`` in front, and its still poses."""
    robot = Robot.from_urdf(URDF)
    g = np.random.default_rng(1)
    q = g.uniform(-2.0, 2.0, (K, robot.dof))
    p = g.uniform(-1.0, 1.0, (K, 3)) + np.array([2.0, 0.5, 0.3])
    path = tmp_path_factory.mktemp("bag") / "run.bag"
    write_bag(path, q, p, [f"ur_{j}" for j in robot.joint_names], noise_m=1e-5)
    return path, q


def _cli(*args):
    return main(["import-bag", *map(str, args), "--no-progress"])


def test_prefixed_names_are_refused_with_the_way_out(tmp_path, prefixed_bag, capsys):
    path, _ = prefixed_bag
    assert _cli(path, "--robot", URDF, "--marker", "tcp=/tracker/point", "--out", tmp_path / "x.csv") == 2
    err = capsys.readouterr().err
    assert "ur_shoulder_pan_joint" in err and "--strip-prefix" in err and "--joint-map" in err
    assert not (tmp_path / "x.csv").exists()


@pytest.mark.parametrize("how", [["--strip-prefix", "ur_"],
                                 [x for j in Robot.from_urdf(URDF).joint_names for x in ("--joint-map", f"ur_{j}={j}")]])
def test_prefix_or_name_map_reads_the_bag(tmp_path, prefixed_bag, how):
    path, q = prefixed_bag
    out = tmp_path / "data.csv"
    assert _cli(path, "--robot", URDF, "--marker", "tcp=/tracker/point", "--out", out, *how) == 0
    data = load_measurements(out, Robot.from_urdf(URDF, markers=["tcp@flange"]))
    assert len(data) == K and np.abs(data.q.numpy() - q).max() < 1e-5  # joint noise 1e-6 rad, averaged


@pytest.mark.parametrize("make, words", [
    (lambda d: (d / "data.csv").write_text("a,b\n1,2\n") and d / "data.csv", "is not a bag"),
    (lambda d: (d / "folder").mkdir() or d / "folder", "no metadata.yaml"),
])
def test_a_path_that_is_no_bag_says_what_a_bag_looks_like(tmp_path, capsys, make, words):
    path = make(tmp_path)
    assert _cli(path, "--robot", URDF, "--marker", "tcp=/tracker/point", "--out", tmp_path / "x.csv") == 2
    err = capsys.readouterr().err
    assert words in err and "ROS 1 .bag file" in err and "metadata.yaml" in err
    assert "Expected metadata file" not in err
