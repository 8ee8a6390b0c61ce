"""Measurements that are not full positions: per-axis positions, plane contacts, distances between
markers and to fixed points. Residuals against closed forms, Jacobians against central finite
differences, recovery of a simulated robot's geometry from planes alone, and the CSV / CLI path."""
from __future__ import annotations

import json
import math

import pytest
import torch

from torchcal import load
from torchcal.kinematics import robots
from torchcal.kinematics.robot import Robot
from torchcal.kinematics.transforms import kabsch, similarity
from torchcal.measure.data import Measurements
from torchcal.measure.io import load_measurements, save_measurements
from torchcal.measure.observations import Observations
from torchcal.measure.setup import Setup
from torchcal.pipelines.loop.run import run_loop
from torchcal.problems.effect_calibration import EffectCalibrationProblem
from torchcal.problems.unseen import unseen
from torchcal.sim.serial import SimConfig, hide_axes, random_configs, simulate, simulated_robot
from torchcal.report import report_json

NOISE = 0.02e-3  # m


def _tree(tree_urdf):
    return Robot.from_urdf(tree_urdf, markers=["tool", "m1@finger_a=0.01,0.02,0.03"])


def _mixed(robot, params, n=24, seed=0):
    """Rows with every kind of observation, noise-free at ``params``: full and partial positions
    of m1, "contacts" of the tool with two planes (random points: only the residual's formula
    is checked on them), a tool–m1 distance, and distances from m1 to a fixed point."""
    g = torch.Generator().manual_seed(seed)
    q = random_configs(robot, n, g)
    p = robot.positions(q, params)  # (n, 2, 3)
    pos = torch.full_like(p, float("nan"))
    pos[:, 1] = p[:, 1]
    pos[::3, 1, 1] = float("nan")  # m1.y not seen in every third row
    planes = torch.full((n, 2), -1, dtype=torch.long)
    planes[:, 0] = torch.arange(n) % 2
    c = torch.tensor([0.3, -0.2, 0.5], dtype=torch.float64)
    dist = {("tool", "m1"): (p[:, 0] - p[:, 1]).norm(dim=-1), ("m1", "ball"): (p[:, 1] - c).norm(dim=-1)}
    data = Measurements(q, pos, ["tool", "m1"], list(robot.joint_names), planes=planes, plane_names=["A", "B"],
                        distances=dist)
    return data, c


