"""Shared fixtures: a KR 5 arc DH robot, a Craig-style modified-DH arm, a small tree URDF with a
mimic joint, a prismatic joint, a fixed joint and non-z axes, and the TIAGo URDF (shared data)."""
from __future__ import annotations

import math
import os
import resource
import time
from pathlib import Path

import pytest
import torch

from torchcal import Robot
from torchcal.problems.calibration import CalibrationProblem
from torchcal.kinematics.robot_data import get_robot

# The tests run many small ops: one intra-op thread is faster, and on a shared 2-core machine a
# second spinning thread made the suite 5-7x slower. Override with TORCHCAL_TEST_THREADS.
torch.set_num_threads(int(os.environ.get("TORCHCAL_TEST_THREADS", "1")))

REPO = Path(__file__).resolve().parents[1]
SHARED = REPO.parent / "shared"
TIAGO_URDF = SHARED / "data" / "tiago_mocap" / "tiago_48_hey5.urdf"

#: markers of the tree robot: two link frames, the mimic finger and an unknown point on link4
TREE_MARKERS = ["tool", "finger_a", "finger_b", "m1@link4=0.01,0.02,0.03"]

# base -> link1 (yaw, z) -> link2 (pitch, y) -> link3 (slide, prismatic along x) -> link4 (roll,
# axis 0.6 0.8 0) -> tool (fixed); link2 -> finger_a (axis -z) and link2 -> finger_b (mimic of
# finger_a_joint with multiplier -1.5 and offset 0.1, axis x).
TREE_URDF = """<?xml version="1.0"?>
<robot name="tree_mimic">
  <link name="base"/>
  <link name="link1"/>
  <link name="link2"/>
  <link name="link3"/>
  <link name="link4"/>
  <link name="tool"/>
  <link name="finger_a"/>
  <link name="finger_b"/>
  <joint name="yaw_joint" type="revolute">
    <parent link="base"/><child link="link1"/>
    <origin xyz="0.05 -0.02 0.3" rpy="0.1 -0.2 0.3"/>
    <axis xyz="0 0 1"/>
    <limit lower="-2.5" upper="2.5" effort="10" velocity="1"/>
  </joint>
  <joint name="pitch_joint" type="revolute">
    <parent link="link1"/><child link="link2"/>
    <origin xyz="0.0 0.1 0.2" rpy="0.0 0.4 0.0"/>
    <axis xyz="0 1 0"/>
    <limit lower="-2" upper="2" effort="10" velocity="1"/>
  </joint>
  <joint name="slide_joint" type="prismatic">
    <parent link="link2"/><child link="link3"/>
    <origin xyz="0.3 0.0 0.05" rpy="-0.3 0.0 0.2"/>
    <axis xyz="1 0 0"/>
    <limit lower="-0.2" upper="0.4" effort="10" velocity="1"/>
  </joint>
  <joint name="roll_joint" type="continuous">
    <parent link="link3"/><child link="link4"/>
    <origin xyz="0.1 0.05 -0.02" rpy="0.2 0.1 -0.1"/>
    <axis xyz="0.6 0.8 0"/>
  </joint>
  <joint name="tool_joint" type="fixed">
    <parent link="link4"/><child link="tool"/>
    <origin xyz="0.02 0.03 0.15" rpy="0.5 -0.4 1.0"/>
  </joint>
  <joint name="finger_a_joint" type="revolute">
    <parent link="link2"/><child link="finger_a"/>
    <origin xyz="0.1 -0.05 0.0" rpy="0 0 0.7"/>
    <axis xyz="0 0 -1"/>
    <limit lower="-1" upper="1" effort="10" velocity="1"/>
  </joint>
  <joint name="finger_b_joint" type="revolute">
    <parent link="link2"/><child link="finger_b"/>
    <origin xyz="0.1 0.05 0.01" rpy="0.3 0 -0.7"/>
    <axis xyz="1 0 0"/>
    <limit lower="-2" upper="2" effort="10" velocity="1"/>
    <mimic joint="finger_a_joint" multiplier="-1.5" offset="0.1"/>
  </joint>
</robot>
"""


def kr5_table() -> list[tuple[float, float, float, float]]:
    """KR 5 arc classic DH rows (a, d, alpha, theta) from ``robot_data``."""
    return [(j["a"], j["d"], j["alpha"], j["theta"]) for j in get_robot("kuka_kr5_arc")["joints"]]


