"""A battery of bad inputs, run as a new user would (issue 28, "Bad input, second round").

Each case sets up its own folder, runs one CLI command (in-process, or as a subprocess where signals,
concurrency or resource limits matter) or one API call, and judges the behaviour a demanding user
expects: a refusal exits 2 and names the problem and the fix, nothing the user had changes, nothing
partial is left, no traceback unless --verbose, no silently wrong result. It prints one line per
case and a JSON summary line ``{"passed": P, "failed": F, "cases": N}``.

    PYTHONPATH=$PWD python scripts/bad_input_battery.py [-k SUBSTRING] [--keep]

It takes a few minutes (UR5e data from ``torchcal simulate``, 160 poses; small loops).
"""
from __future__ import annotations

import argparse
import contextlib
import io
import json
import math
import os
import re
import shutil
import signal
import subprocess
import sys
import tempfile
import time
import traceback
import warnings
from pathlib import Path

import numpy as np
import torch

REPO = Path(__file__).resolve().parents[1]
UR5E = str(REPO / "urdf" / "ur5e.urdf")
KR5 = str(REPO / "urdf" / "kuka_kr5_arc.urdf")
SMR = "smr@flange=0,0,0.05"
PY = sys.executable
ENV = {**os.environ, "PYTHONPATH": str(REPO)}

CASES = []


def case(fn):
    CASES.append(fn)
    return fn


# ----------------------------------------------------------------------------- running
def cli(*args, cwd=None) -> tuple[int, str, str]:
    """``torchcal ARGS`` in-process: (exit status, stdout, stderr); an escaping exception is a
    traceback (status 99)."""
    from torchcal.cli.app import main

    out, err = io.StringIO(), io.StringIO()
    old = os.getcwd()
    try:
        if cwd:
            os.chdir(cwd)
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err), warnings.catch_warnings():
            warnings.simplefilter("default")
            try:
                rc = main([str(a) for a in args])
            except SystemExit as e:
                rc = e.code if isinstance(e.code, int) else 2
            except BaseException:  # noqa: BLE001 — a traceback is what the battery looks for
                traceback.print_exc(file=err)
                err.write("Traceback (most recent call last):\n")
                rc = 99
    finally:
        os.chdir(old)
    return rc, out.getvalue(), err.getvalue()


def sub(*args, cwd=None, timeout=300, **kw) -> subprocess.CompletedProcess:
    return subprocess.run([PY, "-m", "torchcal", *map(str, args)], cwd=cwd, env=ENV, capture_output=True, text=True,
                          timeout=timeout, **kw)


def api(fn) -> tuple[BaseException | None, object]:
    try:
        with warnings.catch_warnings(record=True) as w:
            warnings.simplefilter("always")
            return None, (fn(), w)
    except BaseException as e:  # noqa: BLE001
        return e, None


def refused(rc, err, *words) -> tuple[bool, str]:
    """Exit 2, one ``error:`` line naming each of ``words`` (regexes), no traceback."""
    ok = rc == 2 and "Traceback" not in err and all(re.search(w, err, re.I | re.S) for w in words)
    return ok, f"rc={rc} " + err.strip().replace("\n", " | ")[:400]


