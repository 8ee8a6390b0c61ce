#!/usr/bin/env python
"""Fleet calibration speed: one batched solve (:func:`torchcal.pipelines.fleet.run.calibrate_fleet`) against a
Python loop of single calibrations (``calibrate(robot, data, method="lm", prior=None)``: without a prior,
the fleet equals it robot by robot), in the same run.

The problem: R simulated KUKA KR5 arc robots (the shipped URDF, an unknown reflector on the
flange), each with its own geometric errors (0.5 mm / 1 mrad), its own tracker 3 m away at a random
rotation, 30 random poses and 0.02 mm noise (``torchcal.sim.serial``, seed per robot). Both sides do the
same work: base registration, identifiability judged per robot at the start and again at the
solution, LM, standard errors and error statistics. The script also reports how far the two
results are apart (largest parameter difference, mm or mrad).

Timing: one torch thread, float64; the fleet and the loop are timed alternately (``--reps`` times
at R = 10 and 100, once at R = 1000), median per side; ``ratio = loop / fleet``. The machine may be
shared with other jobs: ratios measured interleaved, not absolute times, are what to compare; the
CPU time of this process (``*_cpu_*``) is printed beside the wall time, since it counts no time
spent waiting for a core. A fleet's per-robot results are views built when first read
(``fleet_results_s``: building every robot's ``CalibrationResult`` after the solve, not part of
``fleet_s``); the loop's results are built by ``calibrate`` itself.

The bar of issue 26: at R = 1000 the fleet takes at most 1.5 ms per robot on a CPU (``bar``).

On a GPU (when one is present, or ``--device cuda``) it adds the kinematics throughput of a
parameter population × poses, the fleet solve at ``--gpu-robots`` (10 000) robots, the same
machine's CPU on the same robots at a smaller R (``--cpu-robots``), and the device memory the solve
held per robot with its extrapolation to 100 000 robots (``--try-100k`` solves them). The test suite
runs that code path on the CPU at a small size (``device_figures``).

Prints one JSON line.

Usage: python scripts/bench_fleet.py [--robots 10 100 1000] [--reps 3] [--poses 30] [--quick] [--device cuda]

``--quick``: R = 10 and 100 against the loop once each, the R = 1000 bar on the fleet alone, and on
a GPU the 10 000 robots tiled from 1000 simulated ones (the solve's work does not depend on which
robot is which); about a minute on a GPU machine.
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
BAR_MS = 1.5  # issue 26: ms per robot at R = 1000 on a CPU


def fleet_data(robot: Robot, n_robots: int, poses: int, seed: int, distinct: int | None = None) -> list:
    """``n_robots`` simulated data sets; with ``distinct``, that many simulated and repeated."""
    k = n_robots if distinct is None else min(distinct, n_robots)
    sets = [simulate(robot, SimConfig(n=poses, seed=seed * 1_000_003 + r))[0] for r in range(k)]
    return [sets[r % k] for r in range(n_robots)]


def timed(fn):
    t, c = time.perf_counter(), time.process_time()
    out = fn()
    return time.perf_counter() - t, time.process_time() - c, out


def compare(robot: Robot, data: list, reps: int) -> dict:
    """Fleet and loop, alternately ``reps`` times; the results' agreement from the last pair."""
    tf, tl, cf, cl = [], [], [], []
    for i in range(reps):
        order = ("fleet", "loop") if i % 2 == 0 else ("loop", "fleet")
        for side in order:
            if side == "fleet":
                t, c, fr = timed(lambda: calibrate_fleet(robot, data))
                tf.append(t), cf.append(c)
            else:
                t, c, singles = timed(lambda: [calibrate(robot, d, method="lm", prior=None) for d in data])
                tl.append(t), cl.append(c)
    t_res, _, results = timed(lambda: list(fr.results))
    diff = max(float((a.params.values - b.params.values).abs().max()) for a, b in zip(results, singles))
    same_sets = all(a.params.free_names == b.params.free_names for a, b in zip(results, singles))
    f, l_ = statistics.median(tf), statistics.median(tl)
    return {"fleet_s": f, "loop_s": l_, "ratio": l_ / f, "fleet_ms_per_robot": 1e3 * f / len(data),
            "loop_ms_per_robot": 1e3 * l_ / len(data), "ratio_cpu_time": statistics.median(cl) / statistics.median(cf),
            "fleet_cpu_ms_per_robot": 1e3 * statistics.median(cf) / len(data), "fleet_results_s": t_res,
            "fleet_s_all": tf, "loop_s_all": tl, "max_param_diff_mm_or_mrad": 1e3 * diff, "same_free_sets": same_sets}


def fleet_alone(robot: Robot, data: list, reps: int) -> dict:
    """The fleet solve alone, ``reps`` times: median wall and CPU time."""
    runs = [timed(lambda: calibrate_fleet(robot, data))[:2] for _ in range(reps)]
    t, c = statistics.median(r[0] for r in runs), statistics.median(r[1] for r in runs)
    return {"robots": len(data), "fleet_s": t, "fleet_ms_per_robot": 1e3 * t / len(data),
            "fleet_cpu_ms_per_robot": 1e3 * c / len(data), "fleet_s_all": [r[0] for r in runs]}


def sync(device: str) -> None:
    """Wait for the device's queued work, so that a wall-clock time covers it."""
    if device.startswith("cuda"):
        torch.cuda.synchronize()


