"""Bad input to the newer features, ``torchcal plan`` / :func:`torchcal.plan_poses`, ``torchcal
fleet`` / :func:`torchcal.pipelines.fleet.run.calibrate_fleet`, and partial measurements (plane contacts,
distances) in CSV files: every case stops with an error that names what is wrong and how to fix
it, and a refusing command writes nothing. Small simulated data, seeded."""
from __future__ import annotations

import math
import warnings
from pathlib import Path

import pytest
import torch

from torchcal import Robot
from torchcal.cli.app import main
from torchcal.kinematics.robots import shipped, urdf_path
from torchcal.measure.data import Measurements
from torchcal.measure.io import load_measurements, save_measurements
from torchcal.measure.setup import Setup
from torchcal.pipelines.fleet.run import calibrate_fleet
from torchcal.pipelines.plan.run import plan_poses
from torchcal.sim.serial import SimConfig, random_configs, simulate_fleet, simulated_robot

KR5 = str(urdf_path("kuka_kr5_arc"))
SMR = "smr@flange=0,0,0.05"


def _cli(args: list[str], capsys) -> tuple[int, str]:
    """Exit status and stderr of ``torchcal ARGS``, whether refused when parsed or when run."""
    try:
        rc = main(args)
    except SystemExit as e:
        rc = e.code
    return rc, capsys.readouterr().err


def _files(folder: Path) -> list[str]:
    return sorted(p.relative_to(folder).as_posix() for p in folder.rglob("*")) if folder.exists() else []


# ============================================================================ plan
@pytest.fixture(scope="module")
def kr5():
    return Robot.from_urdf(KR5, markers=[SMR])


@pytest.fixture(scope="module")
def cands(kr5):
    return random_configs(kr5, 200, torch.Generator().manual_seed(0))


def _nan_at(q: torch.Tensor) -> torch.Tensor:
    q = q.clone()
    q[3, 1] = math.nan
    return q


@pytest.mark.parametrize("make, kw, exc, what", [
    (lambda c: c[:, :4], {}, ValueError, r"candidates must have shape \(N, 6\).*got \(200, 4\)"),
    (_nan_at, {}, ValueError, r"NaN or inf in joint\(s\) \['joint_a2'\]"),
    (lambda c: c + torch.tensor([0, 0, 0, 0, 0, 1.0]) * 9.0, {}, ValueError,
     r"outside the joint limits.*'joint_a6'.*leave out candidates"),
    (lambda c: c[:10], {"n_select": 20}, ValueError, "cannot select 20 poses from 10 candidates: draw more"),
    (lambda c: c, {"criterion": "A"}, ValueError, r"criterion must be one of \('D', 'O1', 'O4'\)"),
    (lambda c: c, {"noise": math.nan}, ValueError, "noise must be a positive, finite number"),
    (lambda c: c, {"noise": -2e-5}, ValueError, "noise must be a positive, finite number"),
    (lambda c: c, {"noise": math.inf}, ValueError, "noise must be a positive, finite number"),
    (lambda c: c, {"margin": 0.5}, ValueError, "give 0 ≤ margin < 0.5"),
    (lambda c: c, {"n_select": 12.5}, ValueError, r"n_select \(poses to select\) must be a whole number ≥ 1"),
    (lambda c: c, {"n_select": 0}, ValueError, "must be a whole number ≥ 1, got 0"),
    (lambda c: c, {"refine_steps": -3}, ValueError, "refine_steps must be a whole number ≥ 0"),
    (lambda c: c, {"effects": ["foo"]}, ValueError, r"cannot plan for effect\(s\) \['foo'\]; plannable"),
    # one name given as a string is one effect, not its letters
    (lambda c: c, {"effects": "thermal_drift"}, ValueError, r"\['thermal_drift'\] \(it reads a temperature"),
    (lambda c: c, {"reachable": (0, 1, "a", 1, 0, 1)}, ValueError, "give six numbers xmin,xmax"),
    (lambda c: c, {"reachable": (0, 1, 0, 1, 0, math.nan)}, ValueError, "every bound must be a finite number"),
], ids=["shape", "nan", "limits", "select>candidates", "criterion", "noise-nan", "noise-neg", "noise-inf",
        "margin", "select-fraction", "select-0", "refine-neg", "effect", "effect-str", "box-text", "box-nan"])
