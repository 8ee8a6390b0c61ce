#!/usr/bin/env python
"""Issue 33's speed figures, measured in one run against the tree before the change.

Each figure runs in a fresh Python process, once with this tree's ``torchcal`` and once with the
base tree's (a git worktree of ``--base-commit``, made under ``--base-dir`` when missing), so both
meet the same machine at the same time. Figures:

* ``import_torch``, ``import_torchcal``, ``help``: wall time of ``python -c "import torch"``,
  ``python -c "import torchcal"`` and ``python -m torchcal --help`` (the least of ``--reps`` runs:
  the machine may be shared, and the least is the cost without interference).
* ``loop_arm9``: :func:`~torchcal.pipelines.loop.run.run_loop` (as ``torchcal loop`` runs it) on the
  independent simulator's 9-joint arm (``arm9_mocap``: 45 training and 16 held-out rows).
* ``loop_demo``: the loop of ``scripts/demo.py`` (KR5 arc, 300 + 150 poses, an undeclared tool's
  joint compliance), on the data the demo writes and reads back.
* ``report_demo``: writing the demo's loop report (``write_loop_report``) after the loop.
* ``fleet_page``: ``save_fleet`` (``FleetResult.save`` before) with figures on a simulated fleet (``--fleet`` KR5 robots),
  per robot page.
* Real arms, small sets (the data in ``../shared/data``; skipped, with a message, where it is absent):
  ``loop_tiago``: the TIAGo's 37 training postures, marker hand_BL (as ``scripts/tiago_loop.py``);
  ``loop_ur10_17`` and ``loop_ur10_45``: 17 and 45 rows of the IPA UR10 tracker export drawn at random
  (seed 0), 300 others held out. The export is read once by this tree and handed to both trees as
  tensors (the base tree has no reader for its decimal commas and degrees).

Compute figures are CPU seconds of the worker process (``time.process_time``; wall seconds too):
on a shared machine wall time measures the neighbours. Each worker also returns what the loop
decided and the fitted parameters, so the JSON says whether both trees decided the same and how
far the parameters are apart.

Prints a table to stderr and one JSON line to stdout: per figure the base's and this tree's
seconds and base / new, the bars of issue 33 and whether each is met.

Usage: python scripts/bench_speed.py [--base-commit bb752dd] [--base-dir /tmp/torchcal-base]
       [--reps 3] [--only loop_arm9,loop_demo] [--fleet 6] [--data ../shared/data] [--save out/bench_speed]
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
BASE_COMMIT = "bb752dd"
FIGURES = ("import_torch", "import_torchcal", "help", "loop_arm9", "loop_demo", "report_demo", "fleet_page",
           "loop_tiago", "loop_ur10_17", "loop_ur10_45")
REAL_ARMS = ("loop_tiago", "loop_ur10_17", "loop_ur10_45")  # need ../shared/data
LOOPS = ("loop_arm9", "loop_demo", *REAL_ARMS)
DATA = ROOT.parent / "shared" / "data"


# ----------------------------------------------------------------------------- workers (one tree each)
def _loop_summary(res) -> dict:
    """What a loop decided and fitted, comparable across trees."""
    model = res.model()
    geo = model.params if hasattr(model, "params") else None
    out = {"geometric": res.geometric.get("chosen"), "accepted": [a["name"] for a in res.accepted],
           "candidates": [[c.get("name"), c.get("round"), bool(c.get("accepted"))] for c in res.candidates],
           "elm": res.elm is not None, "test_mm": [s["test"]["mean_mm"] for s in res.stages]}
    if geo is not None:
        out["names"], out["values"] = list(geo.names), [float(v) for v in geo.values.tolist()]
    return out


def _timed(fn):
    t, c = time.perf_counter(), time.process_time()
    out = fn()
    return out, time.perf_counter() - t, time.process_time() - c


def worker_loop_arm9() -> dict:
    from torchcal import Robot
    from torchcal.pipelines.loop.run import run_loop
    from torchcal.sim.cases import make_case

    c = make_case("arm9_mocap", 0)
    u = Path(tempfile.mkdtemp()) / "robot.urdf"
    u.write_text(c.urdf)
    robot = Robot.from_urdf(u, markers=c.markers)
    train, test = c.train.to_measurements(), c.test.to_measurements()
    res, wall, cpu = _timed(lambda: run_loop(robot, train, test, seed=0, log=None))
    return {"wall_s": wall, "cpu_s": cpu, **_loop_summary(res)}


def worker_loop_demo() -> dict:
    """The demo's data and loop (scripts/demo.py steps 1 and 2), then its report."""
    import torch

    from torchcal import Robot, load_measurements, run_loop
    from torchcal.report.loop import write_loop_report
    from torchcal.sim.serial import SimConfig, random_configs, simulated_robot, write_dataset

    out = Path(tempfile.mkdtemp())
    robot = Robot.from_urdf(ROOT / "urdf" / "kuka_kr5_arc.urdf", markers=["smr@flange=0,0,0"])
    cfg = SimConfig(n=450, noise=0.02e-3, seed=0)
    real = simulated_robot(robot, cfg, ["joint_compliance"], options={"joint_compliance": {"compliance": 5e-5}},
                           true_params=None)
    real.truth["smr.dx"], real.truth["smr.dy"], real.truth["smr.dz"] = 0.012, -0.008, 0.035
    q = random_configs(robot, cfg.n, torch.Generator().manual_seed(1))
    data = real.measure(q)
    write_dataset(out / "train.csv", data.subset(range(300)), real.truth, out / "truth.json",
                  meta={"noise_mm": 0.02, "effects": real.effects})
    write_dataset(out / "test.csv", data.subset(range(300, 450)))
    train, test = load_measurements(out / "train.csv", robot), load_measurements(out / "test.csv", robot)
    res, wall, cpu = _timed(lambda: run_loop(robot, train, test, seed=0, log=None))
    _, rwall, rcpu = _timed(lambda: write_loop_report(res, out / "report", command="bench_speed"))
    return {"wall_s": wall, "cpu_s": cpu, "report_wall_s": rwall, "report_cpu_s": rcpu, **_loop_summary(res)}


