"""Joint compliance under a load logged row by row (:class:`~torchcal.effects.LoadCompliance`, the
``loads`` of :class:`~torchcal.effects.GravityDeformation`). Independent references: the simulator's
torsion under a payload read from a column (its own URDF parser, kinematics and gravity), the
linear form's exact identity, and the nested rule on made-up scores."""
from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import torch

from torchcal import Robot
from torchcal.effects import GravityDeformation, JointCompliance, LoadCompliance, ParameterDrivers
from torchcal.effects.compliance import load_columns
from torchcal.kinematics.robots import urdf_path
from torchcal.pipelines.crossval.scores import compare
from torchcal.pipelines.loop import diagnosis
from torchcal.sim.physsim import PhysicalRobot

UR5E = urdf_path("ur5e").read_text()
COM = (0.02, -0.03, 0.09)
NU = torch.tensor([1.0, *COM], dtype=torch.float64)  # mass moments per kg of the logged load


def test_a_logged_load_twists_the_joints_as_the_simulator_does():
    """Each row carries the payload its column logs (0 to 8 kg at one centre of mass): the twist with
    the load's moments per kg equal to (1, s) is the simulator's torsion under that row's payload."""
    kw = dict(seed=3, geometric_errors=False, instrument_frame=np.eye(4), payload_column="load_kg", payload_com_m=COM)
    soft = PhysicalRobot(UR5E, ["tool@flange"], **kw, torsion={"elbow_joint": 2e-5, "shoulder_lift_joint": 1e-5})
    q = soft.sample_q(40)
    load = np.random.default_rng(0).choice([0.0, 2.5, 8.0], 40)
    robot = Robot.from_urdf(UR5E, markers=["tool@flange"])
    eff = JointCompliance(robot, ["shoulder_lift_joint", "elbow_joint"], loads=["load_kg"])
    z = torch.zeros
    theta = torch.cat([torch.tensor([1e-5, 2e-5], dtype=torch.float64), z(4, dtype=torch.float64),
                       z(2, dtype=torch.float64), NU])
    assert eff.param_names[-4:] == [f"joint_compliance.load~load_kg.{k}" for k in ("m", "mx", "my", "mz")]
    dq = eff.joint_delta(theta[None], eff.prepare(torch.tensor(q), {"load_kg": torch.tensor(load)}))[0]
    p = robot.positions(torch.tensor(q) + dq).numpy()
    np.testing.assert_allclose(p, soft.reach(q, covariates={"load_kg": load}), atol=1e-12)


def test_loads_logged_by_name_twist_the_joints_as_the_simulator_does():
    """Each row's load named in a text column (0.5 kg empty, 4 kg box, 9 kg pallet): the first level's
    load is the constant payload, each other level's its own mass moments beyond it."""
    masses = {"box": 4.0, "empty": 0.5, "pallet": 9.0}
    kw = dict(seed=3, geometric_errors=False, instrument_frame=np.eye(4), payload_column="level:load",
              payload_levels=masses, payload_com_m=COM)
    soft = PhysicalRobot(UR5E, ["tool@flange"], **kw, torsion={"elbow_joint": 2e-5, "shoulder_lift_joint": 1e-5})
    q = soft.sample_q(30)
    names = np.random.default_rng(1).choice(sorted(masses), 30)
    cov = {f"load={lv}": torch.tensor((names == lv).astype(float)) for lv in masses}
    assert load_columns(cov) == ["load=empty", "load=pallet"]  # the first level (sorted) is the baseline
    robot = Robot.from_urdf(UR5E, markers=["tool@flange"])
    eff = JointCompliance(robot, ["shoulder_lift_joint", "elbow_joint"], loads=load_columns(cov))
    box = masses["box"]
    theta = torch.cat([torch.tensor([1e-5, 2e-5], dtype=torch.float64), box * NU, torch.zeros(2, dtype=torch.float64),
                       (masses["empty"] - box) * NU, (masses["pallet"] - box) * NU])
    dq = eff.joint_delta(theta[None], eff.prepare(torch.tensor(q), cov))[0]
    p = robot.positions(torch.tensor(q) + dq).numpy()
    np.testing.assert_allclose(p, soft.reach(q, covariates={"level:load": names}), atol=1e-12)
    said = eff.describe(theta)
    assert any("is 5 kg more for load = pallet than for the first level" in x for x in said), said


def test_the_linear_form_holds_the_loads_and_factors_back():
    """At coordinates (c, c·μ, c·ν) the linear basis gives exactly the model's displacement and
    deflection, and :meth:`from_linear` gives the parameters back."""
    robot = Robot.from_urdf(UR5E, markers=["tool@flange=0.01,0.02,0.1"])
    eff = GravityDeformation(robot, loads=["load_kg"])
    q = torch.tensor(PhysicalRobot(UR5E, ["tool@flange"], seed=4).sample_q(25))
    cov = {"load_kg": torch.linspace(0.0, 6.0, 25, dtype=torch.float64)}
    prep = eff.prepare(q, cov)
    K = len(eff.mode_labels())
    theta = torch.zeros(eff.n_params, dtype=torch.float64)
    theta[:K] = torch.rand(K, generator=torch.Generator().manual_seed(0), dtype=torch.float64) * 1e-5
    mu = torch.tensor([2.0, 0.01, 0.0, 0.2], dtype=torch.float64)
    theta[K:K + 4], theta[K + 6:] = mu, NU
    basis = eff.linear_basis(prep)
    coords = torch.cat([torch.cat([theta[k:k + 1], theta[k] * mu, theta[k] * NU]) for k in range(K)])
    assert basis.shared == 8 and eff.shared() == list(range(K, K + 10))
    dp, dq = eff.position_delta(theta[None], prep)[0], eff.joint_delta(theta[None], prep)[0]
    assert float((basis.dp @ coords - dp).abs().max()) < 1e-12 * float(dp.abs().max())
    assert float((basis.dq @ coords - dq).abs().max()) < 1e-12 * float(dq.abs().max())
    assert torch.allclose(eff.from_linear(coords), theta, rtol=1e-12, atol=1e-18)


