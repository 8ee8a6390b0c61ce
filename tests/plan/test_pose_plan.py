"""Pose planning: the rank-1 updates, the selection against random subsets, the gradient
refinement inside the limits and the box, the reachability and self-collision filters, effects
(compliance, backlash directions), and the command line's refusals."""
from __future__ import annotations

import math

import pytest
import torch

from torchcal import Robot, calibrate, plan_poses
from torchcal.cli.app import main as cli
from torchcal.problems.identifiability import stacked_jacobian
from torchcal.pipelines.plan.design import CRITERIA, candidate_values, criterion_value, information
from torchcal.pipelines.plan.feasible import SelfCollision, in_box, parse_box
from torchcal.kinematics.robots import shipped, urdf_path
from torchcal.kinematics.bounds import config_bounds
from torchcal.sim.serial import SimConfig, random_configs, simulate
from torchcal.report.plan import plan_markdown

KR5 = str(urdf_path("kuka_kr5_arc"))
SMR = "smr@flange=0,0,0"

# a base block, and two 0.6 m links turning about y: folded back, link2 comes down onto the base
ARM = """<?xml version="1.0"?>
<robot name="folding_arm">
  <link name="base"><collision><geometry><box size="0.2 0.2 0.2"/></geometry></collision></link>
  <link name="l1"><collision><origin xyz="0 0 0.3"/><geometry><box size="0.05 0.05 0.6"/></geometry></collision></link>
  <link name="l2">
    <collision><origin xyz="0 0 0.3"/><geometry><cylinder radius="0.025" length="0.6"/></geometry></collision>
    <collision><geometry><mesh filename="package://arm/meshes/{mesh}"/></geometry></collision>
  </link>
  <joint name="j1" type="revolute"><parent link="base"/><child link="l1"/><origin xyz="0 0 0.1"/>
    <axis xyz="0 1 0"/><limit lower="-1.5" upper="1.5" effort="1" velocity="1"/></joint>
  <joint name="j2" type="revolute"><parent link="l1"/><child link="l2"/><origin xyz="0 0 0.6"/>
    <axis xyz="0 1 0"/><limit lower="-3.1" upper="3.1" effort="1" velocity="1"/></joint>
</robot>
"""


@pytest.fixture(scope="module")
def kr5():
    return shipped("kuka_kr5_arc", markers=[SMR])


@pytest.fixture(scope="module")
def cands(kr5):
    return random_configs(kr5, 600, torch.Generator().manual_seed(3))


@pytest.mark.parametrize("kind", CRITERIA)
def test_rank_one_updates_equal_the_direct_criterion(kind):
    g = torch.Generator().manual_seed(0)
    k, r = 7, 3
    B = torch.randn(5, r, k, generator=g, dtype=torch.float64)
    M = information(B)
    A = torch.randn(40, r, k, generator=g, dtype=torch.float64)
    fast = candidate_values(M, A, 6 * r, kind)
    direct = torch.stack([criterion_value(M + a.T @ a, 6 * r, kind) for a in A])
    assert torch.allclose(fast, direct, rtol=1e-10, atol=1e-10)
    if kind == "D":
        assert torch.allclose(direct, torch.stack([torch.logdet(M + a.T @ a) for a in A]), rtol=1e-12)


def _logdet(robot, q, names):
    J = stacked_jacobian(robot, q, free=names)
    return float(torch.logdet(J.T @ J))


@pytest.mark.parametrize("kind", CRITERIA)
def test_the_plan_beats_random_subsets_of_its_candidates(kr5, cands, kind):
    plan = plan_poses(kr5, 12, candidates=cands, criterion=kind, refine_steps=0, exchange_passes=1)
    st = plan.stages
    assert st["exchange"] >= st["greedy"] and math.isfinite(plan.value)
    assert st["exchange"] > st["random_median"]
    if kind == "D":  # unscaled log det of JᵀJ, computed here, against 20 random subsets
        names = list(plan.std_errors)
        mine = _logdet(kr5, plan.q, names)
        g = torch.Generator().manual_seed(11)
        rnd = [_logdet(kr5, cands[torch.randperm(len(cands), generator=g)[:12]], names) for _ in range(20)]
        assert mine > max(rnd)


def test_refinement_raises_the_criterion_inside_the_limits_and_the_box(kr5, cands):
    box = (-1.2, 1.2, -1.2, 1.2, 0.3, 1.5)
    plan = plan_poses(kr5, 12, candidates=cands, reachable=box, refine_steps=25, exchange_passes=1)
    h = plan.refine_history
    assert max(h) > h[0] and plan.value == pytest.approx(max(h), rel=1e-9) and plan.stages["refined"] > plan.stages["exchange"]
    lo, hi = config_bounds(kr5, 0.1)
    assert bool(((plan.q >= lo) & (plan.q <= hi)).all())
    assert bool(in_box(kr5, plan.q, parse_box(box)).all())
    assert plan.feasibility["in_box"] < plan.feasibility["drawn"]


def test_the_box_keeps_exactly_the_poses_whose_markers_are_inside(kr5, cands):
    box = parse_box("-1,1,-1,1,0.2,1.2")
    p = kr5.positions(cands, base=False)[:, 0]
    inside = (p[:, 0].abs() <= 1) & (p[:, 1].abs() <= 1) & (p[:, 2] >= 0.2) & (p[:, 2] <= 1.2)
    assert 0 < int(inside.sum()) < len(cands)
    assert torch.equal(in_box(kr5, cands, box), inside)
    with pytest.raises(ValueError, match="widen the box"):
        plan_poses(kr5, 5, candidates=cands, reachable=(5, 6, 5, 6, 5, 6))