def worker_loop_tiago(data: Path) -> dict:
    from torchcal import Robot, load_measurements, run_loop

    urdf, names = data / "tiago_48_hey5.urdf", [f"hand_{c}@wrist_ft_tool_link" for c in ("BL", "BR", "TR", "TL")]
    every, robot = Robot.from_urdf(urdf, markers=names), Robot.from_urdf(urdf, markers=names[:1])
    train = load_measurements(data / "train.csv", every).select_markers(["hand_BL"])
    test = load_measurements(data / "test.csv", every).select_markers(["hand_BL"])
    res, wall, cpu = _timed(lambda: run_loop(robot, train, test, seed=0, log=None))
    return {"wall_s": wall, "cpu_s": cpu, **_loop_summary(res)}


def ur10_tensors(data: Path, out: Path) -> Path:
    """The IPA UR10 export read by this tree, saved as the tensors of its rows (what both trees read)."""
    import torch

    sys.path.insert(0, str(ROOT / "scripts"))
    import ipa_ur10

    _, d = ipa_ur10.read(data)
    torch.save({"q": d.q, "positions": d.positions, "quaternions": d.quaternions, "marker_names": d.marker_names,
                "joint_names": d.joint_names, "covariates": d.covariates, "robot": d.robot}, out)
    return out


def worker_loop_ur10(tensors: Path, n_train: int) -> dict:
    import torch

    from torchcal import Robot, run_loop
    from torchcal.measure.data import Measurements
    from torchcal.sim.ur10 import ur10_urdf

    d = torch.load(tensors)
    robot = Robot.from_urdf(ur10_urdf(), markers=["tmac@flange=0,0,0.109"])
    order = torch.randperm(d["q"].shape[0], generator=torch.Generator().manual_seed(0))

    def rows(idx):
        return Measurements(q=d["q"][idx], positions=d["positions"][idx], quaternions=d["quaternions"][idx],
                            marker_names=d["marker_names"], joint_names=d["joint_names"], robot=d["robot"],
                            covariates={k: v[idx] for k, v in d["covariates"].items()})
    train, test = rows(order[:n_train]), rows(order[n_train:n_train + 300])
    res, wall, cpu = _timed(lambda: run_loop(robot, train, test, seed=0, log=None))
    return {"wall_s": wall, "cpu_s": cpu, **_loop_summary(res)}