#: Craig-style modified DH 3R arm plus a prismatic row (rows: alpha_{i-1}, a_{i-1} as a, alpha).
MODIFIED_TABLE = [
    dict(a=0.0, d=0.35, alpha=0.0, theta=0.0),
    dict(a=0.05, d=0.02, alpha=-math.pi / 2, theta=-math.pi / 2),
    dict(a=0.45, d=-0.03, alpha=0.0, theta=0.1),
    dict(a=0.04, d=0.4, alpha=math.pi / 2, theta=0.2),
]

#: SCARA-like classic DH table R-R-P-R (the third row prismatic).
SCARA_TABLE = [
    dict(a=0.325, d=0.387, alpha=0.0, theta=0.0),
    dict(a=0.275, d=0.0, alpha=math.pi, theta=0.0),
    dict(a=0.0, d=0.1, alpha=0.0, theta=0.3, type="prismatic", lower=0.0, upper=0.21),
    dict(a=0.0, d=0.05, alpha=0.0, theta=0.0),
]


#: modified DH with a prismatic row (RPR).
MODIFIED_PRISMATIC_TABLE = [
    dict(a=0.0, d=0.2, alpha=0.0, theta=0.0),
    dict(a=0.1, d=0.3, alpha=math.pi / 2, theta=0.4, type="prismatic", lower=0.0, upper=0.5),
    dict(a=0.02, d=0.05, alpha=-math.pi / 2, theta=0.0),
]


@pytest.fixture(scope="session")
def kr5() -> Robot:
    return Robot.from_dh(kr5_table(), name="kr5_arc")


@pytest.fixture(scope="session")
def modified_arm() -> Robot:
    return Robot.from_dh(MODIFIED_TABLE, convention="modified", name="craig_arm")


@pytest.fixture(scope="session")
def scara() -> Robot:
    return Robot.from_dh(SCARA_TABLE, name="scara_like")


@pytest.fixture(scope="session")
def tree_urdf() -> str:
    return TREE_URDF


@pytest.fixture(scope="session")
def tree_markers() -> list[str]:
    return list(TREE_MARKERS)


@pytest.fixture(scope="session")
def tree_robot() -> Robot:
    return Robot.from_urdf(TREE_URDF, markers=TREE_MARKERS)


@pytest.fixture(scope="session")
def tiago_path() -> Path:
    if not TIAGO_URDF.is_file():
        pytest.skip(f"TIAGo URDF not found: {TIAGO_URDF}; shared data is needed for this test")
    return TIAGO_URDF


@pytest.fixture(scope="session")
def dh_tables() -> dict:
    """name -> (rows as dicts, convention) for the DH robots above."""
    kr5 = [dict(a=a, d=d, alpha=al, theta=th) for a, d, al, th in kr5_table()]
    return {"kr5": (kr5, "classic"), "scara": (SCARA_TABLE, "classic"),
            "modified_arm": (MODIFIED_TABLE, "modified"),
            "modified_prismatic": (MODIFIED_PRISMATIC_TABLE, "modified")}


@pytest.fixture(scope="session")
def make_params():
    """``make_params(robot, seed)``: random non-zero errors (see :func:`random_params`)."""
    return random_params


@pytest.fixture(scope="session")
def make_q():
    """``make_q(robot, n, seed)``: configurations inside the limits (see :func:`random_q`)."""
    return random_q


def random_params(robot: Robot, seed: int, scale: float = 0.05, base_rot: float = 2.5,
                  base_trans: float = 1.5) -> torch.Tensor:
    """Random non-zero errors: ``scale`` (m / rad) on every entry, a base rotation vector of norm
    ``base_rot`` rad and a base translation of about ``base_trans`` m."""
    g = torch.Generator().manual_seed(seed)
    p = scale * (2 * torch.rand(robot.n_params, generator=g, dtype=torch.float64) - 1)
    ax = torch.randn(3, generator=g, dtype=torch.float64)
    p[3:6] = base_rot * ax / ax.norm()
    p[0:3] = base_trans * (2 * torch.rand(3, generator=g, dtype=torch.float64) - 1)
    return p.to(robot.dtype)


def random_q(robot: Robot, n: int, seed: int) -> torch.Tensor:
    """``(n, dof)`` configurations inside the limits (±π where a joint has none)."""
    g = torch.Generator().manual_seed(seed)
    lo, hi = (x.clone() for x in robot.joint_limits)
    lo = torch.where(torch.isfinite(lo), lo, torch.full_like(lo, -math.pi))
    hi = torch.where(torch.isfinite(hi), hi, torch.full_like(hi, math.pi))
    u = torch.rand(n, robot.dof, generator=g, dtype=torch.float64).to(robot.dtype)
    return lo + (hi - lo) * u

