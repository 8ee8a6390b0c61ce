"""Train the small model shipped in ``models/kuka_kr5_arc/`` (KUKA KR 5 arc demo).

Simulated data: the KR 5 arc of ``urdf/kuka_kr5_arc.urdf`` with geometric errors
(:func:`torchcal.sim.serial.random_errors`, 0.5 mm / 1 mrad std) plus non-geometric errors: joint
compliance under gravity (lumped link masses: KUKA publishes no per-link inertials, so the
masses below are an illustrative split of the arm's weight) and a cyclic joint error on A2/A3.
The instrument measures the flange pose (position 20 µm, orientation 20 µrad noise) in the
robot base frame. The truth stays inside :class:`CompliantArm`; the fitting code sees only
(commanded q, measured pose).

Model: ``calibrate(kind="pose")`` on 300 + 100 poses, then an MMA-ELM (30 hidden neurons) on the
6-D pose error left after the calibrated kinematics. Written with :func:`torchcal.save`, with
``targets.csv`` (a few targets with IK start columns, one of them out of reach) and
``expected_corrections.csv`` (what ``torchcal correct`` gives for them), so that a test can check
that loading and correcting reproduces the stored results.

Run: ``.venv/bin/python scripts/train_kr5_model.py [--out models/kuka_kr5_arc]``.
"""
from __future__ import annotations

import argparse
import csv
import json
import sys
import time
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "scripts"))

from torchcal.sim.compliant_arm import CompliantArm  # noqa: E402

from torchcal import calibrate  # noqa: E402
from torchcal.cli.correct import correct_main  # noqa: E402
from torchcal.kinematics.transforms import matrix_to_quat  # noqa: E402
from torchcal.deploy.correct import Corrector  # noqa: E402
from torchcal.elm import tune_elm  # noqa: E402
from torchcal.measure.data import Measurements  # noqa: E402
from torchcal.deploy.model import CalibratedModel, pose_error  # noqa: E402
from torchcal.deploy.persist import load, save  # noqa: E402
from torchcal.kinematics.robots import shipped  # noqa: E402

#: lumped masses (kg) at points on the links (m, link frames): upper arm, elbow housing, forearm,
#: wrist, and a 3 kg tool 5 cm beyond the flange
KR5_MASSES = [("upper_arm@link2=0.3,0,0", 25.0), ("elbow@link3=0.06,0,0", 15.0),
              ("forearm@link4=0,0,0.31", 10.0), ("wrist@link5=0,0,0", 4.0),
              ("payload@flange=0,0,0.05", 3.0)]
#: rad per N m; A2/A3 carry the large gravity torques (~100–250 N m)
KR5_COMPLIANCE = (0.0, 2e-6, 3e-6, 1e-5, 1e-5, 0.0)
KR5_CYCLIC = {1: (1e-4, 5e-5), 2: (-1e-4, 5e-5)}
#: working region (rad): centre and half-width per joint, in front of the robot
CENTER = (0.0, -1.0, 1.2, 0.0, 0.6, 0.0)
HALF = (0.8, 0.4, 0.5, 1.0, 0.6, 1.2)


def sample_q(n: int, g: torch.Generator) -> torch.Tensor:
    c, h = torch.tensor(CENTER, dtype=torch.float64), torch.tensor(HALF, dtype=torch.float64)
    return c + h * (2 * torch.rand(n, 6, generator=g, dtype=torch.float64) - 1)