def test_residuals_match_closed_forms(tree_urdf):
    robot = _tree(tree_urdf)
    params = robot.params().values.clone()
    params[6:] += 1e-3 * torch.randn(robot.n_params - 6, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    data, c = _mixed(robot, params)
    setup = Setup.from_data(robot, data, params)
    obs = Observations(robot, data, setup)
    s = setup.start.clone()
    s[0], s[1], s[4] = 0.01, -0.02, 0.005  # tilt plane A, tilt plane B
    p = robot.positions(data.q, params)
    r = obs.residuals(p[None], s[None])[0]
    n, d, _ = setup.planes_of(s[None])
    for i in range(obs.n):
        row, mk, kind = int(obs.rows[i]), int(obs.marker[i]), int(obs.kind[i])
        if kind == 0:
            want = torch.nan_to_num((p[row, mk] - data.positions[row, 1]), nan=0.0)
        elif kind == 1:
            k = int(obs.other[i])
            want = torch.tensor([float(n[0, k] @ p[row, mk] - d[0, k]), 0, 0], dtype=torch.float64)
        elif kind == 2:
            want = torch.tensor([float((p[row, 0] - p[row, 1]).norm() - data.distances[("tool", "m1")][row]), 0, 0],
                                dtype=torch.float64)
        else:
            cc = setup.centres_of(s[None])[0, 0]
            want = torch.tensor([float((p[row, 1] - cc).norm() - data.distances[("m1", "ball")][row]), 0, 0],
                                dtype=torch.float64)
        torch.testing.assert_close(r[i], want, atol=1e-12, rtol=0)
    # the set-up located from noise-free data: the fixed point exactly; positions and distances fit
    torch.testing.assert_close(setup.centres_of(setup.start[None])[0, 0], c, atol=1e-9, rtol=0)
    r0 = obs.residuals(p[None], setup.start[None])[0]
    assert float(r0[obs.kind != 1].abs().max()) < 1e-9
    assert obs.dims.tolist().count(2) == len(range(0, 24, 3))


def test_mixed_jacobian_matches_finite_differences(tree_urdf):
    robot = _tree(tree_urdf)
    g = torch.Generator().manual_seed(2)
    params = robot.params().values + 2e-3 * torch.randn(robot.n_params, generator=g, dtype=torch.float64)
    data, _ = _mixed(robot, params, seed=3)
    # measured values off the model, so that no residual sits at a kink
    data.positions = data.positions + 1e-3 * torch.randn(data.positions.shape, generator=g, dtype=torch.float64)
    setup = Setup.from_data(robot, data, robot.params().values)
    ps = robot.params(params)
    full = type(ps).concat(ps, setup.params())
    full.values[robot.n_params:] += 1e-3
    prob = EffectCalibrationProblem(robot, full, [], data, setup=setup)
    x = prob.x0
    J = prob.data_jacobian(x)
    h = 1e-6
    E = torch.eye(x.numel(), dtype=x.dtype) * h
    rp = prob.residual_vectors(prob.full(x[None] + E)).reshape(x.numel(), -1)
    rm = prob.residual_vectors(prob.full(x[None] - E)).reshape(x.numel(), -1)
    fd = ((rp - rm) / (2 * h)).T
    scale = fd.abs().max(0).values.clamp(min=1e-3)
    err = ((J - fd).abs().max(0).values / scale).max()
    assert float(err) < 1e-5, float(err)
    assert J.shape == (3 * prob.n_obs, x.numel())


def test_csv_round_trip_and_bad_input(tree_urdf, tmp_path):
    robot = _tree(tree_urdf)
    data, _ = _mixed(robot, robot.params().values)
    path = tmp_path / "mixed.csv"
    save_measurements(path, data)
    header = path.read_text().splitlines()[0].split(",")
    assert "tool.plane" in header and "tool.dist.m1" in header and "m1.dist.ball" in header
    assert "tool.x" not in header  # the tool is only ever in contact with planes
    back = load_measurements(path, robot)
    assert back.marker_names == ["tool", "m1"] and back.plane_names == ["A", "B"] and back.pivots == ["ball"]
    torch.testing.assert_close(back.planes, data.planes)
    assert torch.equal(back.axes_seen, data.axes_seen) and back.n_values == data.n_values
    torch.testing.assert_close(back.distances[("m1", "ball")], data.distances[("m1", "ball")])
    assert "contacts on planes ['A', 'B']" in repr(back) and "partial" in repr(back)
    # millimetres: distances are converted with the positions
    mm = tmp_path / "mm.csv"
    lines = path.read_text().splitlines()
    i_d = header.index("m1.dist.ball")
    rows = [r.split(",") for r in lines[1:]]
    for r in rows:
        r[i_d] = repr(float(r[i_d]) * 1000)
    mm.write_text("\n".join([",".join(header)] + [",".join(r) for r in rows]) + "\n")
    with pytest.raises(ValueError, match="distances have median"):
        load_measurements(mm, robot)
    # a contact row that also has a position for the same marker
    both = tmp_path / "both.csv"
    h2 = header + ["tool.x", "tool.y", "tool.z"]
    rows2 = [r + ["0.1", "0.2", "0.3"] for r in (ln.split(",") for ln in lines[1:])]
    both.write_text("\n".join([",".join(h2)] + [",".join(r) for r in rows2]) + "\n")
    with pytest.raises(ValueError, match=r"line 2: marker 'tool' has a plane contact \('A'\) and position cells"):
        load_measurements(both, robot)
    # calibrate() fits positions only and says where contacts go
    from torchcal import calibrate

    with pytest.raises(ValueError, match="run_loop"):
        calibrate(robot, back)
    # held-out rows touching a plane the training rows never touched
    setup = Setup.from_data(robot, data.subset(data.planes[:, 0] != 1), robot.params().values)
    with pytest.raises(ValueError, match=r"\['B'\], which the set-up does not know"):
        Observations(robot, data, setup)


def _workspace_planes(sim, robot, normals, g):
    P = sim.reach(random_configs(robot, 2000, g))[:, 0]
    out = {}
    for k, n in normals.items():
        n = torch.tensor(n, dtype=torch.float64)
        n = n / n.norm()
        out[k] = (n, float((P @ n).median()))
    return out


@pytest.fixture(scope="module")
def kr5_planes():
    robot = robots.shipped("kuka_kr5_arc")
    sim = simulated_robot(robot, SimConfig(n=0, noise=NOISE, seed=4, base_distance=2.0))
    g = torch.Generator().manual_seed(5)
    planes = _workspace_planes(sim, robot, {"A": [0, 0, 1.0], "B": [1.0, 0.2, 0], "C": [-0.3, 1.0, 0.2]}, g)
    return robot, sim, planes, g


@pytest.mark.slow
def test_geometry_from_three_planes_alone(kr5_planes):
    """A KR 5 arc with undeclared geometric errors touches three planes of unknown pose; the loop
    identifies robot and planes. Fresh poses: the shape (after the rigid motion and size that
    contacts cannot see) within 2× the noise; and the loop says why those are not seen."""
    robot, sim, planes, g = kr5_planes
    train, test = sim.touch(planes, 70), sim.touch(planes, 20)
    res = run_loop(robot, train, test, candidates=[], elm=False, folds=3, log=None)
    assert res.setup is not None and res.setup.planes == ["A", "B", "C"]
    q = random_configs(robot, 200, g)
    truth = sim.reach(q)[:, 0]
    K = robot.n_params
    pred = robot.positions(q, res.params.values[:K])[:, 0]
    nominal = robot.positions(q, robot.params().values)[:, 0]
    rms = lambda p: float((similarity(p, truth)[0] - truth).pow(2).mean().sqrt())  # noqa: E731  per axis
    assert rms(nominal) > 20 * NOISE  # there was something to find
    assert rms(pred) < 2 * NOISE, rms(pred)
    # held-out contacts at the noise: mean |N(0, σ)| = σ √(2/π)
    assert res.stages[-1]["test"]["mean_mm"] < 2 * NOISE * 1e3 * math.sqrt(2 / math.pi)
    seen = res.observability["not_seen"]
    assert "scale" in seen and "cannot tell how large the robot is" in seen["scale"]
    assert all(f"base.{a}" in seen for a in ("x", "y", "z", "rx", "ry", "rz"))
    assert "nothing says where the robot stands" in seen["base.x"]
    rep = report_json(res)
    assert set(rep["setup"]["planes"]) == {"A", "B", "C"}
    Rb, _ = robot.base_transform(sim.truth.values)
    for k, (n, d) in planes.items():
        # identified in the robot's base frame, whose rotation the contacts fix only up to the
        # first joint's unseen origin errors (a few mrad): normals agree up to sign and those
        got = torch.tensor(rep["setup"]["planes"][k]["normal"], dtype=torch.float64)
        cos = abs(float(got @ (Rb.reshape(3, 3).mT @ n)))
        assert math.acos(min(cos, 1.0)) < 5e-3


def test_one_plane_cannot_see_motion_within_it(kr5_planes):
    """One horizontal plane: turning joint 1 (a vertical axis) moves the tool only within the
    plane, which no contact sees; the reason says so in words."""
    robot, sim, _, g = kr5_planes
    flat = {"floor": (torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64), 0.0)}
    robot0 = robots.shipped("kuka_kr5_arc")
    sim0 = simulated_robot(robot0, SimConfig(n=0, noise=NOISE, seed=4, base_distance=0.0))
    P = sim0.reach(random_configs(robot0, 500, g))[:, 0]
    flat["floor"] = (flat["floor"][0], float(P[:, 2].median()))
    data = sim0.touch(flat, 60)
    why = unseen(robot0, data)
    assert "joint_a1.offset" in why
    assert "only in directions none of these measurements sees" in why["joint_a1.offset"]
    assert "along the plane's normal" in why["joint_a1.offset"]