# ----------------------------------------------------------------------------- CPU time per test
# How a test is judged slow: its CPU seconds (this process and the children it waited for, e.g. a
# command-line run), not its wall time, which a loaded machine stretches. ``--cpu-times FILE``
# appends "cpu_s<TAB>wall_s<TAB>node id" per test (setup, call and teardown); with xdist every
# worker appends to the same file.

def pytest_addoption(parser):
    parser.addoption("--cpu-times", metavar="FILE", default=None,
                     help="append each test's CPU seconds (process + children) and wall seconds to FILE")


def _cpu_seconds() -> float:
    own, kids = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return own.ru_utime + own.ru_stime + kids.ru_utime + kids.ru_stime


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_protocol(item, nextitem):
    out = item.config.getoption("--cpu-times")
    if out is None:
        yield
        return
    cpu0, wall0 = _cpu_seconds(), time.perf_counter()
    yield
    with open(out, "a") as f:
        f.write(f"{_cpu_seconds() - cpu0:.2f}\t{time.perf_counter() - wall0:.2f}\t{item.nodeid}\n")


# ---------------------------------------------------------------------------------- shared helpers
# Imported by test files as ``from conftest import ...`` (pytest puts tests/ on sys.path).

class Recorder:
    """Wraps a batched fitness and keeps every batch it is given (copies: a solver may reuse its
    buffers)."""

    def __init__(self, fn):
        self.fn = fn
        self.batches: list[torch.Tensor] = []

    def __call__(self, X):
        self.batches.append(X.detach().clone())
        return self.fn(X)

    @property
    def points(self) -> torch.Tensor:
        return torch.cat(self.batches, 0)

    @property
    def n_points(self) -> int:
        return sum(b.shape[0] for b in self.batches)


def rank_margin(robot: Robot, template, d, rtol: float = 1e-9) -> float:
    """How many decades every singular value of the robot's column-scaled candidate Jacobian (at the
    nominal ``template``, on measurements ``d``) stands from the rank tolerance ``rtol``: a rank
    decision with a margin of several decades cannot flip by rounding, so tests may compare such
    decisions exactly across batch shapes."""
    J = CalibrationProblem(robot, template, d).full_jacobian(template.values)[:, template.free_index]
    J = J / J.norm(dim=0).clamp(min=1e-300)
    s = torch.linalg.svdvals(J)
    return float((torch.log10(s / s[0]).clamp(min=-300) - math.log10(rtol)).abs().min())


def same_run(batched, alone, rtol: float = 1e-9) -> None:
    """A run of a batch of independent runs is the run alone: the point and its fitness (to
    ``rtol``: the batch evaluates the fitness on other shapes than the run alone, so the last bits
    may differ), the history of the best fitness, and the counts and the reason to stop, exactly
    (the tests pick problems whose counts no rounding decides: a fixed iteration budget, or a
    fitness in steps). Used by the restart tests on the CPU and on CUDA."""
    torch.testing.assert_close(batched.x, alone.x, rtol=rtol, atol=rtol * float(alone.x.abs().max()))
    assert batched.fun == pytest.approx(alone.fun, rel=rtol)
    assert batched.history == pytest.approx(alone.history, rel=rtol)
    assert (batched.n_evals, batched.n_iter, batched.converged, batched.message) == \
        (alone.n_evals, alone.n_iter, alone.converged, alone.message)
    assert batched.extra == alone.extra  # the population schedule: counts, set before the run


@pytest.fixture
def torchcal_cli(capsys):
    """``torchcal ARGS`` in-process: ``run(*args, cwd=None) -> (exit status, stdout, stderr)``."""
    from torchcal.cli.app import main

    def run(*args, cwd=None) -> tuple[int, str, str]:
        old = os.getcwd()
        capsys.readouterr()
        try:
            if cwd is not None:
                os.chdir(cwd)
            try:
                rc = main([str(a) for a in args])
            except SystemExit as e:  # argparse's own refusals
                rc = e.code if isinstance(e.code, int) else 2
        finally:
            os.chdir(old)
        got = capsys.readouterr()
        return rc, got.out, got.err
    return run


UR5E_URDF = REPO / "urdf" / "ur5e.urdf"
UR5E_SMR = "smr@flange=0,0,0.05"


