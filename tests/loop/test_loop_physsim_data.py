"""The loop on data nobody declared, made by :mod:`torchcal.sim.physsim`: a simulator with its own
URDF parser, kinematics and gravity, sharing no code with torchcal's effect classes. Each case is
a failure seen on held-back data (an undeclared heavy tool, one warm link, bending, a tilting
base, outliers, a humanoid upper body); the loop must name what the simulator put in and end at
the noise floor: the mean Euclidean norm of the simulated noise on the held-out rows.

Set-ups follow the issue: a 6R arm with link inertials (UR5e), 300 training and 150 held-out
poses, tracker noise 0.02 mm per axis, the instrument 3 m away at a random rotation, geometric
errors of 0.5 mm and 1 mrad on every joint origin.
"""
from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from torchcal import Robot, run_loop
from torchcal.report.loop import write_loop_report
from torchcal.kinematics.robots import urdf_path
from torchcal.sim.cases import CASES, TORSION, make_case
from torchcal.sim.drift_cases import DRIFT_CASES

# every test here runs whole loops (or reads a module cache of them): the full lane only
pytestmark = pytest.mark.slow

UR5E = urdf_path("ur5e").read_text()
N_TRAIN = CASES["payload_12kg"]["n_train"]
FLOOR_FACTOR = 1.15  # the bar: held-out mean within 1.15x the noise floor
# every case but the humanoid (its own test below) and the 7-joint twist-and-seats case, whose loop
# (an unknown 8 kg tool, bending at two seats) takes minutes: scripts/loop_effects.py measures it over
# seeds 1-6 with the others; issue 32's drifting parameters have their own tests (tests/sim)
UR5E_CASES = [n for n in CASES if n not in ("humanoid", "twist_seat_7dof") and n not in DRIFT_CASES]

_CACHE: dict = {}


def _data(case: str, seed: int = 0, outliers: float | None = None):
    key = (case, seed, outliers)
    if key not in _CACHE:
        _CACHE[key] = make_case(case, seed, outliers)
    return _CACHE[key]


def _run(case: str, seed: int = 0, outliers: float | None = None):
    key = ("run", case, seed, outliers)
    if key not in _CACHE:
        c = _data(case, seed, outliers)
        robot = Robot.from_urdf(c.urdf, markers=c.markers)  # the reflector: an unknown point
        res = run_loop(robot, c.train.to_measurements(), c.test.to_measurements(), log=None)
        _CACHE[key] = (res, c.floor_mm)
    return _CACHE[key]


def _final(res) -> float:
    return res.stages[-1]["test"]["mean_mm"]


@pytest.mark.parametrize("case", UR5E_CASES)
def test_the_loop_names_what_the_simulator_put_in_and_reaches_the_floor(case):
    res, floor = _run(case)
    names = [a["name"] for a in res.accepted]
    named = CASES[case]["named"]
    if not named:
        assert names == [], f"clean data: nothing should be accepted, got {names}"
    else:
        # the rounds take effects in the order of their gains: the named set is what must match
        assert names and names[0] in named, f"{case}: named {names}; candidates {res.candidates}"
        assert set(names) == set(named), f"{case}: something else accepted too: {names}"
    assert 0.025 < floor < 0.04  # σ·sqrt(8/π) for σ = 0.02 mm
    assert _final(res) <= FLOOR_FACTOR * floor, f"{case}: held-out {_final(res):.4f} mm vs floor {floor:.4f} mm"
    assert res.timings["total"] < 60


def _recovered(res, name: str) -> float:
    return dict(zip(res.params.names, res.params.values.tolist()))[name]


def test_the_payload_and_the_compliances_are_recovered():
    """Compliances and the tool's mass within 5 % where the data pin them down to better than a
    third of that, and within three of the loop's own standard errors everywhere (on an arm with
    light links, like this one, the mass splits from the compliances only to about 6 %)."""
    res, _ = _run("payload_12kg")
    acc = res.accepted[0]
    se = acc["standard_errors"]
    truth = {f"joint_compliance.{j}.twist": c for j, c in TORSION.items()}
    truth["joint_compliance.payload.m"] = 12.0
    for name, want in truth.items():
        got, s = _recovered(res, name), se[name]
        rel, rel_se = abs(got / want - 1), s / abs(want)
        assert rel_se < 0.1, f"{name}: standard error {100 * rel_se:.1f} %"
        assert rel <= max(0.05, 3 * rel_se), f"{name}: {got:.4g} vs {want:.4g} (standard error {100 * rel_se:.1f} %)"
        if rel_se < 0.05 / 3:
            assert rel <= 0.05
    # the sentence a person reads
    assert any("payload" in s and "kg" in s for s in acc["found"])
    assert any(s.startswith("elbow_joint twists about its axis") for s in acc["found"])


