"""Fleet calibration (:mod:`torchcal.pipelines.fleet.run`): the batched solve against per-robot ``calibrate``,
the batched building blocks against their single-robot versions, the outlier flag, the
hierarchical prior, joint compliance fleet-wide, validation and the ``torchcal fleet`` command.

Simulated robots (``torchcal.sim.serial``), seeded; the truth is used only to score.
"""
from __future__ import annotations

import json
import math
import re
import shlex
import statistics
import warnings
from pathlib import Path

import numpy as np
import pytest
import torch

from torchcal import Robot, calibrate
from torchcal.cli.app import main
from torchcal.pipelines.fleet.run import calibrate_fleet
from torchcal.pipelines.fleet.identify import decide, explain
from torchcal.problems.identifiability import analyse_jacobian
from torchcal.measure.io import save_measurements
from torchcal.optim import get_solver
from torchcal.optim.lm_batched import lm_batched
from torchcal.problems.calibration import CalibrationProblem
from torchcal.kinematics.robots import shipped, urdf_path
from torchcal.sim.serial import SimConfig, random_configs, simulate, simulate_fleet, simulated_robot
from conftest import rank_margin
from torchcal.kinematics.transforms import kabsch, so3_exp
from torchcal.report import report_json
from torchcal.report.fleet import fleet_markdown

MARKERS = ["smr@flange=0,0,0", "b@link6=0.06,0.02,0.03"]
REPO = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def kr5():
    return Robot.from_urdf(urdf_path("kuka_kr5_arc"), markers=MARKERS)


@pytest.fixture(scope="module")
def ragged(kr5):
    """Six robots with 20–45 rows; some rows miss one marker."""
    out = []
    for s, n in enumerate((30, 20, 45, 25, 33, 38)):
        d, _ = simulate(kr5, SimConfig(n=n, seed=40 + s))
        g = torch.Generator().manual_seed(s)
        hide = torch.rand(n, generator=g) < 0.15
        d.positions[hide, 1] = float("nan")
        out.append(d)
    return out


def test_paired_param_jacobian_equals_per_robot(kr5):
    g = torch.Generator().manual_seed(0)
    q = random_configs(kr5, 12, g).reshape(3, 4, kr5.dof)
    X = 1e-3 * torch.randn(3, kr5.n_params, generator=g, dtype=torch.float64)
    J = kr5.param_jacobian(q, X)
    assert J.shape == (3, 4, 2, 3, kr5.n_params)
    for r in range(3):
        assert torch.allclose(J[r], kr5.param_jacobian(q[r], X[r]), atol=1e-13, rtol=0)


def test_batched_kabsch_equals_single():
    g = torch.Generator().manual_seed(1)
    src = torch.randn(4, 10, 3, generator=g, dtype=torch.float64)
    R = so3_exp(torch.randn(4, 3, generator=g, dtype=torch.float64))
    dst = (R @ src.transpose(-1, -2)).transpose(-1, -2) + torch.randn(4, 1, 3, generator=g, dtype=torch.float64)
    w = torch.ones(4, 10, dtype=torch.float64)
    w[2, 7:] = 0  # a shorter problem, padded
    Rb, tb = kabsch(src, dst, weights=w)
    for b in range(4):
        n = int(w[b].sum())
        R1, t1 = kabsch(src[b, :n], dst[b, :n])
        assert torch.allclose(Rb[b], R1, atol=1e-12) and torch.allclose(tb[b], t1, atol=1e-12)


def _errors(robot, p, seed):
    t = p.clone()
    g = torch.Generator().manual_seed(seed)
    t.values = torch.where(p.free, 1e-3 * torch.randn(len(p), generator=g, dtype=torch.float64), t.values)
    return t


