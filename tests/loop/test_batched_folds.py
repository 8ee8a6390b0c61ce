"""The loop's cross-validation folds fitted as one batched Levenberg-Marquardt equal the folds fitted
one by one on their own rows; the batched Jacobians equal the single ones; kept gravity features
equal fresh ones."""
from __future__ import annotations

import pytest
import torch

from torchcal import Robot
from torchcal.effects.compliance import JointCompliance
from torchcal.effects.gravity import _gravity_features, gravity_features
from torchcal.params import ParamSet
from torchcal.pipelines.crossval.evaluate import fit_folds, fit_params
from torchcal.pipelines.crossval.models import Context, effect_problem, folds_of, observation_errors
from torchcal.pipelines.crossval.priors import prior_weights
from torchcal.problems.template import geometric_start
from torchcal.problems.uncertainty import standard_errors
from torchcal.sim.serial import SimConfig, random_configs, simulated_robot

D = torch.float64


def _case(n=40, seed=0):
    robot = Robot.from_urdf("urdf/kuka_kr5_arc.urdf", markers=["smr@flange=0.01,-0.02,0.1"])
    cfg = SimConfig(n=n, noise=0.05e-3, seed=seed)
    real = simulated_robot(robot, cfg, ["joint_compliance"], options={"joint_compliance": {"compliance": 5e-5}},
                           true_params=None)
    data = real.measure(random_configs(robot, n, torch.Generator().manual_seed(seed + 1)))
    eff = JointCompliance(robot).bind(data)
    geo = geometric_start(robot, data, None)
    lo = torch.full((eff.n_params,), -float("inf"), dtype=D)
    start = ParamSet.concat(geo, ParamSet(eff.param_names, eff.param_units, torch.zeros(eff.n_params, dtype=D),
                                          torch.ones(eff.n_params, dtype=torch.bool), lo, -lo))
    ctx = Context(robot, data, folds_of(n, 5, seed), c=0.1e-3, sigma=0.05e-3)  # Huber: outer rows count
    return ctx, start, [eff]


def test_batched_folds_equal_each_fold_fitted_alone():
    ctx, start, effects = _case()
    prior = prior_weights(ctx.robot, start, 1.0, ctx.sigma, effects)
    full = fit_params(ctx, start, effects, ctx.data, prior, reduce=True)
    prob = effect_problem(ctx, full, effects, ctx.data, prior)
    batched = fit_folds(ctx, full, prob)
    assert len(batched) == len(ctx.folds)
    moved = 0.0
    for f, pb in zip(ctx.folds, batched):
        keep = torch.ones(len(ctx.data), dtype=torch.bool)
        keep[f] = False
        sub = ctx.data.subset(keep)
        alone = fit_params(ctx, full, effects, sub, prior, reduce=False)
        assert pb.names == alone.names and torch.equal(pb.free, alone.free)
        # the two runs round differently, and a Huber fit ends where its steps stop paying: they may
        # part by what noise could never tell apart, a thousandth of each value's standard error ...
        prob = effect_problem(ctx, alone, effects, sub, prior)
        J = prob.data_jacobian(prob.x0) * prob.observation_weights(prob.x0).repeat_interleave(3)[:, None]
        se = standard_errors(J, sigma=ctx.sigma, prior=prior[alone.free_index], singular="pinv")
        idx = alone.free_index
        assert float(((pb.values[idx] - alone.values[idx]).abs() / se).max()) < 1e-3
        # ... and predict the fold's own rows alike, to a ten-thousandth of the noise
        ea, _ = observation_errors(ctx, alone, effects, ctx.data.subset(f))
        eb, _ = observation_errors(ctx, pb, effects, ctx.data.subset(f))
        assert float((ea - eb).abs().max()) < 1e-4 * ctx.sigma
        moved = max(moved, float(((alone.values[idx] - full.values[idx]).abs() / se).max()))
    assert moved > 0.01  # each fold fit moved from the full fit, far beyond the tolerance above


def test_folds_too_short_for_the_free_set_are_refused_as_alone():
    """All rows hold more residuals than free parameters, a fold's training rows fewer: the batch
    refuses with the words a fold fitted alone refuses with."""
    ctx, start, effects = _case(n=70)
    prob = effect_problem(ctx, start, effects, ctx.data, None)
    assert prob.m >= prob.dim > prob.m * 4 // 5  # so the whole set fits and no fold does
    with pytest.raises(ValueError) as batched:
        fit_folds(ctx, start, prob)
    first = next(i for i, f in enumerate(ctx.folds) if 3 * (len(ctx.data) - len(f)) < prob.dim)
    keep = torch.ones(len(ctx.data), dtype=torch.bool)
    keep[ctx.folds[first]] = False
    with pytest.raises(ValueError) as alone:
        fit_params(ctx, start, effects, ctx.data.subset(keep), None, reduce=False)
    assert "free parameters (no reduction asked)" in str(alone.value)
    assert str(batched.value) == str(alone.value)