@pytest.fixture(scope="session")
def ur5e_csv(tmp_path_factory) -> Path:
    """60 simulated UR5e poses of one SMR on the flange (``UR5E_SMR``), as a measurement CSV."""
    from torchcal.measure.io import save_measurements
    from torchcal.sim.serial import SimConfig, simulate

    robot = Robot.from_urdf(str(UR5E_URDF), markers=[UR5E_SMR])
    data, _ = simulate(robot, SimConfig(n=60, seed=1))
    out = tmp_path_factory.mktemp("ur5e") / "train.csv"
    save_measurements(out, data)
    return out


# ----------------------------------------------------------------------------- report pages
#: held-out rows of :func:`report_data` moved by 8 mm along x
MOVED = (3, 17)


@pytest.fixture(scope="session")
def report_data(tmp_path_factory):
    """A compliant UR5e: 90 training rows with a `marker_std_mm` column, 30 held-out rows of the
    same robot of which two (:data:`MOVED`) are moved 8 mm along x. Returns (folder, median of
    the `marker_std_mm` column)."""
    import numpy as np

    from torchcal.cli.app import main as cli
    from torchcal.kinematics.robots import urdf_path

    d = tmp_path_factory.mktemp("reports_data")
    assert cli(["simulate", "--robot", str(urdf_path("ur5e")), "--poses", "120", "--effect", "joint_compliance",
                "--seed", "4", "--out", str(d / "all.csv")]) == 0
    head, *rows = (d / "all.csv").read_text().splitlines()
    spread = np.random.default_rng(0).uniform(0.015, 0.025, 90)
    (d / "train.csv").write_text("\n".join([head + ",marker_std_mm"] + [f"{r},{float(s)!r}" for r, s in
                                                                        zip(rows[:90], spread)]) + "\n")
    test = rows[90:]
    x = head.split(",").index("flange.x")
    for i in MOVED:
        v = test[i].split(",")
        v[x] = repr(float(v[x]) + 0.008)
        test[i] = ",".join(v)
    (d / "test.csv").write_text("\n".join([head] + test) + "\n")
    return d, float(np.median(spread))


@pytest.fixture(scope="session")
def looped_report(report_data, tmp_path_factory):
    """``python -m torchcal loop`` on :func:`report_data`: its output folder."""
    import subprocess
    import sys

    from torchcal.kinematics.robots import urdf_path

    d, _ = report_data
    out = tmp_path_factory.mktemp("reports_runs") / "loop"
    r = subprocess.run([sys.executable, "-m", "torchcal", "loop", "--robot", str(urdf_path("ur5e")), "--data",
                        str(d / "train.csv"), "--test", str(d / "test.csv"), "--no-elm", "--effect",
                        "joint_compliance", "--out", str(out)],
                       capture_output=True, text=True, env={**os.environ, "PYTHONPATH": str(REPO)})
    assert r.returncode == 0, r.stderr
    return out


@pytest.fixture(scope="session")
def fleet_report_out(tmp_path_factory):
    """``torchcal fleet`` on 10 simulated KR5s, robot 6 with joint_a3's offset moved 8 mrad: its
    output folder."""
    from torchcal.cli.app import main as cli
    from torchcal.kinematics.robots import shipped, urdf_path
    from torchcal.measure.io import save_measurements
    from torchcal.sim.serial import SimConfig, simulate_fleet

    robot = shipped("kuka_kr5_arc")
    cfg = SimConfig(n=30, seed=5)
    train, _, _ = simulate_fleet(robot, 10, cfg, spread=0.2e-3 / cfg.angle_error,
                                 moved={6: {"joint_a3.offset": 8e-3}})
    d = tmp_path_factory.mktemp("fleet")
    (d / "train").mkdir()
    for i, m in enumerate(train):
        save_measurements(d / "train" / f"kr5_{i:02d}.csv", m)
    assert cli(["fleet", "--robot", str(urdf_path("kuka_kr5_arc")), "--data", str(d / "train"),
                "--out", str(d / "out")]) == 0
    return d / "out"


@pytest.fixture(scope="session")
def chromium() -> str:
    """The headless Chromium to render report pages with; the test is skipped, saying so, where
    none is installed."""
    import shutil

    for name in ("chromium", "chromium-browser", "google-chrome"):
        if shutil.which(name):
            return shutil.which(name)
    pytest.skip("headless Chromium is not installed (Debian: apt-get install chromium); the HTML pages are not "
                "rendered in this run")
