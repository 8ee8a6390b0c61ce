"""A load that changed mid-session with nothing logged, found by its own shape
(:mod:`torchcal.pipelines.loop.loadscan`): the scan's explained power against each break's projected
columns computed directly; a load change a later finding explains leaves
(:mod:`torchcal.pipelines.loop.prune`). The loop on a payload swapped beside a tracker knocked in one session
(``swap_and_knock``) is checked in ``tests/loop/test_loop_physsim_data.py``, on the run its
case-by-case test makes."""
from __future__ import annotations

import pytest
import torch

from torchcal import Robot
from torchcal.effects import ParameterDrivers, effect_params
from torchcal.effects.compliance import LoadCompliance
from torchcal.effects.shapes import step_breaks
from torchcal.measure.data import Measurements
from torchcal.params import ParamSet
from torchcal.pipelines.crossval.evaluate import evaluate
from torchcal.pipelines.crossval.models import Context, folds_of
from torchcal.pipelines.crossval.scores import T_EXIT, compare
from torchcal.pipelines.loop.loadscan import step_power
from torchcal.pipelines.loop.prune import prune
from torchcal.pipelines.loop.start import _at_fitted, _fitted_shared
from torchcal.problems.template import geometric_start
from torchcal.sim.cases import make_case

D = torch.float64


def test_the_step_scan_matches_each_projected_least_squares_fit():
    """Every break's explained power equals ``‖P r‖²`` of its own columns (``G`` past the break,
    projected off the model's columns) fitted by least squares directly, and its rank the columns'."""
    g = torch.Generator().manual_seed(7)
    n_obs, P = 30, 4
    x = torch.arange(n_obs, dtype=D)[torch.randperm(n_obs, generator=g)]  # the rows in any order
    b = step_breaks(x)
    at = torch.tensor(b, dtype=D)
    G = torch.randn(3 * n_obs, P, generator=g, dtype=D)
    G[:, 3] = G[:, 0] + G[:, 1]  # one column a combination of two others: rank 3
    Q, _ = torch.linalg.qr(torch.randn(3 * n_obs, 5, generator=g, dtype=D))
    r = torch.randn(3 * n_obs, generator=g, dtype=D)
    rp = r - Q @ (Q.T @ r)
    x3 = x.repeat_interleave(3)
    power, rank = step_power(G, x3, at, Q, rp)
    for i, br in enumerate(b):
        C = G * (x3 >= br).to(D)[:, None]
        C = C - Q @ (Q.T @ C)
        coef = torch.linalg.lstsq(C, rp[:, None], driver="gelsd").solution
        fit = C @ coef[:, 0]
        assert float(power[i]) == pytest.approx(float(fit @ fit), rel=1e-8)
        assert int(rank[i]) == 3


def test_a_load_change_is_one_part_that_can_leave_alone():
    """A load at a step is one part of four mass moments (the last four parameters of its load);
    without it the effect keeps its modes, payload and other loads under the same names."""
    robot = Robot.from_urdf("urdf/ur5e.urdf", markers=["tool@flange"])
    eff = LoadCompliance(robot, joints=["shoulder_lift_joint", "elbow_joint"],
                         loads=["payload_kg", "row~step9.5", "row~win3.5@7.5"])
    parts = eff.break_parts()
    assert [lab for lab, _ in parts] == ["load~row~step9.5", "load~row~win3.5@7.5"]  # a logged load is no part
    for lab, idx in parts:
        assert [eff.param_names[i] for i in idx] == [f"{eff.name}.{lab}.{k}" for k in ("m", "mx", "my", "mz")]
    out = eff.without_part("load~row~step9.5")
    assert out.loads == ["payload_kg", "row~win3.5@7.5"] and out.joints == eff.joints
    assert set(out.param_names) == set(eff.param_names) - {eff.param_names[i] for i in parts[0][1]}
    assert eff.without_part("load~row~step4.5") is eff
    assert LoadCompliance(robot, joints=["elbow_joint"], lumped=True, loads=["row~step9.5"]).break_parts() == []


