"""The lumped joint compliance's parameters are products of a compliance and a link's mass or first
mass moment (issue 35 §3): checked by building them from a compliance and the URDF's inertials,
which must give the deflections of the plain compliance, and then reading their units off the
plain parameters' units."""
from __future__ import annotations

import torch

from torchcal.effects.compliance import JointCompliance
from torchcal.effects.gravity import body_inertials
from torchcal.kinematics.robots import shipped
from torchcal.params import display_unit


def test_lumped_parameters_are_compliance_times_mass_moment_in_that_unit():
    robot = shipped("ur5e")
    plain, lumped = JointCompliance(robot), JointCompliance(robot, lumped=True)
    c = torch.tensor([3e-5, 5e-5, 4e-5, 2e-5, 1e-5, 1e-5], dtype=torch.float64)  # rad/(N·m)
    theta_plain = torch.zeros(len(plain.param_names), dtype=torch.float64)
    theta_plain[: len(c)] = c
    inertials = body_inertials(robot)  # link -> (mass kg, COM (3,) m in the link frame)
    theta_lumped = torch.zeros(len(lumped.param_names), dtype=torch.float64)
    c_unit = plain.param_units[0]
    mass_unit = dict(zip(plain.param_names, plain.param_units))
    for i, (name, unit) in enumerate(zip(lumped.param_names, lumped.param_units)):
        _, joint, link, term = name.split(".")
        m, com = inertials.get(link, (0.0, [0.0, 0.0, 0.0]))
        cj = c[plain.joints.index(joint)]
        theta_lumped[i] = cj * m if term == "m" else cj * m * com["xyz".index(term[1])]
        # the unit of the product: compliance times kg (the mass) or kg·m (a first moment)
        other = mass_unit[f"joint_compliance.payload.{term}"]
        assert c_unit == "rad/(N*m)" and other in ("kg", "kg*m")
        assert unit == ("rad*kg/(N*m)" if other == "kg" else "rad*kg/N"), (name, unit)
    g = torch.Generator().manual_seed(0)
    q = (torch.rand(30, robot.dof, generator=g, dtype=torch.float64) - 0.5) * 4
    d_plain = plain.joint_delta(theta_plain[None], plain.prepare(q, {}))[0]
    d_lumped = lumped.joint_delta(theta_lumped[None], lumped.prepare(q, {}))[0]
    assert float(d_plain.abs().max()) > 1e-4  # a deflection worth comparing (rad)
    torch.testing.assert_close(d_lumped, d_plain, rtol=0, atol=1e-15)
    # and a report shows them in their own unit, never as a plain compliance
    assert display_unit("rad*kg/N") == (1e6, "µrad·kg/N") and display_unit("rad*kg/(N*m)")[1] == "µrad·kg/(N·m)"