def worker_fleet_page(n_robots: int) -> dict:
    from torchcal import Robot
    from torchcal.pipelines.fleet.run import calibrate_fleet
    from torchcal.sim.serial import SimConfig, simulate_fleet

    robot = Robot.from_urdf(ROOT / "urdf" / "kuka_kr5_arc.urdf", markers=["smr@flange=0,0,0"])
    data, test, _ = simulate_fleet(robot, n_robots, SimConfig(n=60, seed=0), n_test=20)
    fr = calibrate_fleet(robot, data, test=test)
    try:  # the tree after issue 33: results are records, report/ writes them
        from torchcal.report.fleet import save_fleet
    except ImportError:  # the tree before: the result saved itself
        def save_fleet(r, out, figures):
            return r.save(out, figures=figures)
    _, wall, cpu = _timed(lambda: save_fleet(fr, Path(tempfile.mkdtemp()) / "fleet", figures=True))
    return {"wall_s": wall / n_robots, "cpu_s": cpu / n_robots, "n_robots": n_robots}


# ----------------------------------------------------------------------------- the driver
def _env(tree: Path) -> dict:
    env = dict(os.environ, PYTHONPATH=str(tree), OMP_NUM_THREADS="1", TORCHCAL_THREADS="1", MPLBACKEND="Agg")
    return env


def _wall(cmd: list[str], trees: dict[str, Path], reps: int) -> dict[str, float]:
    """The least wall time of ``cmd`` per tree over ``reps`` runs, the trees taking turns (so that both
    meet the same load on a shared machine)."""
    best = {tag: float("inf") for tag in trees}
    for _ in range(reps):
        for tag, tree in trees.items():
            t = time.perf_counter()
            subprocess.run(cmd, cwd=tree, env=_env(tree), check=True, capture_output=True)
            best[tag] = min(best[tag], time.perf_counter() - t)
    return best


def _worker(name: str, tree: Path, fleet: int, data: str | None = None) -> dict:
    cmd = [sys.executable, str(Path(__file__).resolve()), "--worker", name, "--fleet", str(fleet)] \
        + (["--data", data] if data else [])
    p = subprocess.run(cmd, cwd=tree, env=_env(tree), check=True, capture_output=True, text=True)
    return json.loads(p.stdout.strip().splitlines()[-1])


def _base_tree(commit: str, where: Path) -> Path:
    if not (where / "torchcal").is_dir():
        subprocess.run(["git", "-C", str(ROOT), "worktree", "add", "--detach", str(where), commit], check=True,
                       capture_output=True)
    return where


