"""The any-parameter, any-driver family: its columns against finite differences of the kinematics,
its shapes, and its words."""
from __future__ import annotations

import torch

from torchcal.effects import ParameterDrivers
from torchcal.effects.anydriver_space import expanded
from torchcal.effects.shapes import settle_tags, shape_column, step_breaks
from torchcal.kinematics.robots import shipped


def _robot_and_rows(n: int = 12, seed: int = 0):
    robot = shipped("ur5e")
    g = torch.Generator().manual_seed(seed)
    q = (torch.rand(n, robot.dof, generator=g, dtype=torch.float64) - 0.5) * 3.0
    geo = torch.randn(robot.n_params, generator=g, dtype=torch.float64) * 1e-3
    cov = {"row": torch.arange(n, dtype=torch.float64),
           "tool=a": (torch.arange(n) % 2 == 0).double(), "tool=b": (torch.arange(n) % 2 == 1).double()}
    return robot, q, geo, cov


def test_columns_match_finite_differences_of_the_parameter():
    """Each term's column (a joint's zero as Δq, any other parameter through the geometric
    Jacobian) equals the change of the marker positions when that parameter alone moves by
    ε·f(driver) row by row (central differences)."""
    robot, q, geo, cov = _robot_and_rows()
    mk = robot.marker_names[0]
    terms = [("elbow_joint.offset", "row", "step5.5"), ("base.rx", "row", "lin"),
             (f"{mk}.dy", "level:tool", "lvl=b"), ("wrist_1_joint.dz", "q:wrist_1_joint", "sin1"),
             ("shoulder_lift_joint.droll", "q:elbow_joint", "hinge0.2")]
    eff = ParameterDrivers(robot, geometry=geo, terms=terms, ranges={"row": (5.5, 5.5)})
    prep = eff.prepare(q, cov)
    basis = eff.linear_basis(prep)
    Rb, _ = robot.base_transform(geo)
    Jq = robot.joint_jacobian(q, geo, check=False)[:, :, :3, :]
    D = torch.zeros(q.shape[0], len(robot.marker_names), 3, len(terms), dtype=torch.float64)
    if basis.dq is not None:
        D = D + Jq @ basis.dq[:, None]
    if basis.dp is not None:
        D = D + Rb @ basis.dp
    eps = 1e-6
    for t, (p, _, _) in enumerate(terms):
        k = robot.param_names.index(p)
        f = prep.features["F"][:, t]
        pp, pm = geo.repeat(q.shape[0], 1), geo.repeat(q.shape[0], 1)
        pp[:, k] += eps * f
        pm[:, k] -= eps * f
        fd = (robot.positions(q[:, None], pp) - robot.positions(q[:, None], pm))[:, 0] / (2 * eps)
        assert torch.allclose(D[..., t], fd, atol=1e-7, rtol=1e-5), p


def test_step_breaks_and_shapes():
    x = torch.arange(10, dtype=torch.float64)
    b = step_breaks(x, min_side=3)
    assert b[0] == 2.5 and b[-1] == 6.5 and len(b) == 5
    col = shape_column("step4.5", x, 0.0, 1.0)
    assert col.tolist() == [0.0] * 5 + [1.0] * 5
    hinge = shape_column("hinge3", x, 0.0, 1.0)
    assert torch.allclose(hinge, torch.clamp(x - 3, min=0))


def test_settling_shapes_start_at_the_first_value_on_a_grid_of_time_constants():
    """A settling ``exp(-(x - x0)/tau)``: 1 at the session's start and before it, e^-1 one time
    constant later; the time constants run from the span / sqrt(2) down in steps of 2^(1/4)."""
    x = torch.tensor([100.0, 160.0, 400.0, 1300.0], dtype=torch.float64)
    tags = settle_tags(x)
    taus = [float(t[3:].split("@")[0]) for t in tags]
    assert len(tags) == 24 and all(t.endswith("@100") for t in tags)
    assert abs(taus[0] - 1200 / 2 ** 0.5) < 1e-3 and all(abs(a / b - 2 ** 0.25) < 1e-5 for a, b in zip(taus, taus[1:]))
    col = shape_column("exp300@100", torch.tensor([50.0, 100.0, 400.0, 1000.0], dtype=torch.float64), 0.0, 1.0)
    want = torch.tensor([1.0, 1.0, torch.e ** -1, torch.e ** -3], dtype=torch.float64)
    assert torch.allclose(col, want, rtol=1e-12)
    assert settle_tags(torch.full((5,), 3.0, dtype=torch.float64)) == []  # a driver that never moves