def test_lm_batched_replicates_single_lm(kr5):
    """Exact mode: each problem of the batch reaches the single solver's minimum. What is compared is
    what the user gets (the parameters, to a thousandth of their standard error, and the sum of
    squares at the end), not the count of steps: the batch computes its residuals and Jacobians
    with other shapes than the single solver, so near the stop both see a gradient at gtol to
    rounding, and one may try (and reject) a step that the other does not."""
    from torchcal.problems.uncertainty import standard_errors
    p = kr5.params().only("joint_a2.dx", "joint_a2.dz", "joint_a3.offset", "joint_a5.offset", "smr.dx", "smr.dz")
    data = [simulate(kr5, SimConfig(n=n, seed=70 + n, base_distance=0.0), true_params=_errors(kr5, p, n))[0]
            for n in (12, 20, 31)]  # robot-frame data: the base stays at 0
    probs = [CalibrationProblem(kr5, p, d) for d in data]
    singles = [get_solver("lm").minimize(pr) for pr in probs]
    m = max(pr.m for pr in probs)
    pad = lambda t, n: torch.cat([t, t.new_zeros(n - t.shape[0], *t.shape[1:])])  # noqa: E731
    res = lm_batched(lambda X, i: torch.stack([pad(probs[k].residuals(X[j:j + 1, p.free_index])[0], m)
                                               for j, k in enumerate(i.tolist())]),
                     lambda X, i: torch.stack([pad(probs[k].full_jacobian(X[j]), m)
                                               for j, k in enumerate(i.tolist())]),
                     p.values.expand(3, -1), p.free.expand(3, -1), p.lower, p.upper)
    for b, (pr, s) in enumerate(zip(probs, singles)):
        assert bool(res.converged[b]) and s.converged
        x = p.values.clone()
        x[p.free_index] = s.x
        se = standard_errors(pr.full_jacobian(x)[:, p.free_index], pr.residuals(s.x[None])[0])
        assert ((res.x[b, p.free_index] - s.x).abs() <= 1e-3 * se).all(), b
        # the start is the same point, so the first sum of squares is the same number up to rounding
        assert res.history[b][0] == pytest.approx(s.history[0], rel=1e-12)
        assert res.history[b][-1] == pytest.approx(s.history[-1], rel=1e-9)


def test_batched_identifiability_equals_analyse_jacobian(kr5):
    p = kr5.params().fix("smr.droll", "smr.dpitch", "smr.dyaw", "b.droll", "b.dpitch", "b.dyaw")
    names, units = p.free_names, [p.units[i] for i in p.free_index.tolist()]
    Js, reps = [], []
    for s, n in enumerate((30, 8, 5)):  # 8 and 5 poses: rank-deficient designs
        d, truth = simulate(kr5, SimConfig(n=n, seed=60 + s))
        J = CalibrationProblem(kr5, p, d).full_jacobian(truth.values)[:, p.free_index]
        Js.append(torch.cat([J, J.new_zeros(200 - J.shape[0], J.shape[1])]))  # padded rows, as a fleet pads
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # the rank of the short designs is ambiguous: that is the point
            reps.append(analyse_jacobian(J, names, units, markers=kr5.marker_names))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        dec = decide(torch.stack(Js), names, kr5.marker_names)
    why = explain(dec, names, units)
    for b, rep in enumerate(reps):
        assert [names[i] for i in torch.nonzero(dec.kept[b]).flatten().tolist()] == rep.identifiable
        assert sorted(why[b]) == sorted(rep.dropped)


def test_fleet_equals_per_robot_calibrate(kr5, ragged):
    fr = calibrate_fleet(kr5, ragged)
    for a, d in zip(fr.results, ragged):
        b = calibrate(kr5, d, method="lm", prior=None)
        assert a.params.free_names == b.params.free_names
        assert sorted(a.unidentifiable) == sorted(b.unidentifiable)
        for n in b.std_errors:
            # the same minimum: apart by a thousandth of a standard error at most
            assert abs(a.params[n] - b.params[n]) <= 1e-3 * b.std_errors[n], n
            assert a.std_errors[n] == pytest.approx(b.std_errors[n], rel=1e-4)
        for sa, sb in zip(a.stages, b.stages):
            assert sa["train"]["mean_mm"] == pytest.approx(sb["train"]["mean_mm"], rel=1e-6)
            assert sa["train"]["per_marker"].keys() == sb["train"]["per_marker"].keys()
        # what the error figures plot (error vectors, norms, distance from the base), per stage
        for name, e in b.errors.items():
            da, db = a.errors[name]["train_details"], e["train_details"]
            for k in ("e", "xyz", "dist"):
                assert torch.allclose(da[k], db[k], atol=1e-8, rtol=0), (name, k)