def test_a_payload_swapped_beside_a_knocked_tracker_is_found_at_its_own_row():
    """``swap_and_knock``: 6 kg from row 150 on and the tracker knocked at row 240, nothing logged
    (the case-by-case run above). The knock's step is the easier to see; the payload's change is found
    at its own row (a load tied to the knock's step would explain nothing of the swap), its mass within
    a quarter, and the knock's step, placed by the screening at row 240.5, is placed again at 239.5
    (:mod:`torchcal.pipelines.loop.breaks`)."""
    res, _ = _run("swap_and_knock")
    load = next(e for e in res.model().effects if e.name == "load_compliance")
    steps = {s: float(s.split("~step")[1]) for s in load.loads if "~step" in s}
    swap = [s for s, at in steps.items() if abs(at - 149.5) <= 1.0]
    assert swap, load.loads
    mass = float(load.theta[load.param_names.index(f"load_compliance.load~{swap[0]}.m")])
    assert abs(mass - 6.0) < 1.5, mass
    assert any(b["kept"] and b["to"] == "row~step239.5" for b in res.breaks_placed), res.breaks_placed
    frame = next(a for a in res.accepted if a.name == "parameter_drivers")
    assert frame.modes == ["base.frame~row~step239.5"]


def test_a_logged_load_is_recovered_with_the_compliances():
    """Four payloads swapped every 25 poses and logged in kg (``logged_loads``): the loop names joint
    compliance under the logged load, each twisting joint's compliance and the load's mass per logged
    kg within three of the loop's standard errors of the truth (1 kg per kg), the load's centre of mass
    within 30 mm of where it was put."""
    res, _ = _run("logged_loads")
    acc = res.accepted[0]
    assert acc["name"] == "load_compliance", [a["name"] for a in res.accepted]
    se = acc["standard_errors"]
    truth = {f"load_compliance.{j}.twist": c for j, c in TORSION.items()}
    truth["load_compliance.load~payload_kg.m"] = 1.0
    for name, want in truth.items():
        got = _recovered(res, name)
        assert abs(got - want) <= 3 * se[name], f"{name}: {got:.4g} vs {want:.4g} (standard error {se[name]:.2g})"
    m = _recovered(res, "load_compliance.load~payload_kg.m")
    com = [_recovered(res, f"load_compliance.load~payload_kg.m{a}") / m for a in "xyz"]
    assert np.allclose(com, (0.03, 0.0, 0.12), atol=0.03), com
    assert any("the load on flange grows by" in s and "per unit of payload_kg" in s for s in acc["found"])


def test_a_heavier_arm_pins_the_compliances_within_5_percent():
    """The same tool on an arm whose links weigh four times as much (an industrial arm's
    proportions): the link weights then set the scale of the compliances."""
    import re

    heavy = re.sub(r'<mass value="([0-9.eE+-]+)"', lambda m: f'<mass value="{4 * float(m.group(1))}"', UR5E)
    c = make_case("payload_12kg", urdf=heavy)
    res = run_loop(Robot.from_urdf(heavy, markers=c.markers), c.train.to_measurements(), c.test.to_measurements(),
                   log=None)
    assert [a["name"] for a in res.accepted] == ["joint_compliance"]
    se = res.accepted[0]["standard_errors"]
    for j, c in TORSION.items():
        name = f"joint_compliance.{j}.twist"
        got = _recovered(res, name)
        assert abs(got / c - 1) <= max(0.05, 3 * se[name] / c), f"{j}: {got:.4g} vs {c:.4g}"
    for j in ("shoulder_lift_joint", "elbow_joint"):  # the joints the arm's own weight loads most
        assert abs(_recovered(res, f"joint_compliance.{j}.twist") / TORSION[j] - 1) <= 0.05
    m = _recovered(res, "joint_compliance.payload.m")
    assert abs(m / 12 - 1) <= max(0.05, 3 * se["joint_compliance.payload.m"] / 12)


def test_one_warm_link_is_found_as_that_link():
    res, _ = _run("one_warm_link")
    acc = res.accepted[0]
    assert acc["modes"] == ["elbow_joint.growth"], acc["modes"]
    alpha = acc["params"]["thermal_drift.elbow_joint.growth"]
    assert abs(alpha / 2.3e-5 - 1) < max(0.05, 3 * acc["standard_errors"]["thermal_drift.elbow_joint.growth"] / 2.3e-5)
    assert "the link carrying elbow_joint" in acc["found"][0] and "µm/(m·K)" in acc["found"][0]


