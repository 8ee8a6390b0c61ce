"""Unknowns of the set-up (the instrument frame, marker points, and the effects' parameters that move
them) are kept where the data cannot tell them from a robot error, and never dropped for imprecision
(:func:`~torchcal.pipelines.fitting.setup_first`, :func:`~torchcal.pipelines.fitting.reduce_free`).
Independent references: Jacobians with exact ties built by hand; a noise so coarse that no joint error
is seen to its plausible size."""
from __future__ import annotations

import torch

from torchcal.effects import ParameterDrivers
from torchcal.kinematics.robots import shipped
from torchcal.pipelines.crossval.models import Context, effect_problem
from torchcal.pipelines.fitting import reduce_free, setup_first
from torchcal.problems.identifiability import analyse_jacobian
from torchcal.problems.template import geometric_start

from .test_creeping_fit import _seventeen_poses


def _drivers():
    robot = shipped("ur5e")
    mk = robot.marker_names[0]
    terms = [("base.rz", "level:station", "lvl=B"), (f"{mk}.dz", "level:tool", "lvl=b"),
             ("elbow_joint.offset", "row", "lin")]
    return robot, ParameterDrivers(robot, terms=terms)


def test_an_effect_names_the_parameters_that_move_the_set_up():
    _, eff = _drivers()
    frame, point, zero = eff.param_names
    assert eff.setup_parameters() == {frame: "frame", point: "marker"}
    tiers = setup_first([eff])
    assert "base.*" in tiers[0] and point not in tiers[0] and zero not in sum(tiers, [])
    assert setup_first([]) is None


def test_a_set_up_parameter_tied_to_a_robot_error_is_the_one_kept():
    """The station's turn has exactly the first joint's zero's column, the tool's length exactly the
    last joint's: by default the textbook parameters win the ties; with the effect's set-up tiers the
    set-up's parameters do, and the robot errors are the ones dropped."""
    robot, eff = _drivers()
    frame, point, _ = eff.param_names
    g = torch.Generator().manual_seed(3)
    a, b, c = torch.randn(3, 40, generator=g, dtype=torch.float64)
    names = ["shoulder_pan_joint.offset", "wrist_3_joint.dz", "elbow_joint.dx", frame, point]
    units = ["rad", "m", "m", "rad", "m"]
    J = torch.stack([a, b, c, -2.0 * a, 0.5 * b], 1)
    plain = analyse_jacobian(J, names, units, markers=robot.marker_names)
    assert frame in plain.dropped and "shoulder_pan_joint.offset" in plain.identifiable
    kept = analyse_jacobian(J, names, units, markers=robot.marker_names, prefer=setup_first([eff]))
    assert sorted(kept.dropped) == ["shoulder_pan_joint.offset", "wrist_3_joint.dz"], kept.dropped
    assert {frame, point, "elbow_joint.dx"} == set(kept.identifiable)


def test_the_instrument_frame_is_never_dropped_for_imprecision():
    """At a noise of 1 m no joint error is seen to its plausible size (10 mm, 10 mrad), and each is
    dropped; the instrument frame stands metres from the robot, turned any way, has no plausible
    size, and stays free: without it the positions mean nothing."""
    robot, data = _seventeen_poses()
    ctx = Context(robot, data, [], None, 1.0)
    p = geometric_start(robot, data, None)
    out, rep = reduce_free(lambda q: effect_problem(ctx, q, [], data, None), p, markers=robot.marker_names,
                           noise=1.0, plausible=ctx.plausible)
    base = [n for n in p.free_names if n.startswith("base.")]
    assert base and set(base) <= set(out.free_names), rep.imprecise
    joints = [n for n in p.free_names if n.split(".")[0] in robot.joint_names]
    assert joints and not set(joints) & set(out.free_names), out.free_names