def test_load_compliance_takes_the_numeric_columns_but_time():
    robot = Robot.from_urdf(UR5E, markers=["tool@flange"])
    n = 12
    one = torch.ones(n, dtype=torch.float64)
    data = SimpleNamespace(q=torch.tensor(PhysicalRobot(UR5E, ["tool@flange"], seed=5).sample_q(n)),
                           marker_names=["tool"],
                           covariates={"time": torch.arange(n, dtype=torch.float64), "load_kg": torch.arange(n) % 3 * one,
                                       "marker_std_mm": one, "dir.elbow_joint": one, "steady": one})
    eff = LoadCompliance(robot)
    assert eff.applicable(data) == (True, "")
    bound = eff.bind(data)
    assert bound.loads == ["load_kg"] and bound.covariates == ["load_kg"]
    assert bound.covariate_range == {"load_kg": (0.0, 2.0)}
    said = bound.describe(torch.cat([bound.theta[:-4], NU * 1.5]))
    assert any("grows by 1.5 kg per unit of load_kg" in s and "(20, -30, 90) mm" in s for s in said), said
    bare = SimpleNamespace(**{**vars(data), "covariates": {"time": data.covariates["time"]}})
    waits = LoadCompliance(robot).bind(bare)
    assert waits.loads == [] and waits.waiting() is not None  # nothing logs a load, no set-up change found yet
    none = SimpleNamespace(**{**vars(data), "covariates": {}})
    assert not LoadCompliance(robot).applicable(none)[0]


def test_a_set_up_change_found_in_time_becomes_a_load_step():
    """A step an accepted effect found in time (the frame moved at t = 5.5 s) is offered as a load
    that steps there: a payload swapped with nothing logged changes the deflection too."""
    robot = Robot.from_urdf(UR5E, markers=["tool@flange"])
    n = 12
    t = torch.arange(n, dtype=torch.float64)
    data = SimpleNamespace(q=torch.tensor(PhysicalRobot(UR5E, ["tool@flange"], seed=5).sample_q(n)),
                           marker_names=["tool"], covariates={"time": t})
    found = ParameterDrivers(robot, terms=[("base.x", "time:time", "step5.5"), ("elbow_joint.offset", "time:time", "lin")])
    eff = LoadCompliance(robot).bind(data).given([found], data)
    assert eff.loads == ["time~step5.5"] and eff.covariates == ["time"] and eff.waiting() is None
    K = len(eff.mode_labels())
    theta = torch.zeros(eff.n_params, dtype=torch.float64)
    theta[:K] = 1e-5
    theta[K + 6:] = NU * 5.0  # 5 kg more from t = 5.5 s on
    dq = eff.joint_delta(theta[None], eff.prepare(data.q, data.covariates))[0]
    before = JointCompliance(robot, eff.joints)
    ref0 = before.joint_delta(theta[None, :K + 6], before.prepare(data.q, {}))[0]
    th1 = theta[:K + 6].clone()
    th1[K:K + 4] = NU * 5.0
    ref1 = before.joint_delta(th1[None], before.prepare(data.q, {}))[0]
    late = t >= 5.5
    assert torch.allclose(dq[~late], ref0[~late], rtol=1e-12, atol=1e-18)
    assert torch.allclose(dq[late], ref1[late], rtol=1e-12, atol=1e-18)


def test_an_effect_that_holds_another_must_beat_it():
    """Of two passing trials, one holding the other (joint compliance under a logged load holds plain
    joint compliance) wins only where it beats that one by the rule: a lower penalised error made of
    scatter does not do; a clear gain does."""
    n = 200
    g = torch.Generator().manual_seed(1)
    base = torch.rand(n, generator=g, dtype=torch.float64) + 1.0
    current = SimpleNamespace(scores=base + 0.2, k=20.0)

    def trial(name, scores, k):
        return SimpleNamespace(name=name, ok=True, model=SimpleNamespace(scores=scores, k=k))

    plain = trial("joint_compliance", base, 22.0)
    ctx = SimpleNamespace(n_obs=20 * n)
    rule = lambda ctx, a, b, n_obs: compare(a.scores, b.scores, a.k, b.k, n_obs)  # noqa: E731
    names = ["joint_compliance", "load_compliance"]
    scatter = torch.randn(n, generator=g, dtype=torch.float64) * 0.5
    barely = trial("load_compliance", base - 0.01 + (scatter - scatter.mean()), 26.0)
    t, lower, ok = rule(ctx, plain.model, barely.model, ctx.n_obs)
    assert lower and not ok, t  # lower penalised error, no gain the rule sees
    orig = diagnosis.compare_at
    diagnosis.compare_at = rule
    try:
        assert diagnosis._winner(ctx, current, [plain, barely], names) is plain
        clearly = trial("load_compliance", base - 0.1, 26.0)
        assert diagnosis._winner(ctx, current, [plain, clearly], names) is clearly
    finally:
        diagnosis.compare_at = orig