def test_words_say_the_finding_in_units():
    robot, q, geo, cov = _robot_and_rows()
    eff = ParameterDrivers(robot, geometry=geo, terms=[("elbow_joint.offset", "row", "step212.5"),
                                                        ("base.ry", "time:time", "lin"),
                                                        (f"{robot.marker_names[0]}.dy", "level:tool", "lvl=probe")])
    eff.theta = torch.tensor([1.9e-3, 0.8e-3 / 3600, 12.4e-3], dtype=torch.float64)
    words = eff.describe()
    assert "joint elbow_joint's zero shifts by 1.9 mrad at row 213, and stays" == words[0]
    assert "0.8 mrad per hour" in words[1] and "instrument frame" in words[1]
    assert "differs by 12.4 mm for tool = probe" in words[2]
    eff = ParameterDrivers(robot, geometry=geo, terms=[("base.rx", "time:time", "exp900@0")])
    eff.theta = torch.tensor([-0.5e-3], dtype=torch.float64)  # 0.5 mrad below its settled value at the start
    assert eff.describe() == ["the instrument frame (turn about x) moves by 0.5 mrad as it settles along time (time), "
                              "with a time constant of 15 min"]
    assert eff.mode_words("base.rx~time:time~exp900@0") == (
        "the instrument frame (turn about x) settles along time (time), with a time constant of 15 min")


def test_saved_and_loaded_effect_predicts_the_same():
    robot, q, geo, cov = _robot_and_rows()
    eff = ParameterDrivers(robot, geometry=geo, terms=[("elbow_joint.offset", "row", "step5.5"),
                                                        ("base.rx", "row", "lin")], ranges={"row": (5.5, 5.5)})
    eff.theta = torch.tensor([1e-3, 2e-5], dtype=torch.float64)
    eff.covariate_range = {"row": (0.0, 11.0)}
    again = ParameterDrivers.from_state_dict(eff.state_dict(), robot)
    p = robot.positions(q, geo)
    assert torch.allclose(eff.position_correction(p, q, cov), again.position_correction(p, q, cov), atol=1e-12)
    assert torch.allclose(eff.joint_correction(q, cov), again.joint_correction(q, cov), atol=1e-12)


def test_direct_columns_equal_the_effect_evaluated_term_by_term():
    """The family's own linear basis (built directly) is the generic one (the effect evaluated
    at each unit coefficient)."""
    from torchcal.effects.base import Effect

    robot, q, geo, cov = _robot_and_rows()
    terms = [("elbow_joint.offset", "row", "step5.5"), ("base.rx", "row", "lin"),
             (f"{robot.marker_names[0]}.dy", "level:tool", "lvl=b"), ("wrist_1_joint.offset", "q:elbow_joint", "cos1"),
             ("shoulder_lift_joint.droll", "q:elbow_joint", "hinge0.2")]
    eff = ParameterDrivers(robot, geometry=geo, terms=terms, ranges={"row": (5.5, 5.5)})
    prep = eff.prepare(q, cov)
    a, b = eff.linear_basis(prep), Effect.linear_basis(eff, prep)
    # the marker point moved on its link, and the instrument frame moved per row, are no robot-base
    # displacements of the generic form: their columns are the point's and the base's own columns at
    # the effect's geometry
    mk = robot.marker_names[0]
    J = robot.param_jacobian(q, geo)
    own = J[..., [robot.param_names.index(f"{mk}.{c}") for c in ("dx", "dy", "dz")]]
    frame = J[..., [robot.param_names.index(f"base.{c}") for c in ("x", "y", "z", "rx", "ry", "rz")]]
    E = torch.eye(len(terms), dtype=torch.float64)
    dl, df = eff.point_delta(E, prep), eff.frame_delta(E, prep)  # (T, N, M, 3), (T, N, 6)
    assert dl.abs().sum((1, 2, 3)).nonzero().flatten().tolist() == [2]
    assert df.abs().sum((1, 2)).nonzero().flatten().tolist() == [1]
    Rb, _ = robot.base_transform(geo)
    moved = torch.einsum("ij,nmjc,tnmc->nmit", Rb.T, own, dl) + torch.einsum("ij,nmjc,tnc->nmit", Rb.T, frame, df)
    assert torch.allclose(a.dq, b.dq, atol=1e-15) and torch.allclose(a.dp, b.dp + moved, atol=1e-15)
    assert a.groups == b.groups