def write_targets(path: Path, T: torch.Tensor, q0: torch.Tensor, joint_names: list[str]) -> None:
    qt = matrix_to_quat(T[:, :3, :3])
    with open(path, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["x", "y", "z", "qw", "qx", "qy", "qz", *joint_names])
        for i in range(T.shape[0]):
            w.writerow([repr(float(v)) for v in (*T[i, :3, 3], *qt[i], *q0[i])])


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", default=str(ROOT / "models" / "kuka_kr5_arc"))
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--hidden", type=int, default=30)
    a = ap.parse_args(argv)
    torch.set_num_threads(1)
    t0 = time.perf_counter()

    robot = shipped("kuka_kr5_arc")
    sim = CompliantArm(robot, KR5_MASSES, seed=a.seed, compliance=KR5_COMPLIANCE, cyclic=KR5_CYCLIC)
    g = torch.Generator().manual_seed(a.seed + 1)
    q = {s: sample_q(n, g) for s, n in (("train", 300), ("val", 100), ("test", 200))}
    T = {s: sim.measure(v) for s, v in q.items()}  # the only thing fitting code sees, with q

    qa, Ta = torch.cat([q["train"], q["val"]]), torch.cat([T["train"], T["val"]])
    meas = Measurements(qa, Ta[:, None, :3, 3].clone(), list(robot.marker_names), list(robot.joint_names),
                        quaternions=matrix_to_quat(Ta[:, :3, :3])[:, None].clone())
    test = Measurements(q["test"], T["test"][:, None, :3, 3].clone(), list(robot.marker_names),
                        list(robot.joint_names), quaternions=matrix_to_quat(T["test"][:, :3, :3])[:, None].clone())
    cal = calibrate(robot, meas, test=test, method="lm", kind="pose")
    R = {s: pose_error(robot.fk(q[s], cal.params)[:, 0], T[s]) for s in q}
    elm, res = tune_elm(q["train"], R["train"], q["val"], R["val"], "mma", a.hidden,
                        options={"pop_size": 10, "max_iter": 40}, seed=a.seed)
    rmse = elm.rmse(q["test"], R["test"])

    # correction on held-out targets, evaluated on the simulated robot
    T_t = robot.fk(q["test"])[:, 0]  # nominal targets; IK on the nominal model gives q["test"]
    model = CalibratedModel(robot, cal.params, residual=elm)
    cr = Corrector(model, frame="instrument").correct(T_t, q0=q["test"])
    before = (sim.pose(q["test"])[:, :3, 3] - T_t[:, :3, 3]).norm(dim=-1) * 1e3
    after = (sim.pose(cr.q)[:, :3, 3] - T_t[:, :3, 3]).norm(dim=-1) * 1e3
    geo = Corrector(CalibratedModel(robot, cal.params), frame="instrument").correct(T_t, q0=q["test"])
    after_geo = (sim.pose(geo.q)[:, :3, 3] - T_t[:, :3, 3]).norm(dim=-1) * 1e3

    model.meta = {
        "description": "KUKA KR 5 arc demo model: simulated data (geometric errors + gravity compliance + "
                       "cyclic joint error), pose calibration + MMA-ELM residual. Made by scripts/train_kr5_model.py.",
        "frame": "robot base frame (the simulated instrument measured in the base frame)",
        "training": {"n_train": 300, "n_val": 100, "n_test": 200, "seed": a.seed, "simulated": True,
                     "q_center_rad": list(CENTER), "q_half_width_rad": list(HALF),
                     "noise": {"position_m": sim.noise_m, "rotation_rad": sim.noise_rad},
                     "calibration": {"method": "lm", "kind": "pose", "n_params": int(cal.params.free.sum())},
                     "residual": {"method": "mma", "pop_size": 10, "max_iter": 40, "n_evals": res.n_evals,
                                  "val_rmse_standardised": res.fun}},
        "metrics": {"calibration_test_mean_mm": cal.stages[-1]["test"]["mean_mm"],
                    "nominal_test_mean_mm": cal.stages[0]["test"]["mean_mm"],
                    "residual_rmse_test": {n: float(v) * 1e3 for n, v in
                                           zip(["dx_mm", "dy_mm", "dz_mm", "droll_mrad", "dpitch_mrad", "dyaw_mrad"], rmse)},
                    "correction_before_mean_mm": float(before.mean()),
                    "correction_after_geometric_only_mean_mm": float(after_geo.mean()),
                    "correction_after_mean_mm": float(after.mean()),
                    "correction_reduction_pct": float(100 * (1 - after.mean() / before.mean()))},
    }
    out = Path(a.out)
    save(model, out, force=True)  # this script regenerates the shipped model

    # a few demo targets: nominal poses in the region (IK start = their nominal command), and one
    # out of reach, corrected through the saved model exactly as `torchcal correct` does
    gd = torch.Generator().manual_seed(a.seed + 7)
    qd = sample_q(6, gd)
    Td = robot.fk(qd)[:, 0]
    far = Td[:1].clone()
    far[0, :3, 3] = torch.tensor([2.5, 0.0, 0.5], dtype=torch.float64)
    write_targets(out / "targets.csv", torch.cat([Td, far]), torch.cat([qd, qd[:1]]), robot.joint_names)
    args = argparse.Namespace(model=str(out), targets=str(out / "targets.csv"),
                              out=str(out / "expected_corrections.csv"), tol_mm=1e-3, tol_mrad=1e-3,
                              max_outer=10, allow_failures=True, threads=1, frame="instrument", force=True)
    correct_main(args)
    # the loaded model must predict exactly what the trained one does
    m2 = load(out)
    assert torch.equal(m2.predict_pose(q["test"]), model.predict_pose(q["test"]))
    summary = {"out": str(out), "files_kb": {p.name: round(p.stat().st_size / 1024, 1) for p in sorted(out.iterdir())},
               **model.meta["metrics"], "wall_s": time.perf_counter() - t0}
    print(json.dumps(summary))
    return summary


if __name__ == "__main__":
    main()
