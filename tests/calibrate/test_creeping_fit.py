"""A fit that creeps: seventeen poses of a UR10 (positions of one point, 0.25 mm noise) and every
geometric error of its joint origins. A combination of a wrist offset, a wrist origin and the
probe's length is barely seen, and one fit walks along the valley it spans for 75 steps, to be
judged imprecise only then. With precision checkpoints (every 30 steps, the default) the
walk is judged while it goes and refitted without the vague parameter at once: the same free set
and the same fitted values (the refit starts from the start values either way), in fewer steps.

Independent reference: the same fit with checkpoints off (``checkpoint_every=None``), which judges
precision only at the end of each fit."""
from __future__ import annotations

import pytest
import torch

from torchcal import Robot
from torchcal.measure.data import Measurements
from torchcal.pipelines.crossval.models import Context, effect_problem, fit_noise
from torchcal.pipelines.fitting import fit_identified
from torchcal.problems.template import geometric_start
from torchcal.sim.ur10 import ur10_urdf

D = torch.float64


def _seventeen_poses():
    robot = Robot.from_urdf(ur10_urdf(), markers=["tmac@flange=0,0,0.109"])
    g = torch.Generator().manual_seed(0)
    q = (torch.rand(17, 6, generator=g, dtype=D) * 2 - 1) * 2.5
    errors = torch.randn(robot.n_params, generator=g, dtype=D) * 1e-3
    p = robot.positions(q, errors) + 2.5e-4 * torch.randn(17, 1, 3, generator=g, dtype=D)
    data = Measurements(q=q, positions=p, marker_names=robot.marker_names, joint_names=robot.joint_names,
                        robot=robot.name)
    return robot, data


def _fit(robot, data, every):
    ctx = Context(robot, data, [], None, 1.0)
    steps = []

    def make(p):
        prob = effect_problem(ctx, p, [], data, None)
        plain = prob.residuals

        def counted(X):
            steps.append(X.shape[0])
            return plain(X)
        prob.residuals = counted
        return prob

    ps, res, rep = fit_identified(make, geometric_start(robot, data, None), reduce=True, markers=robot.marker_names,
                                  options={"max_iter": 200}, noise=fit_noise, plausible=ctx.plausible,
                                  checkpoint_every=every)
    return ps, rep, sum(steps)


def test_a_creeping_fit_is_judged_while_it_creeps():
    robot, data = _seventeen_poses()
    late, rep_late, n_late = _fit(robot, data, None)
    early, rep_early, n_early = _fit(robot, data, 30)
    vague = sorted(n for n, why in rep_late.reasons.items() if "plausibly" in why)
    assert vague, "the case must have a parameter judged imprecise, or it tests nothing"
    assert sorted(rep_early.dropped) == sorted(rep_late.dropped)
    assert sorted(n for n, why in rep_early.reasons.items() if "plausibly" in why) == vague
    assert early.free_names == late.free_names
    # far below the standard errors (tenths of a mm and mrad at this noise): the same refit
    assert torch.allclose(early.values, late.values, rtol=0, atol=1e-9)
    # the walk is cut at a checkpoint: at least one checkpoint's worth of steps saved
    assert n_early <= n_late - 30, (n_early, n_late)


@pytest.mark.slow
def test_calibrate_judges_a_creeping_fit_while_it_creeps(monkeypatch):
    """``calibrate`` solves through its own ``solve`` (a swarm's box, a polish): the checkpoint reaches
    its Levenberg-Marquardt too. A UR5e whose elbow origin is 40 mm off, 40 poses: one fit walked its
    whole 500-step budget before. Reference: the same calibration with the checkpoint refused: the
    same free set and values, in fewer steps."""
    import torchcal.pipelines.calibrate as cal
    from torchcal import calibrate
    from torchcal.kinematics.robots import shipped
    from torchcal.sim.serial import SimConfig, simulate

    robot = shipped("ur5e")
    truth = robot.params()
    truth["elbow_joint.dx"] = 0.04
    d, _ = simulate(robot, SimConfig(n=40, seed=2), true_params=truth)
    steps = []
    plain_solve = cal._Fitter.solve

    def counted(self, prob, **creep):
        res = plain_solve(self, prob, **creep)
        steps.append(res.n_iter)
        return res
    monkeypatch.setattr(cal._Fitter, "solve", counted)
    early = calibrate(robot, d)
    n_early, steps[:] = sum(steps), []
    monkeypatch.setattr(cal._Fitter, "solve", lambda self, prob, **creep: counted(self, prob))
    late = calibrate(robot, d)
    n_late = sum(steps)
    assert early.params.free_names == late.params.free_names
    torch.testing.assert_close(early.params.values, late.params.values, rtol=0, atol=1e-9)
    assert early.problems() == late.problems()
    assert n_early <= n_late - 300, (n_early, n_late)  # measured: 544 trial steps against 1 437