def test_bending_is_named_in_words():
    res, _ = _run("lateral")
    acc = res.accepted[0]
    bends = [m for m in acc["modes"] if ".bend" in m]
    assert {m.split(".")[0] for m in bends} == {"shoulder_lift_joint", "elbow_joint"}, acc["modes"]
    assert any(s.startswith("elbow_joint bends about its y axis") for s in acc["found"]), acc["found"]
    assert any(s.startswith("shoulder_lift_joint bends about its x axis") for s in acc["found"]), acc["found"]


def test_bending_before_the_joint_turns_is_found_as_seats():
    res, _ = _run("lateral_seat")
    modes = set(res.accepted[0]["modes"])
    assert "elbow_joint.seat_y" in modes, modes
    # a horizontal axis sees gravity's moment across it in one direction only, the horizontal one,
    # so a seat bending about it and a plane bend are the same statement there
    assert modes & {"shoulder_lift_joint.seat_x", "shoulder_lift_joint.bend"}, modes
    assert any(s.startswith("the seat of elbow_joint bends about its y axis") for s in res.accepted[0]["found"])


def test_a_tilting_base_is_found_through_the_family():
    res, _ = _run("tilting_base")
    acc = res.accepted[0]
    assert all(m.startswith("base.tilt") for m in acc["modes"] if "payload" not in m), acc["modes"]
    line = next(s for s in acc["found"] if s.startswith("the base tilts"))
    assert "per N·m of overturning moment" in line
    c = acc["params"]["elastic_deformation.base.tilt"]
    assert abs(c / 3e-6 - 1) < 0.05


def test_outliers_are_listed_not_deleted_and_barely_move_the_result(tmp_path):
    res, floor = _run("outliers")
    clean, _ = _run("outliers", outliers=0.0)
    truth = sorted(int(r) for r in _data("outliers").train.outlier_rows)
    assert len(truth) == round(0.05 * N_TRAIN)
    assert sorted({s["row"] for s in res.suspects}) == truth
    assert all(s["error_mm"] > 1.0 for s in res.suspects)
    assert res.n_train == N_TRAIN  # nothing dropped
    assert _final(res) <= 1.2 * _final(clean), f"{_final(res):.4f} vs {_final(clean):.4f} mm without outliers"
    assert [a["name"] for a in res.accepted][0] == "joint_compliance"
    write_loop_report(res, tmp_path)
    rep = json.loads((tmp_path / "report.json").read_text())
    assert sorted({s["row"] for s in rep["suspect_rows"]}) == truth
    assert "suspect observation" in (tmp_path / "report.md").read_text()


def test_a_time_covariate_from_another_day_is_flagged():
    """Thermal drift read from a time column: the held-out day's times lie outside the training
    range, so the candidate is flagged and the deployed model clamps the time."""
    c = _data("one_warm_link")
    train, test = c.train.to_measurements(), c.test.to_measurements()
    for d, t0 in ((train, 1.6e9), (test, 1.6e9 + 86400.0)):
        d.covariates["time"] = t0 + 10.0 * torch.arange(len(d), dtype=torch.float64)
        del d.covariates["temperature"]
    robot = Robot.from_urdf(UR5E, markers=["tool@flange"])
    res = run_loop(robot, train, test, candidates=["thermal_drift"], elm=False, log=None)
    flags = [f for f in res.flags if f["covariate"] == "time"]
    assert flags and flags[0]["fraction_outside"] == 1.0
    if res.effects:
        eff = res.effects[0]
        q = test.q[:3]
        far = {"time": torch.full((3,), 1.6e9 + 86400.0, dtype=torch.float64)}
        edge = {"time": torch.full((3,), float(train.covariates["time"].max()), dtype=torch.float64)}
        p = torch.zeros(3, 1, 3, dtype=torch.float64)
        assert torch.equal(eff.position_correction(p, q, far), eff.position_correction(p, q, edge))


def test_humanoid_upper_body_compliance_then_lateral_bending():
    """19 joints, three motion-capture markers, 500 poses, 0.3 mm noise: joint compliance is found
    first and the sideways bending of the torso after it, as in the published figures."""
    res, floor = _run("humanoid")
    names = [a["name"] for a in res.accepted]
    assert names[:2] == ["joint_compliance", "elastic_deformation"], names
    geo = next(s for s in res.stages if s["name"] == "geometric")["test"]["mean_mm"]
    after_jc = res.stages[2]["test"]["mean_mm"]
    assert geo > 2 * after_jc > 2 * _final(res) * 0.99
    assert _final(res) <= FLOOR_FACTOR * floor
    bend = [s for s in res.accepted[1]["found"] if "bends" in s or "tilts" in s]
    assert bend, res.accepted[1]["found"]
