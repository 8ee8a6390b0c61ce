#!/usr/bin/env python
"""The GPU figures of issue 26, one per call, each against the CPU of the same machine in the same run.

``python scripts/gpu_figures.py FIGURE [--device cuda] [--cpu-dry-run]`` prints one JSON line:
the figure, the card, the CPU (model, threads), the times on the CPU with one thread (and with all
cores where a batch is large enough to use them), on the device, their ratio, the bar of the issue
and whether it is met, and how far the device's numbers are from the CPU's. scripts/gpu_check.sh
runs every figure, each in its own process and time limit.

Figures:
  calibrate   calibrate(method="lm"), KR5 arc URDF, 300 simulated poses (bar: device <= 1.5x CPU 1 thread)
  loop        run_loop, KR5 arc, 300 + 150 poses with joint compliance (bar: <= 1.5x CPU 1 thread)
  fleet       calibrate_fleet, 30 poses per robot: CPU at R = 1000, device at R = 1000 and 10 000
              (bar: <= 2 s at 10 000, goal 1 s). The 10 000 data sets are the 1000 simulated ones ten
              times over: the same work per robot, a tenth of the simulation time.
  fk          positions of the KR5 flange at batch 1e3, 1e5, 1e6: robot.positions (eager), the fused
              kernel (torchcal.kinematics.fk_fused, compiled) and pytorch-kinematics' FK
              (bars: >= 5e8 cfg/s at 1e6; at 1e3 at least pytorch-kinematics)
  pop240      one swarm step's fitness kinematics: 240 parameter vectors x 30 poses (bar: <= 0.3 ms):
              robot.positions, the compact kernel, the fused kernel (and the CPU's best, compact)
  pop240_cudagraph  the same fused call with CUDA graphs on top (compiles again)
  pop10000    10 000 parameter vectors x 1000 poses (pairs/s; keep >= 4e8)

``--cpu-dry-run`` runs the same code with the device part on the CPU, at reduced sizes and with
the fused kernel uncompiled: it checks the script, not the figures.

Timing: the median of repeated calls after warm-up calls (a figure's first device call is
reported apart as ``*_first_s``: it loads kernels); ``torch.cuda.synchronize`` before every clock
read on the device; float64 throughout.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import platform
import statistics
import sys
import time
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "scripts"))

from torchcal import Robot, calibrate  # noqa: E402
from torchcal.kinematics.fk_compact import PositionKernel  # noqa: E402
from torchcal.kinematics.fk_fused import FusedPositions  # noqa: E402
from torchcal.kinematics.robots import shipped  # noqa: E402
from torchcal.sim.serial import SimConfig, simulate  # noqa: E402

URDF = ROOT / "urdf" / "kuka_kr5_arc.urdf"
ALL = os.cpu_count() or 1


def cpu_name() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


class Clock:
    """Timing on one device: ``sync`` waits for its queued work."""

    def __init__(self, device: torch.device):
        self.device = device
        self.sync = torch.cuda.synchronize if device.type == "cuda" else (lambda: None)

    def once(self, fn):
        self.sync()
        t = time.perf_counter()
        out = fn()
        self.sync()
        return time.perf_counter() - t, out

    def median(self, fn, reps: int = 5, warm: int = 2, min_time: float = 0.0) -> float:
        for _ in range(warm):
            fn()
        times, start = [], time.perf_counter()
        while len(times) < reps or time.perf_counter() - start < min_time:
            times.append(self.once(fn)[0])
            if len(times) >= 200:
                break
        return statistics.median(times)


def attempt(fn):
    """``fn()``, or the error in words: one path failing leaves the figure's other numbers."""
    try:
        return fn()
    except Exception as e:  # noqa: BLE001 - reported in the JSON line
        return f"error: {type(e).__name__}: {str(e).splitlines()[0] if str(e) else ''}"[:300]


def on_threads(n: int, fn):
    old = torch.get_num_threads()
    torch.set_num_threads(n)
    try:
        return fn()
    finally:
        torch.set_num_threads(old)


