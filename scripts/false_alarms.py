#!/usr/bin/env python
"""False alarms of the loop on clean data, measured: the loop on the independent simulator's clean
sets (geometry only, nothing else put in) over many seeds, counting the runs in which it accepted
any effect, and those in which the any-parameter, any-driver family (``parameter_drivers``) was
accepted.

Prints one line per run and a JSON summary (the last line).

Usage: python scripts/false_alarms.py [--seeds 1-20] [--cases clean,clean_covariates]
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from torchcal import Robot  # noqa: E402
from torchcal.pipelines.loop.run import run_loop  # noqa: E402
from torchcal.sim.cases import make_case  # noqa: E402


def _seeds(text: str) -> list[int]:
    if "-" in text:
        a, b = text.split("-")
        return list(range(int(a), int(b) + 1))
    return [int(s) for s in text.split(",")]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", default="1-20")
    ap.add_argument("--cases", default="clean", help="comma-separated clean cases of torchcal.sim.cases")
    args = ap.parse_args()
    torch.set_num_threads(1)
    runs = []
    for name in args.cases.split(","):
        for seed in _seeds(args.seeds):
            c = make_case(name, seed)
            robot = Robot.from_urdf(c.urdf, markers=c.markers)
            t0 = time.perf_counter()
            res = run_loop(robot, c.train.to_measurements(), c.test.to_measurements(), seed=seed, log=None)
            found = [a["name"] for a in res.accepted]
            ratio = res.stages[-1]["test"]["mean_mm"] / c.floor_mm
            runs.append({"case": name, "seed": seed, "accepted": found, "ratio_to_floor": ratio,
                         "loop_s": time.perf_counter() - t0})
            print(f"{name} seed {seed}: accepted {', '.join(found) or '(none)'}  final / floor {ratio:.3f}", flush=True)
    n = len(runs)
    any_alarm = sum(1 for r in runs if r["accepted"])
    drivers = sum(1 for r in runs if "parameter_drivers" in r["accepted"])
    print(json.dumps({"runs": n, "cases": args.cases, "seeds": args.seeds, "any_effect_accepted": any_alarm,
                      "parameter_drivers_accepted": drivers, "false_alarm_rate": any_alarm / max(n, 1),
                      "max_ratio_to_floor": max(r["ratio_to_floor"] for r in runs), "runs_detail": runs}))


if __name__ == "__main__":
    main()
