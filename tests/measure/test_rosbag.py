"""ROS bags in (``torchcal import-bag``, :mod:`torchcal.measure.rosbag`): bags written here by
``rosbags`` from a simulated robot with known still poses, in ROS 1 and ROS 2 (sqlite3, MCAP)."""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest
import torch

pytest.importorskip("rosbags", reason="the ROS bag tests need rosbags: pip install 'torchcal[ros]' "
                                      "(make test installs it)")

from torchcal.cli.app import main  # noqa: E402
from torchcal.kinematics.robot import Robot  # noqa: E402
from torchcal.kinematics.transforms import quat_to_matrix  # noqa: E402
from torchcal.measure.io import load_measurements  # noqa: E402
from torchcal.measure.rosbag import read_bag  # noqa: E402
from torchcal.measure.still import still_windows  # noqa: E402
from torchcal.sim.bag import write_bag  # noqa: E402

URDF = str(Path(__file__).resolve().parents[2] / "urdf" / "ur5e.urdf")
K, NOISE = 5, 5e-5  # still poses; marker noise per axis (m)


@pytest.fixture(scope="module")
def robot():
    return Robot.from_urdf(URDF)


@pytest.fixture(scope="module")
def stops(robot):
    """``(K, 6)`` still joint values (rad), ``(K, 3)`` marker positions (m, instrument frame),
    ``(K, 4)`` marker orientations."""
    g = np.random.default_rng(0)
    q = g.uniform(-2.0, 2.0, (K, robot.dof))
    p = g.uniform(-1.0, 1.0, (K, 3)) + np.array([2.0, 0.5, 0.3])
    r = g.normal(size=(K, 4))
    return q, p, r / np.linalg.norm(r, axis=1, keepdims=True)


def _bag(tmp_path, robot, stops, storage="ros1", **kw):
    q, p, r = stops
    path = tmp_path / ("run.bag" if storage == "ros1" else f"run_{storage}")
    return path, write_bag(path, q, p, robot.joint_names, storage=storage, quat=r, noise_m=NOISE, **kw)


def _check_rows(data, truth, marker=0):
    """K rows; joints equal to the still values; marker means within noise / sqrt(n); the spread
    covariate matching the injected noise."""
    assert len(data) == K
    assert np.abs(data.q.numpy() - truth.q).max() < 1e-6  # joint noise 1e-6 rad, averaged over 150 samples
    n = data.covariates["marker_samples"].numpy()
    assert (n >= 70).all()  # 1.5 s at 50 Hz
    err = np.abs(data.positions[:, marker].numpy() - truth.p)
    assert (err < 4.5 * NOISE / np.sqrt(n)[:, None]).all(), err
    # marker_std_mm: RMS 3-D deviation from the window mean; expected 3σ²(n-1)/n squared
    want = 1000 * NOISE * np.sqrt(3 * (n - 1) / n)
    got = data.covariates["marker_std_mm"].numpy()
    assert np.all(np.abs(got / want - 1) < 0.25), (got, want)
    assert abs(np.sqrt(np.mean(got ** 2) / np.mean(want ** 2)) - 1) < 0.08
    ts, te = data.covariates["t_start_robot"].numpy(), data.covariates["t_end_robot"].numpy()
    assert np.abs(ts - truth.still[:, 0]).max() < 0.011 and np.abs(te - truth.still[:, 1]).max() < 0.011


@pytest.mark.parametrize("storage", ["ros1", "sqlite3", "mcap"])
def test_still_poses_become_rows(tmp_path, robot, stops, storage):
    path, truth = _bag(tmp_path, robot, stops, storage, extra_joints=("finger_joint",))
    res = read_bag(path, robot, ["tcp=/tracker/point"])
    _check_rows(res.data, truth)
    assert res.data.quaternions is None  # PointStamped has no orientation
    assert res.stamps == {"/joint_states": "header stamps", "/tracker/point": "header stamps"}
    # every sample taken in motion is reported, none used
    unused = sum(c for _, _, c in res.unused["tcp"])
    assert unused == res.n_samples["tcp"] - int(res.data.covariates["marker_samples"].sum())
    assert len(res.unused["tcp"]) == K - 1  # one run per motion between poses
    assert any("finger_joint" in line for line in res.summary())


