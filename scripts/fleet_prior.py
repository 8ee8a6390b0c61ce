#!/usr/bin/env python
"""Does a robot with few poses borrow strength from its fleet? The hierarchical prior measured.

A simulated fleet of R KUKA KR5 arc robots (the shipped URDF, marker on the flange): every robot's
geometric errors are a fleet-wide mean (0.5 mm / 1 mrad) plus its own deviation (``--spread``
times that), its own tracker 3 m away, 0.02 mm noise (``torchcal.sim.serial.simulate_fleet``). Each robot
is measured at 10 poses (``--poses``) for training and 100 fresh poses for scoring.

Compared, on the same data:

* ``alone``: every robot calibrated from its own poses (``calibrate_fleet`` without a prior, which
  equals ``calibrate(..., method="lm")`` per robot);
* ``fleet_prior``: ``calibrate_fleet(..., prior="fleet")``: each robot's errors drawn around the
  fleet mean, scales and noise estimated from the fleet (the truth is never shown to it);
* ``alone_30``: every robot alone with 30 poses, for reference;
* ``noise_floor``: the mean norm of the simulated noise on the held-out rows (measured minus true
  positions; the truth is used only here, to score).

The figure is the held-out mean position error (mm) over all robots and poses, per seed, and its
mean over seeds. Prints one JSON line.

Usage: python scripts/fleet_prior.py [--robots 20] [--poses 10] [--spread 0.2] [--seeds 1 2 3]
"""
from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from torchcal.pipelines.fleet.run import calibrate_fleet  # noqa: E402
from torchcal.kinematics.robots import shipped  # noqa: E402
from torchcal.sim.serial import SimConfig, simulate_fleet  # noqa: E402


def held_out_mm(fr) -> float:
    """Mean held-out position error (mm) over every robot's held-out observations."""
    n = sum(r.stages[-1]["test"]["n"] for r in fr.results)
    return sum(r.stages[-1]["test"]["mean_mm"] * r.stages[-1]["test"]["n"] for r in fr.results) / n


def noise_floor_mm(robot, test, truths) -> float:
    e = torch.cat([(d.positions - robot.positions(d.q, t.values)).norm(dim=-1).flatten() for d, t in zip(test, truths)])
    return float(e.mean()) * 1e3


def one_seed(robot, R: int, poses: int, spread: float, seed: int) -> dict:
    cfg = SimConfig(n=30, seed=seed)
    train30, test, truths = simulate_fleet(robot, R, cfg, spread=spread, n_test=100)
    train = [d.subset(range(poses)) for d in train30]  # the first `poses` of the same robots
    out = {}
    for name, fn in (("alone", lambda: calibrate_fleet(robot, train, test=test)),
                     ("fleet_prior", lambda: calibrate_fleet(robot, train, test=test, prior="fleet")),
                     ("alone_30", lambda: calibrate_fleet(robot, train30, test=test))):
        t = time.perf_counter()
        fr = fn()
        out[name] = held_out_mm(fr)
        out[f"{name}_s"] = time.perf_counter() - t
        if name == "fleet_prior":
            out["prior_sigma_mm"] = fr.prior["sigma_m"] * 1e3
    out["noise_floor"] = noise_floor_mm(robot, test, truths)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--robots", type=int, default=20)
    ap.add_argument("--poses", type=int, default=10)
    ap.add_argument("--spread", type=float, default=0.2)
    ap.add_argument("--seeds", type=int, nargs="+", default=[1, 2, 3])
    ap.add_argument("--threads", type=int, default=1)
    a = ap.parse_args()
    torch.set_num_threads(a.threads)
    robot = shipped("kuka_kr5_arc")
    rows = {s: one_seed(robot, a.robots, a.poses, a.spread, s) for s in a.seeds}
    for s, r in rows.items():
        print(f"seed {s}: alone {r['alone']:.4f} mm, fleet prior {r['fleet_prior']:.4f} mm, alone with 30 poses "
              f"{r['alone_30']:.4f} mm, noise floor {r['noise_floor']:.4f} mm", file=sys.stderr)
    mean = {k: statistics.mean(r[k] for r in rows.values()) for k in ("alone", "fleet_prior", "alone_30", "noise_floor")}
    print(json.dumps({"problem": f"{a.robots} KR5 arc robots, {a.poses} poses each (held-out: 100), per-robot spread "
                                 f"{a.spread} x the fleet-mean errors (0.5 mm / 1 mrad), 0.02 mm noise",
                      "held_out_mean_mm": mean, "improvement_alone_over_prior": mean["alone"] / mean["fleet_prior"],
                      "per_seed": rows, "threads": a.threads, "torch": torch.__version__}))


if __name__ == "__main__":
    main()