def test_fleet_exact_mode_follows_calibrate(kr5, ragged):
    """Without Jacobian reuse the batched LM reaches calibrate's minimum: the same parameters to a
    thousandth of a standard error and the same training error. Step counts are not compared: a
    round that starts at its minimum has a gradient cosine at gtol to rounding, and one solver may
    then try (and reject) one step that the other does not."""
    fr = calibrate_fleet(kr5, ragged[:3], options={"reuse": None})
    for a, d in zip(fr.results, ragged[:3]):
        b = calibrate(kr5, d, method="lm", prior=None)
        assert a.solver.converged and b.solver.converged
        assert a.params.free_names == b.params.free_names
        for n, se in b.std_errors.items():
            assert abs(a.params[n] - b.params[n]) <= 1e-3 * se, n
        assert a.stages[-1]["train"]["mean_mm"] == pytest.approx(b.stages[-1]["train"]["mean_mm"], rel=1e-6)


def test_moved_joint_offset_is_flagged():
    robot = shipped("kuka_kr5_arc")  # URDF, marker on the flange
    spread = 0.2e-3  # rad: per-robot deviation of every angle around the fleet mean
    cfg = SimConfig(n=30, seed=5)
    base, _, _ = simulate_fleet(robot, 16, cfg, spread=spread / cfg.angle_error)
    # The identified joint_a3.offset also carries what the unidentifiable angles about the same axis
    # project onto it: its siblings spread by about 0.4 mrad, not 0.2. A 4 mrad jump is ~9 of those.
    moved, _, _ = simulate_fleet(robot, 16, cfg, spread=spread / cfg.angle_error,
                                 moved={6: {"joint_a3.offset": 20 * spread}})
    clean = calibrate_fleet(robot, base)
    assert not clean.flags
    fr = calibrate_fleet(robot, moved)
    assert [(f["robot"], f["parameter"]) for f in fr.flags] == [("robot_006", "joint_a3.offset")]
    assert fr.flags[0]["z"] > fr.flags[0]["z_needed"] >= 5
    assert fr.spread["joint_a3.offset"]["outliers"] == ["robot_006"]
    assert "robot_006" in fleet_markdown(fr) and report_json(fr)["flags"][0]["robot"] == "robot_006"
    assert "the bound for 16 robots" in fleet_markdown(fr)  # a small fleet raises the bound above 5


def test_sibling_z_is_student_t_on_healthy_fleets():
    """On normally spread parameters, |z| follows Student's t with k - 1 degrees of freedom (its
    two-sided tail at 3 is checked against scipy), and a fleet flags with probability at most
    ``false_alarm``; one robot far from its siblings is found even when another one is too."""
    from scipy import stats
    from torchcal.pipelines.fleet.spread import sibling_z
    rng = np.random.default_rng(3)
    for n in (6, 10):
        z = np.concatenate([sibling_z(rng.standard_normal(n), np.zeros(n))[0] for _ in range(4000)])
        screened = 2 * stats.t.sf(3.0, n - 2)  # every sibling kept: t with n - 2 degrees of freedom
        assert abs(float(np.mean(np.abs(z) > 3.0)) - screened) < 0.5 * screened + 0.004
    x = rng.standard_normal(8)
    x[2] += 40.0
    x[5] += 40.0  # two damaged robots: the screen keeps each out of the other's yardstick
    z, k = sibling_z(x, np.zeros(8))
    assert abs(z[2]) > 20 and abs(z[5]) > 20 and (np.abs(np.delete(z, [2, 5])) < 6).all()


def test_small_clean_fleets_raise_few_flags():
    """Twelve healthy fleets of 6 and 10 robots: the spread of a handful of siblings is uncertain,
    and the Student-t bound keeps healthy robots unflagged (the median / 5-MAD rule it replaced
    flagged 22 here; identified parameters have heavier tails than normal, so one is allowed)."""
    robot = shipped("kuka_kr5_arc")
    flags = []
    for R in (6, 10):
        for seed in range(100, 106):
            train, _, _ = simulate_fleet(robot, R, SimConfig(n=30, seed=seed), spread=0.2)
            fr = calibrate_fleet(robot, train)
            flags += fr.flags
            assert all(e["z_needed"] is None or e["z_needed"] >= 5 for e in fr.spread.values())
    assert len(flags) <= 1


