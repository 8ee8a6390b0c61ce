"""Issue 36, items 2 and 3: a saved model is covered by its checksum in full, its JSON is checked
field by field, a robot passed to load() must match by geometry, and a mirrored target frame is no
target."""
from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest
import torch

from torchcal import Robot, load, save
from torchcal.deploy.model import CalibratedModel
from torchcal.kinematics.ik import target_frames

REPO = Path(__file__).resolve().parents[2]
UR5E = str(REPO / "urdf" / "ur5e.urdf")
SMR = "smr@flange=0,0,0.05"


@pytest.fixture(scope="module")
def saved(tmp_path_factory) -> Path:
    d = tmp_path_factory.mktemp("model") / "m"
    save(CalibratedModel(Robot.from_urdf(UR5E, markers=[SMR])), d)
    return d


def _edited(saved: Path, tmp_path: Path, edit) -> Path:
    m = tmp_path / "m"
    shutil.copytree(saved, m)
    meta = json.loads((m / "model.json").read_text())
    meta = edit(meta)
    (m / "model.json").write_text(json.dumps(meta))
    return m


def test_an_edited_marker_point_is_refused_by_the_api_and_the_cli(saved, tmp_path, torchcal_cli):
    def move(meta):
        meta["robot"]["markers"][0]["xyz"][2] += 0.1  # 100 mm
        return meta
    m = _edited(saved, tmp_path, move)
    with pytest.raises(ValueError, match=r"model\.json does not match its checksum"):
        load(m)
    t = tmp_path / "targets.csv"
    t.write_text("x,y,z\n0.3,0.2,0.5\n")
    rc, _, err = torchcal_cli("correct", "--model", m, "--targets", t, "--out", tmp_path / "cmd.csv")
    assert rc == 2 and "checksum" in err and "save the model again" in err, err
    assert not (tmp_path / "cmd.csv").exists()
    load(saved)  # the untouched copy loads: the check can pass


SCHEMA = [
    ("a text format_version", lambda m: {**m, "format_version": "1"}, r"'format_version' must be a whole number"),
    ("a JSON list", lambda m: [m], r"holds a JSON list, not a torchcal model"),
    ("no robot section", lambda m: {k: v for k, v in m.items() if k != "robot"}, r"field 'robot' is missing"),
    ("dtype int64", lambda m: {**m, "robot": {**m["robot"], "dtype": "int64"}},
     r"'robot.dtype' must be float32 or float64, got 'int64'"),
    ("a marker point of two numbers", lambda m: {**m, "robot": {**m["robot"], "markers": [
        {**m["robot"]["markers"][0], "xyz": [0, 0]}]}}, r"'robot.markers\[0\].xyz' must be three finite numbers"),
]


@pytest.mark.parametrize("what, edit, words", SCHEMA, ids=[s[0] for s in SCHEMA])
def test_a_malformed_model_json_is_refused_naming_the_field(saved, tmp_path, torchcal_cli, what, edit, words):
    m = _edited(saved, tmp_path, edit)
    with pytest.raises(ValueError, match=words):
        load(m)
    t = tmp_path / "targets.csv"
    t.write_text("x,y,z\n0.3,0.2,0.5\n")
    rc, _, err = torchcal_cli("correct", "--model", m, "--targets", t, "--out", tmp_path / "cmd.csv")
    assert rc == 2 and "(a bug)" not in err and "model.json" in err, err


def test_a_robot_with_another_marker_point_is_refused_by_load(saved):
    other = Robot.from_urdf(UR5E, markers=["smr@flange=0,0,0.15"])  # the same name, 100 mm further
    with pytest.raises(ValueError, match=r"marker 'smr' has the point .*0\.15.*the model's .*0\.05"):
        load(saved, robot=other)
    same = Robot.from_urdf(UR5E, markers=[SMR])
    assert load(saved, robot=same).robot is same


def test_a_mirrored_target_frame_is_refused():
    robot = Robot.from_urdf(UR5E, markers=[SMR])
    T = torch.eye(4, dtype=torch.float64).repeat(2, 1, 1)
    T[:, :3, 3] = torch.tensor([0.3, 0.2, 0.5], dtype=torch.float64)
    R, p = target_frames(robot, T)  # proper frames pass
    assert R.shape == (2, 3, 3)
    T[1, :3, 0] *= -1  # one axis flipped: orthonormal, det = -1
    with pytest.raises(ValueError, match=r"target 1 has a mirrored rotation part \(det = -1"):
        target_frames(robot, T)


def test_a_targets_file_with_blank_lines_names_the_right_line(saved, tmp_path, torchcal_cli):
    t = tmp_path / "targets.csv"
    t.write_text("x,y,z\n0.3,0.2,0.5\n\n\n0.3,abc,0.5\n")  # the bad cell is on line 5 of the file
    rc, _, err = torchcal_cli("correct", "--model", saved, "--targets", t, "--out", tmp_path / "cmd.csv")
    assert rc == 2 and "targets.csv, line 5, column 'y'" in err, err
