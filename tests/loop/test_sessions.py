"""Held-out rows from another session (:mod:`torchcal.pipelines.loop.sessions`): time terms held at
a stated value, a moved instrument told from an effect that extrapolates outside its fitted range,
both simulated with the simulator's own tools (the robot's truth stays with the simulator)."""
from __future__ import annotations

from pathlib import Path

import pytest
import torch

from torchcal import Robot, run_loop
from torchcal.measure.trust import FOREIGN
from torchcal.pipelines.loop.sessions import hold_session_terms, other_session
from torchcal.sim.serial import SimConfig, simulate, simulate_with_effects

UR5E = Path(__file__).resolve().parents[2] / "urdf" / "ur5e.urdf"


@pytest.fixture(scope="module")
def robot():
    return Robot.from_urdf(UR5E, markers=["flange"])


def _with(data, source=None, **cov):
    out = data._with(data.q, data.positions, list(data.marker_names), data.quaternions,
                     {**data.covariates, **{k: torch.as_tensor(v, dtype=data.q.dtype) for k, v in cov.items()}},
                     data.planes, dict(data.distances))
    out.source = source
    return out


def test_rows_of_one_file_are_one_session_and_time_is_held_at_the_training_median(robot):
    d, _ = simulate(robot, SimConfig(n=20, seed=0))
    a, b = _with(d, "s.csv", time=torch.arange(20.0)).split(0.3, seed=0)
    assert other_session(a, b) is None
    assert other_session(a, _with(b, "s2.csv")) is None  # interleaved times: one session in two files
    later = _with(b, "s2.csv", time=b.covariates["time"] + 1e4)
    assert "does not overlap" in other_session(a, later)
    untimed = {k: v for k, v in a.covariates.items() if k != "time"}
    a2 = a._with(a.q, a.positions, list(a.marker_names), None, untimed, None, {})
    b2 = b._with(b.q, b.positions, list(b.marker_names), None, {}, None, {})
    a2.source, b2.source = "s.csv", "s2.csv"
    assert "another file" in other_session(a2, b2)
    held, at = hold_session_terms(a, later)
    med = float(a.covariates["time"].median())
    assert at == {"time": pytest.approx(med)} and torch.allclose(held.covariates["time"], torch.full((len(b),), med,
                                                                                                   dtype=d.q.dtype))


@pytest.mark.slow
def test_an_effect_extrapolating_outside_its_range_is_named_not_the_instrument(robot):
    """Session 1 grows with its temperature (20-50 °C); session 2, at 80-90 °C, does not grow (the
    growth saturated): the thermal model extrapolates. The loop must say so, and not blame the
    instrument, which stayed where it was."""
    d1, truth, _ = simulate_with_effects(robot, SimConfig(n=80, seed=1), ["thermal_drift"])
    d2, _ = simulate(robot, SimConfig(n=30, seed=2), true_params=truth)
    d1 = _with(d1, "session1.csv")
    d2 = _with(d2, "session2.csv", temperature=torch.linspace(80.0, 90.0, len(d2)))
    res = run_loop(robot, d1, d2, candidates=["thermal_drift"], elm=False, log=None, reregister=True)
    assert [e.name for e in res.effects] == ["thermal_drift"]
    h = res.heldout
    assert h.session and not h.instrument_moved
    assert h.extrapolating() == ["thermal_drift"]
    cause = " ".join(h.causes())
    assert "thermal_drift does not carry over" in cause and "temperature spans 80–90" in cause
    # the geometry alone carries over to within a few noise levels (0.02 mm per axis)
    assert h.without["thermal_drift"] < 0.1 < h.final_mm


@pytest.mark.slow
def test_a_moved_instrument_is_registered_anew_and_rows_nothing_explains_stay_refused(robot):
    d1, truth = simulate(robot, SimConfig(n=60, seed=3))
    moved = truth.clone()
    moved.values[moved.names.index("base.z")] += 0.02
    moved.values[moved.names.index("base.ry")] -= 0.01
    d2, _ = simulate(robot, SimConfig(n=30, seed=4), true_params=moved)
    d1, d2 = _with(d1, "a.csv"), _with(d2, "b.csv")
    res = run_loop(robot, d1, d2, candidates=[], elm=False, log=None, reregister=True)
    h = res.heldout
    assert h.instrument_moved and not res.problems()
    assert h.reregistered_mm < 0.1 < 10 < h.final_mm
    # within 2 % of the frame change simulated (20 mm, 10 mrad); its noise: 0.02 mm on 30 rows
    assert h.frame_turn_mrad == pytest.approx(10.0, rel=0.02)
    # another robot altogether: a link 30 mm longer, which no frame explains
    other = truth.clone()
    other.values[other.names.index("elbow_joint.dx")] += 0.03
    d3, _ = simulate(robot, SimConfig(n=30, seed=5), true_params=other)
    res = run_loop(robot, d1, _with(d3, "c.csv"), candidates=[], elm=False, log=None, reregister=True)
    assert any(p.startswith(FOREIGN) for p in res.problems()), res.problems()
    assert not res.heldout.explained_by_reregistration