@pytest.mark.slow
def test_fleet_prior_helps_robots_with_few_poses():
    robot = shipped("kuka_kr5_arc")
    train, test, _ = simulate_fleet(robot, 12, SimConfig(n=10, seed=7), spread=0.2, n_test=40)
    alone = calibrate_fleet(robot, train, test=test)
    pooled = calibrate_fleet(robot, train, test=test, prior="fleet")
    held = lambda fr: statistics.mean(r.stages[-1]["test"]["mean_mm"] for r in fr.results)  # noqa: E731
    # alone drops what 10 poses pin down worse than a plausible error (0.080 mm here); the prior
    # keeps those parameters near the fleet's mean instead (0.073 mm)
    assert held(pooled) < 0.95 * held(alone)
    assert pooled.prior["sigma_m"] == pytest.approx(0.02e-3, rel=0.3)  # the simulated tracker noise
    assert len(pooled.prior["tau"]) == len(pooled.prior["parameters"]) > 0


def test_fleet_joint_compliance_shared_and_per_robot_payload():
    robot = Robot.from_urdf(urdf_path("ur5e"), markers=["smr@flange=0,0,0.08"])
    train, test, truth = [], [], []
    for r in range(4):
        sim = simulated_robot(robot, SimConfig(n=50, seed=300 + r), ["joint_compliance"])
        train.append(sim.measure(random_configs(robot, 50, sim.g)))
        test.append(sim.measure(random_configs(robot, 50, sim.g)))
        truth.append(sim.effects["joint_compliance"])
    geo = calibrate_fleet(robot, train, test=test)
    held = lambda fr: statistics.mean(r.stages[-1]["test"]["mean_mm"] for r in fr.results)  # noqa: E731
    shared = calibrate_fleet(robot, train, test=test, effects=["joint_compliance"])
    assert held(shared) < 0.15 * held(geo)
    assert shared.effects["shared"]["payload.m"] == pytest.approx(truth[0]["payload_kg"], rel=0.1)
    names = shared.effects["names"]
    for r in range(4):
        for j, n in enumerate(names):
            v = shared.effects["values"][r][j]
            if v is not None and n in ("shoulder_lift_joint.twist", "elbow_joint.twist"):
                true = truth[r]["compliance_rad_per_Nm"][robot.joint_names.index(n.split(".")[0])]
                assert v == pytest.approx(true, rel=0.1), (r, n)
    own = calibrate_fleet(robot, train, test=test, effects=["joint_compliance"], payload="per_robot")
    assert held(own) < 0.15 * held(geo)
    assert "payload.m" in own.effects["names"] and not own.effects["shared"]


def test_one_covariance_batched_equals_single():
    """The fleet's batched standard errors (each robot its own free columns and noise) are the single
    problem's; a prior's pseudo-inverse route (the loop's) equals the inverse where that is regular."""
    from torchcal.problems.uncertainty import standard_errors
    g = torch.Generator().manual_seed(3)
    J = torch.randn(3, 20, 5, generator=g, dtype=torch.float64)
    r = torch.randn(3, 20, generator=g, dtype=torch.float64)
    free = torch.tensor([[1, 1, 1, 1, 1], [1, 0, 1, 1, 0], [0, 1, 1, 1, 1]], dtype=torch.bool)
    se = standard_errors(J, r, free=free)
    for b in range(3):
        assert torch.allclose(se[b, free[b]], standard_errors(J[b][:, free[b]], r[b]), rtol=1e-12, atol=0)
    w = torch.rand(5, generator=g, dtype=torch.float64)
    assert torch.allclose(standard_errors(J[0], sigma=0.1, prior=w),
                          standard_errors(J[0], sigma=0.1, prior=w, singular="pinv"), rtol=1e-10, atol=0)
    tied = J[0].clone()
    tied[:, 1] = tied[:, 0]
    assert torch.isnan(standard_errors(tied, r[0])).all()


def test_fleet_settings_record_equals_keywords(kr5, ragged):
    from torchcal.pipelines.fleet.options import FleetOptions
    with pytest.raises(TypeError, match="did you mean 'prior'"):
        calibrate_fleet(kr5, ragged[:3], priors="fleet")
    a = calibrate_fleet(kr5, ragged[:3], plausible={"m": 1e-3, "rad": 1e-3})
    b = calibrate_fleet(kr5, ragged[:3], settings=FleetOptions(plausible={"m": 1e-3, "rad": 1e-3}))
    assert torch.equal(a.values, b.values) and torch.equal(a.free, b.free)


