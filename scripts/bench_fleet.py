#!/usr/bin/env python
"""Fleet calibration speed: one batched solve (:func:`torchcal.pipelines.fleet.run.calibrate_fleet`) against a
Python loop of single calibrations (``calibrate(robot, data, method="lm")``), in the same run.

The problem: R simulated KUKA KR5 arc robots (the shipped URDF, an unknown reflector on the
flange), each with its own geometric errors (0.5 mm / 1 mrad), its own tracker 3 m away at a random
rotation, 30 random poses and 0.02 mm noise (``torchcal.sim.serial``, seed per robot). Both sides do the
same work: base registration, identifiability judged per robot at the start and again at the
solution, LM, standard errors and error statistics. The script also reports how far the two
results are apart (largest parameter difference, mm or mrad).

Timing: one torch thread, float64; the fleet and the loop are timed alternately (``--reps`` times
at R = 10 and 100, once at R = 1000), median per side; ``ratio = loop / fleet``. The machine may be
shared with other jobs: ratios measured interleaved, not absolute times, are what to compare.

On a GPU (when one is present, or ``--device cuda``) it adds the kinematics throughput of a
parameter population × poses and the fleet solve at ``--gpu-robots`` (10 000) robots. The test
suite runs that code path on the CPU at a small size (``device_figures``).

Prints one JSON line.

Usage: python scripts/bench_fleet.py [--robots 10 100 1000] [--reps 3] [--poses 30] [--quick]
"""
from __future__ import annotations

import argparse
import json
import platform
import statistics
import sys
import time
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from torchcal import Robot, calibrate  # noqa: E402
from torchcal.pipelines.fleet.run import calibrate_fleet  # noqa: E402
from torchcal.sim.serial import SimConfig, simulate  # noqa: E402

MARKERS = ["smr@flange=0,0,0"]


def fleet_data(robot: Robot, n_robots: int, poses: int, seed: int) -> list:
    return [simulate(robot, SimConfig(n=poses, seed=seed * 1_000_003 + r))[0] for r in range(n_robots)]


def timed(fn):
    t = time.perf_counter()
    out = fn()
    return time.perf_counter() - t, out


def compare(robot: Robot, data: list, reps: int) -> dict:
    """Fleet and loop, alternately ``reps`` times; the results' agreement from the last pair."""
    tf, tl = [], []
    for i in range(reps):
        order = ("fleet", "loop") if i % 2 == 0 else ("loop", "fleet")
        for side in order:
            if side == "fleet":
                t, fr = timed(lambda: calibrate_fleet(robot, data))
                tf.append(t)
            else:
                t, singles = timed(lambda: [calibrate(robot, d, method="lm") for d in data])
                tl.append(t)
    diff = max(float((a.params.values - b.params.values).abs().max()) for a, b in zip(fr.results, singles))
    same_sets = all(a.params.free_names == b.params.free_names for a, b in zip(fr.results, singles))
    f, l_ = statistics.median(tf), statistics.median(tl)
    return {"fleet_s": f, "loop_s": l_, "ratio": l_ / f, "fleet_ms_per_robot": 1e3 * f / len(data),
            "loop_ms_per_robot": 1e3 * l_ / len(data), "fleet_s_all": tf, "loop_s_all": tl,
            "max_param_diff_mm_or_mrad": 1e3 * diff, "same_free_sets": same_sets}


def sync(device: str) -> None:
    """Wait for the device's queued work, so that a wall-clock time covers it."""
    if device.startswith("cuda"):
        torch.cuda.synchronize()


def device_figures(device: str, n_robots: int, poses: int, seed: int, populations=(1000, 10000)) -> dict:
    """Population × poses FK throughput and the fleet solve at ``n_robots`` on ``device`` (the
    GPU figures; on ``cpu`` the same code path, which the tests run at a small size)."""
    robot = Robot.from_urdf(ROOT / "urdf" / "kuka_kr5_arc.urdf", markers=MARKERS, device=device)
    g = torch.Generator().manual_seed(seed)
    out = {"device": torch.cuda.get_device_name(torch.device(device)) if device.startswith("cuda") else device}
    fk = {}
    N = 1000
    for P in populations:
        q = torch.rand(N, robot.dof, generator=g, dtype=torch.float64).to(device)
        X = (1e-3 * torch.randn(P, robot.n_params, generator=g, dtype=torch.float64)).to(device)
        robot.positions(q, X, check=False)
        sync(device)
        t, p = timed(lambda: (robot.positions(q, X, check=False), sync(device))[0])
        fk[f"{P}x{N}"] = {"s": t, "pairs_per_s": P * N / t, "shape": list(p.shape)}
    out["fk_population_x_poses"] = fk
    cpu = Robot.from_urdf(ROOT / "urdf" / "kuka_kr5_arc.urdf", markers=MARKERS)
    data = [d.to(device) for d in fleet_data(cpu, n_robots, poses, seed)]
    calibrate_fleet(robot, data[:10])
    sync(device)
    t, fr = timed(lambda: calibrate_fleet(robot, data))
    sync(device)
    out["fleet_solve"] = {"robots": n_robots, "s": t, "ms_per_robot": 1e3 * t / n_robots,
                          "converged": sum(r.solver.converged for r in fr.results)}
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--robots", type=int, nargs="+", default=[10, 100, 1000])
    ap.add_argument("--poses", type=int, default=30)
    ap.add_argument("--reps", type=int, default=3)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--quick", action="store_true", help="R = 10 and 100 only")
    ap.add_argument("--device", default=None, help="GPU figures on this device (default: cuda when present)")
    ap.add_argument("--gpu-robots", type=int, default=10000)
    a = ap.parse_args()
    torch.set_num_threads(a.threads)
    robot = Robot.from_urdf(ROOT / "urdf" / "kuka_kr5_arc.urdf", markers=MARKERS)
    sizes = [r for r in a.robots if not (a.quick and r > 100)]
    calibrate_fleet(robot, fleet_data(robot, 4, a.poses, a.seed + 1))  # warm-up
    rows = {}
    for R in sizes:
        data = fleet_data(robot, R, a.poses, a.seed)
        rows[str(R)] = compare(robot, data, a.reps if R <= 100 else 1)
        print(f"R={R}: fleet {rows[str(R)]['fleet_s']:.2f} s, loop {rows[str(R)]['loop_s']:.2f} s, "
              f"ratio {rows[str(R)]['ratio']:.1f}", file=sys.stderr)
    device = a.device or ("cuda" if torch.cuda.is_available() else None)
    out = {"problem": f"KUKA KR5 arc URDF, marker on the flange, {a.poses} poses per robot, 0.5 mm / 1 mrad errors, "
                      "0.02 mm noise; fleet = calibrate_fleet, loop = calibrate(method='lm') per robot",
           "ratio": {R: v["ratio"] for R, v in rows.items()}, "results": rows,
           "target_10x_at_100": rows["100"]["ratio"] >= 10 if "100" in rows else None,
           "threads": a.threads, "torch": torch.__version__, "python": platform.python_version(),
           "machine": platform.machine(),
           "gpu": device_figures(device, a.gpu_robots, a.poses, a.seed) if device else "no GPU on this machine"}
    print(json.dumps(out))


if __name__ == "__main__":
    main()
