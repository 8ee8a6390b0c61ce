"""An instrument's own export read as it is (:mod:`torchcal.measure.instrument`): ``;``-separated,
decimal commas, millimetres, Euler angles in degrees, its own column names, prefixed joint names.
The reference for the angles is scipy's ``Rotation.from_euler``, which the reader does not use."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from torchcal import Robot
from torchcal.measure.instrument import InstrumentFormat, euler_to_quat
from torchcal.measure.io import load_measurements

Rotation = pytest.importorskip("scipy.spatial.transform", reason="scipy is the Euler reference").Rotation

UR5E = Path(__file__).resolve().parents[2] / "urdf" / "ur5e.urdf"
N = 12


def _german(x: float) -> str:
    return repr(float(x)).replace(".", ",")


@pytest.fixture(scope="module")
def export(tmp_path_factory):
    """A tracker export of N rows and the values it was written from (m, rad, scipy's quaternions)."""
    robot = Robot.from_urdf(UR5E, markers=["probe@flange=0,0,0.1"])
    g = np.random.default_rng(3)
    q = g.uniform(-2, 2, (N, robot.dof))
    p = g.uniform(-1, 1, (N, 3)) + [2.0, 0.5, 0.3]
    eul = g.uniform(-170, 170, (N, 3))
    eul[:, 1] = g.uniform(-80, 80, N)
    header = ["Timestamp"] + [f"ur_{j}" for j in robot.joint_names] + ["temp", "mx", "my", "mz", "mrx", "mry", "mrz"]
    lines = [";".join(header)]
    for i in range(N):
        cells = ["2,02011E+13"] + [_german(v) for v in q[i]] + [_german(21.5 + 0.1 * i)]
        cells += [_german(1000 * v) for v in p[i]] + [_german(v) for v in eul[i]]
        lines.append(";".join(cells))
    path = tmp_path_factory.mktemp("export") / "tracker.csv"
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")
    return robot, path, q, p, eul


def _fmt(euler="XYZ", strip_prefix="ur_"):
    cols = {"mx": "probe.x", "my": "probe.y", "mz": "probe.z", "mrx": "probe.rx", "mry": "probe.ry",
            "mrz": "probe.rz", "Timestamp": ""}
    return InstrumentFormat(sep=";", decimal=",", rot_units="deg", euler=euler, columns=cols, strip_prefix=strip_prefix)


@pytest.mark.parametrize("seq", ["XYZ", "xyz", "ZYX", "zyz"])
def test_export_reads_as_written(export, seq):
    robot, path, q, p, eul = export
    d = load_measurements(path, robot, units=["mm"], fmt=_fmt(seq))
    assert np.abs(d.q.numpy() - q).max() < 1e-12
    assert np.abs(d.positions[:, 0].numpy() - p).max() < 1e-12  # mm converted to m
    ref = Rotation.from_euler(seq, eul, degrees=True).as_quat(scalar_first=True)
    got = d.quaternions[:, 0].numpy()
    dot = np.abs((ref * got).sum(1))  # q and -q are one rotation
    assert (1 - dot).max() < 1e-12
    assert list(d.covariates) == ["temp"]  # the damaged time stamp is left out, as mapped


def test_euler_helper_matches_scipy_matrices():
    g = np.random.default_rng(0)
    a = g.uniform(-3, 3, (20, 3))
    for seq in ("XYZ", "xyz", "ZXZ", "yxy"):
        ref = Rotation.from_euler(seq, a).as_matrix()
        got = Rotation.from_quat(euler_to_quat(torch.as_tensor(a), seq).numpy(), scalar_first=True).as_matrix()
        assert np.abs(ref - got).max() < 1e-12


def test_euler_columns_need_a_stated_convention(export):
    robot, path, *_ = export
    with pytest.raises(ValueError, match="sequence must be stated"):
        load_measurements(path, robot, units=["mm"], fmt=_fmt(None))


def test_semicolon_file_without_the_format_names_the_options(export):
    robot, path, *_ = export
    with pytest.raises(ValueError, match="--sep ';' --decimal ','|sep=';'"):
        load_measurements(path, robot, units=["mm"])


def test_prefixed_joints_without_the_prefix_option_are_refused(export):
    robot, path, *_ = export
    with pytest.raises(ValueError, match="shoulder_pan_joint"):
        load_measurements(path, robot, units=["mm"], fmt=_fmt(strip_prefix=""))


@pytest.mark.parametrize("kw, words", [({"sep": ",", "decimal": ","}, "both ','"),
                                       ({"euler": "XXY"}, "not an Euler sequence"),
                                       ({"euler": "XyZ"}, "not an Euler sequence"),
                                       ({"rot_units": "grad"}, "rot_units")])
def test_a_format_that_cannot_be_is_refused(kw, words):
    with pytest.raises(ValueError, match=words):
        InstrumentFormat(**kw)


def test_a_column_map_naming_no_column_is_refused(export):
    robot, path, *_ = export
    fmt = InstrumentFormat(sep=";", decimal=",", columns={"measurement_x": "probe.x"})
    with pytest.raises(ValueError, match="measurement_x"):
        load_measurements(path, robot, units=["mm"], fmt=fmt)