def test_fleet_validation(kr5, ragged):
    with pytest.raises(ValueError, match="no robots"):
        calibrate_fleet(kr5, [])
    with pytest.raises(TypeError, match="list of Measurements"):
        calibrate_fleet(kr5, ragged[0])
    with pytest.raises(TypeError, match="expected Measurements"):
        calibrate_fleet(kr5, [ragged[0], "robot.csv"])
    other = shipped("ur5e")
    d_other, _ = simulate(other, SimConfig(n=10, seed=1))
    with pytest.raises(ValueError, match="same model"):
        calibrate_fleet(kr5, [ragged[0], d_other])
    with pytest.raises(ValueError, match="share one marker set"):
        calibrate_fleet(kr5, [ragged[0], ragged[1].select_markers(["smr"])])
    with pytest.raises(ValueError, match="at least 10 rows"):
        calibrate_fleet(kr5, [ragged[0], ragged[1].subset(range(6))], min_rows=10)
    with pytest.raises(ValueError, match="too few rows"):
        calibrate_fleet(kr5, [ragged[0], ragged[1].subset(range(3))])
    with pytest.raises(ValueError, match="prior must be"):
        calibrate_fleet(kr5, ragged[:2], prior="global")
    with pytest.raises(ValueError, match="only 'joint_compliance'"):
        calibrate_fleet(kr5, ragged[:2], effects=["backlash"])
    with pytest.raises(ValueError, match="inertials"):
        calibrate_fleet(kr5, ragged[:2], effects=["joint_compliance"])
    with pytest.raises(ValueError, match="unique"):
        calibrate_fleet(kr5, ragged[:2], names=["a", "a"])


def _write_fleet(folder, robot, data):
    folder.mkdir(parents=True, exist_ok=True)
    for i, d in enumerate(data):
        save_measurements(folder / f"kr5_{i:02d}.csv", d)


def test_cli_fleet(tmp_path, capsys):
    robot = shipped("kuka_kr5_arc")
    train, test, _ = simulate_fleet(robot, 6, SimConfig(n=30, seed=9), spread=0.2, n_test=10)
    _write_fleet(tmp_path / "train", robot, train)
    _write_fleet(tmp_path / "test", robot, test)
    urdf = str(urdf_path("kuka_kr5_arc"))
    out = tmp_path / "out"
    rc = main(["fleet", "--robot", urdf, "--data", str(tmp_path / "train"), "--test", str(tmp_path / "test" / "*.csv"),
               "--out", str(out), "--no-figures", "--with-markers"])
    assert rc == 0
    rep = json.loads((out / "fleet.json").read_text())
    assert rep["n_robots"] == 6 and [r["robot"] for r in rep["robots"]] == [f"kr5_{i:02d}" for i in range(6)]
    assert "joint_a3.offset" in rep["spread"] and (out / "fleet.md").is_file()
    for i in range(6):
        d = out / f"kr5_{i:02d}"
        assert (d / "calibrated.urdf").is_file() and (d / "report.md").is_file()
        assert json.loads((d / "report.json").read_text())["n_test"] == 10
    # the exported URDF (rooted in the robot's own base frame) reproduces the calibrated kinematics
    res = calibrate_fleet(robot, train)
    cal = Robot.from_urdf(out / "kr5_00" / "calibrated.urdf", markers=["marker_flange"])
    q = random_configs(robot, 5, torch.Generator().manual_seed(0))
    # it holds the joints changed beyond their standard errors (robot.significant), the rest nominal
    held = robot.significant(res.values[0], res.results[0].std_errors)
    assert torch.allclose(cal.positions(q)[:, 0], robot.positions(q, held, base=False)[:, 0], atol=1e-9)


@pytest.mark.slow
def test_the_readme_fleet_command_writes_its_figures(tmp_path, monkeypatch, capsys):
    """The README's command as written: figures on (the default), held-out files."""
    line = re.search(r"^torchcal fleet .*$", (REPO / "README.md").read_text(), re.M).group(0)
    robot = Robot.from_urdf(urdf_path("kuka_kr5_arc"), markers=MARKERS[:1])
    train, test, _ = simulate_fleet(robot, 4, SimConfig(n=30, seed=9), spread=0.2, n_test=10)
    _write_fleet(tmp_path / "cell_data", robot, train)
    _write_fleet(tmp_path / "held_out", robot, test)
    (tmp_path / "urdf").symlink_to(REPO / "urdf")
    monkeypatch.chdir(tmp_path)
    rc = main(shlex.split(line)[1:])
    assert rc == 0, capsys.readouterr().err
    out = tmp_path / shlex.split(line)[shlex.split(line).index("--out") + 1]
    for i in range(4):
        d = out / f"kr5_{i:02d}"
        for png in ("errors.png", "errors_test.png"):
            assert (d / png).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n", d / png
        assert "(errors.png)" in (d / "report.md").read_text() and "(errors_test.png)" in (d / "report.md").read_text()