def test_a_load_change_a_knock_explains_leaves_and_the_swap_stays():
    """``swap_and_knock`` (simulated: 6 kg carried from row 150 on, the tracker knocked at row 240,
    nothing logged), fitted with the joints' twists, the frame's step at the knock, the load changed
    at the swap and, standing in for the knock as an earlier round found it, at row 243.5. Judged
    again, the load at the knock leaves; the swap's load, the twists and the frame's step stay."""
    c = make_case("swap_and_knock", 0)
    robot = Robot.from_urdf(c.urdf, markers=c.markers)
    tr = c.train
    data = Measurements(q=torch.as_tensor(tr.q), positions=torch.as_tensor(tr.positions),
                        marker_names=list(tr.marker_names), joint_names=list(tr.joint_names),
                        covariates={"row": torch.arange(len(tr.q), dtype=D)})
    eff = LoadCompliance(robot, joints=["shoulder_lift_joint", "elbow_joint", "wrist_1_joint"],
                         loads=["row~step149.5", "row~step243.5"])
    frame = [(f"base.{a}", "row", "step239.5") for a in ("x", "y", "z", "rx", "ry", "rz")]
    knock = ParameterDrivers(robot, terms=frame, ranges={"row": (239.5, 239.5)})
    start = ParamSet.concat(geometric_start(robot, data, ["*"]), effect_params([eff, knock]))
    ctx = Context(robot, data, folds_of(len(data), 5, 0), c=0.06e-3, sigma=0.02e-3)
    m = evaluate(ctx, "swap and knock", start, [eff, knock], None)
    said = []
    out, gone = prune(ctx, m, say=said.append)
    assert [(g["effect"], g["mode"]) for g in gone] == [("load_compliance", "load~row~step243.5")], said
    assert out.effects[0].loads == ["row~step149.5"]
    assert [lab for lab, _ in out.effects[0].modes()] == [f"{j}.twist" for j in eff.joints]
    assert out.effects[1].terms == knock.terms
    # what the rule read, refitted: the model without the knock's load is no worse ...
    t, pen_ok, _ = compare(out.scores, m.scores, out.k, m.k, ctx.n_obs)
    assert not (t > T_EXIT and pen_ok)
    # ... and the swap's load is carried by the data: 6 kg within a quarter
    mass = float(out.params.values[out.params.names.index("load_compliance.load~row~step149.5.m")])
    assert abs(mass - 6.0) < 1.5


def test_a_new_mode_of_a_fitted_family_is_one_column_at_its_payload():
    """A twist joining a load compliance whose payload and load an accepted effect fitted is linearised
    at them: its column is the joint's deflection per unit compliance under that load, as the effect's
    own model computes it. A load offered this round (fitted by nobody) keeps its four product columns."""
    robot = Robot.from_urdf("urdf/ur5e.urdf", markers=["tool@flange"])
    n = 16
    g = torch.Generator().manual_seed(11)
    q = (torch.rand(n, robot.dof, generator=g, dtype=D) - 0.5) * 2.0
    cov = {"row": torch.arange(n, dtype=D)}
    joints = ["shoulder_lift_joint", "elbow_joint", "wrist_1_joint"]
    old = LoadCompliance(robot, joints=joints[:2], loads=["row~step7.5"])
    old_theta = torch.tensor([6e-6, 9e-6, 0.3, 0.01, -0.02, 0.04, 0.0, 0.0, 5.5, 0.1, 0.0, 0.6], dtype=D)
    old.theta = old_theta
    eff = LoadCompliance(robot, joints=joints, loads=["row~step7.5", "row~step11.5"])
    at = _fitted_shared(eff, [old], [effect_params([old])])
    assert at.shape == (1 + 12,) and torch.isnan(at[9:]).all()  # the payload and the first load, then the new one
    prep = eff.prepare(q, cov)
    basis = eff.linear_basis(prep)
    k = [lab for lab, _ in eff.modes()].index("wrist_1_joint.twist")
    cols = basis.dq[:, :, basis.groups[k]].reshape(n * robot.dof, -1)
    got = _at_fitted(cols, at)
    assert got.shape[1] == 1 + 4  # one column for the twist, four for the load nobody fitted
    theta = torch.zeros(eff.n_params, dtype=D)
    theta[k] = 1.0  # unit compliance of the wrist, the fitted payload and first load, no second load
    theta[3:7], theta[9:13] = old_theta[2:6], old_theta[8:12]
    want = eff.joint_delta(theta[None], prep)[0].reshape(-1)
    # the same sums taken in another order: rounding of the largest deflection's size
    assert torch.allclose(got[:, 0], want, rtol=0.0, atol=1e-12 * float(want.abs().max()))
    assert torch.equal(got[:, 1:], cols[:, 9:])
    assert _fitted_shared(eff, [], []) is None
