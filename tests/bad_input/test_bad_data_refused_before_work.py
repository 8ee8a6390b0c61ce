"""Bad input, second round (issue 28): nothing the user had is lost, nothing "perfect" comes from
broken data, no traceback, every refusal before the work, exit status 2, and a message that names
the problem and the fix (in the command line's own words). One test per class of case, through the
command line where the case is command-line behaviour. Small simulated UR5e data, seeded."""
from __future__ import annotations

import errno
import math
import os
import re
import shutil
import warnings
from pathlib import Path

import numpy as np
import pytest
import torch

import torchcal
from torchcal import Corrector, Robot, calibrate, load_measurements, run_loop
from torchcal.cli.app import main
from torchcal.deploy.model import CalibratedModel
from torchcal.kinematics.robots import shipped, urdf_path
from torchcal.kinematics.transforms import so3_exp
from torchcal.measure.data import Measurements
from torchcal.measure.io import UnitsError, save_measurements
from torchcal.measure.registration import registration_inliers
from torchcal.outputs import claim
from torchcal.pipelines.fleet.run import calibrate_fleet
from torchcal.sim.serial import SimConfig, simulate_fleet

UR5E = str(urdf_path("ur5e"))
KR5 = str(urdf_path("kuka_kr5_arc"))
SMR = "smr@flange=0,0,0.05"
API_WORDS = r"ParamSet|\.unfix\(|urdf_links\(|Robot\.from_urdf|load_measurements\(|force=True|units=\["


def _cli(args, capsys, cwd=None) -> tuple[int, str, str]:
    """Exit status, stdout and stderr of ``torchcal ARGS`` (an exception escaping main fails the test)."""
    old = os.getcwd()
    try:
        if cwd is not None:
            os.chdir(cwd)
        try:
            rc = main([str(a) for a in args])
        except SystemExit as e:
            rc = e.code
    finally:
        os.chdir(old)
    out = capsys.readouterr()
    return rc, out.out, out.err


def _refused(rc: int, err: str, *words: str) -> None:
    assert rc == 2, err
    assert "Traceback" not in err and ": error: " in err, err
    for w in words:
        assert re.search(w, err, re.S), (w, err)