def _same(a: dict, b: dict) -> tuple[bool, float | None]:
    """Whether two loop summaries decided the same (the geometric set, the effects accepted, the
    ELM; and every candidate both trees tried, judged alike: a tree may try a family the other does
    not have, which then changes no decision), and the largest parameter difference."""
    keys = ("geometric", "accepted", "elm")
    tried_b = {(c[0], c[1]): c[2] for c in b.get("candidates", [])}
    both = [c for c in a.get("candidates", []) if (c[0], c[1]) in tried_b]
    same = (all(a.get(k) == b.get(k) for k in keys) and a.get("names") == b.get("names")
            and all(tried_b[(c[0], c[1])] == c[2] for c in both))
    if "values" not in a or a.get("names") != b.get("names"):
        return same, None
    return same, max((abs(x - y) for x, y in zip(a["values"], b["values"])), default=0.0)


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--base-commit", default=BASE_COMMIT)
    ap.add_argument("--base-dir", default=str(Path(tempfile.gettempdir()) / "torchcal-base"))
    ap.add_argument("--reps", type=int, default=3, help="runs of each start-up figure (the least counts)")
    ap.add_argument("--only", help="comma-separated figures (default all): " + ", ".join(FIGURES))
    ap.add_argument("--fleet", type=int, default=6, help="robots of the fleet figure")
    ap.add_argument("--save", help="a folder for each worker's full output (decisions, parameters), per tree")
    ap.add_argument("--data", default=str(DATA), help="the shared data folder (tiago_mocap, ipa_ur10)")
    ap.add_argument("--worker", help=argparse.SUPPRESS)
    a = ap.parse_args(argv)
    if a.worker:
        out = {"loop_arm9": worker_loop_arm9, "loop_demo": worker_loop_demo,
               "loop_tiago": lambda: worker_loop_tiago(Path(a.data)),
               "loop_ur10_17": lambda: worker_loop_ur10(Path(a.data), 17),
               "loop_ur10_45": lambda: worker_loop_ur10(Path(a.data), 45),
               "fleet_page": lambda: worker_fleet_page(a.fleet)}[a.worker]()
        print(json.dumps(out))
        return out
    only = set(a.only.split(",")) if a.only else set(FIGURES)
    # the real arms' data, where it is: each worker gets its folder (TIAGo) or its rows as tensors (UR10)
    given = {}
    # absolute: each worker runs in its own tree, where a relative path would mean another folder
    data = Path(a.data).resolve()
    tiago, ur10 = data / "tiago_mocap", data / "ipa_ur10"
    if {"loop_tiago"} & only:
        if (tiago / "train.csv").is_file():
            given["loop_tiago"] = str(tiago)
        else:
            print(f"loop_tiago skipped: no TIAGo data at {tiago}", file=sys.stderr)
    if {"loop_ur10_17", "loop_ur10_45"} & only:
        if (ur10 / "measurements_joint_configurations.csv").is_file():
            rows = str(ur10_tensors(ur10, Path(tempfile.mkdtemp()) / "ur10_rows.pt"))
            given.update({n: rows for n in ("loop_ur10_17", "loop_ur10_45")})
        else:
            print(f"loop_ur10_17, loop_ur10_45 skipped: no IPA UR10 data at {ur10}", file=sys.stderr)
    trees = {"base": _base_tree(a.base_commit, Path(a.base_dir)), "new": ROOT}
    fig: dict[str, dict] = {}
    py = sys.executable
    starts = {"import_torch": [py, "-c", "import torch"], "import_torchcal": [py, "-c", "import torchcal"],
              "help": [py, "-m", "torchcal", "--help"]}
    for name, cmd in starts.items():
        if name in only:
            fig[name] = _wall(cmd, trees, a.reps)
    runs: dict[str, dict] = {}
    for name in (*LOOPS, "fleet_page"):
        want = name in only or (name == "loop_demo" and "report_demo" in only)
        if name in REAL_ARMS and name not in given:
            want = False
        if want:
            runs[name] = {tag: _worker(name, tree, a.fleet, given.get(name)) for tag, tree in trees.items()}
            if a.save:
                Path(a.save).mkdir(parents=True, exist_ok=True)
                (Path(a.save) / f"{name}.json").write_text(json.dumps(runs[name]))
    for name in (*LOOPS, "fleet_page"):
        if name in runs and name in only:
            fig[name] = {tag: r["cpu_s"] for tag, r in runs[name].items()}
            fig[name + "_wall"] = {tag: r["wall_s"] for tag, r in runs[name].items()}
    if "loop_demo" in runs and "report_demo" in only:
        fig["report_demo"] = {tag: r["report_cpu_s"] for tag, r in runs["loop_demo"].items()}
        fig["report_demo_wall"] = {tag: r["report_wall_s"] for tag, r in runs["loop_demo"].items()}
    for v in fig.values():
        v["ratio"] = round(v["base"] / v["new"], 2) if v.get("new") else None
        v["base"], v["new"] = round(v["base"], 3), round(v["new"], 3)
    out: dict = {"bench": "speed", "base_commit": a.base_commit, "figures": fig}
    for name in LOOPS:
        if name in runs:
            same, diff = _same(runs[name]["base"], runs[name]["new"])
            out[name + "_same_decisions"], out[name + "_max_param_diff"] = same, diff
    bars = {}
    if "import_torchcal" in fig and "import_torch" in fig:
        t0 = fig["import_torch"]["new"]
        bars["import_le_2s_and_1.5s_beyond_torch"] = fig["import_torchcal"]["new"] <= min(2.0, t0 + 1.5)
    if "help" in fig and "import_torch" in fig:
        bars["help_le_2s_and_1.5s_beyond_torch"] = fig["help"]["new"] <= min(2.0, fig["import_torch"]["new"] + 1.5)
    if "loop_arm9" in fig:
        d = out.get("loop_arm9_max_param_diff")
        bars["loop_arm9_5x_same_decisions_1e-8"] = (fig["loop_arm9"]["ratio"] >= 5 and out["loop_arm9_same_decisions"]
                                                   and d is not None and d <= 1e-8)
    if "loop_demo" in fig:
        bars["loop_demo_3x"] = fig["loop_demo"]["ratio"] >= 3
    if "report_demo" in fig:
        bars["report_demo_le_2s"] = fig["report_demo_wall"]["new"] <= 2.0
    if "fleet_page" in fig:
        bars["fleet_page_le_1s"] = fig["fleet_page_wall"]["new"] <= 1.0
    out["bars"] = bars
    for k, v in fig.items():
        print(f"{k:<22} base {v['base']:>9.3f} s   new {v['new']:>9.3f} s   base/new {v['ratio']}", file=sys.stderr)
    print(json.dumps(out))
    return out


if __name__ == "__main__":
    main()
