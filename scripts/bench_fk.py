#!/usr/bin/env python
"""FK throughput of torchcal against pytorch-kinematics (and Pinocchio when installed), measured
in the same run on the same URDF, float64.

Three torchcal paths: ``robot.fk`` (4x4 poses, what pytorch-kinematics' ``get_matrix`` gives),
``robot.positions`` (points only, eager) and the fused position kernel
(:class:`~torchcal.kinematics.fk_fused.FusedPositions`, compiled with ``torch.compile`` unless
``--no-compile``; the time of its first calls, the compilation, is reported apart). The fused
kernel's largest difference from ``robot.positions`` is reported with its speed.

Prints one JSON line. Ratios are the figures to quote: absolute times depend on the machine and
on what else runs on it.

Threading: torch defaults to one thread per core. On small batches (a single configuration, a
240 x 30 population) the per-op work is microseconds, and a second thread only adds hand-off
cost — and when another process holds one of the two cores, a 2-thread torch waits on it and
collapses by 60-90x. We therefore measure (and recommend) ``torch.set_num_threads(1)`` for
small batches; ``--threads`` changes it for all measurements.

Usage: python scripts/bench_fk.py [--robot kuka_kr5_arc] [--threads 1] [--device cpu]
       [--sizes 1 1000 100000] [--no-compile] [--mode reduce-overhead]
"""
from __future__ import annotations

import argparse
import json
import math
import platform
import statistics
import sys
import time
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from torchcal import Robot  # noqa: E402
from torchcal.kinematics.fk_fused import FusedPositions  # noqa: E402

TAGS = {1: "1", 1000: "1e3", 100000: "1e5", 1000000: "1e6"}