def _solve_on(robot: Robot, data: list, device: str, results: bool = False) -> dict:
    """One fleet solve on ``device`` (data moved there first), timed to its last kernel, with the
    device memory it held at most (cuda) and, with ``results``, the time to build every robot's
    result afterwards (reasons in words included: Python per robot and parameter)."""
    cuda = device.startswith("cuda")
    if cuda:
        torch.cuda.empty_cache()
        torch.cuda.reset_peak_memory_stats()
        base = torch.cuda.memory_allocated()
    sync(device)
    t, c, fr = timed(lambda: (calibrate_fleet(robot, data), sync(device))[0])
    out = {"robots": len(data), "s": t, "ms_per_robot": 1e3 * t / len(data),
           "converged": sum(fr.results.converged())}
    if results:
        out["results_s"] = timed(lambda: list(fr.results))[0]
    if cuda:
        per = (torch.cuda.max_memory_allocated() - base) / len(data)
        out["peak_bytes_per_robot"] = per
        out["peak_gb_at_100k_extrapolated"] = per * 100_000 / 1e9
    return out


def device_figures(device: str, n_robots: int, poses: int, seed: int, populations=(1000, 10000),
                   cpu_robots: int | None = None, distinct: int | None = None, try_100k: bool = False) -> dict:
    """Population × poses FK throughput and the fleet solve at ``n_robots`` on ``device``, with this
    machine's CPU solving ``cpu_robots`` of the same robots in the same run (default
    ``min(n_robots, 1000)``) and the device solving them too (the GPU figures; on ``cpu`` the same
    code path, which the tests run at a small size)."""
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
        t, _, p = timed(lambda: (robot.positions(q, X, check=False), sync(device))[0])
        fk[f"{P}x{N}"] = {"s": t, "pairs_per_s": P * N / t, "shape": list(p.shape)}
    out["fk_population_x_poses"] = fk
    cpu = Robot.from_urdf(ROOT / "urdf" / "kuka_kr5_arc.urdf", markers=MARKERS)
    host = fleet_data(cpu, n_robots, poses, seed, distinct)
    data = [d.to(device) for d in host]
    calibrate_fleet(robot, data[:10])  # warm-up: kernels, caches
    sync(device)
    out["fleet_solve"] = _solve_on(robot, data, device)
    small = min(n_robots, cpu_robots or 1000)
    out["same_robots_smaller_fleet"] = {"robots": small, "cpu": _solve_on(cpu, host[:small], "cpu", True),
                                        "device": _solve_on(robot, data[:small], device, True)}
    if try_100k:
        big = fleet_data(cpu, 100_000, poses, seed, distinct or 1000)
        out["fleet_solve_100k"] = _solve_on(robot, [d.to(device) for d in big], device)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--robots", type=int, nargs="+", default=[10, 100, 1000])
    ap.add_argument("--poses", type=int, default=30)
    ap.add_argument("--reps", type=int, default=3)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--quick", action="store_true", help="R = 10 and 100 against the loop, the R = 1000 bar alone")
    ap.add_argument("--device", default=None, help="GPU figures on this device (default: cuda when present)")
    ap.add_argument("--gpu-robots", type=int, default=10000)
    ap.add_argument("--cpu-robots", type=int, default=None, help="the CPU's share of the GPU run (default 1000)")
    ap.add_argument("--try-100k", action="store_true", help="also solve 100 000 robots on the device")
    a = ap.parse_args()
    torch.set_num_threads(a.threads)
    robot = Robot.from_urdf(ROOT / "urdf" / "kuka_kr5_arc.urdf", markers=MARKERS)
    sizes = [r for r in a.robots if not (a.quick and r > 100)]
    reps = 1 if a.quick else a.reps
    calibrate_fleet(robot, fleet_data(robot, 4, a.poses, a.seed + 1))  # warm-up
    rows = {}
    for R in sizes:
        data = fleet_data(robot, R, a.poses, a.seed)
        rows[str(R)] = compare(robot, data, reps if R <= 100 else 1)
        print(f"R={R}: fleet {rows[str(R)]['fleet_s']:.2f} s, loop {rows[str(R)]['loop_s']:.2f} s, "
              f"ratio {rows[str(R)]['ratio']:.1f}", file=sys.stderr)
    if "1000" in rows:
        at = rows["1000"]
    else:
        at = fleet_alone(robot, fleet_data(robot, 1000, a.poses, a.seed), 1 if a.quick else 3)
    bar = {"robots": 1000, "fleet_ms_per_robot": at["fleet_ms_per_robot"],
           "fleet_cpu_ms_per_robot": at["fleet_cpu_ms_per_robot"], "bar_ms": BAR_MS,
           "met": at["fleet_ms_per_robot"] <= BAR_MS}
    print(f"R=1000: fleet {bar['fleet_ms_per_robot']:.2f} ms per robot (bar {BAR_MS} ms)", file=sys.stderr)
    device = a.device or ("cuda" if torch.cuda.is_available() else None)
    out = {"problem": f"KUKA KR5 arc URDF, marker on the flange, {a.poses} poses per robot, 0.5 mm / 1 mrad errors, "
                      "0.02 mm noise; fleet = calibrate_fleet, loop = calibrate(method='lm', prior=None) per robot",
           "ratio": {R: v["ratio"] for R, v in rows.items()}, "results": rows, "bar": bar,
           "target_10x_at_100": rows["100"]["ratio"] >= 10 if "100" in rows else None,
           "threads": a.threads, "torch": torch.__version__, "python": platform.python_version(),
           "machine": platform.machine(), "cpu": platform.processor() or platform.machine(),
           "gpu": device_figures(device, a.gpu_robots, a.poses, a.seed, cpu_robots=a.cpu_robots,
                                 distinct=1000 if a.quick else None, try_100k=a.try_100k)
           if device else "no GPU on this machine"}
    print(json.dumps(out))


if __name__ == "__main__":
    main()