def test_bag_time_instead_of_header_stamps(tmp_path, robot, stops):
    path, truth = _bag(tmp_path, robot, stops, "mcap")
    res = read_bag(path, robot, ["tcp=/tracker/point"], stamps="bag")
    assert res.stamps["/joint_states"] == "bag time"
    got = res.data.covariates["t_start_robot"].numpy()
    assert np.abs(got - (truth.still[:, 0] + 0.002)).max() < 1e-6  # the simulated receive latency


def test_stray_sample_in_motion_is_reported_not_used(tmp_path, robot, stops):
    """A triggered instrument samples only at still poses; one sample taken mid-motion is not
    averaged into any row and is reported with its time."""
    path, truth = _bag(tmp_path, robot, stops, "sqlite3", in_motion=False, stray=(2.0,))
    res = read_bag(path, robot, ["tcp=/tracker/point"])
    _check_rows(res.data, truth)
    assert res.unused["tcp"] == [(pytest.approx(truth.stray[0]), pytest.approx(truth.stray[0]), 1)]
    line = next(s for s in res.summary() if s.startswith("marker tcp"))
    t0 = res.t0
    assert "1 not used" in line and f"{truth.stray[0] - t0:.2f} s" in line


def test_window_without_marker_is_skipped_and_reported(tmp_path, robot, stops):
    path, truth = _bag(tmp_path, robot, stops, "ros1", lost=(2,))
    res = read_bag(path, robot, ["tcp=/tracker/point"])
    assert len(res.windows) == K and len(res.data) == K - 1
    (ts, te, why), = res.skipped
    assert why == "no marker sample" and abs(ts - truth.still[2, 0]) < 0.011
    keep = [0, 1, 3, 4]
    assert np.abs(res.data.q.numpy() - truth.q[keep]).max() < 1e-6
    assert "1 still window(s) skipped" in "\n".join(res.summary())


@pytest.mark.parametrize("storage", ["ros1", "mcap"])
def test_tf_marker_direct_and_through_a_static_chain(tmp_path, robot, stops, storage):
    """The pose of frame smr in frame tracker from /tf, and in frame world through a static
    world -> tracker edge: positions R p + t, orientations composed."""
    t_s = np.array([0.3, -0.2, 1.1])
    r_s = np.array([0.9, 0.1, -0.3, 0.2])
    r_s /= np.linalg.norm(r_s)
    path, truth = _bag(tmp_path, robot, stops, storage, marker="tf", static=(t_s, r_s))
    direct = read_bag(path, robot, ["smr=tf:tracker,smr"]).data
    _check_rows(direct, truth)
    R = quat_to_matrix(torch.as_tensor(truth.quat)).numpy()
    got = quat_to_matrix(direct.quaternions[:, 0]).numpy()
    assert np.abs(got - R).max() < 1e-9  # orientations carry no noise here
    chained = read_bag(path, robot, ["smr=tf:world,smr"]).data
    Rs = quat_to_matrix(torch.as_tensor(r_s)).numpy()
    assert np.abs(chained.positions[:, 0].numpy() - (direct.positions[:, 0].numpy() @ Rs.T + t_s)).max() < 1e-12
    assert np.abs(quat_to_matrix(chained.quaternions[:, 0]).numpy() - Rs @ R).max() < 1e-9
    # the same chain walked backwards: the pose of world in smr
    back = read_bag(path, robot, ["w=tf:smr,world"]).data
    Tinv = -np.einsum("kji,kj->ki", Rs @ R, chained.positions[:, 0].numpy())
    assert np.abs(back.positions[:, 0].numpy() - Tinv).max() < 1e-9


def test_still_windows_match_a_brute_force_search():
    """Maximal, earliest-start, non-overlapping windows within the tolerance, on joint values that
    creep (steps under the tolerance) as well as jump."""
    g = np.random.default_rng(3)
    t = np.cumsum(g.uniform(0.005, 0.015, 600))
    t[300:] += 0.5  # a gap in the joint states
    scale = np.repeat(g.choice([2e-6, 8e-6, 1e-4], size=12), 50)[:, None]  # still, creeping, moving blocks
    q = np.cumsum(g.uniform(-1, 1, (600, 2)) * scale, 0)
    tol, still_s = 4e-5, 0.3

    def brute():
        out, i, n = [], 0, len(t)
        while i < n:
            j = i + 1
            while j < n and np.ptp(q[i:j + 1], 0).max() <= tol and t[j] - t[j - 1] <= still_s:
                j += 1
            if t[j - 1] - t[i] >= still_s:
                out.append((i, j))
                i = j
            else:
                i += 1
        return out

    want = brute()
    assert len(want) >= 3
    assert still_windows(t, q, still_s, tol) == want