def snapshot(folder: Path) -> dict:
    return {p.relative_to(folder).as_posix(): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def hidden_left(folder: Path) -> list[str]:
    return [p.name for p in folder.rglob(".*") if ".partial" in p.name or ".replaced" in p.name or ".lock" in p.name]


# ----------------------------------------------------------------------------- data
def data_dir(root: Path) -> Path:
    d = root / "data"
    if not (d / "all.csv").exists():
        d.mkdir(parents=True, exist_ok=True)
        rc, _, err = cli("simulate", "--robot", UR5E, "--marker", SMR, "--poses", 160, "--seed", 1, "--out",
                         d / "all.csv", "--quiet")
        assert rc == 0, err
        lines = (d / "all.csv").read_text().splitlines()
        (d / "train.csv").write_text("\n".join(lines[:101]) + "\n")
        (d / "test.csv").write_text("\n".join([lines[0]] + lines[101:161]) + "\n")
    return d


def table(path: Path) -> tuple[list[str], np.ndarray]:
    lines = path.read_text().splitlines()
    return lines[0].split(","), np.array([[float(c) for c in ln.split(",")] for ln in lines[1:]])


def write_table(path: Path, header: list[str], M: np.ndarray) -> Path:
    path.write_text(",".join(header) + "\n" + "\n".join(",".join(repr(float(v)) for v in r) for r in M) + "\n")
    return path


def edited(src: Path, dst: Path, fn) -> Path:
    h, M = table(src)
    h, M = fn(h, M.copy())
    return write_table(dst, h, M)


def fleet_dir(root: Path, name=lambda i: f"r{i}.csv", rows=lambda i, t: t) -> Path:
    """Three simulated KR 5 arcs (15 poses each), one CSV per robot: ``name(i)``, rows ``rows(i, t)``."""
    from torchcal.kinematics.robots import shipped
    from torchcal.measure.io import save_measurements
    from torchcal.sim.serial import SimConfig, simulate_fleet

    train, _, _ = simulate_fleet(shipped("kuka_kr5_arc"), 3, SimConfig(n=15, seed=3), spread=0.2)
    fl = root / "fleet"
    fl.mkdir()
    for i, t in enumerate(train):
        save_measurements(fl / name(i), rows(i, t))
    return fl


def loop(d: Path, *extra, data=None, test=None, out=None, marker=SMR, cwd=None):
    args = ["loop", "--robot", UR5E, "--data", data or d / "train.csv", "--effect", "none", "--no-elm", "--folds", 2,
            "--out", out or d.parent / "out"]
    if marker:
        args += ["--marker", marker]
    if test:
        args += ["--test", test]
    return cli(*args, *extra, cwd=cwd)


def calibrate(d: Path, *extra, data=None, test=None, out=None, marker=SMR):
    args = ["calibrate", "--robot", UR5E, "--data", data or d / "train.csv", "--out", out or d.parent / "out"]
    if marker:
        args += ["--marker", marker]
    if test:
        args += ["--test", test]
    return cli(*args, *extra)


# ============================================================================ the ten worst
@case
def force_keeps_inputs(root):
    d = data_dir(root)
    cell = root / "cell1"
    cell.mkdir()
    shutil.copy(d / "train.csv", cell)
    shutil.copy(d / "test.csv", cell)
    before = snapshot(cell)
    rc, _, err = loop(d, "--force", data=cell / "train.csv", test=cell / "test.csv", out=cell)
    ok, why = refused(rc, err, "input|reads", "out")
    return ok and snapshot(cell) == before, why


@case
def force_keeps_a_folder_torchcal_did_not_write(root):
    d = data_dir(root)
    res = root / "res"
    res.mkdir()
    (res / "notes.txt").write_text("mine")
    rc, _, err = calibrate(d, "--force", out=res)
    ok, why = refused(rc, err, "not written by torchcal|did not write|not.*torchcal", "notes.txt|choose")
    return ok and (res / "notes.txt").read_text() == "mine", why


@case
def force_replaces_own_output(root):
    d = data_dir(root)
    out = root / "o"
    rc1, _, e1 = calibrate(d, out=out)
    rc2, _, e2 = calibrate(d, "--force", out=out)
    return rc1 == 0 and rc2 == 0 and (out / "calibrated.urdf").exists() and not hidden_left(root), f"{rc1} {rc2} {e2[-300:]}"


@case
def yaml_force_quoted_false(root):
    d = data_dir(root)
    res = root / "res"
    res.mkdir()
    (res / "notes.txt").write_text("mine")
    cfg = root / "run.yaml"
    cfg.write_text(f"robot: {UR5E}\ndata: {d / 'train.csv'}\nmarker: ['{SMR}']\nout: {res}\nforce: \"false\"\n")
    rc, _, err = cli("calibrate", "--config", cfg)
    ok, why = refused(rc, err, "force", "true or false|boolean")
    return ok and (res / "notes.txt").read_text() == "mine", why


@case
def yaml_boolean_as_number(root):
    d = data_dir(root)
    cfg = root / "run.yaml"
    cfg.write_text(f"robot: {UR5E}\ndata: {d / 'train.csv'}\nmarker: ['{SMR}']\nout: {root / 'o'}\nquiet: 1\n")
    rc, _, err = cli("calibrate", "--config", cfg)
    return refused(rc, err, "quiet", "true or false|boolean")


def _two_at_once(args: list, root: Path) -> tuple[bool, str]:
    procs = [subprocess.Popen([PY, "-m", "torchcal", *map(str, args)], cwd=root, env=ENV, stdout=subprocess.PIPE,
                              stderr=subprocess.PIPE, text=True) for _ in range(2)]
    res = [(p.wait(300), p.stderr.read()) for p in procs]
    rcs = sorted(r for r, _ in res)
    errs = " | ".join(e.strip()[-300:] for _, e in res)
    # started together, the second finds the first's claim; started a moment later, its result
    ok = rcs == [0, 2] and re.search(r"another (torchcal )?run|exists", errs, re.I) is not None and "Traceback" not in errs
    return ok, f"rcs={rcs} {errs}"


@case
def two_loops_one_out(root):
    d = data_dir(root)
    return _two_at_once(["loop", "--robot", UR5E, "--marker", SMR, "--data", d / "train.csv", "--effect", "none",
                         "--no-elm", "--folds", 2, "--out", root / "o"], root)


@case
def two_simulates_one_file(root):
    return _two_at_once(["simulate", "--robot", UR5E, "--marker", SMR, "--poses", 400, "--out", root / "s.csv"],
                        root)


@case
def api_data_of_another_robot(root):
    from torchcal import Robot, calibrate as cal, load_measurements

    d = data_dir(root)
    ur = Robot.from_urdf(UR5E, markers=[SMR])
    kr = Robot.from_urdf(KR5, markers=[SMR])
    data = load_measurements(d / "train.csv", ur)
    e, _ = api(lambda: cal(kr, data))
    ok = isinstance(e, ValueError) and "ur5e" in str(e) and re.search("load_measurements", str(e)) is not None
    return ok, repr(e)[:300]


@case
def api_run_loop_data_of_another_robot(root):
    from torchcal import Robot, load_measurements, run_loop

    d = data_dir(root)
    ur = Robot.from_urdf(UR5E, markers=[SMR])
    kr = Robot.from_urdf(KR5, markers=[SMR])
    data = load_measurements(d / "train.csv", ur)
    e, _ = api(lambda: run_loop(kr, data, candidates=[], elm=False, folds=2, log=None))
    return isinstance(e, ValueError) and "ur5e" in str(e), repr(e)[:300]


@case
def frozen_marker(root):
    d = data_dir(root)

    def freeze(h, M):
        M[:, 6:9] = M[0, 6:9]
        return h, M
    f = edited(d / "train.csv", root / "frozen.csv", freeze)
    rc, _, err = calibrate(d, data=f)
    return refused(rc, err, "does not move|never moves|frozen|same position", "instrument|tracker")


@case
def frozen_marker_loop(root):
    d = data_dir(root)

    def freeze(h, M):
        M[:, 6:9] = M[0, 6:9] + 1e-6 * np.random.default_rng(0).standard_normal((len(M), 3))
        return h, M
    f = edited(d / "train.csv", root / "frozen.csv", freeze)
    rc, _, err = loop(d, data=f)
    return refused(rc, err, "does not move|never moves|frozen|same position")


@case
def units_mm_on_metres_calibrate(root):
    d = data_dir(root)
    rc, _, err = calibrate(d, "--units", "mm")
    return refused(rc, err, "--units mm", "metres")


@case
def units_mm_on_metres_loop(root):
    d = data_dir(root)
    rc, _, err = loop(d, "--units", "mm")
    return refused(rc, err, "--units mm", "metres")


@case
def units_deg_on_radians(root):
    d = data_dir(root)
    rc, _, err = calibrate(d, "--units", "deg")
    return refused(rc, err, "--units deg", "radians")


@case
def marker_on_wrong_link(root):
    d = data_dir(root)
    rc, _, err = loop(d, marker="smr@link4=0,0,0.05")
    return refused(rc, err, "wrist_2_joint", "link4", "--marker")


@case
def marker_on_wrong_link_calibrate(root):
    d = data_dir(root)
    rc, _, err = calibrate(d, marker="smr@link4=0,0,0.05")
    return refused(rc, err, "wrist_2_joint", "link4")


@case
def loop_three_rows(root):
    d = data_dir(root)
    lines = (d / "train.csv").read_text().splitlines()
    f = root / "three.csv"
    f.write_text("\n".join(lines[:4]) + "\n")
    rc, _, err = loop(d, data=f)
    ok, why = refused(rc, err, "3 rows|3 row", "at least")
    return ok and not (root / "out").exists(), why


@case
def calibrate_three_rows(root):
    d = data_dir(root)
    lines = (d / "train.csv").read_text().splitlines()
    f = root / "three.csv"
    f.write_text("\n".join(lines[:4]) + "\n")
    rc, _, err = calibrate(d, data=f)
    return refused(rc, err, "3 rows|3 row", "at least")


@case
def out_dot(root):
    d = data_dir(root)
    work = root / "work"
    work.mkdir()
    shutil.copy(d / "train.csv", work)
    rc, _, err = loop(d, data="train.csv", out=".", cwd=work)
    ok, why = refused(rc, err, "--out")
    return ok and sorted(p.name for p in work.iterdir()) == ["train.csv"], why


@case
def out_dot_calibrate(root):
    d = data_dir(root)
    work = root / "work"
    work.mkdir()
    rc, _, err = cli("calibrate", "--robot", UR5E, "--marker", SMR, "--data", d / "train.csv", "--out", ".", cwd=work)
    return rc == 0 and (work / "calibrated.urdf").exists() and not hidden_left(work) or \
        (refused(rc, err, "--out")[0] and list(work.iterdir()) == []), f"rc={rc} {err[-300:]}"


def _glitch(root, d, metres):
    def fn(h, M):
        M[17, 6] += metres
        return h, M
    return edited(d / "train.csv", root / "glitch.csv", fn)


@case
def glitch_6m_loop(root):
    d = data_dir(root)
    rc, out, err = loop(d, data=_glitch(root, d, 6.0))
    return rc == 0 and "suspect" in out + err, f"rc={rc} {err[-400:]}"


@case
def glitch_6m_calibrate_huber(root):
    d = data_dir(root)
    rc, out, err = calibrate(d, "--loss", "huber", data=_glitch(root, d, 6.0))
    return rc == 0, f"rc={rc} {err[-400:]}"


@case
def glitch_100m_loop(root):
    d = data_dir(root)
    rc, out, err = loop(d, data=_glitch(root, d, 100.0))
    return rc == 0 and "suspect" in out + err, f"rc={rc} {err[-400:]}"


# ============================================================================ silent acceptance
@case
def joints_beyond_limits(root):
    d = data_dir(root)

    def fn(h, M):
        M[: int(0.4 * len(M)), 2] = np.sign(M[: int(0.4 * len(M)), 2]) * 3.5  # elbow limit ±π
        return h, M
    f = edited(d / "train.csv", root / "lim.csv", fn)
    rc, out, err = calibrate(d, data=f)
    return ("elbow_joint" in err and re.search("limit", err) is not None), f"rc={rc} {err[-300:]}"


@case
def xacro_file(root):
    x = root / "robot.urdf.xacro"
    x.write_text('<?xml version="1.0"?>\n<robot name="r" xmlns:xacro="http://www.ros.org/wiki/xacro">\n'
                 '<xacro:macro name="arm"><link name="a"/></xacro:macro>\n<link name="base"/><link name="l1"/>\n'
                 '<joint name="j1" type="revolute"><parent link="base"/><child link="l1"/><axis xyz="0 0 1"/>'
                 '<limit lower="-1" upper="1" effort="1" velocity="1"/></joint>\n<xacro:arm/>\n</robot>\n')
    rc, _, err = cli("plan", "--robot", x, "--marker", "l1", "--out", root / "p.csv")
    ok, why = refused(rc, err, "xacro")
    return ok and not (root / "p.csv").exists(), why


@case
def fleet_upper_case_csv(root):
    fl = fleet_dir(root, name=lambda i: f"r{i}.CSV" if i == 2 else f"r{i}.csv")
    rc, out, err = cli("fleet", "--robot", KR5, "--data", fl, "--no-figures", "--out", root / "o")
    ok = (rc == 0 and "3 robots" in out) or refused(rc, err, r"r2\.CSV")[0]
    return ok, f"rc={rc} {out[-200:]} {err[-300:]}"


@case
def same_file_data_and_test(root):
    d = data_dir(root)
    rc, out, err = calibrate(d, test=d / "train.csv")
    return re.search("same file|same rows|is the training file", err, re.I) is not None, f"rc={rc} {err[-300:]}"


@case
def simulate_50m_marker_guess(root):
    rc, _, err = cli("simulate", "--robot", UR5E, "--marker", "smr@flange=0,0,50", "--poses", 10,
                     "--out", root / "s.csv")
    ok, why = refused(rc, err, "millimetres", "metres")
    return ok and not (root / "s.csv").exists(), why


@case
def calibrate_float32_robot(root):
    from torchcal import Robot, calibrate as cal, load_measurements

    d = data_dir(root)
    r32 = Robot.from_urdf(UR5E, markers=[SMR], dtype=torch.float32)
    data = load_measurements(d / "train.csv", r32)
    e, res = api(lambda: cal(r32, data))
    if e is not None:
        return isinstance(e, (ValueError, TypeError)) and "float64" in str(e), repr(e)[:300]
    r, w = res
    said = any("float32" in str(x.message) for x in w)
    return said and r.stages[-1]["train"]["mean_mm"] < 0.05, f"said={said} {r}"


@case
def correct_failed_rows(root):
    d = data_dir(root)
    out = root / "cell"
    rc, _, err = calibrate(d, out=root / "c")
    rc, _, err = loop(d, out=out)
    t = root / "targets.csv"
    t.write_text("x,y,z\n0.3,0.2,0.5\n5.0,5.0,5.0\n")
    rc, o, err = cli("correct", "--model", out / "model", "--targets", t, "--out", root / "cmd.csv",
                     "--allow-failures")
    if rc != 0:
        return False, f"rc={rc} {err[-300:]}"
    lines = (root / "cmd.csv").read_text().splitlines()
    h = lines[0].split(",")
    bad = lines[2].split(",")
    j = h.index("shoulder_pan_joint")
    return bad[j] in ("", "nan", "NaN"), lines[0] + " || " + lines[2]


# ============================================================================ tracebacks
@case
def disk_full_simulate(root):
    import resource

    def limit():
        resource.setrlimit(resource.RLIMIT_FSIZE, (20000, 20000))
    p = sub("simulate", "--robot", UR5E, "--marker", SMR, "--poses", 2000, "--out", root / "s.csv", cwd=root,
            preexec_fn=limit)
    ok = p.returncode == 2 and "Traceback" not in p.stderr and len(p.stderr.strip().splitlines()) <= 2
    left = [x.name for x in root.iterdir() if x.name != "data"]
    return ok and not left, f"rc={p.returncode} left={left} {p.stderr.strip()[-300:]}"


@case
def disk_full_loop(root):
    import resource

    d = data_dir(root)

    def limit():
        resource.setrlimit(resource.RLIMIT_FSIZE, (30000, 30000))
    p = sub("loop", "--robot", UR5E, "--marker", SMR, "--data", d / "train.csv", "--effect", "none", "--no-elm",
            "--folds", 2, "--out", root / "o", cwd=root, preexec_fn=limit)
    ok = p.returncode == 2 and "Traceback" not in p.stderr
    left = [x.name for x in root.iterdir() if x.name != "data"]
    return ok and not left, f"rc={p.returncode} left={left} {p.stderr.strip()[-300:]}"


@case
def nan_marker_guess(root):
    d = data_dir(root)
    rc, _, err = calibrate(d, marker="smr@flange=nan,0,0.05")
    return refused(rc, err, "smr@flange", "finite|number")


@case
def nan_marker_guess_simulate(root):
    rc, _, err = cli("simulate", "--robot", UR5E, "--marker", "smr@flange=0,inf,0", "--out", root / "s.csv")
    return refused(rc, err, "finite|number")


@case
def float32_run_loop(root):
    from torchcal import Robot, load_measurements, run_loop

    d = data_dir(root)
    r32 = Robot.from_urdf(UR5E, markers=[SMR], dtype=torch.float32)
    data = load_measurements(d / "train.csv", r32)
    e, res = api(lambda: run_loop(r32, data, candidates=[], elm=False, folds=2, log=None))
    if e is not None:
        return isinstance(e, (ValueError, TypeError)) and "float64" in str(e), repr(e)[:300]
    return True, "converted"


@case
def api_load_measurements_path_robot(root):
    from torchcal import load_measurements

    d = data_dir(root)
    e, _ = api(lambda: load_measurements(d / "train.csv", UR5E))
    return isinstance(e, TypeError) and "Robot.from_urdf" in str(e), repr(e)[:300]


@case
def api_run_loop_path_data(root):
    from torchcal import Robot, run_loop

    d = data_dir(root)
    ur = Robot.from_urdf(UR5E, markers=[SMR])
    e, _ = api(lambda: run_loop(ur, str(d / "train.csv"), log=None))
    return isinstance(e, TypeError) and "load_measurements" in str(e), repr(e)[:300]


@case
def api_calibrate_numpy_data(root):
    from torchcal import Robot, calibrate as cal

    ur = Robot.from_urdf(UR5E, markers=[SMR])
    e, _ = api(lambda: cal(ur, np.zeros((10, 9))))
    return isinstance(e, TypeError) and "Measurements" in str(e), repr(e)[:300]


@case
def api_calibrate_path_robot(root):
    from torchcal import Robot, calibrate as cal, load_measurements

    d = data_dir(root)
    data = load_measurements(d / "train.csv", Robot.from_urdf(UR5E, markers=[SMR]))
    e, _ = api(lambda: cal(UR5E, data))
    return isinstance(e, TypeError) and "Robot.from_urdf" in str(e), repr(e)[:300]


def _interrupt(root: Path, args: list, delay: float) -> tuple[bool, str]:
    """Ctrl-C ``delay`` seconds after the command's first log line: exit 130, one line, nothing left."""
    p = subprocess.Popen([PY, "-m", "torchcal", *map(str, args)], cwd=root, env=ENV, stdout=subprocess.PIPE,
                         stderr=subprocess.PIPE, text=True)
    first = p.stderr.readline()  # the run has started working
    time.sleep(delay)
    p.send_signal(signal.SIGINT)
    rc = p.wait(60)
    err = first + p.stderr.read()
    left = [x.name for x in root.iterdir() if x.name != "data"]
    lines = [ln for ln in err.strip().splitlines() if "interrupt" in ln.lower()]
    return rc == 130 and "Traceback" not in err and len(lines) == 1 and not left, f"rc={rc} left={left} {err[-300:]}"


@case
def sigint(root):
    d = data_dir(root)
    return _interrupt(root, ["loop", "--robot", UR5E, "--marker", SMR, "--data", d / "all.csv", "--out", root / "o"], 0)


# ============================================================================ messages that help
@case
def tab_separated(root):
    d = data_dir(root)
    f = root / "tab.csv"
    f.write_text((d / "train.csv").read_text().replace(",", "\t"))
    rc, _, err = calibrate(d, data=f)
    return refused(rc, err, "tab", "comma")


@case
def comment_before_header(root):
    d = data_dir(root)
    f = root / "c.csv"
    f.write_text("# exported by tracker X\n" + (d / "train.csv").read_text())
    rc, _, err = calibrate(d, data=f)
    return (rc == 0) or refused(rc, err, "comment|#", "line 1")[0], f"rc={rc} {err[-300:]}"


@case
def huge_value(root):
    d = data_dir(root)

    def fn(h, M):
        M[4, 1] = 1e308
        return h, M
    f = edited(d / "train.csv", root / "big.csv", fn)
    rc, _, err = calibrate(d, data=f)
    ok, why = refused(rc, err, "line 6|1e\\+308")
    return ok and not re.search(r"\d{30}", err), why


def _huge_refused(root, d, name: str, row: int, col: int, *words) -> tuple[bool, str]:
    """``calibrate`` with one cell of ``name`` (train.csv or test.csv) set to 1e308."""
    def fn(h, M):
        M[row, col] = 1e308
        return h, M
    f = edited(d / name, root / "big.csv", fn)
    rc, _, err = calibrate(d, **({"data": f} if name == "train.csv" else {"test": f}))
    ok, why = refused(rc, err, *words)
    return ok and not re.search(r"\d{30}", err), why


@case
def huge_position(root):
    return _huge_refused(root, data_dir(root), "train.csv", 4, 7, "line 6", "smr")


@case
def multi_turn_continuous(root):
    urdf = root / "ur5e_cont.urdf"
    txt = Path(UR5E).read_text()
    i = txt.index('<joint name="wrist_3_joint" type="revolute"')
    j = txt.index("</joint>", i)
    block = re.sub(r"<limit[^>]*/>", "", txt[i:j]).replace('type="revolute"', 'type="continuous"')
    urdf.write_text(txt[:i] + block + txt[j:])
    rc, _, err = cli("simulate", "--robot", urdf, "--marker", SMR, "--poses", 60, "--seed", 1, "--out", root / "a.csv",
                     "--quiet")

    def turns(h, M):
        M[:, 5] += 2 * np.pi * np.arange(len(M)) % 5 * 2  # up to 4 turns
        return h, M
    f = edited(root / "a.csv", root / "turns.csv", turns)
    rc, _, err = cli("calibrate", "--robot", urdf, "--marker", SMR, "--data", f, "--out", root / "o")
    return rc == 0 or (rc == 2 and "--units deg" not in err), f"rc={rc} {err[-300:]}"


@case
def marker_name_with_space(root):
    d = data_dir(root)
    f = root / "sp.csv"
    f.write_text((d / "train.csv").read_text().replace("smr.", "my smr.", 3))
    rc, _, err = calibrate(d, data=f, marker="my smr@flange=0,0,0.05")
    return rc == 0 or refused(rc, err, "space", "my smr|my_smr")[0], f"rc={rc} {err[-300:]}"


@case
def data_is_a_directory(root):
    d = data_dir(root)
    rc, _, err = calibrate(d, data=d)
    return refused(rc, err, "directory", "CSV|csv")


@case
def model_one_level_off(root):
    d = data_dir(root)
    out = root / "cell"
    rc, _, err = loop(d, out=out)
    t = root / "targets.csv"
    t.write_text("x,y,z\n0.3,0.2,0.5\n")
    rc, _, err = cli("correct", "--model", out, "--targets", t, "--out", root / "cmd.csv")
    return refused(rc, err, re.escape(str(out / "model")))


@case
def latin1_urdf(root):
    u = root / "latin.urdf"
    u.write_bytes(Path(UR5E).read_text().replace("<robot name=\"ur5e\"", "<!-- Gerät für Förderband -->\n<robot name=\"ur5e\"", 1)
                  .encode("latin-1"))
    rc, _, err = cli("plan", "--robot", u, "--marker", SMR, "--out", root / "p.csv")
    return refused(rc, err, "latin.urdf", "UTF-8|encoding")


@case
def units_string_deg(root):
    from torchcal import Robot, load_measurements

    d = data_dir(root)
    ur = Robot.from_urdf(UR5E, markers=[SMR])
    e, res = api(lambda: load_measurements(d / "train.csv", ur, units="deg"))
    if e is None:
        m, _ = res
        return float(m.q.abs().max()) < 0.2, "converted"  # degrees 0..~6 -> rad
    return "'d'" not in str(e), repr(e)[:300]


@case
def corrector_mm_targets(root):
    import torchcal
    from torchcal import Corrector

    d = data_dir(root)
    out = root / "cell"
    loop(d, out=out)
    model = torchcal.load(out / "model")
    e, res = api(lambda: Corrector(model).correct(torch.tensor([[300.0, 200.0, 500.0]], dtype=torch.float64)))
    if e is not None:
        return "millimetres" in str(e) and "1000" in str(e), repr(e)[:300]
    return False, "accepted"


@case
def covariate_missing_in_test(root):
    d = data_dir(root)

    def temp(h, M):
        return h + ["temperature"], np.c_[M, 20 + np.arange(len(M)) * 0.05]
    f = edited(d / "train.csv", root / "t.csv", temp)
    rc, _, err = cli("loop", "--robot", UR5E, "--marker", SMR, "--data", f, "--test", d / "test.csv",
                     "--effect", "thermal_drift", "--no-elm", "--folds", 2, "--out", root / "o")
    ok, why = refused(rc, err, "temperature", "test.csv")
    return ok and "stage geometric" not in err and "noise estimate" not in err, why


@case
def yaml_unknown_key_lists_no_hidden_option(root):
    d = data_dir(root)
    cfg = root / "run.yaml"
    cfg.write_text(f"robot: {UR5E}\ndata: {d / 'train.csv'}\nout: o\nfolds2: 3\n")
    rc, _, err = cli("loop", "--config", cfg)
    ok, why = refused(rc, err, "folds2", "folds")
    return ok and "'command'" not in err, why


@case
def yaml_hidden_option_refused(root):
    d = data_dir(root)
    cfg = root / "run.yaml"
    cfg.write_text(f"robot: {UR5E}\ndata: {d / 'train.csv'}\nmarker: ['{SMR}']\nout: o\ncommand: rm -rf\n")
    rc, _, err = cli("loop", "--config", cfg)
    return refused(rc, err, "command")


@case
def cli_message_names_no_api(root):
    d = data_dir(root)
    rc, _, err = calibrate(d, "--free", "nothing_matches*")
    bad = re.search(r"ParamSet|\.unfix|urdf_links\(|Robot\.from_urdf|load_measurements\(", err)
    return rc == 2 and bad is None and "--free" in err, f"rc={rc} {err[-300:]}"


@case
def cli_unknown_marker_column_names_no_api(root):
    d = data_dir(root)
    f = root / "x.csv"
    f.write_text((d / "train.csv").read_text().replace("smr.", "tool.", 3))
    rc, _, err = calibrate(d, data=f, marker=None)
    bad = re.search(r"ParamSet|\.unfix|urdf_links\(|Robot\.from_urdf|load_measurements\(", err)
    return rc == 2 and bad is None and "--marker" in err, f"rc={rc} {err[-300:]}"


@case
def cli_no_marker_names_no_api(root):
    d = data_dir(root)
    f = root / "x.csv"
    f.write_text((d / "train.csv").read_text().replace("smr.", "tool.", 3))
    rc, _, err = calibrate(d, data=f, marker="smr@flange")
    bad = re.search(r"ParamSet|\.unfix|urdf_links\(|Robot\.from_urdf|load_measurements\(", err)
    return rc == 2 and bad is None and "--marker" in err, f"rc={rc} {err[-300:]}"


# ============================================================================ noise
@case
def quiet_run_has_no_raw_warnings(root):
    d = data_dir(root)
    p = sub("loop", "--robot", UR5E, "--marker", SMR, "--data", d / "train.csv", "--test", d / "test.csv",
            "--out", root / "o", cwd=root)
    raw = re.findall(r"Warning:|warnings.warn|^\s+\w.*\(.*\)$", p.stderr, re.M)
    return p.returncode == 0 and not raw, f"rc={p.returncode} {raw[:3]} {p.stderr[-300:]}"


@case
def rank_ambiguous_once(root):
    d = data_dir(root)
    p = sub("calibrate", "--robot", UR5E, "--marker", "smr@flange=0,0,0", "--data", d / "train.csv", "--out",
            root / "o", cwd=root)
    raw = re.findall(r"RuntimeWarning|UserWarning|warnings.warn", p.stderr)
    return p.returncode in (0, 2) and not raw and "Traceback" not in p.stderr, f"rc={p.returncode} {p.stderr[-400:]}"


# ============================================================================ more of each class
@case
def force_output_is_the_urdf(root):
    u = root / "robot.urdf"
    shutil.copy(UR5E, u)
    before = u.read_bytes()
    rc, _, err = cli("simulate", "--robot", u, "--marker", SMR, "--poses", 10, "--out", u, "--force")
    ok, why = refused(rc, err, "input")
    return ok and u.read_bytes() == before, why


@case
def force_correct_out_is_targets(root):
    t = root / "targets.csv"
    t.write_text("x,y,z\n0.3,0.2,0.5\n")
    rc, _, err = cli("correct", "--model", root / "nomodel", "--targets", t, "--out", t, "--force")
    ok, why = refused(rc, err, "input")
    return ok and t.read_text() == "x,y,z\n0.3,0.2,0.5\n", why


@case
def force_config_inside_out(root):
    d = data_dir(root)
    out = root / "cell"
    rc, _, _ = calibrate(d, out=out)
    before = snapshot(out)
    rc, _, err = cli("calibrate", "--config", out / "run.yaml", "--force")
    ok, why = refused(rc, err, "input")
    return ok and snapshot(out) == before, why


@case
def force_fleet_out_is_data(root):
    fl = fleet_dir(root)
    before = snapshot(fl)
    rc, _, err = cli("fleet", "--robot", KR5, "--data", fl, "--out", fl, "--force", "--no-figures")
    ok, why = refused(rc, err, "input")
    return ok and snapshot(fl) == before, why


@case
def out_dotdot(root):
    d = data_dir(root)
    work = root / "a" / "b"
    work.mkdir(parents=True)
    rc, _, err = cli("calibrate", "--robot", UR5E, "--marker", SMR, "--data", d / "train.csv", "--out", "..",
                     "--force", cwd=work)
    ok, why = refused(rc, err, "current directory|--out")
    return ok and sorted(x.name for x in (root / "a").iterdir()) == ["b"], why


@case
def yaml_list_for_one_value(root):
    d = data_dir(root)
    cfg = root / "run.yaml"
    cfg.write_text(f"robot: [{UR5E}, {KR5}]\ndata: {d / 'train.csv'}\nmarker: ['{SMR}']\nout: o\n")
    rc, _, err = cli("calibrate", "--config", cfg)
    return refused(rc, err, "robot", "one value")


@case
def frozen_for_twenty_rows(root):
    d = data_dir(root)

    def freeze(h, M):
        M[30:50, 6:9] = M[30, 6:9]
        return h, M
    f = edited(d / "train.csv", root / "stale.csv", freeze)
    rc, _, err = calibrate(d, data=f)
    return refused(rc, err, "line 3[23]|lines|same position|repeat")


@case
def glitch_in_test_file(root):
    d = data_dir(root)

    def fn(h, M):
        M[5, 7] += 6.0
        return h, M
    t = edited(d / "test.csv", root / "tglitch.csv", fn)
    rc1, _, e1 = calibrate(d, test=t, out=root / "c")
    rc2, _, e2 = loop(d, test=t, out=root / "l")
    return rc1 == 0 and rc2 == 0, f"{rc1} {rc2} {e1[-200:]} {e2[-200:]}"


@case
def glitch_1e5_metres(root):
    d = data_dir(root)
    rc, _, err = calibrate(d, data=_glitch(root, d, 1e5))
    return rc == 0, f"rc={rc} {err[-300:]}"


@case
def five_rows_everywhere_one_rule(root):
    d = data_dir(root)
    lines = (d / "train.csv").read_text().splitlines()
    f = root / "five.csv"
    f.write_text("\n".join(lines[:6]) + "\n")
    rc1, _, e1 = calibrate(d, data=f, out=root / "c")
    rc2, _, e2 = loop(d, data=f, out=root / "l")
    ok1, w1 = refused(rc1, e1, "at least \\d+ poses")
    ok2, w2 = refused(rc2, e2, "at least \\d+ poses")
    return ok1 and ok2, w1 + " || " + w2


@case
def fleet_three_rows(root):
    fl = fleet_dir(root, rows=lambda i, t: t.subset(range(3)) if i == 1 else t)
    rc, _, err = cli("fleet", "--robot", KR5, "--data", fl, "--out", root / "o", "--no-figures")
    return refused(rc, err, "r1", "at least \\d+ poses")


@case
def marker_on_the_base_link(root):
    d = data_dir(root)
    rc, _, err = calibrate(d, marker="smr@link0=0,0,0.05")
    return refused(rc, err, "link0")


@case
def xacro_calibrate(root):
    d = data_dir(root)
    x = root / "ur5e.urdf.xacro"
    shutil.copy(UR5E, x)
    rc, _, err = cli("calibrate", "--robot", x, "--marker", SMR, "--data", d / "train.csv", "--out", root / "o")
    return refused(rc, err, "xacro first")


@case
def latin1_urdf_calibrate(root):
    d = data_dir(root)
    u = root / "latin.urdf"
    u.write_bytes(Path(UR5E).read_text().replace("<robot name=\"ur5e\"", "<!-- für -->\n<robot name=\"ur5e\"", 1)
                  .encode("latin-1"))
    rc, _, err = cli("calibrate", "--robot", u, "--marker", SMR, "--data", d / "train.csv", "--out", root / "o")
    return refused(rc, err, "latin.urdf", "UTF-8")


@case
def api_calibrate_path_test(root):
    from torchcal import Robot, calibrate as cal, load_measurements

    d = data_dir(root)
    ur = Robot.from_urdf(UR5E, markers=[SMR])
    data = load_measurements(d / "train.csv", ur)
    e, _ = api(lambda: cal(ur, data, test=str(d / "test.csv")))
    return isinstance(e, TypeError) and "load_measurements" in str(e), repr(e)[:300]


@case
def api_run_loop_path_robot(root):
    from torchcal import Robot, load_measurements, run_loop

    d = data_dir(root)
    data = load_measurements(d / "train.csv", Robot.from_urdf(UR5E, markers=[SMR]))
    e, _ = api(lambda: run_loop(UR5E, data, log=None))
    return isinstance(e, TypeError) and "Robot.from_urdf" in str(e), repr(e)[:300]


@case
def api_load_measurements_numpy_robot(root):
    from torchcal import load_measurements

    d = data_dir(root)
    e, _ = api(lambda: load_measurements(d / "train.csv", np.zeros(6)))
    return isinstance(e, TypeError) and "Robot" in str(e), repr(e)[:300]


@case
def api_fleet_paths(root):
    from torchcal.kinematics.robots import shipped
    from torchcal.pipelines.fleet.run import calibrate_fleet

    d = data_dir(root)
    e, _ = api(lambda: calibrate_fleet(shipped("kuka_kr5_arc"), [str(d / "train.csv")] * 3))
    return isinstance(e, TypeError) and "load_measurements" in str(e), repr(e)[:300]


@case
def numpy_header_comment(root):
    d = data_dir(root)
    f = root / "np.csv"
    f.write_text("# " + (d / "train.csv").read_text())
    rc, _, err = calibrate(d, data=f)
    return refused(rc, err, "#", "header")


@case
def data_empty_directory(root):
    d = data_dir(root)
    (root / "empty").mkdir()
    rc, _, err = calibrate(d, data=root / "empty")
    return refused(rc, err, "directory")


@case
def model_json_given(root):
    d = data_dir(root)
    out = root / "cell"
    loop(d, out=out)
    t = root / "targets.csv"
    t.write_text("x,y,z\n0.3,0.2,0.5\n")
    rc, _, err = cli("correct", "--model", out / "model" / "model.json", "--targets", t, "--out", root / "cmd.csv")
    return refused(rc, err, re.escape(str(out / "model")))


@case
def huge_value_in_test(root):
    return _huge_refused(root, data_dir(root), "test.csv", 2, 0, "big.csv", "line 4")


@case
def huge_target(root):
    d = data_dir(root)
    out = root / "cell"
    loop(d, out=out)
    t = root / "targets.csv"
    t.write_text("x,y,z\n1e308,0.2,0.5\n")
    rc, _, err = cli("correct", "--model", out / "model", "--targets", t, "--out", root / "cmd.csv")
    ok, why = refused(rc, err, "targets.csv")
    return ok and not re.search(r"\d{30}", err), why


@case
def marker_guess_two_numbers(root):
    d = data_dir(root)
    rc, _, err = calibrate(d, marker="smr@flange=0,0.05")
    return refused(rc, err, "3", "x,y,z")


@case
def sigint_in_the_diagnosis(root):
    d = data_dir(root)
    return _interrupt(root, ["loop", "--robot", UR5E, "--marker", SMR, "--data", d / "all.csv", "--out", root / "o",
                             "--verbose"], 1.5)


@case
def limits_warning_once_in_words(root):
    d = data_dir(root)

    def fn(h, M):
        M[:40, 2] = np.sign(M[:40, 2]) * 3.5
        return h, M
    f = edited(d / "train.csv", root / "lim.csv", fn)
    p = sub("calibrate", "--robot", UR5E, "--marker", SMR, "--data", f, "--out", root / "o", cwd=root)
    n = p.stderr.count("beyond its URDF limits")
    return n == 1 and "warnings.warn" not in p.stderr and "UserWarning" not in p.stderr, f"n={n} {p.stderr[-300:]}"


@case
def refused_run_makes_no_folders(root):
    d = data_dir(root)
    rc, _, err = calibrate(d, "--units", "mm", out=root / "new" / "deeper" / "o")
    ok, why = refused(rc, err, "--units mm")
    return ok and not (root / "new").exists(), why


# ============================================================================ issue 36: the third round
# one case per class (faults, data, environment, messages) and one per item of the ten worst; the
# names start with r3_ (run them alone with -k r3_)
@case
def r3_mimic_multiplier_zero(root):
    from torchcal import Robot

    urdf = (REPO / "tests" / "conftest.py").read_text().split('TREE_URDF = """', 1)[1].split('"""', 1)[0]
    tip = "tip@finger_b=0,0.05,0.02"
    r = Robot.from_urdf(urdf.replace('multiplier="-1.5"', 'multiplier="0"'), markers=[tip])
    q = torch.zeros(2, r.dof, dtype=torch.float64)
    q[1, r.joint_names.index("finger_a_joint")] = 0.8
    gap = float((r.positions(q)[0] - r.positions(q)[1]).norm())
    return gap < 1e-12, f"the marker moved {gap * 1e3:.3f} mm with a mimic multiplier of 0"


@case
def r3_model_json_edited(root):
    d = data_dir(root)
    out = root / "cell"
    loop(d, out=out)
    f = out / "model" / "model.json"
    meta = json.loads(f.read_text())
    meta["robot"]["markers"][0]["xyz"][2] += 0.1
    f.write_text(json.dumps(meta))
    t = root / "targets.csv"
    t.write_text("x,y,z\n0.3,0.2,0.5\n")
    rc, _, err = cli("correct", "--model", out / "model", "--targets", t, "--out", root / "cmd.csv")
    ok, why = refused(rc, err, "checksum", "save the model again|restore")
    return ok and not (root / "cmd.csv").exists(), why


@case
def r3_mirrored_target(root):
    from torchcal import Robot
    from torchcal.kinematics.ik import target_frames

    r = Robot.from_urdf(UR5E, markers=[SMR])
    T = torch.eye(4, dtype=torch.float64)[None].clone()
    T[0, :3, 3] = torch.tensor([0.3, 0.2, 0.5])
    T[0, :3, 1] *= -1
    e, _ = api(lambda: target_frames(r, T))
    return isinstance(e, ValueError) and "mirrored" in str(e), repr(e)


@case
def r3_force_keeps_user_file(root):
    d = data_dir(root)
    out = root / "o"
    calibrate(d, out=out)
    (out / "notes.txt").write_text("mine")
    rc, _, err = calibrate(d, "--force", out=out)
    kept = (out / "notes.txt").exists() and (out / "notes.txt").read_text() == "mine"
    return rc == 0 and kept and "notes.txt" in err and not hidden_left(root), f"rc={rc} kept={kept} {err[-300:]}"


@case
def r3_urdf_axis_nan(root):
    d = data_dir(root)
    bad = root / "bad.urdf"
    bad.write_text(Path(UR5E).read_text().replace('<axis xyz="0.0 0.0 1.0"/>', '<axis xyz="nan 1 0"/>', 1))
    rc, _, err = cli("calibrate", "--robot", bad, "--marker", SMR, "--data", d / "train.csv", "--out", root / "o")
    return refused(rc, err, r"bad\.urdf, line \d+", "axis", "finite")


@case
def r3_urdf_bom(root):
    d = data_dir(root)
    bom = root / "bom.urdf"
    bom.write_bytes(b"\xef\xbb\xbf" + Path(UR5E).read_bytes())
    rc, _, err = cli("calibrate", "--robot", bom, "--marker", SMR, "--data", d / "train.csv", "--out", root / "o")
    return rc == 0 and "File name too long" not in err, f"rc={rc} {err[-300:]}"


@case
def r3_one_pose_repeated(root):
    d = data_dir(root)
    lines = (d / "train.csv").read_text().splitlines()
    f = root / "same.csv"
    f.write_text("\n".join([lines[0]] + [lines[1]] * 100) + "\n")
    rc, _, err = calibrate(d, "--prior", "none", data=f)
    return refused(rc, err, "never moved")


@case
def r3_data_and_holdout_conflict(root):
    d = data_dir(root)
    rc, _, err = calibrate(d, "--holdout", "0.3", test=d / "test.csv")
    return refused(rc, err, "--test and --holdout")


@case
def r3_repeated_data_option(root):
    d = data_dir(root)
    rc, _, err = calibrate(d, "--data", d / "test.csv")
    return refused(rc, err, "--data takes one value")


@case
def r3_sigterm_leaves_no_lock(root):
    d = data_dir(root)
    p = subprocess.Popen([PY, "-m", "torchcal", "loop", "--robot", UR5E, "--marker", SMR, "--data", d / "all.csv",
                          "--out", root / "o"], cwd=root, env=ENV, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                         text=True)
    time.sleep(6.0)
    p.send_signal(signal.SIGTERM)
    _, err = p.communicate(timeout=120)
    left = [x.name for x in root.iterdir() if x.name != "data"]
    return p.returncode == 143 and "terminated" in err and not left, f"rc={p.returncode} left={left} {err[-300:]}"


@case
def r3_force_on_a_fifo(root):
    fifo = root / "pipe"
    os.mkfifo(fifo)
    rc, _, err = cli("simulate", "--robot", UR5E, "--marker", SMR, "--poses", 5, "--out", fifo, "--force")
    ok, why = refused(rc, err, "FIFO")
    return ok and fifo.is_fifo(), why


@case
def r3_faults_stdout_full(root):
    d = data_dir(root)
    with open("/dev/full", "w") as full:
        p = subprocess.run([PY, "-m", "torchcal", "calibrate", "--robot", UR5E, "--marker", SMR, "--data",
                            d / "train.csv", "--out", root / "o"], cwd=root, env=ENV, stdout=full,
                           stderr=subprocess.PIPE, text=True, timeout=300)
    ok = "nothing was written" not in p.stderr and "complete" in p.stderr and (root / "o" / "calibrated.urdf").exists()
    return ok and p.returncode not in (0, 70) and "Traceback" not in p.stderr, f"rc={p.returncode} {p.stderr[-300:]}"


@case
def r3_data_blank_lines_keep_line_numbers(root):
    d = data_dir(root)
    lines = (d / "train.csv").read_text().splitlines()
    bad = lines[:3] + ["", ""] + lines[3:]
    bad[7] = "x," + bad[7].split(",", 1)[1]  # line 8 of the file
    f = root / "blank.csv"
    f.write_text("\n".join(bad) + "\n")
    rc, _, err = calibrate(d, data=f)
    return refused(rc, err, "line 8")


@case
def r3_environment_threads_zero_and_backend(root):
    d = data_dir(root)
    args = [PY, "-m", "torchcal", "calibrate", "--robot", UR5E, "--marker", SMR, "--data", d / "train.csv"]
    a = subprocess.run(args + ["--out", root / "a"], env={**ENV, "TORCHCAL_THREADS": "0"}, capture_output=True,
                       text=True, timeout=300)
    b = subprocess.run(args + ["--out", root / "b"], env={**ENV, "MPLBACKEND": "module://nowhere.backend"},
                       capture_output=True, text=True, timeout=300)
    ok = a.returncode == 2 and "TORCHCAL_THREADS" in a.stderr and b.returncode == 0
    return ok and "Traceback" not in a.stderr + b.stderr, f"{a.returncode} {b.returncode} {(a.stderr + b.stderr)[-300:]}"


@case
def r3_messages_name_too_long_is_not_the_disk(root):
    d = data_dir(root)
    rc, _, err = calibrate(d, out=root / ("x" * 300))
    return refused(rc, err, "too long|shorter") if "free some space" not in err else (False, err[-300:])


# ----------------------------------------------------------------------------- main
def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("-k", default="", help="run only the cases whose name contains this")
    ap.add_argument("--keep", action="store_true", help="keep the case folders")
    a = ap.parse_args()
    torch.set_num_threads(1)
    base = Path(tempfile.mkdtemp(prefix="torchcal-battery-"))
    shared = base / "shared"
    shared.mkdir()
    data_dir(shared)
    passed, failed = [], []
    for fn in CASES:
        if a.k not in fn.__name__:
            continue
        root = base / fn.__name__
        root.mkdir()
        os.symlink(shared / "data", root / "data")
        t = time.perf_counter()
        try:
            ok, why = fn(root)
        except BaseException as e:  # noqa: BLE001
            ok, why = False, "battery error: " + "".join(traceback.format_exception_only(type(e), e)).strip()
        (passed if ok else failed).append(fn.__name__)
        print(f"{'PASS' if ok else 'FAIL'}  {fn.__name__:<44} {time.perf_counter() - t:5.1f}s  "
              f"{'' if ok else why}", flush=True)
    if not a.keep:
        shutil.rmtree(base, ignore_errors=True)
    print(json.dumps({"passed": len(passed), "failed": len(failed), "cases": len(passed) + len(failed),
                      "failed_cases": failed}))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
