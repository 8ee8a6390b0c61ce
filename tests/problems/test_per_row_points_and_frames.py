"""Effects that move marker points on their links (a tool per level) and the instrument frame per row
(a set-up per level): the problem's model is the kinematics with each row's point and frame moved,
exactly, at any geometry (against per-row parameter vectors, an independent path); its Jacobian, the
geometry's columns and the effect's, positions and measured orientations, is the derivative of that
model (central differences)."""
from __future__ import annotations

import pytest
import torch

from torchcal.effects import ParameterDrivers
from torchcal.kinematics.robots import shipped
from torchcal.measure.data import Measurements
from torchcal.params import ParamSet
from torchcal.problems.effect_calibration import EffectCalibrationProblem

D = torch.float64


def _problem(seed: int = 0):
    robot = shipped("ur5e")
    g = torch.Generator().manual_seed(seed)
    n = 10
    q = (torch.rand(n, robot.dof, generator=g, dtype=D) - 0.5) * 3.0
    geo = torch.randn(robot.n_params, generator=g, dtype=D) * 2e-3
    tool = (torch.arange(n) % 2).double()
    cov = {"tool=a": 1 - tool, "tool=b": tool}
    mk = robot.marker_names[0]
    terms = [(f"{mk}.dx", "level:tool", "lvl=b"), (f"{mk}.dz", "level:tool", "lvl=b"),
             ("elbow_joint.offset", "level:tool", "lvl=b")]
    eff = ParameterDrivers(robot, geometry=geo, terms=terms)
    data = Measurements(q=q, positions=robot.positions(q, geo)[:, :, :], marker_names=list(robot.marker_names),
                        joint_names=list(robot.joint_names), covariates=cov)
    theta = torch.tensor([0.03, -0.08, 0.0], dtype=D)  # a tool 30 mm aside and 80 mm shorter
    k = len(terms)
    params = ParamSet.concat(robot.params(), ParamSet([f"t{i}" for i in range(k)], ["m"] * k, theta,
                                                      torch.ones(k, dtype=torch.bool),
                                                      torch.full((k,), -1.0, dtype=D), torch.full((k,), 1.0, dtype=D)))
    params.values[: robot.n_params] = geo
    params.free[: robot.n_params] = True
    return robot, eff, data, params, geo, theta, mk


def _fd_error(prob, seed: int) -> float:
    """The largest difference, relative, between the problem's Jacobian near its start and central
    differences of its residuals."""
    x = prob.x0 + 1e-3 * torch.randn(prob.dim, generator=torch.Generator().manual_seed(seed), dtype=D)
    h = 1e-6
    E = h * torch.eye(prob.dim, dtype=D)
    fd = (prob.residuals(x + E) - prob.residuals(x - E)).T / (2 * h)
    return float((fd - prob.jacobian(x)).abs().max()) / float(fd.abs().max())


def test_the_model_is_the_kinematics_with_each_rows_point_moved():
    robot, eff, data, params, geo, theta, mk = _problem()
    prob = EffectCalibrationProblem(robot, params, [eff], data)
    # a geometry far from the one the effect's features were taken at: the points turn with their link
    other = params.values.clone()
    other[: robot.n_params] += torch.randn(robot.n_params, generator=torch.Generator().manual_seed(5), dtype=D) * 5e-3
    got = prob.marker_positions(other[None])[0]
    rows = other[: robot.n_params].repeat(len(data), 1)
    on = data.covariates["tool=b"]
    rows[:, robot.param_names.index(f"{mk}.dx")] += on * theta[0]
    rows[:, robot.param_names.index(f"{mk}.dz")] += on * theta[1]
    want = robot.positions(data.q[:, None], rows)[:, 0]
    torch.testing.assert_close(got, want, rtol=0, atol=1e-12)


def test_the_jacobian_is_the_derivative_of_the_model():
    robot, eff, data, params, geo, theta, mk = _problem(seed=1)
    params.values[-1] = -1e-3  # the elbow's zero differs by level too
    err = _fd_error(EffectCalibrationProblem(robot, params, [eff], data), seed=2)
    assert err < 1e-7, err