def test_the_instrument_frame_per_level_is_one_rigid_mode():
    """A set-up that differs by level moves the instrument frame as one rigid body: any base
    coordinate found with a text column expands into all six, in one mode, whose evidence is the
    markers' displacement (against central differences of the kinematics with the base frame moved
    on the rows of that level) and whose words say so."""
    from types import SimpleNamespace

    robot, q, geo, cov = _robot_and_rows()
    eff = ParameterDrivers(robot, geometry=geo)
    out = expanded(eff, [("base.rz", "level:tool")], SimpleNamespace(q=q, covariates=cov))
    assert out.terms == [(f"base.{a}", "level:tool", "lvl=b") for a in ("x", "y", "z", "rx", "ry", "rz")]
    assert [lab for lab, _ in out.modes()] == ["base.frame~level:tool~levels"]
    assert "instrument frame moves as one rigid body" in out.mode_words("base.frame~level:tool~levels")
    theta = torch.tensor([0.1e-3, 0.3e-3, -0.1e-3, 0.2e-3, 0.25e-3, 0.1e-3], dtype=torch.float64)
    prep = out.prepare(q, cov)
    sig = out.signature(prep, "base.frame~level:tool~levels", theta)
    eps = 1e-3
    on = cov["tool=b"][:, None]
    pp, pm = geo.repeat(q.shape[0], 1), geo.repeat(q.shape[0], 1)
    pp[:, :6] += eps * on * theta
    pm[:, :6] -= eps * on * theta
    fd = (robot.positions(q[:, None], pp) - robot.positions(q[:, None], pm))[:, 0] / (2 * eps)
    Rb, _ = robot.base_transform(geo)
    moved = sig["fitted"][:, None, None] * (Rb @ sig["G"][..., None])[..., 0]
    assert torch.allclose(moved, fd, atol=1e-9), (moved - fd).abs().max()
    assert bool((sig["fitted"][cov["tool=a"] == 1] == 0).all()) and bool((sig["fitted"][cov["tool=b"] == 1] > 0).all())


def test_a_rigid_thing_steps_and_settles_as_a_whole():
    """A step or a settling found for one coordinate of the instrument frame (or of a marker point)
    is offered for all of them at that break, one mode: a set-up changed mid-session, or a tracker
    warming up, is one rigid motion. The other shapes stay the coordinate's own; a joint's parameter
    keeps its step to itself."""
    from types import SimpleNamespace

    robot, q, geo, cov = _robot_and_rows()
    mk = robot.marker_names[0]
    eff = ParameterDrivers(robot, geometry=geo, ranges={"row": (5.5, 5.5)})
    pairs = [("base.ry", "row"), (f"{mk}.dz", "row"), ("elbow_joint.offset", "row")]
    steps = {("base.ry", "row"): ["step5.5", "exp4@0"], (f"{mk}.dz", "row"): ["step3.5"],
             ("elbow_joint.offset", "row"): ["step7.5"]}
    out = expanded(eff, pairs, SimpleNamespace(q=q, covariates=cov), steps)
    modes = dict(out.modes())
    frame = [out.terms[i] for i in modes["base.frame~row~step5.5"]]
    assert frame == [(f"base.{a}", "row", "step5.5") for a in ("x", "y", "z", "rx", "ry", "rz")]
    assert [out.terms[i] for i in modes[f"{mk}.point~row~step3.5"]] == [(f"{mk}.{a}", "row", "step3.5")
                                                                         for a in ("dx", "dy", "dz")]
    assert [out.terms[i] for i in modes["base.frame~row~exp4@0"]] == [(f"base.{a}", "row", "exp4@0")
                                                                        for a in ("x", "y", "z", "rx", "ry", "rz")]
    assert "base.ry~row~lin" in modes and "base.rx~row~lin" not in modes
    assert out.mode_words("base.frame~row~exp4@0") == ("the instrument frame moves as one rigid body (3 shifts, "
                                                        "3 turns) as it settles along the row order, with a time "
                                                        "constant of 4 rows")
    assert "elbow_joint.offset~row~step7.5" in modes
    assert out.mode_words("base.frame~row~step5.5") == (
        "the instrument frame moves as one rigid body (3 shifts, 3 turns) at row 6, and stays")
    assert out.mode_words(f"{mk}.point~row~step3.5") == f"the marker point {mk} moves at row 4, and stays"