# ------------------------------------------------------------------------------------------ figures
def fig_calibrate(dev: torch.device, small: bool) -> dict:
    n = 60 if small else 300
    cpu = Robot.from_urdf(URDF, markers=["smr@flange=0,0,0"])
    data = simulate(cpu, SimConfig(n=n, seed=0))[0]
    c = Clock(torch.device("cpu"))
    reps = 2 if small else 5
    res_cpu = calibrate(cpu, data, method="lm")
    t1 = on_threads(1, lambda: c.median(lambda: calibrate(cpu, data, method="lm"), reps=reps, warm=1))
    tall = on_threads(ALL, lambda: c.median(lambda: calibrate(cpu, data, method="lm"), reps=reps, warm=1))
    gpu, dd = cpu.to(dev), data.to(dev)
    d = Clock(dev)
    first, res = d.once(lambda: calibrate(gpu, dd, method="lm"))
    td = d.median(lambda: calibrate(gpu, dd, method="lm"), reps=reps, warm=1)
    return dict(poses=n, n_params=len(res.params.free_names), lm_iter=res.solver.n_iter, cpu_1thread_s=t1,
                cpu_all_s=tall, device_first_s=first, device_s=td, ratio_device_vs_cpu_1thread=td / t1, bar=1.5,
                met=td / t1 <= 1.5, same_free_set=res.params.free_names == res_cpu.params.free_names,
                max_param_diff=float((res.params.values.cpu() - res_cpu.params.values).abs().max()))


def fig_loop(dev: torch.device, small: bool) -> dict:
    import bench_loop
    from torchcal.pipelines.loop.run import run_loop

    n_tr, n_te = (60, 30) if small else (300, 150)
    robot = shipped("kuka_kr5_arc")
    train, test, _ = bench_loop.make_data(robot, "joint_compliance", n_tr, n_te, 0, 2e-5)
    c, d = Clock(torch.device("cpu")), Clock(dev)
    t1, a = on_threads(1, lambda: c.once(lambda: run_loop(robot, train, test, log=None)))
    gpu = robot.to(dev)
    calibrate(gpu, train.subset(torch.arange(30)).to(dev), method="lm")  # load the kernels
    td, b = d.once(lambda: run_loop(gpu, train.to(dev), test.to(dev), log=None))
    return dict(train=n_tr, test=n_te, cpu_1thread_s=t1, device_s=td, ratio_device_vs_cpu_1thread=td / t1, bar=1.5,
                met=td / t1 <= 1.5, stages_cpu=[s["name"] for s in a.stages], stages_device=[s["name"] for s in b.stages],
                same_decisions=[s["name"] for s in a.stages] == [s["name"] for s in b.stages],
                max_param_diff=float((b.params.values.cpu() - a.params.values).abs().max())
                if a.params.names == b.params.names else None,
                test_mean_mm_cpu=a.stages[-1]["test"]["mean_mm"], test_mean_mm_device=b.stages[-1]["test"]["mean_mm"])