def test_plan_poses_refuses_bad_arguments(kr5, cands, make, kw, exc, what):
    args = {"n_select": 12, "refine_steps": 0, **kw}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the out-of-limits candidates also look like degrees
        with pytest.raises(exc, match=what):
            plan_poses(kr5, args.pop("n_select"), candidates=make(cands), **args)


def test_plan_poses_refuses_a_path_for_the_robot(cands):
    with pytest.raises(TypeError, match=r"must be a torchcal.Robot.*Robot.from_urdf\(path, markers="):
        plan_poses(KR5, 12, candidates=cands)
    with pytest.raises(ValueError, match="n_candidates must be a whole number ≥ 1, got -5"):
        plan_poses(shipped("kuka_kr5_arc"), 12, n_candidates=-5)


PLAN_BAD = [
    (["--reachable", "0,1,1,0,0,1"], "minimum must be below the maximum along y"),
    (["--reachable", "0,1,0,1,0,nan"], "every bound must be a finite number"),
    (["--reachable=-800,800,-800,800,0,1200"], "look like millimetres; give metres"),
    (["--reachable", "5,6,5,6,5,6"], "no candidate pose keeps every marker inside the box"),
    (["--effect", "thermal_drift"], "temperature or time, which a plan cannot choose"),
    (["--effect", "foo"], r"cannot plan for effect\(s\) \['foo'\]; plannable: \['joint_compliance'"),
    (["--noise-mm", "-1"], "argument --noise-mm: must be positive"),
    (["--noise-mm", "nan"], "argument --noise-mm: must be a finite number"),
    (["--noise-mm", "inf"], "argument --noise-mm: must be a finite number"),
    (["--margin", "0.5"], "argument --margin: must be below 0.5"),
    (["--collision-margin-mm", "inf"], "argument --collision-margin-mm: must be a finite number"),
    (["--criterion", "A"], r"invalid choice: 'A' \(choose from 'D', 'O1', 'O4'\)"),
    (["--select", "300"], "--select 300 is more than --candidates 200"),
    (["--marker", "smr@flange_link=0,0,0.05"], r"not in the URDF; did you mean flange\?"),
]


@pytest.mark.parametrize("extra, what", PLAN_BAD, ids=[" ".join(e) for e, _ in PLAN_BAD])
def test_plan_cli_refuses_bad_input_and_writes_nothing(tmp_path, capsys, extra, what):
    import re

    markers = [] if any(e.startswith("--marker") for e in extra) else ["--marker", SMR]
    select = [] if "--select" in extra else ["--select", "12"]  # an option given twice is refused as such
    rc, err = _cli(["plan", "--robot", KR5, *markers, "--candidates", "200", *select, "--refine-steps", "0",
                    "--out", str(tmp_path / "poses.csv"), *extra], capsys)
    assert rc == 2 and re.search(what, err), err
    assert "torchcal plan: error:" in err and _files(tmp_path) == []


def test_plan_cli_missing_urdf_and_marker_guess_in_millimetres(tmp_path, capsys):
    out = str(tmp_path / "poses.csv")
    rc, err = _cli(["plan", "--robot", str(tmp_path / "no.urdf"), "--out", out], capsys)
    assert rc == 2 and "URDF file not found" in err and "no.urdf" in err
    rc, err = _cli(["plan", "--robot", KR5, "--marker", "smr@flange=0,0,50", "--out", out], capsys)
    assert rc == 2 and "looks like millimetres; give metres (e.g. smr@flange=0,0,0.05)" in err
    assert "--units" not in err  # plan has no --units option: the advice must not name one
    assert _files(tmp_path) == []


# ============================================================================ fleet
@pytest.fixture(scope="module")
def fleet():
    robot = shipped("kuka_kr5_arc")
    train, test, _ = simulate_fleet(robot, 3, SimConfig(n=15, seed=3), spread=0.2, n_test=4)
    return robot, train, test


def _write(folder: Path, data: list[Measurements], names: list[str]) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    for n, d in zip(names, data):
        save_measurements(folder / f"{n}.csv", d)
    return folder


def _fleet(args: list[str], out: Path, capsys) -> tuple[int, str]:
    return _cli(["fleet", "--robot", KR5, "--no-figures", "--out", str(out), *args], capsys)


