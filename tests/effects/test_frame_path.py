"""The instrument frame along a path: its ramps, its columns against finite differences of the
kinematics, each row's pose against the kinematics at that row's frame, its knots from the
training rows, and its words."""
from __future__ import annotations

import pytest
import torch

from torchcal import CalibratedModel, Measurements
from torchcal.effects import FramePath
from torchcal.effects.frame_path import ramps
from torchcal.kinematics.robots import shipped
from torchcal.params import ParamSet

BASE = ("x", "y", "z", "rx", "ry", "rz")


def _data(robot, q: torch.Tensor, cov: dict) -> Measurements:
    p = robot.positions(q, robot.params().values)[:, 0]
    return Measurements(q, p[:, None], marker_names=robot.marker_names, joint_names=robot.joint_names, covariates=cov)


def _robot_and_rows(n: int = 14, seed: int = 0):
    robot = shipped("ur5e")
    g = torch.Generator().manual_seed(seed)
    q = (torch.rand(n, robot.dof, generator=g, dtype=torch.float64) - 0.5) * 3.0
    geo = torch.randn(robot.n_params, generator=g, dtype=torch.float64) * 1e-3
    t = torch.sort(torch.rand(n, generator=g, dtype=torch.float64) * 3600.0).values
    return robot, q, geo, {"time": t}


def test_ramps_rise_across_their_interval_and_stay():
    knots = [0.0, 10.0, 30.0, 60.0]
    x = torch.tensor([-5.0, 0.0, 5.0, 10.0, 20.0, 30.0, 45.0, 60.0, 99.0], dtype=torch.float64)
    want = torch.tensor([[0, 0, 0], [0, 0, 0], [0.5, 0, 0], [1, 0, 0], [1, 0.5, 0], [1, 1, 0], [1, 1, 0.5],
                         [1, 1, 1], [1, 1, 1]], dtype=torch.float64)
    assert torch.equal(ramps(x, knots), want)