def timeit(fn, *, min_time=0.3, max_reps=2000, sync=lambda: None) -> float:
    """Median seconds per call over repeated calls (after two warm-up calls)."""
    fn(), fn()
    sync()
    times, start = [], time.perf_counter()
    while len(times) < max_reps and (time.perf_counter() - start < min_time or len(times) < 5):
        t = time.perf_counter()
        fn()
        sync()
        times.append(time.perf_counter() - t)
    return statistics.median(times)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--robot", default="kuka_kr5_arc", help="shipped URDF name in urdf/")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--sizes", type=int, nargs="+", default=[1, 1000, 100000], choices=sorted(TAGS),
                    help="batch sizes (configurations per call)")
    ap.add_argument("--no-compile", action="store_true", help="run the fused kernel eagerly")
    ap.add_argument("--mode", default=None, help="torch.compile mode of the fused kernel")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    dev = torch.device(args.device)
    sync = (lambda: torch.cuda.synchronize()) if dev.type == "cuda" else (lambda: None)
    urdf = ROOT / "urdf" / f"{args.robot}.urdf"
    text = urdf.read_text()
    robot = Robot.from_urdf(urdf, markers=["flange"], device=dev)
    g = torch.Generator().manual_seed(args.seed)
    lo, hi = robot.joint_limits
    lo, hi = lo.clamp(min=-math.pi).cpu(), hi.clamp(max=math.pi).cpu()

    def configs(n):
        return (lo + (hi - lo) * torch.rand(n, robot.dof, generator=g, dtype=torch.float64)).to(dev)

    out = {"robot": args.robot, "device": str(dev), "threads": args.threads, "dtype": "float64",
           "torch": torch.__version__, "python": platform.python_version()}

    import pytorch_kinematics as pk

    chain = pk.build_serial_chain_from_urdf(text, "flange").to(dtype=torch.float64, device=dev)
    names = chain.get_joint_parameter_names()
    perm = [robot.joint_names.index(n) for n in names]

    params = (1e-3 * torch.randn(robot.n_params, generator=g, dtype=torch.float64)).to(dev)
    fused = FusedPositions(robot, compile=not args.no_compile, mode=args.mode)
    t0 = time.perf_counter()
    fused(configs(7)), fused(configs(9))  # compile (batch sizes symbolic: once)
    sync()
    out["fused_first_calls_s"] = time.perf_counter() - t0
    out["fused_compiled"] = fused.compiled
    out["fused_mode"] = args.mode
    for n in args.sizes:
        q = configs(n)
        qp = q[:, perm].contiguous()
        t_tc = timeit(lambda: robot.fk(q), sync=sync)
        t_pk = timeit(lambda: chain.forward_kinematics(qp).get_matrix(), sync=sync)
        t_pos = timeit(lambda: robot.positions(q, check=False), sync=sync)
        t_fu = timeit(lambda: fused(q), sync=sync)
        tag = TAGS[n]
        out[f"positions_cfg_per_s_{tag}"] = n / t_pos
        out[f"fused_cfg_per_s_{tag}"] = n / t_fu
        out[f"fused_vs_pk_{tag}"] = t_pk / t_fu
        out[f"fused_vs_positions_{tag}"] = t_pos / t_fu
        out[f"fused_max_abs_diff_m_{tag}"] = float((fused(q) - robot.positions(q)).abs().max())

        def with_grad():
            p = params.clone().requires_grad_(True)
            robot.fk(q, p).sum().backward()

        t_gr = timeit(with_grad, sync=sync)
        out[f"torchcal_cfg_per_s_{tag}"] = n / t_tc
        out[f"pk_cfg_per_s_{tag}"] = n / t_pk
        out[f"ratio_vs_pk_{tag}"] = t_pk / t_tc
        out[f"torchcal_grad_params_cfg_per_s_{tag}"] = n / t_gr
    if "torchcal_cfg_per_s_1" in out:
        out["single_config_ms"] = 1e3 / out["torchcal_cfg_per_s_1"]
        out["pk_single_config_ms"] = 1e3 / out["pk_cfg_per_s_1"]
    # agreement, so the speed is for the same numbers
    q = configs(100)
    Tp = chain.forward_kinematics(q[:, perm]).get_matrix()
    out["max_abs_diff_vs_pk"] = float((robot.fk(q)[:, 0] - Tp).abs().max())

    # population: 240 parameter vectors x 30 poses (what a swarm evaluates per iteration)
    P = (1e-3 * torch.randn(240, robot.n_params, generator=g, dtype=torch.float64)).to(dev)
    q30 = configs(30)
    out["population_240x30_ms"] = 1e3 * timeit(lambda: robot.positions(q30, P), sync=sync)
    out["population_240x30_pose_ms"] = 1e3 * timeit(lambda: robot.fk(q30, P), sync=sync)
    fused(q30, P), fused(q30, P[:7])  # compile the population call
    out["population_240x30_fused_ms"] = 1e3 * timeit(lambda: fused(q30, P), sync=sync)
    out["population_240x30_fused_max_abs_diff_m"] = float((fused(q30, P) - robot.positions(q30, P)).abs().max())
    out["population_measures"] = ("population_240x30_ms: marker positions (what position residuals use); _pose_ms: "
                                  "full 4x4; _fused_ms: the fused position kernel")

    try:  # Pinocchio, one configuration at a time from Python, 4x4 copied out (optional peer)
        import pinocchio as pin

        model = pin.buildModelFromXML(text)
        data = model.createData()
        fid = model.getFrameId("flange")
        if list(model.names)[1:] != robot.joint_names:
            raise ImportError("joint order differs")  # not comparable as is: skip the peer
        qn = configs(2000).cpu().numpy()

        def pin_loop():
            for row in qn:
                pin.framesForwardKinematics(model, data, row)
                data.oMf[fid].homogeneous.copy()

        t = timeit(pin_loop, min_time=0.5, max_reps=20)
        out["pinocchio_loop_cfg_per_s"] = len(qn) / t
        if "torchcal_cfg_per_s_1e5" in out:
            out["ratio_vs_pinocchio_loop_1e5"] = out["torchcal_cfg_per_s_1e5"] / out["pinocchio_loop_cfg_per_s"]
        pin.framesForwardKinematics(model, data, qn[0])
        T0 = robot.fk(torch.as_tensor(qn[:1], device=dev))[0, 0].cpu().numpy()
        out["max_abs_diff_vs_pinocchio"] = float(abs(T0 - data.oMf[fid].homogeneous).max())
    except ImportError:
        out["pinocchio_loop_cfg_per_s"] = None
    print(json.dumps(out))


if __name__ == "__main__":
    main()