def test_fleet_cli_empty_directory_and_ids_repeated_across_folders(fleet, tmp_path, capsys):
    robot, train, _ = fleet
    (tmp_path / "empty").mkdir()
    rc, err = _fleet(["--data", str(tmp_path / "empty")], tmp_path / "o", capsys)
    assert rc == 2 and "no CSV files in the directory" in err and "<robot>.csv" in err
    _write(tmp_path / "d1", train[:2], ["a", "b"])
    _write(tmp_path / "d2", train[2:], ["a"])
    rc, err = _fleet(["--data", str(tmp_path / "d*" / "*.csv")], tmp_path / "o", capsys)
    assert rc == 2 and "robot ids must be unique" in err and "['a']" in err and "rename" in err
    assert not (tmp_path / "o").exists()


def test_fleet_cli_held_out_files_of_unknown_robots_are_refused_by_name(fleet, tmp_path, capsys):
    robot, train, test = fleet
    data = _write(tmp_path / "train", train, ["r0", "r1", "r2"])
    held = _write(tmp_path / "test", test, ["x0", "r1", "r2"])
    rc, err = _fleet(["--data", str(data), "--test", str(held)], tmp_path / "o", capsys)
    assert rc == 2 and "held-out data for robots ['x0']" in err and "'r0'" in err
    assert "same file name <robot>.csv" in err and not (tmp_path / "o").exists()


def test_fleet_cli_one_file_in_millimetres_is_named(fleet, tmp_path, capsys):
    robot, train, _ = fleet
    mm = [Measurements(d.q, d.positions * (1000.0 if i == 1 else 1.0), d.marker_names, d.joint_names)
          for i, d in enumerate(train)]
    data = _write(tmp_path / "mixed", mm, ["r0", "r1", "r2"])
    rc, err = _fleet(["--data", str(data)], tmp_path / "o", capsys)
    assert rc == 2 and "r1.csv: marker coordinates have median" in err and "looks like millimetres" in err
    assert "r0.csv" not in err and "--units applies to every file of the fleet" in err
    assert not (tmp_path / "o").exists()


def test_fleet_cli_refuses_a_filled_output_a_wrong_effect_and_a_prior_on_two_robots(fleet, tmp_path, capsys):
    robot, train, _ = fleet
    data = _write(tmp_path / "train", train, ["r0", "r1", "r2"])
    out = tmp_path / "o"
    out.mkdir()
    (out / "keep.txt").write_text("mine")
    rc, err = _fleet(["--data", str(data)], out, capsys)
    assert rc == 2 and "exists and is not empty" in err and "--force" in err
    assert _files(out) == ["keep.txt"] and (out / "keep.txt").read_text() == "mine"
    rc, err = _fleet(["--data", str(data), "--effect", "backlash"], tmp_path / "o2", capsys)
    assert rc == 2 and "invalid choice: 'backlash' (choose from 'joint_compliance')" in err
    rc, err = _fleet(["--data", str(data), "--z", "inf"], tmp_path / "o2", capsys)
    assert rc == 2 and "argument --z: must be a finite number" in err
    rc, err = _fleet(["--data", str(data), "--false-alarm", "5"], tmp_path / "o2", capsys)
    assert rc == 2 and "argument --false-alarm: must be a probability in (0, 1)" in err
    two = _write(tmp_path / "two", train[:2], ["r0", "r1"])
    rc, err = _fleet(["--data", str(two), "--prior", "fleet"], tmp_path / "o2", capsys)
    assert rc == 2 and "2 robot(s) are too few" in err and "at least 3 robots" in err
    assert not (tmp_path / "o2").exists()