def test_torque_drivers_carry_the_load_each_row_logs():
    """A stiffness that changes with the torque it carries sees what each row carries: with a load
    logged per row (a mass column, a text level), the torque drivers equal the simulator's gravity
    torques of the rigid robot with that row's payload on the flange (its own numpy wrenches), and
    a saved and loaded effect reads the same columns at correction time."""
    import numpy as np

    from torchcal.sim.physsim import PhysicalRobot

    robot = shipped("ur5e")
    g = torch.Generator().manual_seed(3)
    n = 9
    q = (torch.rand(n, robot.dof, generator=g, dtype=torch.float64) - 0.5) * 3.0
    kg = torch.tensor([0.0, 3.0, 6.0] * 3, dtype=torch.float64)
    box = (torch.arange(n) % 3 == 1).double()
    com = np.array([0.02, -0.01, 0.06])
    cov = {"payload_kg": kg, "load=box": box}
    link = robot.markers[0].link
    # 0.5 kg always there, 1 kg per unit of the mass column at `com`, 2.5 kg more for the box at its origin
    loads = {"payload_kg": [1.0, *com.tolist()], "load=box": [2.5, 0.0, 0.0, 0.0]}
    eff = ParameterDrivers(robot, terms=[("elbow_joint.offset", "torque:elbow_joint", "cube")],
                           payload=[0.5, 0.0, 0.0, 0.0], payload_link=link, loads=loads)
    assert set(eff.covariates) == {"payload_kg", "load=box"}  # needed again at correction time
    got = eff.torques(q, cov)
    ref = np.zeros((n, robot.dof))
    for i in range(n):
        # the simulator's rigid robot with this row's payload: its mass and centre from the three parts
        m = 0.5 + float(kg[i]) + 2.5 * float(box[i])
        sim = PhysicalRobot(robot.urdf_text, ["flange"], geometric_errors=False, instrument_frame=np.eye(4),
                            noise_m=0.0, payload_kg=m, payload_com_m=tuple(float(kg[i]) * com / m), payload_link=link)
        W = sim.gravity_wrenches(q[i:i + 1].numpy())
        ref[i] = [W["joints"][j]["tau_Nm"][0] for j in robot.joint_names]
    assert np.abs(got.numpy() - ref).max() < 1e-9 * np.abs(ref).max()
    # the loads matter: without them the torques are newtons-metres off
    assert np.abs(got.numpy() - eff.torques(q, {"payload_kg": 0 * kg, "load=box": 0 * box}).numpy()).max() > 10.0
    back = ParameterDrivers.from_state_dict(eff.state_dict(), robot)
    assert torch.equal(back.torques(q, cov), got)


def test_odd_torque_shapes_sit_about_zero_torque_and_are_offered_for_torques_only():
    """``τ|τ|`` and ``τ³`` over the half range, about zero torque (a stiffness that changes with the
    load's size turns either way alike), not about the training mean as the bow and the S; offered
    for a torque driver, never for a joint angle or time, and said as a stiffness."""
    from torchcal.effects.anydriver_space import shapes_for
    from torchcal.effects.anydriver_words import mode_words

    x = torch.tensor([-30.0, -5.0, 0.0, 10.0, 50.0], dtype=torch.float64)
    mean, half = float(x.mean()), 40.0
    assert torch.equal(shape_column("odd2", x, mean, half), torch.tensor([-0.5625, -0.015625, 0.0, 0.0625, 1.5625],
                                                                          dtype=torch.float64))
    assert torch.equal(shape_column("odd3", x, mean, half), (x / 40.0) ** 3)
    robot = shipped("ur5e")
    eff = ParameterDrivers(robot, terms=[("elbow_joint.offset", "torque:elbow_joint", "odd2")])
    assert {"odd2", "odd3"} <= set(shapes_for(eff, "torque:elbow_joint", x))
    assert not {"odd2", "odd3"} & set(shapes_for(eff, "q:elbow_joint", x) + shapes_for(eff, "time", x))
    words = mode_words(eff, "elbow_joint.offset~torque:elbow_joint~odd3")
    assert "cubed" in words and "stiffness" in words, words