def test_cli_fleet_refuses_bad_input(tmp_path, capsys):
    robot = shipped("kuka_kr5_arc")
    urdf = str(urdf_path("kuka_kr5_arc"))
    rc = main(["fleet", "--robot", urdf, "--data", str(tmp_path / "nothing" / "*.csv"), "--out", str(tmp_path / "o")])
    assert rc == 2 and "no CSV files" in capsys.readouterr().err
    train, _, _ = simulate_fleet(robot, 3, SimConfig(n=20, seed=2))
    _write_fleet(tmp_path / "a", robot, train)
    text = (tmp_path / "a" / "kr5_01.csv").read_text().replace("joint_a2", "axis_2", 1)
    (tmp_path / "a" / "kr5_01.csv").write_text(text)
    rc = main(["fleet", "--robot", urdf, "--data", str(tmp_path / "a"), "--out", str(tmp_path / "o")])
    assert rc == 2 and "same joint columns" in capsys.readouterr().err
    _write_fleet(tmp_path / "b", robot, [train[0], train[1].subset(range(2))])
    rc = main(["fleet", "--robot", urdf, "--data", str(tmp_path / "b"), "--out", str(tmp_path / "o")])
    err = capsys.readouterr().err
    assert rc == 2 and "kr5_01" in err and "rows" in err


def test_ray_missing_says_how_to_install(monkeypatch):
    import sys

    from torchcal.pipelines.fleet.run import import_ray

    monkeypatch.setitem(sys.modules, "ray", None)  # as if it were not installed
    with pytest.raises(ImportError, match=r"pip install torchcal\[ray\]"):
        import_ray()


def test_bench_device_figures_run_on_cpu():
    """The GPU figures of scripts/bench_fleet.py, run on the CPU at a small size: the code path a
    lent GPU takes (population × poses kinematics, the fleet solve on the device)."""
    import importlib.util
    from pathlib import Path
    path = Path(__file__).resolve().parents[2] / "scripts" / "bench_fleet.py"
    spec = importlib.util.spec_from_file_location("bench_fleet", path)
    bench = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(bench)
    out = bench.device_figures("cpu", 12, 15, 0, populations=(20,))
    assert out["device"] == "cpu"
    assert out["fk_population_x_poses"]["20x1000"]["shape"] == [20, 1000, 1, 3]
    assert out["fleet_solve"]["robots"] == 12 and out["fleet_solve"]["converged"] == 12


def test_batched_error_stats_equal_per_robot():
    """errors_by_marker_batched gives, per data set, what errors_by_marker gives on its observations
    (ragged masks, a marker never seen, a set with one observation)."""
    from torchcal.measure.stats import errors_by_marker, errors_by_marker_batched
    g = torch.Generator().manual_seed(0)
    e = 1e-4 * torch.rand(5, 7, 2, generator=g, dtype=torch.float64)
    seen = torch.rand(5, 7, 2, generator=g) > 0.3
    seen[0, :, 1] = False
    seen[1] = False
    seen[1, 0, 0] = True
    got = errors_by_marker_batched(e, seen, ["a", "b"])
    for b in range(5):
        ref = errors_by_marker(e[b][seen[b]], torch.nonzero(seen[b])[:, 1], ["a", "b"])
        assert got[b].keys() == ref.keys() and got[b]["per_marker"].keys() == ref["per_marker"].keys()
        for mine, theirs in [(got[b], ref)] + [(got[b]["per_marker"][m], ref["per_marker"][m]) for m in ref["per_marker"]]:
            for k, v in theirs.items():
                if k != "per_marker":
                    assert mine[k] == pytest.approx(v, rel=1e-12, abs=1e-15), k


