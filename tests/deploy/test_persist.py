"""Saved models: save -> load -> predict bit for bit, refusals, and the shipped KR5 demo model."""
from __future__ import annotations

import argparse
import csv
import json
import shutil
from pathlib import Path

import pytest
import torch

from torchcal.cli.app import main as torchcal_main
from torchcal.cli.correct import correct_main
from torchcal.kinematics.transforms import matrix_to_quat, quat_to_matrix


def cli_main(argv):
    return torchcal_main(["correct", *argv])
from torchcal.elm import ELM
from torchcal.deploy.model import CalibratedModel
from torchcal.effects import register_effect
from torchcal.deploy.persist import FORMAT_VERSION, load, save
from torchcal.kinematics.robots import shipped

torch.set_num_threads(1)
SHIPPED_MODEL = Path(__file__).resolve().parents[2] / "models" / "kuka_kr5_arc"


@register_effect
class OffsetEffect:
    """A test effect with a tensor and a plain value in its state."""

    effect_type = "test_offset"

    def __init__(self, offset: torch.Tensor, gain: float, name: str = "offset"):
        self.name, self.offset, self.gain = name, offset, gain

    def joint_correction(self, q, covariates):
        return self.gain * self.offset * torch.cos(q)

    def state_dict(self):
        return {"offset": self.offset, "gain": self.gain, "name": self.name}

    @classmethod
    def from_state_dict(cls, state, robot=None):
        return cls(state["offset"], state["gain"], state["name"])


@register_effect
class ThermalShiftEffect:
    """A test position effect needing a covariate."""

    covariates = ["temperature"]

    def __init__(self, k: torch.Tensor, name: str = "thermal"):
        self.name, self.k = name, k

    def joint_correction(self, q, covariates):
        return torch.zeros_like(q)

    def position_correction(self, p, q, covariates):
        return p * (1 + self.k * (covariates["temperature"] - 20.0))[:, None, None]

    def state_dict(self):
        return {"k": self.k, "name": self.name}

    @classmethod
    def from_state_dict(cls, state, robot=None):
        return cls(state["k"], state["name"])


def _model(robot, covariates=None):
    g = torch.Generator().manual_seed(0)
    p = robot.params()
    p.values = p.values + 1e-3 * torch.randn(robot.n_params, generator=g, dtype=torch.float64)
    q = torch.rand(60, robot.dof, generator=g, dtype=torch.float64)
    X = q if not covariates else torch.cat([q, torch.rand(60, len(covariates), generator=g, dtype=torch.float64)], 1)
    elm = ELM(12, seed=1).fit(X, 1e-4 * torch.randn(60, 6, generator=g, dtype=torch.float64))
    eff = OffsetEffect(1e-4 * torch.arange(1, robot.dof + 1, dtype=torch.float64), 0.5)
    effects = [eff] + ([ThermalShiftEffect(torch.tensor(1.2e-5, dtype=torch.float64))] if covariates else [])
    return CalibratedModel(robot, p, effects, elm, covariates=covariates,
                           meta={"training": {"n_train": 60}, "metrics": {"rmse_mm": 0.01}})


