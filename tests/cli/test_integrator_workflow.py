"""The integrator's workflow from URDF and CSV to a calibrated robot: nothing is lost, wrong units
and wrong data stop the run, and every output an integrator needs is there. One test per item,
through the command line where the item is a command-line behaviour."""
from __future__ import annotations

import json
import logging
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest
import torch
import yaml

import torchcal
from torchcal import Robot, load, load_measurements, run_loop, save
from torchcal.cli.app import main as cli
from torchcal.cli.common import EXIT_BUG, EXIT_REFUSED, is_refusal
from torchcal.params import NoSuchParameter
from torchcal.measure.io import UnitsError
from torchcal.pipelines.crossval.models import folds_of
from torchcal.kinematics.robots import urdf_path
from torchcal.kinematics.transforms import quat_to_matrix

REPO = Path(__file__).resolve().parents[2]
TIAGO = REPO.parent / "shared" / "data" / "tiago_mocap"
UR5E = str(urdf_path("ur5e"))
KR5 = str(urdf_path("kuka_kr5_arc"))


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    """A compliant UR5e measured by a tracker (120 rows), and another UR5e (another seed)."""
    d = tmp_path_factory.mktemp("data")
    assert cli(["simulate", "--robot", UR5E, "--poses", "120", "--effect", "joint_compliance", "--seed", "4",
                "--out", str(d / "train.csv")]) == 0
    assert cli(["simulate", "--robot", UR5E, "--poses", "40", "--seed", "9", "--out", str(d / "other.csv")]) == 0
    return d


@pytest.fixture(scope="module")
def looped(files, tmp_path_factory):
    """One ``torchcal loop`` run (hold-out 25 %), its output folder and what it printed."""
    out = tmp_path_factory.mktemp("runs") / "loop"
    assert cli(["loop", "--robot", UR5E, "--data", str(files / "train.csv"), "--holdout", "0.25", "--no-elm",
                "--out", str(out)]) == 0
    return out


def _tree(path: Path) -> dict:
    return {p.relative_to(path).as_posix(): p.read_bytes() for p in sorted(path.rglob("*")) if p.is_file()}


# ----------------------------------------------------------------------------- nothing is lost
def test_simulate_refuses_to_overwrite(files, capsys):
    before = (files / "train.csv").read_bytes()
    assert cli(["simulate", "--robot", UR5E, "--poses", "5", "--out", str(files / "train.csv")]) == 2
    assert "train.csv exists" in capsys.readouterr().err
    assert (files / "train.csv").read_bytes() == before


@pytest.mark.slow
def test_calibrate_and_loop_refuse_an_existing_output_folder(files, looped, tmp_path, capsys):
    before = _tree(looped)
    args = ["--robot", UR5E, "--data", str(files / "train.csv"), "--out", str(looped)]
    assert cli(["loop", *args, "--no-elm"]) == 2
    assert cli(["calibrate", *args]) == 2
    err = capsys.readouterr().err
    assert err.count(f"{looped} exists and is not empty") == 2 and "--force" in err
    assert _tree(looped) == before
    out = tmp_path / "cal"
    assert cli(["calibrate", *args[:-1], str(out)]) == 0
    assert cli(["calibrate", *args[:-1], str(out), "--force", "--method", "gn"]) == 0
    assert yaml.safe_load((out / "run.yaml").read_text())["method"] == "gn"
    assert not list(tmp_path.glob(".*partial*")) and not list(tmp_path.glob(".*replaced*"))


@pytest.mark.slow
def test_save_refuses_to_overwrite_and_leaves_nothing_half_written(looped, tmp_path, monkeypatch):
    model = load(looped / "model")
    save(model, tmp_path / "m")
    with pytest.raises(FileExistsError, match="not empty"):
        save(model, tmp_path / "m")
    save(model, tmp_path / "m", force=True)
    import torchcal.deploy.persist as persist

    def broken(*a, **k):
        raise OSError("disk full")
    monkeypatch.setattr(persist, "save_file", broken)
    with pytest.raises(OSError, match="disk full"):
        save(model, tmp_path / "m2")
    assert not (tmp_path / "m2").exists()
    assert [p.name for p in tmp_path.iterdir()] == ["m"]  # no partial folder left behind