def test_columns_match_finite_differences_of_the_frame():
    """Each parameter's column (interval k, coordinate c) equals the change of the marker positions
    when the frame's coordinate c alone moves by ε·r_k(t) row by row (central differences)."""
    robot, q, geo, cov = _robot_and_rows()
    eff = FramePath(robot, geometry=geo, driver="time", knots=[0.0, 900.0, 2000.0, 3600.0])
    prep = eff.prepare(q, cov)
    basis = eff.linear_basis(prep)
    assert basis.dq is None and basis.groups == [list(range(6 * i, 6 * i + 6)) for i in range(3)]
    Rb, _ = robot.base_transform(geo)
    D = Rb @ basis.dp  # (N, M, 3, 18) instrument frame
    R = ramps(cov["time"], eff.knots)
    eps = 1e-6
    for j in range(eff.n_params):
        k = robot.param_names.index(f"base.{BASE[j % 6]}")
        pp, pm = geo.repeat(q.shape[0], 1), geo.repeat(q.shape[0], 1)
        pp[:, k] += eps * R[:, j // 6]
        pm[:, k] -= eps * R[:, j // 6]
        fd = (robot.positions(q[:, None], pp) - robot.positions(q[:, None], pm))[:, 0] / (2 * eps)
        assert torch.allclose(D[..., j], fd, atol=1e-7, rtol=1e-5), eff.param_names[j]


def test_each_row_moves_as_its_frame_on_the_path_would_to_first_order():
    """With the path fitted, each row's pose is the kinematics at the geometry whose frame
    coordinates are shifted by that row's point on the path, to first order: a wander of 0.5 mrad
    and 50 µm at about 1 m errs by under |Δθ|²·|p| (a few tenths of a µm), while the path itself
    moves the markers by up to a millimetre."""
    robot, q, geo, cov = _robot_and_rows()
    eff = FramePath(robot, geometry=geo, driver="time", knots=[0.0, 1200.0, 3600.0])
    eff.theta = torch.tensor([5e-5, -2e-5, 1e-5, 5e-4, -2.5e-4, 4e-4, -1e-5, 3e-5, 0.0, -5e-4, 2.5e-4, 1.25e-4],
                             dtype=torch.float64)
    eff.covariate_range = {"time": (0.0, 3600.0)}
    ps = robot.params()
    model = CalibratedModel(robot, ParamSet(ps.names, ps.units, geo, ps.free, ps.lower, ps.upper), effects=[eff])
    path = ramps(cov["time"], eff.knots) @ eff.theta.reshape(2, 6)  # (N, 6) the frame's offsets per row
    per_row = geo.repeat(q.shape[0], 1)
    idx = [robot.param_names.index(f"base.{c}") for c in BASE]
    per_row[:, idx] += path
    exact = robot.positions(q[:, None], per_row)[:, 0]
    still = robot.positions(q, geo)
    got = model.predict_pose(q, cov)[..., :3, 3]
    turn = path[:, 3:].norm(dim=-1)[:, None, None]
    assert float((exact - still).abs().max()) > 1e-4
    bound = turn ** 2 * still.norm(dim=-1, keepdim=True) + 1e-12
    assert bool(((got - exact).norm(dim=-1, keepdim=True) <= bound).all())
    # beyond the training range the path holds its end: a path says nothing of later rows
    late = {"time": cov["time"] + 1e5}
    end = {"time": torch.full_like(cov["time"], 3600.0)}
    assert torch.allclose(model.predict_pose(q, late), model.predict_pose(q, end), atol=1e-15)


def test_knots_sit_at_quantiles_of_the_training_times_and_rows_stand_in_for_time():
    robot = shipped("ur5e")
    g = torch.Generator().manual_seed(3)
    n = 190
    q = (torch.rand(n, robot.dof, generator=g, dtype=torch.float64) - 0.5) * 3.0
    t = torch.cumsum(torch.rand(n, generator=g, dtype=torch.float64) * 10.0, 0)
    eff = FramePath(robot).bind(_data(robot, q, {"time": t}))
    assert eff.driver == "time" and len(eff.knots) == n // 30 + 1
    assert eff.knots[0] == pytest.approx(float(t.min())) and eff.knots[-1] == pytest.approx(float(t.max()))
    inside = [int(((t >= a) & (t <= b)).sum()) for a, b in zip(eff.knots, eff.knots[1:])]
    assert min(inside) >= 29, inside
    assert FramePath(robot).bind(_data(robot, q, {"row": torch.arange(n, dtype=torch.float64)})).driver == "row"
    ok, why = FramePath(robot).applicable(_data(robot, q[:50], {"time": t[:50]}))
    assert not ok and "fewer than 60" in why


def test_words_say_where_and_how_far_the_frame_moved():
    robot, q, geo, cov = _robot_and_rows()
    eff = FramePath(robot, geometry=geo, driver="time", knots=[0.0, 900.0, 3600.0])
    eff = eff.with_modes(["base.frame~interval2"])
    assert eff.param_names[0] == "frame_path.interval2.x" and eff.param_units[:4] == ["m", "m", "m", "rad"]
    eff.theta = torch.tensor([2e-5, 0, 0, 1e-4, 0, 0], dtype=torch.float64)
    line = eff.describe()[0]
    assert "0.02" in line and "0.1" in line and "from time = 900 s to 3600 s (45 min)" in line, line
    assert eff.mode_words("base.frame~interval2").endswith("from time = 900 s to 3600 s (45 min)")


def test_a_saved_model_with_a_path_predicts_the_same_and_asks_for_its_time(tmp_path):
    from torchcal.deploy.persist import load, save

    robot, q, geo, cov = _robot_and_rows()
    eff = FramePath(robot, geometry=geo, driver="time", knots=[0.0, 1200.0, 3600.0])
    eff = eff.with_modes(["base.frame~interval2"])
    eff.theta = torch.tensor([5e-5, -2e-5, 1e-5, 5e-4, -2.5e-4, 4e-4], dtype=torch.float64)
    eff.covariate_range = {"time": (0.0, 3600.0)}
    ps = robot.params()
    model = CalibratedModel(robot, ParamSet(ps.names, ps.units, geo, ps.free, ps.lower, ps.upper), effects=[eff])
    save(model, tmp_path / "m")
    again = load(tmp_path / "m")
    assert torch.equal(again.predict_pose(q, cov), model.predict_pose(q, cov))
    with pytest.raises(ValueError, match="time"):
        again.predict_pose(q, {})