def test_the_deployed_model_moves_the_points_as_the_fit_did(tmp_path):
    """A deployed model with a tool per level (saved and loaded) predicts the positions the
    problem's model gives at its geometry: the kinematics carry each row's point, at any geometry."""
    from torchcal.deploy.model import CalibratedModel
    from torchcal.deploy.persist import load, save

    robot, eff, data, params, geo, theta, mk = _problem(seed=3)
    final = params.values.clone()
    final[: robot.n_params] += 4e-3  # the fit moved on from the geometry the features were taken at
    eff.theta = final[robot.n_params:].clone()
    eff.covariate_range = {}
    geo_ps = robot.params()
    geo_ps.values = final[: robot.n_params].clone()
    model = CalibratedModel(robot, geo_ps, effects=[eff])
    want = EffectCalibrationProblem(robot, params, [eff], data).marker_positions(final[None])[0]
    got = model.geometric_pose(data.q, data.covariates)[..., :3, 3]
    torch.testing.assert_close(got, want, rtol=0, atol=1e-12)
    save(model, tmp_path / "m")
    again = load(tmp_path / "m").geometric_pose(data.q, data.covariates)[..., :3, 3]
    torch.testing.assert_close(again, got, rtol=0, atol=1e-15)


def _frames_problem(seed: int, turns: bool):
    robot, eff, data, params, geo, theta, mk = _problem(seed)
    terms = eff.terms + [("base.x", "level:tool", "lvl=b"), ("base.rz", "level:tool", "lvl=b"),
                         ("base.ry", "level:tool", "lvl=b")]
    eff = ParameterDrivers(robot, geometry=geo, terms=terms)
    k = len(terms)
    vals = torch.cat([theta, torch.tensor([0.02, 0.03, -0.02], dtype=D)])  # 20 mm, 30 mrad, 20 mrad
    p2 = ParamSet.concat(robot.params(), ParamSet([f"t{i}" for i in range(k)], ["m"] * k, vals,
                                                  torch.ones(k, dtype=torch.bool), torch.full((k,), -1.0, dtype=D),
                                                  torch.full((k,), 1.0, dtype=D)))
    p2.values[: robot.n_params] = geo
    p2.free[: robot.n_params] = True
    if turns:
        R, _ = robot.fk_rt(data.q, geo)
        from torchcal.kinematics.transforms import matrix_to_quat
        data = Measurements(q=data.q, positions=data.positions, marker_names=data.marker_names,
                            joint_names=data.joint_names, covariates=data.covariates,
                            quaternions=matrix_to_quat(R))
    return robot, eff, data, p2, vals, mk


def test_the_frame_per_row_is_the_base_moved_per_row():
    robot, eff, data, params, vals, mk = _frames_problem(4, turns=False)
    prob = EffectCalibrationProblem(robot, params, [eff], data)
    got = prob.marker_positions(params.values[None])[0]
    rows = params.values[: robot.n_params].repeat(len(data), 1)
    on = data.covariates["tool=b"]
    F = {f"{mk}.dx": vals[0], f"{mk}.dz": vals[1], "base.x": vals[3], "base.rz": vals[4], "base.ry": vals[5]}
    for name, v in F.items():
        rows[:, robot.param_names.index(name)] += on * v
    q = data.q + torch.outer(on, torch.eye(robot.dof, dtype=D)[robot.joint_names.index("elbow_joint")]) * vals[2]
    want = robot.positions(q[:, None], rows)[:, 0]
    torch.testing.assert_close(got, want, rtol=0, atol=1e-12)


@pytest.mark.parametrize("turns", [False, True])
def test_the_jacobian_with_frames_per_row_is_the_derivative_of_the_model(turns):
    robot, eff, data, params, vals, mk = _frames_problem(5, turns)
    err = _fd_error(EffectCalibrationProblem(robot, params, [eff], data, rot_weight=0.5 if turns else None), seed=6)
    assert err < 1e-7, err


def test_the_deployed_model_moves_the_frame_per_row_as_the_fit_did(tmp_path):
    from torchcal.deploy.model import CalibratedModel
    from torchcal.deploy.persist import load, save

    robot, eff, data, params, vals, mk = _frames_problem(7, turns=False)
    eff.theta = vals.clone()
    eff.covariate_range = {}
    geo_ps = robot.params()
    geo_ps.values = params.values[: robot.n_params].clone()
    model = CalibratedModel(robot, geo_ps, effects=[eff])
    want = EffectCalibrationProblem(robot, params, [eff], data).marker_positions(params.values[None])[0]
    torch.testing.assert_close(model.geometric_pose(data.q, data.covariates)[..., :3, 3], want, rtol=0, atol=1e-12)
    save(model, tmp_path / "m")
    again = load(tmp_path / "m").geometric_pose(data.q, data.covariates)[..., :3, 3]
    torch.testing.assert_close(again, want, rtol=0, atol=1e-12)