@pytest.mark.slow
def test_partial_axes_in_the_loop():
    """Motion capture that loses one or two axes of 40 % of the observations: every measured axis
    counts, and the held-out error (full positions) reaches the noise."""
    robot = robots.shipped("ur5e")
    full, _ = simulate(robot, SimConfig(n=180, noise=NOISE, seed=7))
    train, test = full.subset(torch.arange(120)), full.subset(torch.arange(120, 180))
    part = hide_axes(train, 0.4, torch.Generator().manual_seed(8))
    assert not part.positions_only and part.n_values < train.n_values
    res = run_loop(robot, part, test, candidates=[], elm=False, folds=3, log=None)
    mean_noise = 1e3 * NOISE * math.sqrt(8 / math.pi)  # mean norm of 3-D Gaussian noise, mm
    assert res.stages[-1]["test"]["mean_mm"] < 1.5 * mean_noise
    assert res.stages[-1]["train"]["per_kind"]["position"]["n"] == int(part.observed.sum())


@pytest.mark.slow
def test_planes_and_a_ball_bar_through_the_cli(kr5_planes, tmp_path):
    """Contacts with three planes plus distances from the tool to the fixed pivot of a ball bar,
    written as CSV and run through ``torchcal loop``: the distances fix the size, so the absolute
    geometry (after the rigid motion alone) comes out within 2× the noise."""
    from torchcal.cli.app import main

    robot, sim, planes, g = kr5_planes
    contacts = sim.touch(planes, 60)
    qb = random_configs(robot, 60, g)
    bar = sim.measure_distances(torch.tensor([0.6, 0.2, 0.3], dtype=torch.float64), "pivot", qb)
    # one file: the contact rows, then the ball-bar rows (their other columns empty)
    n1, n2 = len(contacts), len(bar)
    rows = Measurements(torch.cat([contacts.q, bar.q]), torch.full((n1 + n2, 1, 3), float("nan"), dtype=torch.float64),
                        ["flange"], list(robot.joint_names),
                        planes=torch.cat([contacts.planes, torch.full((n2, 1), -1, dtype=torch.long)]),
                        plane_names=list(contacts.plane_names),
                        distances={("flange", "pivot"): torch.cat([torch.full((n1,), float("nan"), dtype=torch.float64),
                                                                   bar.distances[("flange", "pivot")]])})
    csv = tmp_path / "contacts.csv"
    save_measurements(csv, rows)
    out = tmp_path / "run"
    rc = main(["loop", "--robot", str(robots.urdf_path("kuka_kr5_arc")), "--marker", "flange", "--data", str(csv),
               "--holdout", "0.2", "--effect", "none", "--no-elm", "--folds", "3", "--out", str(out), "--quiet"])
    assert rc == 0
    rep = json.loads((out / "report.json").read_text())
    assert set(rep["setup"]["planes"]) == {"A", "B", "C"} and "pivot" in rep["setup"]["fixed_points"]
    assert "scale" not in rep["observability"]["not_seen"]  # the ball bar measures lengths
    assert "What these measurements cannot see" in (out / "report.md").read_text()
    q = random_configs(robot, 200, g)
    truth = sim.reach(q)[:, 0]
    pred = load(out / "model").predict_pose(q)[:, 0, :3, 3]  # the deployed model, instrument frame
    R, t = kabsch(pred, truth)
    rms = float((pred @ R.T + t - truth).pow(2).mean().sqrt())
    assert rms < 2 * NOISE, rms


def test_similarity_recovers_a_known_rotation_scale_and_shift():
    g = torch.Generator().manual_seed(4)
    src = torch.randn(30, 3, generator=g, dtype=torch.float64)
    w = torch.tensor([0.3, -0.5, 0.8], dtype=torch.float64)
    K = torch.tensor([[0, -w[2], w[1]], [w[2], 0, -w[0]], [-w[1], w[0], 0]], dtype=torch.float64)
    R = torch.linalg.matrix_exp(K)
    dst = 1.003 * src @ R.T + torch.tensor([0.1, 2.0, -0.4], dtype=torch.float64)
    mapped, s = similarity(src, dst)
    assert s == pytest.approx(1.003, rel=1e-12) and torch.allclose(mapped, dst, atol=1e-12)
    rigid, one = similarity(src, dst, scale=False)
    assert one == 1.0 and float((rigid - dst).abs().max()) > 1e-4  # the scale is what is left
