"""torchcal's threading (torchcal/threads.py): its entry points run small work on one torch thread
and give the caller's setting back; ``set_threads`` and ``TORCHCAL_THREADS`` change the rule."""
from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch

import torchcal
from torchcal import Corrector, Robot, calibrate, calibrate_fleet, plan_poses, run_loop
from torchcal.kinematics.robots import urdf_path
from torchcal.sim.serial import SimConfig, simulate
from torchcal.threads import SMALL_ROWS, set_threads, threads_by_size

REPO = Path(__file__).resolve().parents[2]


@pytest.fixture
def two_threads():
    """torch at 2 threads, the library's default rule; both as they were afterwards."""
    before, choice = torch.get_num_threads(), set_threads("auto")
    torch.set_num_threads(2)
    yield
    set_threads(choice)
    torch.set_num_threads(before)


@threads_by_size("data", "test")
def _threads_inside(data, test=None, fail: bool = False, inner=None):
    if fail:
        raise ValueError("refused")
    return torch.get_num_threads() if inner is None else inner()


def _rows(n: int) -> torch.Tensor:
    return torch.zeros(n, 3)  # n targets, or poses


def test_small_work_runs_on_one_thread_and_the_callers_setting_returns(two_threads):
    assert _threads_inside(_rows(100), test=_rows(50)) == 1
    assert torch.get_num_threads() == 2
    assert _threads_inside(_rows(SMALL_ROWS), test=_rows(1)) == 2  # large work: the caller's setting
    assert _threads_inside([_rows(SMALL_ROWS // 2)] * 3) == 2  # a fleet counts every robot's rows
    with pytest.raises(ValueError):
        _threads_inside(_rows(10), fail=True)
    assert torch.get_num_threads() == 2
    # the outermost entry point decides: small work inside large work keeps the caller's threads
    assert _threads_inside({"a": _rows(SMALL_ROWS), "b": _rows(5)}, inner=lambda: _threads_inside(_rows(1))) == 2
    assert _threads_inside(_rows(1), inner=lambda: _threads_inside(_rows(2 * SMALL_ROWS))) == 1


def test_set_threads_leaves_torch_alone_or_fixes_the_count(two_threads):
    assert set_threads("caller") == "auto" and torchcal.get_threads() == "caller"
    assert _threads_inside(_rows(10)) == 2
    set_threads(3)
    assert _threads_inside(_rows(3 * SMALL_ROWS)) == 3 and torch.get_num_threads() == 2
    with pytest.raises(ValueError, match="'auto'.*'caller'.*whole number"):
        set_threads(0)


@pytest.mark.slow
def test_the_environment_variable_sets_the_rule():
    def run(value: str):
        return subprocess.run([sys.executable, "-c", "import torchcal; print(torchcal.get_threads())"],
                              capture_output=True, text=True,
                              env={**os.environ, "PYTHONPATH": str(REPO), "TORCHCAL_THREADS": value})
    r = run("caller")
    assert r.returncode == 0 and r.stdout.strip() == "caller"
    # a bad value does not break the import (a notebook could not read the message); an entry point refuses it
    r = run("two")
    assert r.returncode == 0, r.stderr
    r = subprocess.run([sys.executable, "-c", "import torchcal\nfrom torchcal.kinematics.robots import shipped\n"
                        "try:\n    torchcal.calibrate(shipped('kuka_kr5_arc'), None)\nexcept ValueError as e:\n"
                        "    print(e)"], capture_output=True, text=True,
                       env={**os.environ, "PYTHONPATH": str(REPO), "TORCHCAL_THREADS": "0"})
    assert r.returncode == 0 and "TORCHCAL_THREADS='0'" in r.stdout and "unset it" in r.stdout, r.stdout + r.stderr


def test_the_entry_points_choose_their_threads(two_threads, monkeypatch):
    for fn in (calibrate, run_loop, calibrate_fleet, plan_poses, Corrector.correct):
        assert hasattr(fn, "__wrapped__"), fn
    robot = Robot.from_urdf(urdf_path("kuka_kr5_arc"), markers=["smr@flange=0,0,0"])
    data, _ = simulate(robot, SimConfig(n=30, seed=2))
    import torchcal.pipelines.calibrate as cal
    seen = []
    register = cal.register_base
    monkeypatch.setattr(cal, "register_base", lambda *a, **k: seen.append(torch.get_num_threads()) or register(*a, **k))
    calibrate(robot, data)
    assert seen == [1] and torch.get_num_threads() == 2
