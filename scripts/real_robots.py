#!/usr/bin/env python
"""Robots nobody here measured: the loop and ``calibrate`` against a least-squares fit of the true
parameter set, on the independent simulator's stand-ins for the held-back real sets, and on the real
TIAGo when ``../shared/data`` is present.

* ``arm9_mocap``: a 9-joint arm (2 torso + 7 arm joints) seen by motion capture (0.3 mm) at one
  point of its gripper guessed on the last joint's axis; 45 training and 16 held-out rows;
  geometric errors of 2 mm and 3 mrad on every joint origin and zero offset.
* ``pose6d``: a 6R arm of the UR10 class whose camera measures full 6-D poses (0.5 mm, 2 mrad) of an
  unknown tool frame; 17 training and 6 held-out rows. ``pose6d_partial``: orientation on half the rows.

"True LS" fits exactly the parameters the simulator drew errors for (read from its truth, for this
comparison only) by plain least squares; the loop and ``calibrate`` see only the data. Prints a
markdown table (held-out mean position error, mm; orientation error, mrad) and one JSON line.

Usage: python scripts/real_robots.py [--seeds 0,1,2]
"""
from __future__ import annotations

import argparse
import json
import math
import sys
import tempfile
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from torchcal import Robot, calibrate, load_measurements  # noqa: E402
from torchcal.pipelines.loop.run import run_loop  # noqa: E402
from torchcal.sim.cases import make_case  # noqa: E402

INF = {"m": math.inf, "rad": math.inf}
TIAGO = ROOT.parent / "shared" / "data" / "tiago_mocap"


def true_support_fit(c, robot, train, test, kind):
    free = c.true_parameters(robot.marker_names, turns=kind == "pose")
    return calibrate(robot, train, test=test, free=free, prior=None, plausible=INF, kind=kind)


def simulated(name: str, seed: int) -> dict:
    c = make_case(name, seed)
    u = Path(tempfile.mkdtemp()) / "robot.urdf"
    u.write_text(c.urdf)
    robot = Robot.from_urdf(u, markers=c.markers)
    train, test = c.train.to_measurements(), c.test.to_measurements()
    kind = "pose" if train.quaternions is not None else "position"
    ls = true_support_fit(c, robot, train, test, kind)
    cal = calibrate(robot, train, test=test, kind=kind)
    loop = run_loop(robot, train, test, seed=seed, elm=False, log=None)
    rot = (loop.stages[-1].get("test") or {}).get("orientation")
    return {"data": name, "seed": seed, "floor_mm": c.floor_mm, "true_ls_mm": ls.stages[-1]["test"]["mean_mm"],
            "calibrate_mm": cal.stages[-1]["test"]["mean_mm"], "calibrate_refused": bool(cal.problems()),
            "calibrate_prior_mm": cal.prior_mm, "loop_mm": loop.stages[-1]["test"]["mean_mm"],
            "loop_refused": bool(loop.problems()), "loop_geometry": loop.geometric["chosen"],
            "loop_orientation_mrad": None if rot is None else rot["mean_mrad"]}


def tiago() -> dict:
    points = ("BL", "BR", "TR", "TL")
    every = Robot.from_urdf(TIAGO / "tiago_48_hey5.urdf", markers=[f"hand_{c}@wrist_ft_tool_link" for c in points])
    robot = Robot.from_urdf(TIAGO / "tiago_48_hey5.urdf", markers=["hand_BL@wrist_ft_tool_link"])
    train = load_measurements(TIAGO / "train.csv", every).select_markers(["hand_BL"])
    test = load_measurements(TIAGO / "test.csv", every).select_markers(["hand_BL"])
    cal = calibrate(robot, train, test=test)
    loop = run_loop(robot, train, test, seed=0, log=None)
    return {"data": "tiago (real, hand_BL)", "seed": 0, "floor_mm": None, "true_ls_mm": None,
            "calibrate_mm": cal.stages[-1]["test"]["mean_mm"], "calibrate_refused": bool(cal.problems()),
            "calibrate_prior_mm": cal.prior_mm, "loop_mm": loop.stages[-1]["test"]["mean_mm"],
            "loop_refused": bool(loop.problems()), "loop_geometry": loop.geometric["chosen"],
            "loop_orientation_mrad": None, "loop_effects": [a["name"] for a in loop.accepted]}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", default="0")
    args = ap.parse_args()
    torch.set_num_threads(1)
    rows = [simulated(n, int(s)) for s in args.seeds.split(",") for n in ("arm9_mocap", "pose6d", "pose6d_partial")]
    if TIAGO.is_dir():
        rows.append(tiago())
    else:
        print(f"# {TIAGO} is absent: the real TIAGo set is skipped", file=sys.stderr)
    f = lambda v: "–" if v is None else f"{v:.3f}"  # noqa: E731
    print("| data | seed | true LS (mm) | loop (mm) | loop / true LS | calibrate (mm) | calibrate's prior | "
          "loop orientation (mrad) | noise floor (mm) |")
    print("|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        ratio = "–" if r["true_ls_mm"] is None else f"{r['loop_mm'] / r['true_ls_mm']:.2f}"
        prior = "none" if r["calibrate_prior_mm"] is None else f"{r['calibrate_prior_mm']:g} mm/mrad"
        print(f"| {r['data']} | {r['seed']} | {f(r['true_ls_mm'])} | {f(r['loop_mm'])}"
              f"{' (refused)' if r['loop_refused'] else ''} | {ratio} | {f(r['calibrate_mm'])}"
              f"{' (refused)' if r['calibrate_refused'] else ''} | {prior} | {f(r['loop_orientation_mrad'])} | "
              f"{f(r['floor_mm'])} |")
    print(json.dumps({"script": "real_robots", "rows": rows}))


if __name__ == "__main__":
    main()