@pytest.mark.parametrize("kw, exc, what", [
    ({"n": 1, "prior": "fleet"}, ValueError, r"1 robot\(s\) are too few.*at least 3 robots.*prior_scale"),
    ({"n": 2, "prior": "fleet"}, ValueError, r"2 robot\(s\) are too few.*at least 3 robots"),
    ({"n": 1, "prior": "fleet", "prior_scale": {"m": 1e-3, "rad": 1e-3}}, ValueError, "at least 2 robots"),
    ({"test": "short"}, ValueError, r"test: 2 data sets for 3 robot ids; give one per robot"),
    ({"test": {"x": 0}}, ValueError, r"held-out data for robots \['x'\], which are not in the fleet"),
    ({"payload": "everyone"}, ValueError, "payload must be 'shared' or 'per_robot'"),
    ({"z_threshold": -1.0}, ValueError, "z_threshold is a robust z-score.*give a positive number"),
    ({"false_alarm": 1.5}, ValueError, "false_alarm is the chance.*between 0 and 1"),
    ({"false_alarm": 0}, ValueError, "false_alarm is the chance.*between 0 and 1"),
    ({"plausible": {"mm": 10}}, ValueError, r"plausible: unknown unit\(s\) \['mm'\].*metres and radians"),
    # one effect named by a string is that effect (here refused for the model's missing inertials)
    ({"effects": "joint_compliance"}, ValueError, "needs link inertials in the URDF"),
])
def test_calibrate_fleet_refuses_bad_arguments(fleet, kw, exc, what):
    robot, train, test = fleet
    kw = dict(kw)
    data = train[: kw.pop("n", 3)]
    if kw.get("test") == "short":
        kw["test"] = test[:2]
    elif isinstance(kw.get("test"), dict):
        kw["test"] = {"x": test[0]}
    with pytest.raises(exc, match=what):
        calibrate_fleet(robot, data, **kw)


# ============================================================================ partial measurements
@pytest.fixture(scope="module")
def partial(tmp_path_factory):
    """KR 5 arc (marker: the flange): contacts with plane A, ball-bar distances to a pivot, and
    full positions, written as CSV files."""
    d = tmp_path_factory.mktemp("partial")
    robot = shipped("kuka_kr5_arc")
    sim = simulated_robot(robot, SimConfig(n=0, seed=4, base_distance=2.0))
    g = torch.Generator().manual_seed(5)
    n = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)
    z = float((sim.reach(random_configs(robot, 300, g))[:, 0] @ n).median())
    save_measurements(d / "contacts.csv", sim.touch({"A": (n, z)}, 8))
    bar = sim.measure_distances(torch.tensor([0.6, 0.2, 0.3], dtype=torch.float64), "pivot", random_configs(robot, 10, g))
    save_measurements(d / "bar.csv", bar)
    save_measurements(d / "positions.csv", sim.measure(random_configs(robot, 12, g)))
    return robot, d


def _edit(src: Path, dst: Path, fn) -> Path:
    """Copy a CSV through ``fn(header, rows)`` (cells as text)."""
    lines = src.read_text().splitlines()
    header, rows = lines[0].split(","), [ln.split(",") for ln in lines[1:]]
    header, rows = fn(header, rows)
    dst.write_text("\n".join([",".join(header)] + [",".join(r) for r in rows]) + "\n")
    return dst


def _cell(col: str, row: int, value: str):
    def fn(h, rows):
        rows[row][h.index(col)] = value
        return h, rows
    return fn


def _rename(old: str, new: str):
    def fn(h, rows):
        h[h.index(old)] = new
        return h, rows
    return fn


@pytest.mark.parametrize("fn, what", [
    (_cell("flange.dist.pivot", 2, "-0.5"), r"line 4: distance flange.dist.pivot = -0.5 is not a length.*leave it empty"),
    (_cell("flange.dist.pivot", 2, "inf"), r"line 4: distance flange.dist.pivot = inf is not a length"),
    (_cell("flange.dist.pivot", 2, "abc"), r"line 4, column 'flange.dist.pivot': 'abc' is not a number"),
    (_rename("flange.dist.pivot", "flange.dist.flange"), r"'flange.dist.flange' must be named '<marker>.dist.<other"),
], ids=["negative", "inf", "text", "to-itself"])
def test_bad_distance_cells_and_columns(partial, tmp_path, fn, what):
    robot, d = partial
    with pytest.raises(ValueError, match=what):
        load_measurements(_edit(d / "bar.csv", tmp_path / "bad.csv", fn), robot)


def test_a_nan_distance_cell_is_not_measured(partial, tmp_path):
    robot, d = partial
    data = load_measurements(_edit(d / "bar.csv", tmp_path / "nan.csv", _cell("flange.dist.pivot", 2, "NaN")), robot)
    v = data.distances[("flange", "pivot")]
    assert bool(torch.isnan(v[2])) and int(torch.isfinite(v).sum()) == len(data) - 1


