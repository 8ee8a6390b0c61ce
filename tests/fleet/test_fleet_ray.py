"""The fleet on a local Ray cluster of 2 workers gives the in-process results (``pip install
torchcal[ray]``; skipped where ray is not installed)."""
from __future__ import annotations

import importlib.util

import pytest

from conftest import rank_margin
from torchcal.pipelines.fleet.run import calibrate_fleet
from torchcal.kinematics.robots import shipped
from torchcal.sim.serial import SimConfig, simulate_fleet

pytestmark = pytest.mark.skipif(importlib.util.find_spec("ray") is None,
                                reason="ray is not installed (pip install torchcal[ray]); the Ray fleet is optional")


@pytest.mark.slow
def test_ray_fleet_equals_in_process():
    """Two shards on Ray give each robot what one in-process batch gives: the same free set (a rank
    decision, compared exactly because every robot's singular values stand decades from the rank
    tolerance, which the test checks first), the same values to a thousandth of a standard error,
    the same held-out error and the same flags."""
    from torchcal.pipelines.fleet.run import calibrate_fleet_ray
    from torchcal.problems.template import candidate_template

    robot = shipped("kuka_kr5_arc")
    train, test, _ = simulate_fleet(robot, 6, SimConfig(n=30, seed=11), spread=0.2, n_test=10,
                                    moved={2: {"joint_a3.offset": 2e-3}})
    template = candidate_template(robot, train[0].marker_names)
    assert min(rank_margin(robot, template, d) for d in train) > 3  # decisions rounding cannot flip
    names = [f"kr5_{i}" for i in range(6)]
    data, held = dict(zip(names, train)), dict(zip(names, test))
    local = calibrate_fleet(robot, data, test=held)
    remote = calibrate_fleet_ray(robot, data, test=held, address="local", workers=2, shards=2)
    assert remote.names == local.names
    for a, b in zip(remote.results, local.results):
        assert a.params.free_names == b.params.free_names
        for n, se in b.std_errors.items():
            assert abs(a.params[n] - b.params[n]) <= 1e-3 * se, n
        assert a.stages[-1]["test"]["mean_mm"] == pytest.approx(b.stages[-1]["test"]["mean_mm"], rel=1e-6)
    assert [f["robot"] for f in remote.flags] == [f["robot"] for f in local.flags]


def test_ray_refuses_coupled_fleets():
    robot = shipped("kuka_kr5_arc")
    train, _, _ = simulate_fleet(robot, 3, SimConfig(n=20, seed=1))
    with pytest.raises(ValueError, match="in-process"):
        calibrate_fleet(robot, train, prior="fleet", ray="local")