@pytest.mark.parametrize("bad, what", [("1,2,3", "six numbers"), ("0,1,0,1,1,0", "below the maximum along z"),
                                       ("0,1,0,1,0,nan", "finite"), ("0,1000,0,1000,0,1000", "millimetres"),
                                       ("a,b,c,d,e,f", "six numbers")])
def test_a_bad_box_is_named(bad, what):
    with pytest.raises(ValueError, match=what):
        parse_box(bad)


def test_self_collision_drops_folded_poses_and_says_what_it_skips(tmp_path):
    import trimesh

    (tmp_path / "meshes").mkdir()
    trimesh.creation.box(extents=(0.04, 0.04, 0.04)).export(tmp_path / "meshes" / "knob.stl")
    urdf = tmp_path / "arm.urdf"
    urdf.write_text(ARM.format(mesh="knob.stl"))
    robot = Robot.from_urdf(str(urdf), markers=["tip@l2=0,0,0.6"])
    col = SelfCollision(robot, 0.005, urdf)
    d = col.describe()
    assert col.checked and d["pairs_checked"] == [["base", "l2"]]  # l1 touches both by design
    assert d["not_checked_missing_meshes"] == []
    q = torch.tensor([[0.0, 0.0], [0.0, 1.5], [0.0, 3.0], [0.0, -3.0], [1.0, 2.5], [0.5, -2.0]], dtype=torch.float64)
    # folded back (|q2| = 3 rad), link2's far end is 0.16 m from the base block's centre, inside its
    # bounding sphere (0.17 m) plus link2's (0.05 m); straight up or sideways it is metres away
    assert col(q).tolist() == [False, False, True, True, False, False]
    urdf2 = tmp_path / "arm2.urdf"
    urdf2.write_text(ARM.format(mesh="missing.stl"))
    with pytest.warns(UserWarning, match="not found and not checked"):
        col2 = SelfCollision(Robot.from_urdf(str(urdf2), markers=["tip@l2=0,0,0.6"]), 0.005, urdf2)
    assert col2.describe()["not_checked_missing_meshes"] == ["l2: package://arm/meshes/missing.stl"]
    plan = plan_poses(robot, 8, n_candidates=400, margin=0.0, collision_margin=0.005, urdf_path=urdf, refine_steps=10)
    assert plan.feasibility["clear"] < plan.feasibility["in_box"] and not bool(col(plan.q).any())


def test_a_urdf_without_collision_shapes_is_said_to_be_unchecked(kr5, cands):
    with pytest.warns(UserWarning, match="self-collision not checked"):
        plan = plan_poses(kr5, 10, candidates=cands, collision_margin=0.01, refine_steps=0, exchange_passes=1)
    assert plan.feasibility["collision"]["checked"] is False
    assert "no <collision> shapes" in plan_markdown(plan)


def test_effects_add_compliance_columns_and_balanced_backlash_directions(kr5, cands):
    plan = plan_poses(kr5, 25, candidates=cands, effects=["joint_compliance", "backlash"], refine_steps=5,
                      exchange_passes=1)
    names = list(plan.std_errors)
    assert any(n.startswith("joint_compliance.") for n in names)
    assert plan.direction_joints and plan.directions.shape == plan.q.shape
    for j in plan.direction_joints:
        d = plan.directions[:, kr5.joint_names.index(j)]
        assert 5 <= int((d > 0).sum()) <= 20  # both directions, neither rare
    header = plan.csv_text().splitlines()[0].split(",")
    assert header == kr5.joint_names + [f"dir.{j}" for j in plan.direction_joints]
    with pytest.raises(ValueError, match="temperature or time"):
        plan_poses(kr5, 10, candidates=cands, effects=["thermal_drift"])


def test_expected_standard_errors_match_a_calibration_on_the_plan(kr5, cands):
    plan = plan_poses(kr5, 30, candidates=cands, refine_steps=0, exchange_passes=1, noise=2e-5)
    data, _ = simulate(kr5, SimConfig(noise=2e-5, seed=5), q=plan.q)
    res = calibrate(kr5, data, method="lm", prior=None)  # the plain least-squares covariance the plan predicts
    common = [n for n in plan.std_errors if n in res.std_errors]
    assert len(common) >= 20
    ratio = torch.tensor([res.std_errors[n] / plan.std_errors[n] for n in common])
    # the calibration's σ comes from 90 - 25 residual degrees of freedom: within 30 % of the truth
    assert 0.7 < float(ratio.median()) < 1.3


def test_the_cli_writes_a_plan_and_refuses_bad_input(tmp_path, capsys):
    out = tmp_path / "poses.csv"
    base = ["plan", "--robot", KR5, "--marker", SMR, "--out", str(out)]
    assert cli(base + ["--candidates", "10", "--select", "20"]) == 2
    assert "--select 20 is more than --candidates 10" in capsys.readouterr().err
    assert cli(base + ["--candidates", "300", "--select", "5"]) == 2
    assert "select at least 9 poses" in capsys.readouterr().err
    assert not out.exists()
    with pytest.raises(SystemExit):
        cli(base + ["--reachable", "0,1,0,1"])
    assert "six numbers" in capsys.readouterr().err
    assert cli(base + ["--candidates", "300", "--select", "12", "--refine-steps", "3"]) == 0
    text = out.read_text()
    assert text.splitlines()[0] == "joint_a1,joint_a2,joint_a3,joint_a4,joint_a5,joint_a6" and len(text.splitlines()) == 13
    assert (tmp_path / "poses.plan.json").is_file() and (tmp_path / "poses.plan.md").is_file()
    assert cli(base + ["--candidates", "300", "--select", "12"]) == 2
    assert "does not overwrite" in capsys.readouterr().err and out.read_text() == text