def test_measurements_refuse_negative_distances_and_a_contact_with_a_position():
    q = torch.zeros(3, 6, dtype=torch.float64)
    nan = torch.full((3, 1, 3), math.nan, dtype=torch.float64)
    with pytest.raises(ValueError, match=r"distance flange.dist.pivot has negative or infinite values.*metres"):
        Measurements(q, nan, ["flange"], [f"joint_a{i}" for i in range(1, 7)],
                     distances={("flange", "pivot"): torch.tensor([0.5, -0.1, math.nan], dtype=torch.float64)})
    pos = nan.clone()
    pos[1, 0, 2] = 0.4  # one axis seen, in a row that also touches plane A
    with pytest.raises(ValueError, match=r"row 1: marker 'flange' has a plane contact and a position"):
        Measurements(q, pos, ["flange"], [f"joint_a{i}" for i in range(1, 7)],
                     planes=torch.zeros(3, 1, dtype=torch.long), plane_names=["A"])


def test_a_contact_row_with_one_position_axis_is_refused(partial, tmp_path):
    robot, d = partial

    def one_axis(h, rows):
        return h + ["flange.x", "flange.y", "flange.z"], [r + (["", "", "0.4"] if i == 3 else ["", "", ""])
                                                          for i, r in enumerate(rows)]
    with pytest.raises(ValueError, match=r"line 5: marker 'flange' has a plane contact \('A'\) and position cells"):
        load_measurements(_edit(d / "contacts.csv", tmp_path / "both.csv", one_axis), robot)


def _loop(args: list[str], out: Path, capsys) -> tuple[int, str]:
    return _cli(["loop", "--robot", KR5, "--marker", "flange", "--effect", "none", "--no-elm", "--folds", "2", "--quiet",
                 "--out", str(out), *args], capsys)


def test_a_plane_with_two_contacts_is_refused_by_its_label(partial, tmp_path, capsys):
    robot, d = partial

    def two_contacts(h, rows):
        return h, rows[:2]
    few = _edit(d / "contacts.csv", tmp_path / "few.csv", two_contacts)
    rc, err = _loop(["--data", str(few)], tmp_path / "o", capsys)
    assert rc == 2 and "plane 'A' has 2 contact(s)" in err and "drop the rows labelled 'A'" in err
    assert not (tmp_path / "o").exists()
    bar = load_measurements(d / "bar.csv", robot).subset(range(3))
    with pytest.raises(ValueError, match=r"fixed point 'pivot' has 3 distance\(s\).*drop the '<marker>.dist.pivot'"):
        Setup.from_data(robot, bar, robot.params().values)


def test_distances_in_millimetres_stop_the_loop(partial, tmp_path, capsys):
    robot, d = partial

    def mm(h, rows):
        j = h.index("flange.dist.pivot")
        for r in rows:
            r[j] = repr(float(r[j]) * 1000)
        return h, rows
    rc, err = _loop(["--data", str(_edit(d / "bar.csv", tmp_path / "mm.csv", mm))], tmp_path / "o", capsys)
    assert rc == 2 and "distances have median" in err and "--units mm" in err
    assert not (tmp_path / "o").exists()


def test_a_plane_touched_only_in_the_held_out_file(partial, tmp_path, capsys):
    robot, d = partial
    rc, err = _loop(["--data", str(d / "positions.csv"), "--test", str(d / "contacts.csv")], tmp_path / "o", capsys)
    assert rc == 2 and "the held-out rows measure against ['A'], which the training rows never touch" in err
    assert "move some rows that touch them into the training data" in err and not (tmp_path / "o").exists()


@pytest.mark.parametrize("name", ["contacts.csv", "bar.csv"])
def test_calibrate_points_plane_and_distance_data_to_the_loop(partial, tmp_path, capsys, name):
    robot, d = partial
    rc, err = _cli(["calibrate", "--robot", KR5, "--marker", "flange", "--data", str(d / name),
                    "--out", str(tmp_path / "o")], capsys)
    assert rc == 2 and "plane contacts or distances" in err and "'torchcal loop'" in err
    assert not (tmp_path / "o").exists()