@pytest.mark.slow
def test_correct_refuses_to_write_over_its_targets(looped, tmp_path, capsys):
    t = tmp_path / "targets.csv"
    t.write_text("x,y,z\n0.4,0.1,0.5\n")
    assert cli(["correct", "--model", str(looped / "model"), "--targets", str(t), "--out", str(t)]) == 2
    assert "also an input" in capsys.readouterr().err
    assert t.read_text() == "x,y,z\n0.4,0.1,0.5\n"


def test_an_unwritable_output_fails_before_any_work(files, tmp_path, monkeypatch, capsys):
    import torchcal.cli.app as cli_mod

    def never(*a, **k):
        raise AssertionError("the loop ran although its output cannot be written")
    monkeypatch.setattr(cli_mod, "run_loop", never)
    blocker = tmp_path / "a_file"
    blocker.write_text("")
    assert cli(["loop", "--robot", UR5E, "--data", str(files / "train.csv"), "--out", str(blocker / "out")]) == 2
    assert "cannot write under" in capsys.readouterr().err


@pytest.mark.slow
def test_a_changed_or_broken_model_is_refused_naming_the_file(looped, tmp_path):
    import shutil

    m = tmp_path / "m"
    shutil.copytree(looped / "model", m)
    t = m / "tensors.safetensors"
    raw = bytearray(t.read_bytes())
    raw[-3] ^= 0x01  # one flipped bit in the last tensor
    t.write_bytes(bytes(raw))
    with pytest.raises(ValueError, match=r"tensors\.safetensors does not match the SHA-256"):
        load(m)
    shutil.copy(looped / "model" / "tensors.safetensors", t)
    meta = json.loads((m / "model.json").read_text())
    del meta["tensors_sha256"]  # an edit of model.json: its own checksum no longer matches
    (m / "model.json").write_text(json.dumps(meta))
    with pytest.raises(ValueError, match=r"model\.json does not match its checksum"):
        load(m)
    shutil.copy(looped / "model" / "model.json", m / "model.json")
    t.write_bytes(t.read_bytes()[:100])
    with pytest.raises(ValueError, match=r"tensors\.safetensors does not match the SHA-256"):
        load(m)
    (m / "model.json").write_text((looped / "model" / "model.json").read_text()[:200])
    with pytest.raises(ValueError, match=r"model\.json is not valid JSON"):
        load(m)


# ----------------------------------------------------------------------------- wrong units, wrong data
def _rewrite(src: Path, dst: Path, scale: dict) -> Path:
    lines = src.read_text().splitlines()
    head = lines[0].split(",")
    out = [lines[0]]
    for ln in lines[1:]:
        cells = ln.split(",")
        out.append(",".join(repr(float(c) * scale.get(h, 1.0)) if c else c for h, c in zip(head, cells)))
    dst.write_text("\n".join(out) + "\n")
    return dst