def _tree(folder: Path) -> dict:
    return {p.relative_to(folder).as_posix(): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def _table(path: Path) -> tuple[list[str], np.ndarray]:
    lines = path.read_text().splitlines()
    return lines[0].split(","), np.array([[float(c) for c in ln.split(",")] for ln in lines[1:]])


def _edit(src: Path, dst: Path, fn) -> Path:
    """Copy a CSV through ``fn(header, values)``."""
    h, M = _table(src)
    h, M = fn(h, M.copy())
    dst.write_text(",".join(h) + "\n" + "\n".join(",".join(repr(float(v)) for v in r) for r in M) + "\n")
    return dst


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    """``torchcal simulate`` of a UR5e with a reflector 5 cm off the flange: 60 poses, split into
    train.csv (40 rows) and test.csv (20 rows)."""
    d = tmp_path_factory.mktemp("data")
    assert main(["simulate", "--robot", UR5E, "--marker", SMR, "--poses", "60", "--seed", "1", "--quiet",
                 "--out", str(d / "all.csv")]) == 0
    lines = (d / "all.csv").read_text().splitlines()
    (d / "train.csv").write_text("\n".join(lines[:41]) + "\n")
    (d / "test.csv").write_text("\n".join([lines[0]] + lines[41:]) + "\n")
    return d


@pytest.fixture(scope="module")
def ur5e():
    return Robot.from_urdf(UR5E, markers=[SMR])


def _calibrate(data: Path, out: Path, *extra, train: Path | None = None, marker: str = SMR) -> list:
    return ["calibrate", "--robot", UR5E, "--marker", marker, "--data", train or data / "train.csv", "--out", out,
            *extra]


def _loop(data: Path, out: Path, *extra, train: Path | None = None, marker: str = SMR) -> list:
    return ["loop", "--robot", UR5E, "--marker", marker, "--data", train or data / "train.csv", "--effect", "none",
            "--no-elm", "--folds", "2", "--out", out, *extra]


# ============================================================================ outputs: nothing is lost
@pytest.mark.slow
def test_force_replaces_only_what_torchcal_wrote_and_never_an_input(data, tmp_path, capsys):
    cell = tmp_path / "cell1"
    cell.mkdir()
    for f in ("train.csv", "test.csv"):
        shutil.copy(data / f, cell / f)
    before = _tree(cell)
    rc, _, err = _cli(_loop(data, cell, "--force", "--test", cell / "test.csv", train=cell / "train.csv"), capsys)
    _refused(rc, err, "holds .*train.csv, an input of this run", "choose another output directory")
    assert _tree(cell) == before

    mine = tmp_path / "res"
    mine.mkdir()
    (mine / "notes.txt").write_text("mine")
    rc, _, err = _cli(_calibrate(data, mine, "--force"), capsys)
    _refused(rc, err, "was not written by torchcal", r"\['notes.txt'\]", "--force does not replace it")
    assert _tree(mine) == {"notes.txt": b"mine"}

    own = tmp_path / "own"
    assert _cli(_calibrate(data, own), capsys)[0] == 0
    assert _cli(_calibrate(data, own, "--force"), capsys)[0] == 0  # its own earlier result: replaced
    assert (own / "provenance.json").is_file() and sorted(p.name for p in tmp_path.iterdir()) == ["cell1", "own",
                                                                                                  "res"]
    # a file the run reads is never its output, forced or not
    urdf = tmp_path / "robot.urdf"
    shutil.copy(UR5E, urdf)
    rc, _, err = _cli(["simulate", "--robot", urdf, "--marker", SMR, "--poses", "5", "--out", urdf, "--force"], capsys)
    _refused(rc, err, "is also an input")
    assert urdf.read_bytes() == Path(UR5E).read_bytes()


@pytest.mark.parametrize("line, what", [('force: "false"', r"option 'force' must be true or false.*'false'"),
                                        ("quiet: 1", r"option 'quiet' must be true or false"),
                                        ("seed: [1, 2]", r"option 'seed' takes one value"),
                                        ("command: rm -rf x", r"unknown option 'command'")],
                         ids=["quoted-false", "number", "list", "hidden-option"])
def test_a_config_says_what_it_means(data, tmp_path, capsys, line, what):
    res = tmp_path / "res"
    res.mkdir()
    (res / "notes.txt").write_text("mine")
    cfg = tmp_path / "run.yaml"
    cfg.write_text(f"robot: {UR5E}\ndata: {data / 'train.csv'}\nmarker: ['{SMR}']\nout: {res}\n{line}\n")
    rc, _, err = _cli(["loop", "--config", cfg], capsys)
    _refused(rc, err, what)
    assert "'command'" not in err.split("options are")[-1]  # the hidden option is not offered
    assert _tree(res) == {"notes.txt": b"mine"}


def test_a_second_run_on_the_same_output_is_refused_at_once(data, tmp_path, capsys):
    out = tmp_path / "o"
    with claim(out):  # another run holds it
        rc, _, err = _cli(_loop(data, out), capsys)
        _refused(rc, err, f"another torchcal run \\(process {os.getpid()}\\) is writing", "wait for it to finish")
        rc, _, err = _cli(["simulate", "--robot", UR5E, "--poses", "5", "--out", out], capsys)
        _refused(rc, err, "another torchcal run")
    assert not out.exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == []  # the claim went with its run
    # a claim left by a run that no longer exists (killed) is taken over
    (tmp_path / ".s.csv.torchcal-lock").write_text("999999999\n")
    assert _cli(["simulate", "--robot", UR5E, "--marker", SMR, "--poses", "5", "--out", tmp_path / "s.csv"],
                capsys)[0] == 0
    assert sorted(p.name for p in tmp_path.iterdir()) == ["s.csv", "s.truth.json"]


def test_the_working_directory_is_no_output_and_nothing_is_left(data, tmp_path, capsys):
    work = tmp_path / "work"
    work.mkdir()
    shutil.copy(data / "train.csv", work)
    for out in (".", "..", str(work)):
        rc, _, err = _cli(_loop(data, out, "--force", train=work / "train.csv"), capsys, cwd=work)
        _refused(rc, err, "is the current directory", "e.g. --out cell1")
        assert "stage" not in err  # before the work
    assert sorted(p.name for p in tmp_path.rglob("*")) == ["train.csv", "work"]
    # a refused run makes no folder on the way to its output either
    rc, _, err = _cli(_loop(data, tmp_path / "new" / "deeper" / "o", train=work / "train.csv", marker="smr@link4"),
                      capsys)
    _refused(rc, err, "come after link")
    assert sorted(p.name for p in tmp_path.rglob("*")) == ["train.csv", "work"]


@pytest.mark.slow
def test_a_full_disk_and_an_interrupt_leave_nothing(data, tmp_path, capsys, monkeypatch):
    real = os.fdopen

    class Full:
        def __init__(self, fh):
            self.fh = fh

        def __enter__(self):
            return self

        def __exit__(self, *a):
            self.fh.close()

        def write(self, b):
            raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr("torchcal.outputs.os.fdopen", lambda fd, mode="r", *a, **k: Full(real(fd, mode, *a, **k)))
    rc, _, err = _cli(["simulate", "--robot", UR5E, "--marker", SMR, "--poses", "5", "--out", tmp_path / "s.csv"],
                      capsys)
    _refused(rc, err, r"could not write .*s\.csv: No space left on device", "free some space")
    assert len(err.strip().splitlines()) == 1
    rc, _, err = _cli(_calibrate(data, tmp_path / "c"), capsys)
    _refused(rc, err, "No space left on device", "nothing was written")
    monkeypatch.undo()
    assert list(tmp_path.iterdir()) == []

    def interrupted(*a, **k):
        raise KeyboardInterrupt
    monkeypatch.setattr("torchcal.cli.app.run_loop", interrupted)
    rc, _, err = _cli(_loop(data, tmp_path / "o"), capsys)
    assert rc == 130 and err.strip() == "torchcal loop: interrupted; nothing was written"
    assert list(tmp_path.iterdir()) == []


# ============================================================================ data that cannot be right
def test_measurements_are_tied_to_the_robot_they_were_loaded_for(data, ur5e):
    train = load_measurements(data / "train.csv", ur5e)
    assert train.robot == "ur5e" and train.subset([0, 1]).robot == "ur5e"
    kr5 = Robot.from_urdf(KR5, markers=[SMR])
    for fit in (lambda: calibrate(kr5, train), lambda: run_loop(kr5, train, log=None)):
        with pytest.raises(ValueError, match=r"loaded for robot 'ur5e'.*not for 'kuka_kr5_arc'.*load_measurements"):
            fit()
    renamed = Robot.from_urdf(Path(UR5E).read_text().replace('<robot name="ur5e"', '<robot name="ur5e_b"'),
                              markers=[SMR])
    with pytest.raises(ValueError, match="loaded for robot 'ur5e'"):  # same joints, another robot
        calibrate(renamed, train)


def _frozen(h, M):
    M[:, 6:9] = M[0, 6:9] + 1e-6 * np.random.default_rng(0).standard_normal((len(M), 3))
    return h, M


def _stale(h, M):
    M[10:16, 6:9] = M[10, 6:9]
    return h, M


@pytest.mark.parametrize("fn, what", [(_frozen, r"moves 0.00\d+ mm.*instrument fault"),
                                      (_stale, r"exactly the same position in 6 rows \(lines \[12, 13, 14, 15, 16, "
                                               r"17\]\).*stale value")], ids=["frozen", "stale-rows"])
def test_a_point_that_does_not_move_is_an_instrument_fault(data, tmp_path, capsys, fn, what):
    f = _edit(data / "train.csv", tmp_path / "frozen.csv", fn)
    for cmd in (_calibrate, _loop):
        rc, _, err = _cli(cmd(data, tmp_path / "o", train=f), capsys)
        _refused(rc, err, what)
    assert not (tmp_path / "o").exists()


@pytest.mark.parametrize("units, what", [("mm", r"look like metres already.*leave out --units mm"),
                                         ("deg", r"look like radians already: leave out --units deg")])
def test_declared_units_are_checked_as_hard_as_undeclared_ones(data, tmp_path, capsys, units, what):
    for cmd in (_calibrate, _loop):
        rc, _, err = _cli(cmd(data, tmp_path / "o", "--units", units), capsys)
        _refused(rc, err, what)
        assert not re.search(API_WORDS, err), err
    assert not (tmp_path / "o").exists()


def test_a_joint_column_is_never_a_covariate(data, tmp_path, capsys, ur5e):
    rc, _, err = _cli(_loop(data, tmp_path / "o", marker="smr@link4=0,0,0.05"), capsys)
    _refused(rc, err, r"\['wrist_2_joint', 'wrist_3_joint'\] move, but come after link\(s\) \['link4'\]",
             "--marker smr@LINK=x,y,z")
    # joints of the URDF that move no declared marker and stay still are not covariates either
    still = _edit(data / "train.csv", tmp_path / "still.csv",
                  lambda h, M: (h, np.c_[M[:, :4], 0 * M[:, 4:6], M[:, 6:]]))
    d = load_measurements(still, Robot.from_urdf(UR5E, markers=["smr@link4=0,0,0.05"]))
    assert d.joint_names == ur5e.joint_names[:4] and d.covariates == {}


def test_one_minimum_of_data_for_calibrate_loop_and_fleet(data, tmp_path, capsys):
    lines = (data / "train.csv").read_text().splitlines()
    five = tmp_path / "five.csv"
    five.write_text("\n".join(lines[:6]) + "\n")
    rule = (r"too few rows: the training data \(.*five.csv\) have 5 rows \(15 measured values\); these poses can "
            r"identify 15 geometric errors, as many as their values.*identify 27 errors of this robot.*at least 10 poses")
    for cmd in (_calibrate, _loop):
        rc, _, err = _cli(cmd(data, tmp_path / "o", train=five), capsys)
        _refused(rc, err, rule)
    fleet = tmp_path / "fleet"
    fleet.mkdir()
    for r in ("a", "b", "c"):
        shutil.copy(data / "train.csv", fleet / f"{r}.csv")
    shutil.copy(five, fleet / "b.csv")
    rc, _, err = _cli(["fleet", "--robot", UR5E, "--marker", SMR, "--data", fleet, "--no-figures", "--out",
                       tmp_path / "o"], capsys)
    _refused(rc, err, "robot 'b': " + rule.replace("five.csv", "b.csv"))
    assert not (tmp_path / "o").exists()


# ============================================================================ gross errors
def test_registration_is_not_dragged_by_a_gross_error():
    g = torch.Generator().manual_seed(3)
    src = torch.randn(100, 3, generator=g, dtype=torch.float64)
    R, t = so3_exp(torch.tensor([0.3, -0.2, 1.1], dtype=torch.float64)), torch.tensor([2.0, -1.0, 0.5],
                                                                                         dtype=torch.float64)
    dst = src @ R.T + t + 1e-3 * torch.randn(100, 3, generator=g, dtype=torch.float64)
    dst[17, 0] += 6.0
    R1, t1, keep = registration_inliers(src, dst)
    assert keep.sum() == 99 and not keep[17]
    assert float((R1 - R).abs().max()) < 1e-3 and float((t1 - t).abs().max()) < 1e-3


@pytest.mark.slow
@pytest.mark.parametrize("metres", [6.0, 100.0])
def test_one_tracker_glitch_is_listed_not_fatal(data, tmp_path, capsys, metres):
    def glitch(h, M):
        M[17, 6] += metres
        return h, M
    f = _edit(data / "train.csv", tmp_path / "glitch.csv", glitch)
    rc, out, err = _cli(_calibrate(data, tmp_path / "c", "--test", data / "test.csv", train=f), capsys)
    assert rc == 0, err
    assert "1 gross error(s) left out of the fit" in out and "rows 17" in out
    assert "Gross errors left out of the fit" in (tmp_path / "c" / "report.md").read_text()
    held = re.search(r"geometric\s+\d+\s+\S+\s+\S+\s+(\S+)", out)
    assert held and float(held.group(1)) < 0.1, out  # held-out mean error: the glitch did not spoil the fit
    if metres > 50:  # the loop once (it lists what it down-weights)
        rc, out, err = _cli(_loop(data, tmp_path / "l", "--test", data / "test.csv", train=f), capsys)
        assert rc == 0, err
        assert "1 suspect observation(s)" in out


def test_a_glitch_in_one_robot_of_a_fleet_is_listed_not_fatal():
    robot = shipped("kuka_kr5_arc")
    train, test, _ = simulate_fleet(robot, 4, SimConfig(n=40, seed=3), spread=0.2, n_test=10)
    p = train[1].positions.clone()
    p[7, 0, 0] += 6.0
    train[1] = Measurements(train[1].q, p, train[1].marker_names, train[1].joint_names)
    fr = calibrate_fleet(robot, train, test=test)
    gross = [{"row": 7, "marker": "flange", "error_mm": pytest.approx(6000, rel=0.01)}]
    assert [r.suspects for r in fr.results] == [[], gross, [], []]
    held = [r.stages[-1]["test"]["mean_mm"] for r in fr.results]
    assert int(fr.free[1].sum()) == int(fr.free[0].sum()) and held[1] < 2 * max(held[0], held[2])


# ============================================================================ silent acceptance
@pytest.mark.slow
def test_what_was_accepted_silently_now_speaks(data, tmp_path, capsys):
    def beyond(h, M):
        M[:16, 2] = np.sign(M[:16, 2]) * 3.5  # elbow limits ±π
        return h, M
    rc, _, err = _cli(_calibrate(data, tmp_path / "o", train=_edit(data / "train.csv", tmp_path / "l.csv", beyond)),
                      capsys)
    assert err.count("joint 'elbow_joint' is beyond its URDF limits [-3.142, 3.142] rad in 16 of 40") == 1, err
    assert "zero or direction" in err and "Warning" not in err and "warnings.warn" not in err
    # the held-out file is the training file
    rc, _, err = _cli(_calibrate(data, tmp_path / "o2", "--test", data / "train.csv"), capsys)
    assert rc == 0 and "warning: the held-out file is the training file" in err and "--holdout" in err
    # a simulated marker guess of 50 m is a guess in millimetres, as loop says
    rc, _, err = _cli(["simulate", "--robot", UR5E, "--marker", "smr@flange=0,0,50", "--out", tmp_path / "s.csv"],
                      capsys)
    _refused(rc, err, r"looks like millimetres; give metres \(e.g. smr@flange=0,0,0.05\)")
    assert not (tmp_path / "s.csv").exists()


def test_a_xacro_file_is_refused_and_a_fleet_file_named_CSV_is_read(tmp_path, capsys):
    x = tmp_path / "arm.urdf.xacro"
    x.write_text('<robot name="a" xmlns:xacro="http://www.ros.org/wiki/xacro"><link name="base"/>'
                 '<xacro:macro name="m"><link name="l"/></xacro:macro></robot>')
    rc, _, err = _cli(["plan", "--robot", x, "--out", tmp_path / "p.csv"], capsys)
    _refused(rc, err, "arm.urdf.xacro is a xacro file", "Run xacro first")
    robot = shipped("kuka_kr5_arc")
    train, _, _ = simulate_fleet(robot, 3, SimConfig(n=15, seed=3), spread=0.2)
    fl = tmp_path / "fleet"
    fl.mkdir()
    for i, t in enumerate(train):
        save_measurements(fl / (f"r{i}.CSV" if i == 2 else f"r{i}.csv"), t)
    rc, out, err = _cli(["fleet", "--robot", KR5, "--data", fl, "--no-figures", "--out", tmp_path / "o"], capsys)
    assert rc == 0 and "3 robots calibrated" in out, err


def test_single_precision_is_refused_with_the_fix(data):
    r32 = Robot.from_urdf(UR5E, markers=[SMR], dtype=torch.float32)
    d32 = load_measurements(data / "train.csv", r32)
    for fit in (lambda: calibrate(r32, d32), lambda: run_loop(r32, d32, log=None)):
        with pytest.raises(TypeError, match=r"computes in float32.*needs float64.*robot.to\(dtype=torch.float64\)"):
            fit()


def test_failed_targets_carry_no_commands(tmp_path, capsys):
    robot = Robot.from_urdf(UR5E, markers=[SMR])
    torchcal.save(CalibratedModel(robot), tmp_path / "model")
    t = tmp_path / "targets.csv"
    t.write_text("x,y,z\n0.3,0.2,0.5\n3.0,3.0,3.0\n")
    rc, _, err = _cli(["correct", "--model", tmp_path / "model", "--targets", t, "--out", tmp_path / "cmd.csv",
                       "--allow-failures"], capsys)
    assert rc == 0, err
    head, ok, bad = (ln.split(",") for ln in (tmp_path / "cmd.csv").read_text().splitlines())
    j = [head.index(n) for n in robot.joint_names]
    assert all(math.isfinite(float(ok[i])) for i in j) and ok[head.index("converged")] == "1"
    assert all(bad[i] == "nan" for i in j) and bad[head.index("reason")] == "unreachable"


# ============================================================================ no traceback
@pytest.mark.parametrize("call, what", [
    (lambda r, d, p: load_measurements(p, UR5E), r"robot must be a torchcal.Robot, got the path.*Robot.from_urdf"),
    (lambda r, d, p: load_measurements(p, np.zeros(6)), r"robot must be a torchcal.Robot.*got ndarray"),
    (lambda r, d, p: run_loop(r, str(p), log=None), r"data must be Measurements, got the path.*load_measurements"),
    (lambda r, d, p: calibrate(r, np.zeros((10, 9))), r"data must be Measurements, got ndarray.*Measurements\(q, "),
    (lambda r, d, p: calibrate(r, d, test=str(p)), r"test must be Measurements, got the path"),
    (lambda r, d, p: calibrate(UR5E, d), r"robot must be a torchcal.Robot, got the path"),
    (lambda r, d, p: calibrate_fleet(shipped("ur5e"), [str(p)] * 3), r"expected Measurements"),
], ids=["load-path-robot", "load-array-robot", "loop-path-data", "calibrate-array", "calibrate-path-test",
        "calibrate-path-robot", "fleet-paths"])
def test_the_api_names_the_type_it_wants(data, ur5e, call, what):
    d = load_measurements(data / "train.csv", ur5e)
    with pytest.raises(TypeError, match=what):
        call(ur5e, d, data / "train.csv")


@pytest.mark.parametrize("spec, what", [("smr@flange=nan,0,0.05", "three finite numbers"),
                                        ("smr@flange=0,inf,0", "three finite numbers"),
                                        ("my smr@flange=0,0,0.05", r"marker name 'my smr' has a space.*'my_smr'")])
def test_a_marker_spec_that_cannot_be_used(data, tmp_path, capsys, spec, what):
    for args in (_calibrate(data, tmp_path / "o", marker=spec),
                 ["simulate", "--robot", UR5E, "--marker", spec, "--out", tmp_path / "s.csv"]):
        rc, _, err = _cli(args, capsys)
        _refused(rc, err, what)
    assert list(tmp_path.iterdir()) == []


# ============================================================================ messages that help
def _tabs(src: Path, dst: Path) -> Path:
    dst.write_text(src.read_text().replace(",", "\t"))
    return dst


def _comment(src: Path, dst: Path) -> Path:
    dst.write_text("# exported by the tracker\n" + src.read_text())
    return dst


def _huge(src: Path, dst: Path) -> Path:
    def fn(h, M):
        M[4, 1] = 1e308
        return h, M
    return _edit(src, dst, fn)


@pytest.mark.parametrize("make, what", [
    (_tabs, r"is separated by tabs; torchcal reads comma-separated files"),
    (_comment, r"line 1 starts with '#'.*delete comment lines above the header"),
    (_huge, r"line 6, column 'shoulder_lift_joint': 1e\+308 is not a plausible joint value"),
    (lambda src, dst: src.parent, r"is a directory; give the CSV file itself, e.g. .*all.csv"),
], ids=["tabs", "comment", "1e308", "directory"])
def test_a_file_that_cannot_be_read_is_named_with_the_fix(data, tmp_path, capsys, make, what):
    f = make(data / "train.csv", tmp_path / "bad.csv")
    rc, _, err = _cli(_calibrate(data, tmp_path / "o", train=f), capsys)
    _refused(rc, err, what)
    assert not re.search(r"\d{20}", err) and not (tmp_path / "o").exists()


@pytest.mark.slow
def test_a_continuous_joint_may_turn_many_times(tmp_path, capsys):
    txt = Path(UR5E).read_text()
    i = txt.index('<joint name="wrist_3_joint" type="revolute"')
    j = txt.index("</joint>", i)
    block = re.sub(r"<limit[^>]*/>", "", txt[i:j]).replace('type="revolute"', 'type="continuous"')
    urdf = tmp_path / "ur5e_turns.urdf"
    urdf.write_text(txt[:i] + block + txt[j:])
    assert _cli(["simulate", "--robot", urdf, "--marker", SMR, "--poses", "40", "--seed", "2", "--out",
                 tmp_path / "a.csv", "--quiet"], capsys)[0] == 0

    def turns(h, M):
        M[:, 5] += 2 * np.pi * (np.arange(len(M)) % 4)  # up to three more turns: the same poses
        return h, M
    f = _edit(tmp_path / "a.csv", tmp_path / "turns.csv", turns)
    rc, _, err = _cli(["calibrate", "--robot", urdf, "--marker", SMR, "--data", f, "--out", tmp_path / "o"], capsys)
    assert rc == 0 and "degrees" not in err, err


def test_paths_one_level_off_and_files_in_another_encoding(data, tmp_path, capsys):
    robot = Robot.from_urdf(UR5E, markers=[SMR])
    torchcal.save(CalibratedModel(robot), tmp_path / "cell" / "model")
    t = tmp_path / "targets.csv"
    t.write_text("x,y,z\n0.3,0.2,0.5\n")
    for wrong in (tmp_path / "cell", tmp_path / "cell" / "model" / "model.json"):
        rc, _, err = _cli(["correct", "--model", wrong, "--targets", t, "--out", tmp_path / "c.csv"], capsys)
        _refused(rc, err, "model.json is missing", re.escape(str(tmp_path / "cell" / "model")))
    latin = tmp_path / "latin.urdf"
    latin.write_bytes(Path(UR5E).read_text().replace('<robot name="ur5e"', '<!-- Gerät -->\n<robot name="ur5e"', 1)
                      .encode("latin-1"))
    args = _calibrate(data, tmp_path / "o")
    args[args.index("--robot") + 1] = latin  # an option given twice is refused as such
    rc, _, err = _cli(args, capsys)
    _refused(rc, err, r"URDF file .*latin.urdf is not UTF-8 text.*save it as UTF-8")


def test_api_units_mean_what_they_say(data, ur5e, tmp_path):
    deg = _edit(data / "train.csv", tmp_path / "deg.csv", lambda h, M: (h, np.c_[np.rad2deg(M[:, :6]), M[:, 6:]]))
    a = load_measurements(deg, ur5e, units="deg")  # one unit, not the letters d, e, g
    torch.testing.assert_close(a.q, load_measurements(data / "train.csv", ur5e).q)
    model = CalibratedModel(ur5e)
    with pytest.raises(UnitsError, match=r"targets lie up to .* look like millimetres.*divide by 1000"):
        Corrector(model).correct(torch.tensor([[300.0, 200.0, 500.0]], dtype=torch.float64))


def test_a_covariate_the_test_file_lacks_is_refused_at_the_door(data, tmp_path, capsys):
    def temp(h, M):
        return h + ["temperature"], np.c_[M, 20 + 0.05 * np.arange(len(M))]
    f = _edit(data / "train.csv", tmp_path / "t.csv", temp)
    rc, _, err = _cli(_loop(data, tmp_path / "o", "--test", data / "test.csv", train=f), capsys)
    _refused(rc, err, r"held-out rows \(.*test.csv\) have no column for covariate\(s\) \['temperature'\]")
    assert "noise estimate" not in err and not (tmp_path / "o").exists()


@pytest.mark.parametrize("extra, marker, what", [
    (["--free", "nothing*"], SMR, r"no parameter matches \['nothing\*'\].*--free takes glob patterns"),
    ([], "smr@gripper=0,0,0.05", r"not in the URDF; its links are \['flange', 'link0'"),
], ids=["free", "link"])
def test_command_line_messages_name_command_line_options(data, tmp_path, capsys, extra, marker, what):
    rc, _, err = _cli(_calibrate(data, tmp_path / "o", *extra, marker=marker), capsys)
    _refused(rc, err, what)
    assert not re.search(API_WORDS, err), err


# ============================================================================ noise
def test_warnings_go_through_logging_once_in_words(data, tmp_path, capsys):
    def beyond(h, M):
        M[:, 2] = np.clip(M[:, 2] * 1.6, -3.5, 3.5)
        return h, M
    tr = _edit(data / "train.csv", tmp_path / "tr.csv", beyond)
    te = _edit(data / "test.csv", tmp_path / "te.csv", beyond)
    with warnings.catch_warnings():
        warnings.simplefilter("always")
        rc, _, err = _cli(_calibrate(data, tmp_path / "o", "--test", te, "--quiet", train=tr), capsys)
    lines = [ln for ln in err.splitlines() if "beyond its URDF limits" in ln]
    assert len(lines) == 1 and lines[0].startswith("torchcal calibrate: warning: joint 'elbow_joint'"), err
    assert "UserWarning" not in err and "warnings.warn" not in err and "  " not in lines[0][:30]
