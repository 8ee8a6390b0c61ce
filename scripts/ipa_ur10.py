#!/usr/bin/env python
"""A real UR10 measured by a laser tracker with a 6-D probe (../shared/data/ipa_ur10, Series B,
1,495 poses): the nominal model, a plain least-squares fit, and the loop, on a random third held out.

The instrument's export is read as it is: ``;``-separated, decimal commas, millimetres, Euler angles
in degrees (``XYZ``, intrinsic x then y then z, as the source's reader, scipy's
``Rotation.from_euler('XYZ', degrees=True)``). The same reading from the command line::

    torchcal loop --robot ur10.urdf --data measurements_joint_configurations.csv --sep ';' --decimal ',' \\
        --units mm --rot-units deg --euler XYZ --column-map measurement_x=tmac.x ... --marker tmac@flange=0,0,0.109

Models, each measured on the held-out third (mean Euclidean position error, mm):

* nominal: the UR10's published DH, the tracker frame and the probe point registered, nothing else;
* plain: least squares (no robust loss, no selection) of every geometric error of the joint origins,
  the tracker frame, the probe point, and the compliance of the shoulder-lift and elbow joints (the
  two that carry the arm's weight) from the URDF's inertials plus an unknown payload;
* loop: :func:`torchcal.run_loop`, every choice made by cross-validation on the training rows.

Prints a table and one JSON line. The data is read from ../shared and never copied into the repo.

Usage: python scripts/ipa_ur10.py [--data ../shared/data/ipa_ur10] [--seed 0] [--holdout 0.333]
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

from torchcal import Robot, load_measurements, run_loop  # noqa: E402
from torchcal.effects import JointCompliance, effect_params  # noqa: E402
from torchcal.effects.joint import CyclicJointError  # noqa: E402
from torchcal.measure.instrument import InstrumentFormat  # noqa: E402
from torchcal.params import ParamSet  # noqa: E402
from torchcal.pipelines.crossval.evaluate import fit_params  # noqa: E402
from torchcal.pipelines.crossval.models import Context  # noqa: E402
from torchcal.problems.template import geometric_start  # noqa: E402
from torchcal.pipelines.loop.stages import stage_stats  # noqa: E402
from torchcal.sim.ur10 import ur10_urdf  # noqa: E402  (the UR10's published numbers as URDF, no simulation)

FILE = "measurements_joint_configurations.csv"
MARKER = "tmac@flange=0,0,0.109"  # the T-Mac point about 109 mm beyond the flange (Trafo_TM_F_init.txt)
# the export's columns as torchcal names them; the commanded pose is a function of the joints and the
# time stamp was damaged by a spreadsheet (the data README): both left out
COLUMNS = {"measurement_x": "tmac.x", "measurement_y": "tmac.y", "measurement_z": "tmac.z",
           "measurement_rx": "tmac.rx", "measurement_ry": "tmac.ry", "measurement_rz": "tmac.rz",
           "measurement_temperature": "temperature", "Timestamp": "",
           **{f"Goal {a}": "" for a in ("x", "y", "z", "roll", "pitch", "yaw")}}
FORMAT = InstrumentFormat(sep=";", decimal=",", rot_units="deg", euler="XYZ", columns=COLUMNS)
COMPLIANT = ["shoulder_lift_joint", "elbow_joint"]


def read(d: Path):
    """The UR10 with the probe point as an unknown point on the flange, and every row of the export."""
    robot = Robot.from_urdf(ur10_urdf(), markers=[MARKER])
    return robot, load_measurements(d / FILE, robot, units=["mm"], fmt=FORMAT)


def load(d: Path, holdout: float, seed: int):
    """The robot, and the rows split into training rows and a seeded random ``holdout`` part."""
    robot, data = read(d)
    train, test = data.split(holdout, seed=seed)
    return robot, train, test


def nominal(robot, train, test) -> float:
    """The published geometry and the probe point at its guess, the tracker frame registered
    (Kabsch, as the loop's nominal stage)."""
    return stage_stats(robot, geometric_start(robot, train, ["base.*"]), [], test)[0].mean


def plain(robot, train, test, harmonics: int = 0) -> float:
    """Least squares of every geometric error and two joints' compliance, positions only (and,
    with ``harmonics``, a cyclic error of every joint's angle, harmonics 1 to that order)."""
    ctx = Context(robot, train, [], None, 1.0)
    effects = [JointCompliance(robot, COMPLIANT)]
    if harmonics:
        effects.append(CyclicJointError(robot, harmonics=harmonics))
    start = ParamSet.concat(geometric_start(robot, train, None), effect_params(effects))
    p = fit_params(ctx, start, effects, train, None, reduce=True)
    return stage_stats(robot, p, effects, test)[0].mean


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", default=str(ROOT.parent / "shared" / "data" / "ipa_ur10"))
    ap.add_argument("--seed", type=int, default=0, help="seed of the held-out third and of the loop's folds")
    ap.add_argument("--holdout", type=float, default=1 / 3)
    ap.add_argument("--no-loop", action="store_true", help="the nominal model and the plain fit only")
    ap.add_argument("--harmonics", type=int, nargs="*", default=[],
                    help="also the plain fit with a cyclic error of every joint, harmonics 1 to each order given")
    args = ap.parse_args()
    torch.set_num_threads(1)
    d = Path(args.data)
    if not (d / FILE).is_file():
        raise SystemExit(f"IPA UR10 data not found at {d / FILE}; it lives in ../shared/data/ipa_ur10 beside the repo")
    robot, train, test = load(d, args.holdout, args.seed)
    print(f"{len(train)} training poses, {len(test)} held out (seed {args.seed})")
    out = {"n_train": len(train), "n_test": len(test), "seed": args.seed}
    t = time.perf_counter()
    out["nominal_mm"] = nominal(robot, train, test)
    out["plain_mm"] = plain(robot, train, test)
    out["plain_s"] = time.perf_counter() - t
    print(f"nominal {out['nominal_mm']:.3f} mm   plain fit (geometry + {', '.join(COMPLIANT)} compliance) "
          f"{out['plain_mm']:.3f} mm held out")
    for h in args.harmonics:
        out[f"plain_harmonics_{h}_mm"] = plain(robot, train, test, h)
        print(f"plain fit + cyclic error of every joint, harmonics 1-{h}: {out[f'plain_harmonics_{h}_mm']:.3f} mm")
    if not args.no_loop:
        t = time.perf_counter()
        res = run_loop(robot, train, test, seed=args.seed)
        out["loop_s"] = time.perf_counter() - t
        out["loop_mm"] = res.stages[-1].test.mean
        out["loop_effects"] = [e.name for e in res.effects]
        out["loop_stages_mm"] = {s.name: s.test.mean for s in res.stages}
        out["orientation"] = res.geometric.get("orientation")
        out["loop_timings_s"] = res.timings
        for s in res.stages:
            print(f"  loop stage {s.name:<28} {s.n_params:>4} params  held out {s.test.mean:.3f} mm")
        print(f"loop {out['loop_mm']:.3f} mm held out in {out['loop_s']:.0f} s; effects {out['loop_effects']}")
    print(json.dumps(out))


if __name__ == "__main__":
    main()