def fig_fleet(dev: torch.device, small: bool):
    """Yields a row for the CPU's robots on both sides, then one for the device's large fleet."""
    import bench_fleet
    from torchcal.pipelines.fleet.run import calibrate_fleet

    R_cpu, R_dev = (20, 60) if small else (1000, 10000)
    cpu = Robot.from_urdf(URDF, markers=bench_fleet.MARKERS)
    data = bench_fleet.fleet_data(cpu, R_cpu, 30, 0)
    c, d = Clock(torch.device("cpu")), Clock(dev)
    calibrate_fleet(cpu, data[:4])
    t_cpu, fr_cpu = on_threads(1, lambda: c.once(lambda: calibrate_fleet(cpu, data)))
    gpu = cpu.to(dev)
    dd = [x.to(dev) for x in data]
    calibrate_fleet(gpu, dd[:10])  # load the kernels
    t_same, fr_same = d.once(lambda: calibrate_fleet(gpu, dd))
    diff = max(float((a.params.values.cpu() - b.params.values).abs().max()) for a, b in
               zip(fr_same.results, fr_cpu.results))
    yield dict(figure=f"fleet_{R_cpu}", poses=30, robots=R_cpu, cpu_1thread_s=t_cpu, cpu_ms_per_robot=1e3 * t_cpu / R_cpu,
               device_s=t_same, device_ms_per_robot=1e3 * t_same / R_cpu, ratio_device_vs_cpu_1thread=t_same / t_cpu,
               max_param_diff=diff)
    big = dd * (R_dev // R_cpu)
    t_big, fr_big = d.once(lambda: calibrate_fleet(gpu, big))
    yield dict(figure=f"fleet_{len(big)}", poses=30, robots=len(big), cpu_1thread_ms_per_robot_at_1000=1e3 * t_cpu / R_cpu,
               device_s=t_big, device_ms_per_robot=1e3 * t_big / len(big), bar_s=2.0, goal_s=1.0, met=t_big <= 2.0,
               converged_device=sum(fr_big.results.converged()),
               note="the data sets are the simulated ones repeated (the same work per robot)")


def _configs(robot: Robot, n: int, g: torch.Generator) -> torch.Tensor:
    lo, hi = (x.clamp(-math.pi, math.pi) for x in robot.joint_limits)
    return lo + (hi - lo) * torch.rand(n, robot.dof, generator=g, dtype=torch.float64)


def fig_fk(dev: torch.device, small: bool):
    """Yields a row per batch size."""
    import pytorch_kinematics as pk

    cpu = Robot.from_urdf(URDF, markers=["flange"])
    gpu = cpu.to(dev)
    chain = pk.build_serial_chain_from_urdf(URDF.read_text(), "flange").to(dtype=torch.float64, device=dev)
    perm = [cpu.joint_names.index(n) for n in chain.get_joint_parameter_names()]
    fused = FusedPositions(gpu, compile="auto" if not small else False)
    g = torch.Generator().manual_seed(0)
    c, d = Clock(torch.device("cpu")), Clock(dev)
    t_compile, _ = d.once(lambda: (fused(_configs(cpu, 7, g).to(dev)), fused(_configs(cpu, 9, g).to(dev))))
    for n in ((1000, 20000) if small else (1000, 100000, 1000000)):
        q = _configs(cpu, n, g)
        qd = q.to(dev)
        qp = qd[:, perm].contiguous()
        mt = 0.05 if small else 0.2
        t_eager = d.median(lambda: gpu.positions(qd, check=False), min_time=mt)
        t_fused = d.median(lambda: fused(qd), min_time=mt)
        t_pk = d.median(lambda: chain.forward_kinematics(qp).get_matrix(), min_time=mt)
        t_c1 = on_threads(1, lambda: c.median(lambda: cpu.positions(q, check=False), reps=3, warm=1))
        t_ca = on_threads(ALL, lambda: c.median(lambda: cpu.positions(q, check=False), reps=3, warm=1))
        ref = cpu.positions(q[:2000])
        row = dict(figure=f"fk_positions_{n:.0e}".replace("+0", ""), batch=n,
                   device_eager_cfg_per_s=n / t_eager, device_fused_cfg_per_s=n / t_fused, device_pk_cfg_per_s=n / t_pk,
                   cpu_1thread_cfg_per_s=n / t_c1, cpu_all_cfg_per_s=n / t_ca, fused_vs_pk=t_pk / t_fused,
                   fused_vs_eager=t_eager / t_fused, fused_compiled=fused.compiled, fused_first_calls_s=t_compile,
                   fused_max_diff_vs_cpu_m=float((fused(qd[:2000]).cpu() - ref).abs().max()),
                   eager_max_diff_vs_cpu_m=float((gpu.positions(qd[:2000]).cpu() - ref).abs().max()))
        if n == 1000:
            row.update(bar="fused >= pytorch-kinematics", met=t_fused <= t_pk)
        if n == 1000000:
            row.update(bar="fused >= 5e8 cfg/s", met=n / t_fused >= 5e8)
        yield row


def fig_pop240(dev: torch.device, small: bool) -> dict:
    cpu = Robot.from_urdf(URDF, markers=["smr@flange=0,0,0"])
    gpu = cpu.to(dev)
    g = torch.Generator().manual_seed(1)
    q = _configs(cpu, 30, g)
    X = 1e-3 * torch.randn(240, cpu.n_params, generator=g, dtype=torch.float64)
    qd, Xd = q.to(dev), X.to(dev)
    zero, idx = torch.zeros(cpu.n_params, dtype=torch.float64), torch.arange(cpu.n_params)
    c, d = Clock(torch.device("cpu")), Clock(dev)
    compact_cpu = PositionKernel(cpu, q, zero, idx)
    fused = FusedPositions(gpu, compile="auto" if not small else False)
    t_first, _ = d.once(lambda: (fused(qd, Xd), fused(qd, Xd[:7])))
    ref = cpu.positions(q, X)
    ms = lambda clock, fn: 1e3 * clock.median(fn, min_time=0.1)  # noqa: E731

    def compact_dev():
        kern = PositionKernel(gpu, qd, zero.to(dev), idx.to(dev))
        return ms(d, lambda: kern(Xd))

    out = dict(population=240, poses=30,
               cpu_1thread_positions_ms=on_threads(1, lambda: ms(c, lambda: cpu.positions(q, X))),
               cpu_1thread_compact_ms=on_threads(1, lambda: ms(c, lambda: compact_cpu(X))),
               cpu_all_compact_ms=on_threads(ALL, lambda: ms(c, lambda: compact_cpu(X))),
               device_positions_ms=attempt(lambda: ms(d, lambda: gpu.positions(qd, Xd))),
               device_compact_ms=attempt(compact_dev),
               device_fused_ms=ms(d, lambda: fused(qd, Xd)), fused_first_calls_s=t_first, fused_compiled=fused.compiled,
               fused_max_diff_vs_cpu_m=float((fused(qd, Xd).cpu() - ref).abs().max()))
    best = min(v for k, v in out.items() if k.startswith("device_") and k.endswith("_ms") and isinstance(v, float))
    out.update(device_best_ms=best, bar_ms=0.3, met=best <= 0.3)
    return out


def fig_pop240_cudagraph(dev: torch.device, small: bool) -> dict:
    """The fused population call with CUDA graphs on top (``mode="reduce-overhead"``: the launches
    of a call replayed at once); a figure of its own, as it compiles again."""
    cpu = Robot.from_urdf(URDF, markers=["smr@flange=0,0,0"])
    g = torch.Generator().manual_seed(1)
    q = _configs(cpu, 30, g)
    X = 1e-3 * torch.randn(240, cpu.n_params, generator=g, dtype=torch.float64)
    qd, Xd = q.to(dev), X.to(dev)
    d = Clock(dev)
    mode = "reduce-overhead" if dev.type == "cuda" else None
    graphed = FusedPositions(cpu.to(dev), mode=mode, compile="auto" if not small else False)
    t_g, _ = d.once(lambda: (graphed(qd, Xd), graphed(qd, Xd)))
    ms = 1e3 * d.median(lambda: graphed(qd, Xd), min_time=0.1)
    return dict(population=240, poses=30, mode=mode, device_fused_cudagraph_ms=ms, first_calls_s=t_g,
                compiled=graphed.compiled, max_diff_vs_cpu_m=float((graphed(qd, Xd).cpu() - cpu.positions(q, X)).abs().max()),
                bar_ms=0.3, met=ms <= 0.3)


def fig_pop10000(dev: torch.device, small: bool) -> dict:
    P, N = (200, 100) if small else (10000, 1000)
    cpu = Robot.from_urdf(URDF, markers=["smr@flange=0,0,0"])
    gpu = cpu.to(dev)
    g = torch.Generator().manual_seed(2)
    q, X = _configs(cpu, N, g), 1e-3 * torch.randn(P, cpu.n_params, generator=g, dtype=torch.float64)
    qd, Xd = q.to(dev), X.to(dev)
    d, c = Clock(dev), Clock(torch.device("cpu"))
    fused = FusedPositions(gpu, compile="auto" if not small else False)
    t_first, _ = d.once(lambda: (fused(qd, Xd[:50]), fused(qd, Xd[:60])))
    t_eager = d.median(lambda: gpu.positions(qd, Xd, check=False), reps=3, warm=1)
    t_fused = d.median(lambda: fused(qd, Xd), reps=3, warm=1)
    Pc = max(P // 10, 1)  # the CPU at a tenth of the population (pairs/s is what compares)
    t_cpu = on_threads(ALL, lambda: c.median(lambda: cpu.positions(q, X[:Pc], check=False), reps=2, warm=1))
    ref = cpu.positions(q[:50], X[:20])
    return dict(population=P, poses=N, device_eager_pairs_per_s=P * N / t_eager, device_fused_pairs_per_s=P * N / t_fused,
                cpu_all_pairs_per_s=Pc * N / t_cpu, fused_first_calls_s=t_first, fused_compiled=fused.compiled,
                fused_max_diff_vs_cpu_m=float((fused(qd[:50], Xd[:20]).cpu() - ref).abs().max()),
                bar="keep >= 4e8 pairs/s", met=max(P * N / t_eager, P * N / t_fused) >= 4e8)


# what the closing table shows of each figure: (label, key, format)
_SHOWN = {"calibrate": ("cuda / cpu 1 thread", "ratio_device_vs_cpu_1thread", "{:.2f}x"),
          "loop": ("cuda / cpu 1 thread", "ratio_device_vs_cpu_1thread", "{:.2f}x"),
          "fleet": ("cuda s", "device_s", "{:.2f} s"),
          "pop240": ("best cuda ms", "device_best_ms", "{:.3f} ms"),
          "pop240_cudagraph": ("cuda graph ms", "device_fused_cudagraph_ms", "{:.3f} ms"),
          "pop10000": ("fused pairs/s", "device_fused_pairs_per_s", "{:.3g}")}


def print_table(path: Path) -> None:
    """A short table of the JSON lines in ``path``: figure, the headline number, bar, met."""
    print(f"{'figure':<22} {'headline':<34} {'met':<6} card / note")
    for line in path.read_text().splitlines():
        try:
            r = json.loads(line)
        except ValueError:
            continue
        f = r.get("figure", "?")
        if "error" in r:
            print(f"{f:<22} {'ERROR':<34} {'-':<6} {r['error'][:70]}")
            continue
        if f.startswith("fk_positions"):
            head = f"fused {r['device_fused_cfg_per_s']:.3g} cfg/s ({r['fused_vs_pk']:.1f}x pk)"
        elif f == "pytest_gpu":
            head = r.get("summary", "")[:34]
        elif (f if f in _SHOWN else f.split("_")[0]) in _SHOWN:
            label, key, fmt = _SHOWN[f if f in _SHOWN else f.split("_")[0]]
            head = f"{label} {fmt.format(r[key])}" + (f" at R = {r['robots']}" if f.startswith("fleet") else "")
        else:
            head = ""
        print(f"{f:<22} {head:<34} {str(r.get('met', '-')):<6} {r.get('card', '')}")


FIGURES = {"calibrate": fig_calibrate, "loop": fig_loop, "fleet": fig_fleet, "fk": fig_fk, "pop240": fig_pop240,
           "pop10000": fig_pop10000, "pop240_cudagraph": fig_pop240_cudagraph}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("figure", choices=sorted(FIGURES) + ["table"], help="a figure, or 'table' of --jsonl")
    ap.add_argument("--jsonl", type=Path, help="with 'table': the JSON lines to tabulate")
    ap.add_argument("--device", default="cuda")
    ap.add_argument("--cpu-dry-run", action="store_true", help="device part on the CPU, small sizes: checks the script")
    a = ap.parse_args()
    if a.figure == "table":
        return print_table(a.jsonl)
    dev = torch.device("cpu" if a.cpu_dry_run else a.device)
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise SystemExit(f"no CUDA device here (torch {torch.__version__}); use --cpu-dry-run to check the script")
    torch.set_num_threads(1)
    head = dict(card=torch.cuda.get_device_name(dev) if dev.type == "cuda" else "none (dry run on the CPU)",
                cpu=cpu_name(), cpu_threads_all=ALL, torch=torch.__version__, python=platform.python_version(),
                dtype="float64", dry_run=a.cpu_dry_run)
    t0 = time.perf_counter()
    rows = FIGURES[a.figure](dev, a.cpu_dry_run)
    for row in [rows] if isinstance(rows, dict) else rows:  # a generator prints each row as it comes
        print(json.dumps({"figure": row.pop("figure", a.figure), **head, **row, "wall_s": time.perf_counter() - t0}),
              flush=True)


if __name__ == "__main__":
    main()