def _cli(*args):
    return main(["import-bag", *map(str, args), "--no-progress"])


def test_cli_writes_a_csv_that_loads(tmp_path, robot, stops, capsys):
    path, truth = _bag(tmp_path, robot, stops, "mcap", marker="pose", topic="/tracker/pose")
    out = tmp_path / "data.csv"
    assert _cli(path, "--robot", URDF, "--joints", "/joint_states", "--marker", "tcp=/tracker/pose",
                "--out", out) == 0
    printed = capsys.readouterr().out
    assert f"wrote {K} rows" in printed and "marker tcp:" in printed
    data = load_measurements(out, Robot.from_urdf(URDF, markers=["tcp@flange"]))
    _check_rows(data, truth)
    assert {"t_start_robot", "t_end_robot", "marker_std_mm", "marker_samples"} <= set(data.covariates)
    assert np.abs(quat_to_matrix(data.quaternions[:, 0]).numpy()
                  - quat_to_matrix(torch.as_tensor(truth.quat)).numpy()).max() < 1e-9
    assert _cli(path, "--robot", URDF, "--marker", "tcp=/tracker/pose", "--out", out) == 2  # never overwrites
    assert "--force" in capsys.readouterr().err
    assert _cli(path, "--robot", URDF, "--marker", "tcp=/tracker/pose", "--out", out, "--force") == 0


@pytest.mark.parametrize("args, words", [
    (["--joints", "/nope", "--marker", "tcp=/tracker/point"], ["no topic '/nope'", "--joints", "/joint_states"]),
    (["--joints", "/tracker/point", "--marker", "tcp=/tracker/point"], ["carries geometry_msgs/msg/PointStamped",
                                                                        "--joints"]),
    (["--marker", "tcp=/tracker/pose"], ["no topic '/tracker/pose'", "/tracker/point"]),
    (["--marker", "tcp=/joint_states"], ["carries sensor_msgs/msg/JointState", "PointStamped"]),
    (["--marker", "tcp=tf:tracker,smr"], ["no /tf"]),
])
def test_cli_refuses_bad_topics(tmp_path, robot, stops, capsys, args, words):
    path, _ = _bag(tmp_path, robot, stops, "ros1")
    assert _cli(path, "--robot", URDF, "--out", tmp_path / "x.csv", *args) == 2
    err = capsys.readouterr().err
    assert all(w in err for w in words), err
    assert not (tmp_path / "x.csv").exists()


def test_cli_refuses_joint_names_not_in_the_urdf(tmp_path, stops, capsys):
    q, p, _ = stops
    path = tmp_path / "other.bag"
    write_bag(path, q, p, [f"joint_{i}" for i in range(1, 7)])
    assert _cli(path, "--robot", URDF, "--marker", "tcp=/tracker/point", "--out", tmp_path / "x.csv") == 2
    err = capsys.readouterr().err
    assert "joint_1" in err and "shoulder_pan_joint" in err and "URDF" in err


def test_cli_refuses_bad_marker_specs_and_frames(tmp_path, robot, stops, capsys):
    with pytest.raises(SystemExit) as e:
        _cli("x.bag", "--robot", URDF, "--marker", "tcp", "--out", tmp_path / "x.csv")
    assert e.value.code == 2 and "NAME=tf:PARENT,CHILD" in capsys.readouterr().err
    path, _ = _bag(tmp_path, robot, stops, "sqlite3", marker="tf")
    assert _cli(path, "--robot", URDF, "--marker", "smr=tf:tracker,smr_1", "--out", tmp_path / "x.csv") == 2
    err = capsys.readouterr().err
    assert "no chain" in err and "'smr'" in err
    assert _cli(path, "--robot", URDF, "--marker", "smr=tf:world,smr", "--out", tmp_path / "x.csv") == 2


def test_without_rosbags_the_command_says_how_to_install(tmp_path, robot, stops, capsys, monkeypatch):
    path, _ = _bag(tmp_path, robot, stops, "ros1")
    monkeypatch.setitem(sys.modules, "rosbags.highlevel", None)  # import fails as if not installed
    assert _cli(path, "--robot", URDF, "--marker", "tcp=/tracker/point", "--out", tmp_path / "x.csv") == 2
    assert "pip install 'torchcal[ros]'" in capsys.readouterr().err