def test_batched_jacobians_equal_single_ones():
    ctx, start, effects = _case(n=25, seed=3)
    prior = prior_weights(ctx.robot, start, 1.0, ctx.sigma, effects)
    prob = effect_problem(ctx, start, effects, ctx.data, prior)
    g = torch.Generator().manual_seed(7)
    X = prob.x0 + 1e-3 * torch.randn(3, prob.dim, generator=g, dtype=D)
    JB = prob.jacobians(X)
    assert JB.shape == (3, prob.m, prob.dim)
    for b in range(3):
        torch.testing.assert_close(JB[b], prob.jacobian(X[b]), rtol=1e-12, atol=1e-15)
    # without a robust loss (whose Jacobian is IRLS's), the derivative of the residuals: central
    # differences, effect columns too
    plain = effect_problem(ctx, start, effects, ctx.data, prior, loss=False)
    JP = plain.jacobians(X)
    h = 1e-6
    E = h * torch.eye(prob.dim, dtype=D)
    fd = (plain.residuals(X[0] + E) - plain.residuals(X[0] - E)).T / (2 * h)
    err = float((fd - JP[0]).abs().max()) / float(fd.abs().max())
    assert err < 1e-5, err


def test_kept_gravity_features_equal_fresh_ones():
    robot = Robot.from_urdf("urdf/kuka_kr5_arc.urdf", markers=["smr@flange=0,0,0"])
    g = torch.Generator().manual_seed(2)
    links = [robot.joints[-1].child]
    q1 = random_configs(robot, 12, g)
    q2 = random_configs(robot, 12, g)
    a = gravity_features(robot, q1, links)
    b = gravity_features(robot, q1.clone(), links)  # equal commands, another tensor: the kept result
    c = gravity_features(robot, q2, links)
    torch.testing.assert_close(a, _gravity_features(robot, q1, links, (0.0, 0.0, -9.81)), rtol=0, atol=0)
    assert b is a
    torch.testing.assert_close(c, _gravity_features(robot, q2, links, (0.0, 0.0, -9.81)), rtol=0, atol=0)
    assert not torch.equal(a, c)


def test_effect_columns_with_turning_joints_and_moving_points():
    """Elastic deformation twists joints (joint deflections, which also turn the markers) and bends
    links (point displacements, which turn nothing): its columns through the joint Jacobian equal
    central differences of the residuals, orientations measured too."""
    from torchcal.effects.deformation import GravityDeformation
    from torchcal.kinematics.transforms import so3_exp
    from torchcal.measure.data import Measurements

    from torchcal.kinematics.robots import shipped

    robot = shipped("ur5e")  # link inertials: gravity loads the joints
    g = torch.Generator().manual_seed(11)
    q = random_configs(robot, 20, g)
    R, t = robot.fk_rt(q)
    t = t + 1e-4 * torch.randn(t.shape, generator=g, dtype=D)
    R = so3_exp(1e-3 * torch.randn(*R.shape[:-2], 3, generator=g, dtype=D)) @ R
    from scipy.spatial.transform import Rotation

    xyzw = torch.as_tensor(Rotation.from_matrix(R.reshape(-1, 3, 3).numpy()).as_quat(), dtype=D)
    quat = xyzw[:, [3, 0, 1, 2]].reshape(*R.shape[:-2], 4)
    data = Measurements(q, t, robot.marker_names, robot.joint_names, quaternions=quat)
    eff = GravityDeformation(robot).bind(data)
    kinds = {c["label"].split(".")[-1][:4] for c in eff._modes}
    assert "twis" in kinds and ("bend" in kinds or "shif" in kinds)  # both paths are exercised
    geo = geometric_start(robot, data, None)
    theta = 1e-5 * torch.randn(eff.n_params, generator=g, dtype=D)
    inf = torch.full((eff.n_params,), float("inf"), dtype=D)
    start = ParamSet.concat(geo, ParamSet(eff.param_names, eff.param_units, theta,
                                          torch.ones(eff.n_params, dtype=torch.bool), -inf, inf))
    ctx = Context(robot, data, folds_of(20, 5, 0), c=None, sigma=1e-4, rot_weight=0.2)
    prob = effect_problem(ctx, start, [eff], data)
    assert prob.obs.has_orientation and prob._eff_free.numel() == eff.n_params
    X = prob.x0[None]
    J = prob.jacobians(X)[0]
    cols = [prob.params.free_names.index(n) for n in eff.param_names]
    h = 1e-7
    E = h * torch.eye(prob.dim, dtype=D)[cols]
    fd = (prob.residuals(X + E) - prob.residuals(X - E)).T / (2 * h)
    err = float((fd - J[:, cols]).abs().max()) / float(fd.abs().max())
    assert float(fd.abs().max()) > 0 and err < 1e-6, err