@pytest.mark.slow
def test_degrees_and_millimetres_stop_the_run_unless_declared(files, tmp_path, capsys):
    import math

    robot = Robot.from_urdf(UR5E, markers=["flange"])
    joints = {j: 180 / math.pi for j in robot.joint_names}
    mm = {f"flange.{a}": 1000.0 for a in "xyz"}
    bad = _rewrite(files / "train.csv", tmp_path / "deg_mm.csv", {**joints, **mm})
    assert cli(["calibrate", "--robot", UR5E, "--data", str(bad), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert "looks like degrees" in err and "--units deg" in err and not (tmp_path / "o").exists()
    with pytest.raises(UnitsError, match="millimetres"):
        load_measurements(bad, robot, units=["deg"])
    ok = load_measurements(bad, robot, units=["deg", "mm"])
    ref = load_measurements(files / "train.csv", robot)
    torch.testing.assert_close(ok.q, ref.q)
    torch.testing.assert_close(ok.positions, ref.positions)
    assert cli(["calibrate", "--robot", UR5E, "--data", str(bad), "--units", "deg", "--units", "mm",
                "--out", str(tmp_path / "o")]) == 0


@pytest.mark.slow
def test_a_marker_guess_in_millimetres_stops_the_run(files, tmp_path, capsys):
    args = ["calibrate", "--robot", UR5E, "--data", str(files / "train.csv"), "--out", str(tmp_path / "o")]
    assert cli([*args, "--marker", "flange@flange=0,0,50"]) == 2
    assert "looks like millimetres" in capsys.readouterr().err
    # --units mm declares the data's positions and the guess alike: data in metres are then refused
    assert cli([*args, "--marker", "flange@flange=0,0,50", "--units", "mm"]) == 2
    assert "look like metres already" in capsys.readouterr().err
    mm = _rewrite(files / "train.csv", tmp_path / "mm.csv", {f"flange.{a}": 1000.0 for a in "xyz"})
    assert cli(["calibrate", "--robot", UR5E, "--data", str(mm), "--out", str(tmp_path / "o"),
                "--marker", "flange@flange=0,0,50", "--units", "mm"]) == 0


def test_a_declared_marker_without_columns_is_an_error(files, tmp_path, capsys):
    assert cli(["calibrate", "--robot", UR5E, "--data", str(files / "train.csv"), "--marker", "flange",
                "--marker", "m2@link6", "--out", str(tmp_path / "o")]) == 2
    assert "['m2'] are declared but the file has no" in capsys.readouterr().err


@pytest.mark.slow
def test_a_model_worse_than_nominal_is_not_saved(files, tmp_path, monkeypatch, capsys):
    import torchcal.cli.app as cli_mod

    real = cli_mod.calibrate

    def sabotaged(*a, **k):
        from dataclasses import replace
        res = real(*a, **k)
        fin = res.stages[-1]  # the stage records are frozen: the sabotage builds a worse one
        res.stages[-1] = replace(fin, train=replace(fin.train, mean=res.stages[0].train.mean * 2))
        return res
    monkeypatch.setattr(cli_mod, "calibrate", sabotaged)
    assert cli(["calibrate", "--robot", UR5E, "--data", str(files / "train.csv"), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert "worse than the nominal one" in err and "nothing was written" in err
    assert not (tmp_path / "o").exists()


def test_duplicate_rows_warn_and_share_a_fold(files, tmp_path):
    lines = (files / "train.csv").read_text().splitlines()
    dup = tmp_path / "dup.csv"
    dup.write_text("\n".join(lines + lines[1:4]) + "\n")
    robot = Robot.from_urdf(UR5E, markers=["flange"])
    with pytest.warns(UserWarning, match="3 row.*repeat another row exactly"):
        data = load_measurements(dup, robot)
    groups = torch.unique(data.q, dim=0, return_inverse=True)[1]
    folds = folds_of(len(data), 5, 0, groups)
    for k in range(3):  # each copy in its original's fold
        assert any({k, len(data) - 3 + k} <= set(f.tolist()) for f in folds)


def test_excel_byte_order_mark_and_semicolons(files, tmp_path):
    robot = Robot.from_urdf(UR5E, markers=["flange"])
    text = (files / "train.csv").read_text()
    bom = tmp_path / "bom.csv"
    bom.write_bytes(b"\xef\xbb\xbf" + text.encode())
    assert load_measurements(bom, robot).q.shape == (120, 6)
    semi = tmp_path / "semi.csv"
    semi.write_text(text.replace(",", ";"))
    with pytest.raises(ValueError, match="separated by semicolons.*comma"):
        load_measurements(semi, robot)


@pytest.mark.parametrize("opt", [["loop", "--folds", "1"], ["loop", "--threads", "0"], ["simulate", "--poses", "0"],
                                 ["simulate", "--noise-mm", "-0.1"], ["loop", "--holdout", "1.5"]])
def test_out_of_range_options_are_refused_when_parsed(opt, capsys):
    base = {"loop": ["--robot", UR5E, "--data", "x.csv", "--out", "o"], "simulate": ["--robot", UR5E, "--out", "o.csv"]}
    with pytest.raises(SystemExit) as e:
        cli([opt[0], *base[opt[0]], *opt[1:]])
    assert e.value.code == 2
    assert re.search(r"must be|not a|fraction", capsys.readouterr().err)


def test_effect_names_are_checked_before_fitting(files):
    robot = Robot.from_urdf(UR5E, markers=["flange"])
    data = load_measurements(files / "train.csv", robot)
    with pytest.raises(ValueError, match=r"unknown effect\(s\) \['thermal'\]"):
        run_loop(robot, data, candidates=["joint_compliance", "thermal"], log=None)
    with pytest.raises(SystemExit):
        cli(["loop", "--robot", UR5E, "--data", "x.csv", "--out", "o", "--effect", "thermal"])


@pytest.mark.slow
def test_a_test_set_from_another_robot_is_named(files, tmp_path, capsys):
    args = ["--robot", UR5E, "--data", str(files / "train.csv"), "--test", str(files / "other.csv")]
    assert cli(["calibrate", *args, "--out", str(tmp_path / "c")]) == 2
    assert cli(["loop", *args, "--no-elm", "--out", str(tmp_path / "l")]) == 2
    err = capsys.readouterr().err
    refused = [ln for ln in err.splitlines() if ": error: " in ln and "do not belong to this robot" in ln]
    assert [ln.split(":")[0] for ln in refused] == ["torchcal calibrate", "torchcal loop"] and "another robot" in err


# ----------------------------------------------------------------------------- the integrator's outputs
@pytest.mark.slow
def test_loop_writes_the_calibrated_urdf_instrument_and_record(files, looped):
    text = (looped / "calibrated.urdf").read_text()
    rep = json.loads((looped / "report.json").read_text())
    assert [e["name"] for e in rep["effects"]] == ["joint_compliance"]
    assert "<!-- geometric part only: the calibrated model also applies joint_compliance" in text
    back = Robot.from_urdf(looped / "calibrated.urdf", markers=["flange"])
    assert back.root == Robot.from_urdf(UR5E, markers=["flange"]).root  # the robot's own root
    inst = json.loads((looped / "instrument.json").read_text())
    assert abs(float(torch.tensor(inst["quaternion_wxyz"], dtype=torch.float64).norm()) - 1) < 1e-12
    assert 2.0 < float(torch.tensor(inst["translation_m"]).norm()) < 4.0  # the tracker 3 m away
    run = yaml.safe_load((looped / "run.yaml").read_text())
    assert (looped / run["data"]).resolve() == (files / "train.csv").resolve() and run["holdout"] == 0.25
    prov = json.loads((looped / "provenance.json").read_text())
    assert prov["torchcal"] == torchcal.__version__ and prov["torch"] == torch.__version__
    from torchcal.outputs import sha256_file

    assert prov["files"]["data"]["sha256"] == sha256_file(files / "train.csv")
    assert prov["command"][:2] == ["torchcal", "loop"]
    assert load(looped / "model").meta["provenance"] == prov


@pytest.mark.slow
def test_with_instrument_roots_the_urdf_in_the_instrument_frame(files, tmp_path):
    assert cli(["calibrate", "--robot", UR5E, "--data", str(files / "train.csv"), "--with-instrument",
                "--out", str(tmp_path / "c")]) == 0
    assert Robot.from_urdf(tmp_path / "c" / "calibrated.urdf", markers=["flange"]).root == "instrument"


@pytest.mark.slow
def test_correction_in_the_base_or_the_instrument_frame(looped, tmp_path, capsys):
    model = load(looped / "model")
    q = torch.tensor([[0.3, -1.2, 1.3, -1.6, -1.5, 0.2]], dtype=torch.float64)
    p_inst = model.predict_pose(q)[:, 0, :3, 3]
    Rb, tb = model.robot.base_transform(model.params.values)
    p_base = (p_inst - tb) @ Rb
    outs = {}
    for frame, p in (("base", p_base), ("instrument", p_inst)):
        t = tmp_path / f"t_{frame}.csv"
        t.write_text("x,y,z," + ",".join(model.robot.joint_names) + "\n" +
                     ",".join(repr(float(v)) for v in [*p[0], *(q[0] + 0.02)]) + "\n")
        o = tmp_path / f"o_{frame}.csv"
        assert cli(["correct", "--model", str(looped / "model"), "--targets", str(t), "--out", str(o),
                    "--frame", frame]) == 0
        outs[frame] = torch.tensor([[float(v) for v in o.read_text().splitlines()[1].split(",")[3:9]]],
                                   dtype=torch.float64)
    for frame, qc in outs.items():  # both land where the target is (position targets leave orientation free)
        assert float((model.predict_pose(qc)[:, 0, :3, 3] - p_inst).norm()) < 1e-6, frame
    far = tmp_path / "far.csv"
    far.write_text("x,y,z\n5.0,0.0,0.0\n")
    assert cli(["correct", "--model", str(looped / "model"), "--targets", str(far), "--out",
                str(tmp_path / "f.csv")]) == 3  # a failed target fails the command
    assert "failed" in capsys.readouterr().err


@pytest.mark.slow
def test_the_loop_report_has_a_parameter_table_with_observability(looped):
    md = (looped / "report.md").read_text()
    rep = json.loads((looped / "report.json").read_text())
    assert "| parameter | value | standard error | unit |" in md and "Condition number" in md
    names = [p["name"] for p in rep["parameters"]]
    assert "base.x" in names and any(n.startswith("joint_compliance.") for n in names)
    assert all(p["std_error"] is not None and p["std_error"] > 0 for p in rep["parameters"])
    assert rep["observability"]["condition"] > 1 and rep["observability"]["O1"] > 0


@pytest.mark.slow
def test_a_config_file_takes_any_option_and_run_yaml_repeats_the_run(files, looped, tmp_path, capsys):
    cfg = tmp_path / "run.yaml"
    cfg.write_text(yaml.safe_dump({"robot": UR5E, "data": str(files / "train.csv"), "holdout": 0.25,
                                   "no-elm": True, "out": "again"}))
    assert cli(["loop", "--config", str(cfg)]) == 0
    a, b = json.loads((looped / "report.json").read_text()), json.loads((tmp_path / "again" / "report.json").read_text())
    assert a["stages"] == b["stages"] and a["parameters"] == b["parameters"]
    assert cli(["loop", "--config", str(looped / "run.yaml"), "--out", str(tmp_path / "third")]) == 0
    assert json.loads((tmp_path / "third" / "report.json").read_text())["stages"] == a["stages"]
    cfg.write_text("robot: x.urdf\nfolds-count: 3\n")
    assert cli(["loop", "--config", str(cfg)]) == 2
    assert "unknown option 'folds-count'" in capsys.readouterr().err


@pytest.mark.slow
def test_logging_levels_version_and_module_entry(files, tmp_path, capsys):
    logging.getLogger("torchcal").handlers.clear()
    assert cli(["calibrate", "--robot", UR5E, "--data", str(files / "train.csv"), "--quiet",
                "--out", str(tmp_path / "q")]) == 0
    assert capsys.readouterr().err == ""
    logging.getLogger("torchcal").handlers.clear()
    assert cli(["loop", "--robot", UR5E, "--data", str(files / "train.csv"), "--no-elm", "--no-progress",
                "--out", str(tmp_path / "v")]) == 0
    err = capsys.readouterr().err
    assert "stage geometric:" in err and "round 1:" in err
    logging.getLogger("torchcal").handlers.clear()
    r = subprocess.run([sys.executable, "-m", "torchcal", "--version"], capture_output=True, text=True,
                       env={**os.environ, "PYTHONPATH": str(REPO)})
    assert r.returncode == 0 and r.stdout.startswith(f"torchcal {torchcal.__version__}")


@pytest.mark.slow
def test_the_loop_shows_a_progress_bar_when_asked(files, capsys):
    robot = Robot.from_urdf(UR5E, markers=["flange"])
    data = load_measurements(files / "train.csv", robot)
    run_loop(robot, data, candidates=["joint_scale"], elm=False, progress=True, log=None)
    assert "diagnosis" in capsys.readouterr().err


@pytest.mark.slow
def test_figures_and_evidence_without_inertials(looped, tmp_path):
    evidence = sorted(looped.glob("evidence_joint_compliance_*.png"))  # one figure per mode
    assert evidence
    for f in [looped / "errors_train.png", looped / "errors_test.png"] + evidence:
        assert f.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    # the KR5 URDF has no inertials: no torque to plot, and the evidence says so
    assert cli(["simulate", "--robot", KR5, "--poses", "80", "--effect", "joint_compliance", "--seed", "2",
                "--out", str(tmp_path / "kr5.csv")]) == 0
    robot = Robot.from_urdf(KR5, markers=["flange"])
    data = load_measurements(tmp_path / "kr5.csv", robot)
    res = run_loop(robot, data, candidates=["joint_compliance"], elm=False, log=None)
    ev = res.evidence["joint_compliance"]
    # no torque without inertials: plotting against the fitted deflection proves nothing, so the
    # joint angle stands on the x axis and the evidence says there is no independent signature
    assert ev and all(e["independent"] is False and e["xlabel"] == f"{k.split('.')[0]} angle [rad]"
                      and "no signature independent of the fit" in e["note"] for k, e in ev.items())
    assert "only says how well it follows the fit" in res.accepted[0]["evidence"]
    from torchcal.report.loop import write_loop_report
    write_loop_report(res, tmp_path / "kr5_report")
    md = (tmp_path / "kr5_report" / "report.md").read_text()
    assert res.accepted[0]["evidence"] in md and (tmp_path / "kr5_report" / "report.html").is_file()
    # lumped: compliance × mass moment, in its own unit, not a plain compliance's (issue 35 §3)
    assert "rad/N/m" not in md and "rad/N " not in md and "µrad·kg/N" in md and "µrad/(N·m)" not in md


@pytest.mark.slow
def test_reprs_are_short(files, looped):
    robot = Robot.from_urdf(UR5E, markers=["flange"])
    data = load_measurements(files / "train.csv", robot)
    res = torchcal.calibrate(robot, data)
    loop = run_loop(robot, data, candidates=["joint_scale"], elm=False, log=None)
    for obj, word in ((data, "Measurements(120 rows"), (res, "CalibrationResult(ur5e"), (loop, "LoopResult(ur5e")):
        r = repr(obj)
        assert r.startswith(word) and len(r) < 300 and "tensor" not in r
    assert "q: (N, dof)" in run_loop.__doc__ or "rad" in run_loop.__doc__
    assert "Attributes" in torchcal.pipelines.loop.run.LoopResult.__doc__
    assert quat_to_matrix(torch.tensor([1.0, 0, 0, 0])).equal(torch.eye(3))


# ----------------------------------------------------------------------------- refusals and bugs
def _raised(module: str, body: str, **names):
    """The exception a one-line function raises when it is defined in ``module``."""
    g = {"__name__": module, **names}
    exec(compile(f"def f():\n    {body}\n", f"<{module}>", "exec"), g)
    with pytest.raises(Exception) as e:
        g["f"]()
    return e.value


def test_refusals_are_raised_on_purpose_and_everything_else_is_a_bug(tmp_path):
    assert is_refusal(_raised("torchcal.x", "raise ValueError('the file is empty: give one row per pose')"))
    assert is_refusal(_raised("torchcal.x", "raise ImportError('pip install torchcal[ray]')"))
    assert is_refusal(_raised("torchcal.x", "raise NoSuchParameter('no parameter matches')",
                              NoSuchParameter=NoSuchParameter))
    assert is_refusal(_raised("elsewhere", f"open({str(tmp_path / 'none.csv')!r})"))  # the system refuses
    assert not is_refusal(_raised("torchcal.x", "return float('1,5')"))  # converted unchecked: a bug
    assert not is_refusal(_raised("numpy.x", "raise ValueError('operands could not be broadcast')"))
    assert not is_refusal(_raised("torchcal.x", "return {}['train_details']"))
    assert not is_refusal(_raised("torchcal.x", "raise KeyError('train_details')"))
    assert not is_refusal(_raised("torchcal.x", "raise RuntimeError('shape mismatch')"))


def test_a_bug_says_so_and_shows_its_traceback_under_verbose(files, tmp_path, monkeypatch, capsys):
    def broken(*a, **k):
        return {}["train_details"]
    monkeypatch.setattr("torchcal.cli.app.calibrate", broken)
    args = ["calibrate", "--robot", UR5E, "--data", str(files / "train.csv"), "--out", str(tmp_path / "o")]
    assert cli(args) == EXIT_BUG == 70
    err = capsys.readouterr().err
    assert "torchcal calibrate: internal error (a bug): KeyError: 'train_details'" in err
    assert "Rerun with --verbose for the traceback and report it" in err and "Traceback" not in err
    assert cli(args + ["--verbose"]) == EXIT_BUG
    err = capsys.readouterr().err
    assert "Traceback (most recent call last)" in err and "in broken" in err and "(a bug)" in err
    assert not (tmp_path / "o").exists()


def test_a_parameter_pattern_that_names_nothing_is_refused_not_a_bug(files, tmp_path, capsys):
    rc = cli(["calibrate", "--robot", UR5E, "--data", str(files / "train.csv"), "--free", "joint_9.*",
              "--out", str(tmp_path / "o")])
    err = capsys.readouterr().err
    assert rc == EXIT_REFUSED and "error: no parameter matches ['joint_9.*']" in err and "(a bug)" not in err


# ----------------------------------------------------------------------------- options as written
def test_plan_takes_a_box_with_negative_bounds_as_written(tmp_path, capsys):
    box = "-1.2,1.2,-1.2,1.2,0.2,1.6"
    plan = ["plan", "--robot", KR5, "--marker", "smr@flange=0,0,0", "--candidates", "300", "--select", "12",
            "--refine-steps", "0"]
    assert cli(plan + ["--reachable", box, "--seed", "-3", "--out", str(tmp_path / "a.csv")]) == 0, \
        capsys.readouterr().err
    rep = json.loads((tmp_path / "a.plan.json").read_text())
    assert rep["feasibility"]["box_m"] == [-1.2, 1.2, -1.2, 1.2, 0.2, 1.6]
    (tmp_path / "plan.yaml").write_text(f"reachable: {box}\n")  # the same from a --config file
    assert cli(plan + ["--config", str(tmp_path / "plan.yaml"), "--out", str(tmp_path / "b.csv")]) == 0
    assert json.loads((tmp_path / "b.plan.json").read_text())["feasibility"]["box_m"][0] == -1.2


# ----------------------------------------------------------------------------- markers a file has beyond those used
def _left_out_lines(err: str) -> list[str]:
    return [line for line in err.splitlines() if "left out the columns of marker(s)" in line]


@pytest.mark.slow
def test_markers_not_declared_are_left_out_with_one_line(tmp_path, capsys, caplog):
    csv = tmp_path / "two.csv"
    assert cli(["simulate", "--robot", UR5E, "--marker", "a@flange=0,0,0.05", "--marker", "b@flange=0.04,0,0.02",
                "--poses", "40", "--seed", "3", "--out", str(csv)]) == 0
    assert cli(["calibrate", "--robot", UR5E, "--marker", "a@flange=0,0,0.05", "--data", str(csv), "--holdout", "0.25",
                "--out", str(tmp_path / "o")]) == 0
    lines = _left_out_lines(capsys.readouterr().err)
    assert len(lines) == 1 and "['b']" in lines[0] and "--marker" in lines[0]
    rep = json.loads((tmp_path / "o" / "report.json").read_text())
    assert rep["n_train"] + rep["n_test"] == 40 and list(rep["stages"][-1]["train"]["per_marker"]) == ["a"]
    # the Python API: one warning through logging, and the data of a file without b's columns
    robot = Robot.from_urdf(UR5E, markers=["a@flange=0,0,0.05"])
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="torchcal"):
        got = load_measurements(csv, robot)
    assert [r.levelno for r in caplog.records] == [logging.WARNING] and "['b']" in caplog.records[0].getMessage()
    header, *rows = csv.read_text().splitlines()
    keep = [i for i, c in enumerate(header.split(",")) if not c.startswith("b.")]
    (tmp_path / "a_only.csv").write_text("\n".join(",".join(r.split(",")[i] for i in keep) for r in [header] + rows))
    ref = load_measurements(tmp_path / "a_only.csv", robot)
    assert got.marker_names == ["a"] and torch.allclose(got.positions, ref.positions, equal_nan=True)
    assert torch.equal(got.q, ref.q)
    # a declared marker that the file lacks is still refused, naming what the file has
    assert cli(["calibrate", "--robot", UR5E, "--marker", "c@flange", "--data", str(csv), "--out",
                str(tmp_path / "c")]) == 2
    err = capsys.readouterr().err
    assert "['c'] are declared but the file has no columns" in err and "'a', 'b'" in err


@pytest.mark.slow
@pytest.mark.skipif(not TIAGO.is_dir(), reason=f"the TIAGo motion-capture data is not in {TIAGO}")
def test_the_tiago_file_of_four_markers_calibrates_with_the_one_declared(tmp_path, capsys):
    rc = cli(["calibrate", "--robot", str(TIAGO / "tiago_48_hey5.urdf"), "--data", str(TIAGO / "train.csv"),
              "--test", str(TIAGO / "test.csv"), "--marker", "hand_BL@wrist_ft_tool_link", "--out", str(tmp_path / "t")])
    lines = _left_out_lines(capsys.readouterr().err)
    assert rc == 0
    assert len(lines) == 2 and all("['hand_BR', 'hand_TR', 'hand_TL']" in line for line in lines)  # train, test
    rep = json.loads((tmp_path / "t" / "report.json").read_text())
    assert (rep["n_train"], rep["n_test"]) == (37, 62)
    assert list(rep["stages"][-1]["test"]["per_marker"]) == ["hand_BL"]