# ============================================================================ batched decisions
@pytest.fixture(scope="module")
def mixed():
    """A seeded fleet whose rounds grow, drop imprecise parameters and reset robots: short robots
    (12 poses), ragged ones, and two whose wrist barely moves (a rank near the tolerance)."""
    robot = shipped("kuka_kr5_arc")
    data, _, _ = simulate_fleet(robot, 5, SimConfig(n=12, seed=7), spread=0.2)
    data += [simulate(robot, SimConfig(n=n, seed=500 + n))[0] for n in (20, 31)]
    for i, s in enumerate((1e-7, 3e-9)):
        g = torch.Generator().manual_seed(900 + i)
        q = random_configs(robot, 30, g)
        q[:, 5] = 0.3 + s * torch.randn(30, generator=g, dtype=torch.float64)
        q[:, 3] = -0.2 + s * torch.randn(30, generator=g, dtype=torch.float64)
        data.append(simulate(robot, SimConfig(n=30, seed=900 + i, noise=0.0), q=q)[0])
    return robot, data


@pytest.mark.slow
def test_each_robot_of_a_fleet_gets_what_it_gets_alone(mixed):
    """The batched rounds (growing sets, imprecise parameters dropped, robots reset and refitted)
    give each robot what a fleet of that robot alone gives: the same free set and reasons (both are
    decisions, and every decision of these robots stands decades from its tolerance, so rounding
    cannot move it), the same values to a thousandth of a standard error, a converged solver. The
    two wrist robots, placed at the rank tolerance on purpose, share the batch but not the check:
    at the tolerance either answer is right (test_rank_check_needs_no_svd_where_the_factor_decides
    checks what they are told)."""
    from torchcal.problems.template import candidate_template
    robot, data = mixed
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the wrist robots' ambiguous rank: the other test's subject
        fr = calibrate_fleet(robot, data)
    assert any("plausibly" in w for r in fr.results for w in r.unidentifiable.values())  # imprecise drops judged
    template = candidate_template(robot, data[0].marker_names)
    for b in range(7):
        assert rank_margin(robot, template, data[b]) > 3, b  # the premise: far from the tolerance
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            one = calibrate_fleet(robot, [data[b]]).results[0]
        got = fr.results[b]
        assert got.params.free_names == one.params.free_names, b
        assert got.unidentifiable.keys() == one.unidentifiable.keys(), b
        assert got.solver.converged and one.solver.converged
        for n, se in one.std_errors.items():
            assert abs(got.params[n] - one.params[n]) <= 1e-3 * se, (b, n)


def test_reasons_are_worded_when_read(kr5, ragged):
    """The solve words no reason; reading one robot words that robot's, a pass over all words the
    rest at once, with the same sentences."""
    fr = calibrate_fleet(kr5, ragged)
    words = fr.results.reasons
    assert not words._words
    one = dict(fr.results[3].unidentifiable)
    assert set(words._words) == {3} and one
    alone = {b: dict(calibrate_fleet(kr5, ragged).results[b].unidentifiable) for b in (0, 5)}
    every = [r.unidentifiable for r in fr.results]
    assert set(words._words) == set(range(len(ragged)))
    assert every[3] == one and all(every[b] == alone[b] for b in alone)


def test_rank_check_needs_no_svd_where_the_factor_decides(mixed):
    """The Cholesky factor of the kept columns proves the rank of well-conditioned robots (no SVD);
    where it cannot, the SVD decides, so the warnings are the SVD's."""
    from torchcal.problems.template import candidate_template
    from torchcal.pipelines.fleet.identify import _rank_unsure, check_rank
    robot, data = mixed
    p = candidate_template(robot, data[0].marker_names)
    names = p.free_names
    Js = [CalibrationProblem(robot, p, d).full_jacobian(p.values)[:, p.free_index] for d in data]
    m = max(j.shape[0] for j in Js)
    J = torch.stack([torch.cat([j, j.new_zeros(m - j.shape[0], j.shape[1])]) for j in Js])
    dec = decide(J, names, robot.marker_names)
    s = torch.linalg.svdvals(dec.An)
    odd = (s > 1e-9 * s[:, :1]).sum(-1) != dec.kept.sum(-1)
    unsure = _rank_unsure(dec, torch.arange(len(data)), 1e-9)
    assert not (odd & ~unsure).any()  # never certain where the SVD disagrees
    assert not unsure[5:7].any()  # 20 and 31 ordinary poses: no SVD
    assert odd.any()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        check_rank(dec, labels=lambda b: f"r{b}")
    said = {f"r{b}" for b in range(len(data)) if any(repr(f"r{b}") in str(w.message) for w in caught)}
    assert said == {f"r{b}" for b in torch.nonzero(odd).flatten().tolist()}


