"""The independent simulator's drifting parameters, against what they mean: a zero that steps is
the same robot commanded with that joint moved, a tool point per level is the same robot with
that point, the instrument's motion moves every reading rigidly; and each issue-32 case at one
seed (slow: the whole loop)."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from torchcal.sim.physsim import PhysicalRobot
from torchcal.sim.physsim_drifts import Drift

UR5E = (Path(__file__).resolve().parents[2] / "urdf" / "ur5e.urdf").read_text()


def _q(real, n=20, seed=0):
    lo, hi = real.joint_limits
    return np.random.default_rng(seed).uniform(np.maximum(lo, -2.5), np.minimum(hi, 2.5), (n, real.dof))


def test_a_zero_step_is_the_joint_moved_from_its_row_on():
    step = Drift("offset:elbow_joint", "row", lambda r: 2e-3 * (r >= 10))
    real = PhysicalRobot(UR5E, ["tool@flange=0,0,0.1"], seed=1, drifts=[step])
    plain = PhysicalRobot(UR5E, ["tool@flange=0,0,0.1"], seed=1)
    q = _q(real)
    moved = q.copy()
    moved[10:, real.joint_names.index("elbow_joint")] += 2e-3
    assert np.allclose(real.reach(q), plain.reach(moved), atol=1e-12)


def test_a_tool_point_per_level_and_a_moving_instrument():
    probe = Drift("marker:tool", "level:tool", lambda t: np.where((t == "probe")[:, None], [0.0, 0.012, 0.0], 0.0))
    real = PhysicalRobot(UR5E, ["tool@flange"], seed=2, drifts=[probe], marker_true_m={"tool": (0.0, 0.0, 0.0)})
    other = PhysicalRobot(UR5E, ["tool@flange"], seed=2, marker_true_m={"tool": (0.0, 0.012, 0.0)})
    q = _q(real, 6)
    lv = np.array(["gripper", "probe"] * 3)
    got = real.reach(q, covariates={"level:tool": lv})
    assert np.allclose(got[1::2], other.reach(q[1::2]), atol=1e-12)
    turn = Drift("instrument", "cov:time", lambda t: np.stack([0 * t, 0 * t, 0 * t, 0 * t, 0 * t, 1e-3 * t], -1))
    moving = PhysicalRobot(UR5E, ["tool@flange"], seed=3, drifts=[turn])
    still = PhysicalRobot(UR5E, ["tool@flange"], seed=3)
    a = moving.reach(q, covariates={"time": np.full(6, 2.0)})
    b = still.reach(q)
    # a rigid motion: distances between readings are kept, the readings themselves move
    da, db = np.linalg.norm(a[:, None, 0] - a[None, :, 0], axis=-1), np.linalg.norm(b[:, None, 0] - b[None, :, 0], axis=-1)
    assert np.allclose(da, db, atol=1e-12) and np.abs(a - b).max() > 1e-4


def test_a_sample_holds_text_levels_as_the_reader_does():
    probe = Drift("marker:tool", "level:tool", lambda t: np.zeros((len(t), 3)))
    real = PhysicalRobot(UR5E, ["tool@flange"], seed=2, drifts=[probe])
    s = real.measure(_q(real, 4), levels={"tool": np.array(["a", "b", "b", "a"])})
    assert s.covariates["tool=b"].tolist() == [0.0, 1.0, 1.0, 0.0]


@pytest.mark.slow
@pytest.mark.parametrize("name", ["zero_step", "instrument_drift", "tool_levels", "tool_set", "station_levels",
                                  "setup_change", "torque_stiffness", "loaded_stiffness", "prismatic_guide"])
def test_issue32_case_ends_near_the_noise_floor(name):
    from torchcal import Robot
    from torchcal.pipelines.loop.run import run_loop
    from torchcal.sim.cases import make_case

    c = make_case(name, 1)
    robot = Robot.from_urdf(c.urdf, markers=c.markers)
    res = run_loop(robot, c.train.to_measurements(), c.test.to_measurements(), seed=1, log=None)
    assert "parameter_drivers" in [a["name"] for a in res.accepted]
    assert res.stages[-1]["test"]["mean_mm"] <= 1.15 * c.floor_mm


@pytest.mark.slow
def test_a_frame_that_wanders_is_followed_along_its_path(tmp_path):
    """wandering_frame: the tracker's frame creeps in a random walk that no shape of the drivers
    names; the frame's path takes it, near the floor (1.20 of it at this seed before the path), and
    the report says where and how far the frame moved, with its evidence drawn."""
    from torchcal import Robot
    from torchcal.pipelines.loop.run import run_loop
    from torchcal.report.loop import write_loop_report
    from torchcal.sim.cases import make_case

    c = make_case("wandering_frame", 1)
    robot = Robot.from_urdf(c.urdf, markers=c.markers)
    res = run_loop(robot, c.train.to_measurements(), c.test.to_measurements(), seed=1, log=None)
    assert "frame_path" in [a["name"] for a in res.accepted]
    assert res.stages[-1]["test"]["mean_mm"] <= 1.1 * c.floor_mm
    write_loop_report(res, tmp_path)
    text = (tmp_path / "report.md").read_text()
    assert "the instrument frame moves by (" in text and "mrad about x, y, z from time = " in text
    assert list(tmp_path.glob("evidence_frame_path_*.png"))
