"""Benchmark: MMA-ELM training time and command-correction throughput.

Training: MMA-ELM exactly as ``scripts/seed002_mma_elm.py`` runs it (UR5e data, 300 training
+ 100 validation poses, 40 hidden neurons, 20 males + 20 females, 100 generations).

Correction: :class:`torchcal.deploy.correct.Corrector` with the resulting model-free model (nominal
kinematics + MMA-ELM), full 6-D pose targets, IK start = the nominal command (the branch), to
1 µm / 1 µrad predicted error. Throughput at batch 1 (median over repeated single-target calls)
and at batch 10 000 (one call). Also IK alone at batch 10 000.

Prints one JSON line; CPU, one thread (``--threads``), float64.
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
sys.path.insert(0, str(ROOT / "scripts"))

from seed002_mma_elm import make_data  # noqa: E402

from torchcal.sim.compliant_arm import CompliantArm, sample_q, ur5e_masses  # noqa: E402

from torchcal.deploy.correct import Corrector  # noqa: E402
from torchcal.elm import tune_elm  # noqa: E402
from torchcal.kinematics.ik import solve_ik  # noqa: E402
from torchcal.deploy.model import CalibratedModel, pose_error  # noqa: E402
from torchcal.kinematics.robots import shipped  # noqa: E402


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--train-runs", type=int, default=2)
    ap.add_argument("--big", type=int, default=10_000)
    ap.add_argument("--single-reps", type=int, default=30)
    ap.add_argument("--out")
    a = ap.parse_args(argv)
    torch.set_num_threads(a.threads)

    robot = shipped("ur5e")
    sim = CompliantArm(robot, ur5e_masses(robot), seed=0)
    data = make_data(robot, sim, 300, 100, 10, 1)
    X = {s: q for s, (q, _) in data.items()}
    Y = {s: pose_error(T, sim.measure(q)) for s, (q, T) in data.items()}

    opts = {"pop_size": 20, "max_iter": 100}
    times, res = [], None
    for s in range(a.train_runs):
        t0 = time.perf_counter()
        elm, res = tune_elm(X["train"], Y["train"], X["val"], Y["val"], "mma", 40, options=opts, seed=s)
        times.append(time.perf_counter() - t0)
    model = CalibratedModel(robot, robot.params(), residual=elm)
    corr = Corrector(model, frame="instrument")

    g = torch.Generator().manual_seed(123)
    q_big = sample_q(a.big, g)
    T_big = robot.fk(q_big)[:, 0]

    # batch 1: one target per call (what an online controller would do)
    single = []
    for i in range(a.single_reps + 3):
        t0 = time.perf_counter()
        r1 = corr.correct(T_big[i:i + 1], q0=q_big[i:i + 1])
        dt = time.perf_counter() - t0
        if i >= 3:  # warm-up calls excluded
            single.append(dt)
    # batch 1e4: one call
    t0 = time.perf_counter()
    rb = corr.correct(T_big, q0=q_big)
    t_big = time.perf_counter() - t0
    t0 = time.perf_counter()
    ik = solve_ik(robot, None, T_big, q_big + 1e-3)
    t_ik = time.perf_counter() - t0

    out = {
        "device": "cpu", "threads": a.threads, "dtype": "float64", "cpu": platform.processor() or platform.machine(),
        "torch": torch.__version__,
        "mma_elm_config": {"n_train": 300, "n_val": 100, "n_hidden": 40, "pop_size": 20, "max_iter": 100,
                           "n_evals": res.n_evals},
        "mma_elm_train_s": statistics.median(times), "mma_elm_train_s_runs": times,
        "mma_elm_ms_per_eval": 1e3 * statistics.median(times) / res.n_evals,
        "correct_single_ms": 1e3 * statistics.median(single),
        "correct_single_ms_p90": 1e3 * sorted(single)[int(0.9 * (len(single) - 1))],
        "correct_targets_per_s_1": 1.0 / statistics.median(single),
        "correct_batch": a.big, "correct_batch_s": t_big, "correct_targets_per_s_1e4": a.big / t_big,
        "correct_converged_frac_1e4": float(rb.converged.double().mean()),
        "correct_outer_rounds_max_1e4": int(rb.n_outer.max()),
        "correct_outer_rounds_mean_1e4": float(rb.n_outer.double().mean()),
        "ik_targets_per_s_1e4": a.big / t_ik, "ik_iters_mean_1e4": float(ik.n_iter.double().mean()),
    }
    line = json.dumps(out)
    print(line)
    if a.out:
        Path(a.out).write_text(line + "\n")
    return out


if __name__ == "__main__":
    main()