def test_fleet_data_build_equals_robot_by_robot(kr5, ragged):
    """One copy per field for all robots: the padded batch a robot-by-robot fill gives (ragged rows,
    hidden markers, a robot listing its markers in another order)."""
    from torchcal.pipelines.fleet.data import FleetData
    sets = list(ragged[:3]) + [ragged[3].select_markers(["b", "smr"])]
    fd = FleetData.build(kr5, sets)
    for r, d in enumerate(sets):
        n = len(d)
        for j, mname in enumerate(d.marker_names):
            k = kr5.marker_names.index(mname)
            s = d.seen[:, j]
            assert torch.equal(fd.seen[r, :n, k], s) and not fd.seen[r, n:].any()
            assert torch.equal(fd.measured[r, :n, k][s], d.positions[:, j][s])
        assert torch.equal(fd.q[r, :n], d.q) and not fd.q[r, n:].any()
    assert fd.rows == [len(d) for d in sets]


@pytest.mark.gpu
def test_fleet_on_cuda_equals_cpu(ragged):
    """The fleet on a CUDA device: the CPU's decisions, values (within a thousandth of a standard
    error), reasons and flags."""
    if not torch.cuda.is_available():
        pytest.skip("no CUDA device: the GPU comparison runs on a machine with one (scripts/gpu_check.sh)")
    cpu = Robot.from_urdf(urdf_path("kuka_kr5_arc"), markers=MARKERS)
    gpu = Robot.from_urdf(urdf_path("kuka_kr5_arc"), markers=MARKERS, device="cuda")
    a = calibrate_fleet(cpu, ragged)
    b = calibrate_fleet(gpu, [d.to("cuda") for d in ragged])
    assert torch.equal(a.free, b.free.cpu())
    for ra, rb in zip(a.results, b.results):
        assert ra.params.free_names == rb.params.free_names
        assert sorted(ra.unidentifiable) == sorted(rb.unidentifiable)
        for n, se in ra.std_errors.items():
            assert abs(ra.params[n] - rb.params[n]) <= 1e-3 * se, n
    assert [(f["robot"], f["parameter"]) for f in a.flags] == [(f["robot"], f["parameter"]) for f in b.flags]


def test_fleet_waits_for_the_device_as_often_for_twice_the_robots(kr5, ragged):
    """No decision reads one robot at a time: calibrating every robot twice over (the same work per
    robot) takes as many host reads of device values (.tolist, .item, bool(), nonzero, boolean
    masks) as calibrating each once. On a GPU each read is a wait."""
    from torch.overrides import TorchFunctionMode

    class Reads(TorchFunctionMode):
        n = 0

        def __torch_function__(self, func, types, args=(), kwargs=None):
            name = getattr(func, "__name__", "")
            mask = name in ("__getitem__", "__setitem__") and any(
                isinstance(a, torch.Tensor) and a.dtype == torch.bool and a.ndim
                for a in (args[1] if isinstance(args[1], tuple) else (args[1],)))
            if mask or name in ("tolist", "item", "__bool__", "__int__", "__float__", "nonzero", "unique"):
                Reads.n += 1
            return func(*args, **(kwargs or {}))

    counts = []
    for data in (ragged[:3], [d for d in ragged[:3] for _ in range(2)]):
        Reads.n = 0
        with Reads():
            calibrate_fleet(kr5, data)
        counts.append(Reads.n)
    assert counts[0] == counts[1] > 0


def test_a_robot_with_nothing_precise_keeps_its_start_and_says_why():
    """Plausible sizes far below what 30 poses can pin down (0.01 mm, 0.01 mrad): every robot's
    parameters are fixed for imprecision, and the batched LM meets a round with no column to fit.
    Each robot ends with nothing fitted, one reason per candidate parameter, and a model no worse
    than its registered start, instead of a crash."""
    robot = shipped("kuka_kr5_arc")
    train, _, _ = simulate_fleet(robot, 4, SimConfig(n=30, seed=0), spread=0.2)
    fr = calibrate_fleet(robot, train, plausible={"m": 1e-5, "rad": 1e-5})
    for r in fr.results:
        assert r.params.free_names == [] and r.solver.converged
        reasons = list(r.unidentifiable.values())
        assert len(reasons) == len(robot.params().free_names) and all(reasons)  # one per candidate
        assert sum("more than such an error can plausibly be" in why for why in reasons) > len(reasons) / 2
        assert not r.problems() and r.stages[-1].train.mean <= r.stages[0].train.mean * (1 + 1e-9)
