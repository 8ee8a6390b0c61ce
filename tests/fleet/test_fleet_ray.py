"""The fleet on a local Ray cluster of 2 workers gives the in-process results (``pip install
torchcal[ray]``; skipped where ray is not installed)."""
from __future__ import annotations

import importlib.util

import pytest
import torch

from torchcal.pipelines.fleet.run import calibrate_fleet
from torchcal.kinematics.robots import shipped
from torchcal.sim.serial import SimConfig, simulate_fleet

pytestmark = pytest.mark.skipif(importlib.util.find_spec("ray") is None,
                                reason="ray is not installed (pip install torchcal[ray]); the Ray fleet is optional")


def test_ray_fleet_equals_in_process():
    from torchcal.pipelines.fleet.run import calibrate_fleet_ray

    robot = shipped("kuka_kr5_arc")
    train, test, _ = simulate_fleet(robot, 6, SimConfig(n=30, seed=11), spread=0.2, n_test=10,
                                    moved={2: {"joint_a3.offset": 2e-3}})
    names = [f"kr5_{i}" for i in range(6)]
    data, held = dict(zip(names, train)), dict(zip(names, test))
    local = calibrate_fleet(robot, data, test=held)
    remote = calibrate_fleet_ray(robot, data, test=held, address="local", workers=2, shards=2)
    assert remote.names == local.names
    assert torch.equal(remote.free, local.free)
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