def test_save_load_predict_bit_identical(tmp_path):
    robot = shipped("ur5e")
    m = _model(robot, covariates=["temperature"])
    save(m, tmp_path / "m")
    # the three files of a model, and the manifest by which a later force knows what torchcal wrote
    assert sorted(p.name for p in (tmp_path / "m").iterdir()) == [".torchcal-manifest.json", "model.json", "robot.urdf",
                                                                 "tensors.safetensors"]
    q = torch.rand(40, 6, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    cov = {"temperature": torch.linspace(0, 1, 40, dtype=torch.float64)}
    for m2 in (load(tmp_path / "m"), load(tmp_path / "m", robot=robot)):
        assert torch.equal(m2.predict_pose(q, cov), m.predict_pose(q, cov))
        assert torch.equal(m2.predict_error(q, cov), m.predict_error(q, cov))
        assert torch.equal(m2.params.values, m.params.values) and torch.equal(m2.params.free, m.params.free)
        assert m2.covariates == ["temperature"] and m2.meta == m.meta
        assert [e.name for e in m2.effects] == ["offset", "thermal"] and m2.effects[0].gain == 0.5
    meta = json.loads((tmp_path / "m" / "model.json").read_text())
    assert meta["format_version"] == FORMAT_VERSION and meta["robot"]["urdf_sha256"] == robot.urdf_hash()
    assert meta["robot"]["joint_names"] == robot.joint_names and meta["residual"]["n_hidden"] == 12
    assert meta["residual_outputs"] == ["dx", "dy", "dz", "droll", "dpitch", "dyaw"]
    assert [e["type"] for e in meta["effects"]] == ["test_offset", "ThermalShiftEffect"]
    # the base frame, effects and residual all matter to the prediction being compared
    assert float((m.predict_pose(q, cov) - m.geometric_pose(q, cov)).abs().max()) > 1e-6


def test_model_for_another_robot_is_refused(tmp_path):
    save(_model(shipped("ur5e")), tmp_path / "m")
    with pytest.raises(ValueError, match=r"made for robot 'ur5e'.*robot given is 'kuka_kr5_arc'"):
        load(tmp_path / "m", robot=shipped("kuka_kr5_arc"))
    # same URDF, other markers: refused too
    with pytest.raises(ValueError, match="markers"):
        load(tmp_path / "m", robot=shipped("ur5e", markers=["link6"]))
    # a modified robot.urdf no longer matches the recorded hash
    f = tmp_path / "m" / "robot.urdf"
    f.write_text(f.read_text().replace("0.1625", "0.1626", 1))
    with pytest.raises(ValueError, match="does not match the hash"):
        load(tmp_path / "m")


def test_refusals_with_clear_messages(tmp_path, kr5):
    # a DH-built robot has no URDF text to save with the model
    with pytest.raises(ValueError, match="not built from a URDF"):
        save(CalibratedModel(kr5), tmp_path / "dh")
    with pytest.raises(FileNotFoundError, match="not a torchcal model directory"):
        load(tmp_path)
    save(CalibratedModel(shipped("kuka_kr5_arc")), tmp_path / "m")
    meta = json.loads((tmp_path / "m" / "model.json").read_text())
    meta["format_version"] = FORMAT_VERSION + 1
    (tmp_path / "m" / "model.json").write_text(json.dumps(meta))
    with pytest.raises(ValueError, match="newer than this torchcal reads"):
        load(tmp_path / "m")


def test_quaternion_helpers_round_trip():
    from torchcal.kinematics.transforms import so3_exp

    R = so3_exp(torch.randn(50, 3, generator=torch.Generator().manual_seed(0), dtype=torch.float64) * 2)
    torch.testing.assert_close(quat_to_matrix(matrix_to_quat(R)), R, rtol=0, atol=1e-14)


def _read(path):
    with open(path, newline="") as fh:
        return list(csv.DictReader(fh))


@pytest.mark.slow
def test_shipped_kr5_model_reproduces_stored_corrections(tmp_path):
    """``torchcal correct`` with the shipped model gives the stored results."""
    assert SHIPPED_MODEL.is_dir(), "models/kuka_kr5_arc is missing; run scripts/train_kr5_model.py"
    assert sum(p.stat().st_size for p in SHIPPED_MODEL.iterdir()) < 200 * 1024
    m = load(SHIPPED_MODEL)
    assert m.robot.name == "kuka_kr5_arc" and m.residual is not None
    assert m.robot.urdf_hash() == shipped("kuka_kr5_arc").urdf_hash()
    out = tmp_path / "corrected.csv"
    # the stored targets are in the model's instrument frame; one of them is unreachable
    args = ["--model", str(SHIPPED_MODEL), "--targets", str(SHIPPED_MODEL / "targets.csv"), "--out", str(out),
            "--frame", "instrument"]
    assert cli_main(args) == 3  # a failed target fails the command by default
    out.unlink()
    assert cli_main(args + ["--allow-failures"]) == 0
    got, want = _read(out), _read(SHIPPED_MODEL / "expected_corrections.csv")
    assert len(got) == len(want) and got[0].keys() == want[0].keys()
    joints = m.robot.joint_names
    for g, w in zip(got, want):
        assert (g["converged"], g["reason"]) == (w["converged"], w["reason"])
        for j in joints:  # same machine: identical; another CPU/BLAS: equal to far below 1 µrad
            if w["converged"] == "0":  # a failed target carries no command
                assert g[j] == w[j] == "nan", (j, g[j], w[j])
                continue
            assert abs(float(g[j]) - float(w[j])) <= 1e-9, (j, g[j], w[j])
        assert abs(float(g["predicted_error_mm"]) - float(w["predicted_error_mm"])) <= 1e-6
    assert [r["reason"] for r in want].count("unreachable") == 1
    assert all(float(r["predicted_error_mm"]) <= 1e-3 for r in want if r["reason"] == "ok")


def test_cli_errors_are_reported(tmp_path):
    shutil.copytree(SHIPPED_MODEL, tmp_path / "m")
    bad = tmp_path / "bad.csv"
    bad.write_text("x,y\n1,2\n")
    assert cli_main(["--model", str(tmp_path / "m"), "--targets", str(bad), "--out", str(tmp_path / "o.csv")]) == 2
    mm = tmp_path / "mm.csv"
    mm.write_text("x,y,z\n1000,200,500\n")
    with pytest.raises(ValueError, match="looks like millimetres"):
        correct_main(argparse.Namespace(model=str(tmp_path / "m"), targets=str(mm), out=str(tmp_path / "o.csv"),
                                        tol_mm=1e-3, tol_mrad=1e-3, max_outer=10, allow_failures=False, threads=1,
                                        frame="instrument", force=False))


def test_cli_with_covariates_and_effects(tmp_path):
    robot = shipped("ur5e")
    m = _model(robot, covariates=["temperature"])
    save(m, tmp_path / "m")
    q = torch.tensor([[0.1, -1.2, 1.4, -1.7, -1.5, 0.2], [-0.3, -1.0, 1.2, -1.9, -1.4, -0.4]], dtype=torch.float64)
    temp = torch.tensor([21.0, 27.0], dtype=torch.float64)
    T = m.predict_pose(q, {"temperature": temp})[:, 0]  # reachable by construction
    qt = matrix_to_quat(T[:, :3, :3])
    rows = ["x,y,z,qw,qx,qy,qz," + ",".join(robot.joint_names) + ",temperature"]
    for i in range(2):
        vals = [*T[i, :3, 3], *qt[i], *(q[i] + 0.01), temp[i]]
        rows.append(",".join(repr(float(v)) for v in vals))
    (tmp_path / "t.csv").write_text("\n".join(rows) + "\n")
    assert cli_main(["--model", str(tmp_path / "m"), "--targets", str(tmp_path / "t.csv"),
                     "--out", str(tmp_path / "o.csv"), "--frame", "instrument"]) == 0
    out = _read(tmp_path / "o.csv")
    assert [r["reason"] for r in out] == ["ok", "ok"]
    got = torch.tensor([[float(r[j]) for j in robot.joint_names] for r in out], dtype=torch.float64)
    assert float((got - q).abs().max()) < 1e-5  # 1 µm tolerance at ~1 m reach
    (tmp_path / "t2.csv").write_text("x,y,z\n0.5,0.1,0.4\n")
    assert cli_main(["--model", str(tmp_path / "m"), "--targets", str(tmp_path / "t2.csv"),
                     "--out", str(tmp_path / "o2.csv")]) == 2  # the temperature column is missing
