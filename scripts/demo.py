#!/usr/bin/env python
"""The main job on a shipped robot: simulate a laser tracker measuring a KUKA KR5 arc that has
unknown geometric errors, identify them from the measurement file alone, and report the error
before and after on the training poses and on fresh poses.

The simulated truth is written to a separate JSON file that the identification never reads;
it is opened only at the end, to score the result.

Usage: python scripts/demo.py [--out out/demo] [--poses 60] [--noise-mm 0.02] [--seed 0]
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from torchcal import Robot, calibrate  # noqa: E402
from torchcal.calibrate import stage_stats  # noqa: E402
from torchcal.io import load_measurements  # noqa: E402
from torchcal.sim import SimConfig, random_configs, random_errors, simulate, write_dataset  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="out/demo")
    ap.add_argument("--poses", type=int, default=60)
    ap.add_argument("--test-poses", type=int, default=200)
    ap.add_argument("--noise-mm", type=float, default=0.02)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    torch.set_num_threads(1)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    urdf = ROOT / "urdf" / "kuka_kr5_arc.urdf"
    # the tracker reflector sits somewhere on the flange: an unknown point, guessed at the flange origin
    robot = Robot.from_urdf(urdf, markers=["smr@flange=0,0,0"])

    # 1. the "real" robot and its measurements (truth kept apart)
    cfg = SimConfig(n=args.poses + args.test_poses, noise=args.noise_mm * 1e-3, seed=args.seed)
    g = torch.Generator().manual_seed(args.seed)
    truth = random_errors(robot, robot.params().fix("smr.*"), cfg, g)
    truth["smr.dx"], truth["smr.dy"], truth["smr.dz"] = 0.012, -0.008, 0.035  # reflector 3.8 cm off the flange
    q = random_configs(robot, cfg.n, g)
    data, _ = simulate(robot, cfg, true_params=truth, q=q)
    train, test = data.subset(range(args.poses)), data.subset(range(args.poses, cfg.n))
    write_dataset(out / "train.csv", train, truth, out / "truth.json", meta={"noise_mm": args.noise_mm})
    write_dataset(out / "test.csv", test)
    print(f"simulated {len(train)} training and {len(test)} fresh poses of {robot.name} "
          f"(tracker {cfg.base_distance} m away, noise {args.noise_mm} mm per axis) -> {out}/")

    # 2. identification from the files alone
    train = load_measurements(out / "train.csv", robot)
    test = load_measurements(out / "test.csv", robot)
    res = calibrate(robot, train, test=test, method="lm")
    res.save(out)

    # 3. report
    print(f"\n{len(res.params.free_names)} parameters identified, {len(res.unidentifiable)} not identifiable "
          f"from position data (listed in {out}/report.md)")
    print(f"{'stage':<12}{'train mean':>12}{'train max':>12}{'fresh mean':>12}{'fresh max':>12}   [mm]")
    for s in res.stages:
        print(f"{s['name']:<12}{s['train']['mean_mm']:>12.4f}{s['train']['max_mm']:>12.4f}"
              f"{s['test']['mean_mm']:>12.4f}{s['test']['max_mm']:>12.4f}")
    # only now, to score the result, read the truth: the true model on the fresh poses leaves
    # pure instrument noise, the floor no calibration can beat
    t = json.loads((out / "truth.json").read_text())
    truth_vals = torch.tensor(t["values"], dtype=robot.dtype)
    floor = stage_stats(robot, truth_vals, test)
    print(f"noise floor (the true model on the fresh poses): mean {floor['mean_mm']:.4f} mm, "
          f"max {floor['max_mm']:.4f} mm")
    print(f"calibrated URDF: {out}/calibrated.urdf; report: {out}/report.md")


if __name__ == "__main__":
    main()
