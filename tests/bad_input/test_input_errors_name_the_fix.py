"""Bad input gives a clear error that names the problem and the fix."""
from __future__ import annotations

import logging
import math
import re
import warnings

import pytest
import torch

from torchcal import Robot
from torchcal.measure.io import UnitsError, load_measurements


@pytest.fixture
def no_warnings():
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        yield


# ----------------------------------------------------------------------------- joint values
def test_wrong_number_of_joint_columns(tree_robot):
    with pytest.raises(ValueError) as e:
        tree_robot.fk(torch.zeros(3, 4))
    msg = str(e.value)
    assert "(N, 5)" in msg and "got (3, 4)" in msg
    for n in tree_robot.joint_names:
        assert n in msg
    with pytest.raises(ValueError, match=r"\(N, 5\).*got \((1, )?6,?\)"):  # 1-D q: (6,) shown as (1, 6)
        tree_robot.fk(torch.zeros(6))
    with pytest.raises(ValueError, match=r"got \(2, 3, 5\)"):
        tree_robot.positions(torch.zeros(2, 3, 5))
    with pytest.raises(ValueError, match=r"\(N, 5\)"):
        tree_robot.param_jacobian(torch.zeros(2, 7))


@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf])
def test_nan_inf_in_q_names_the_joint(tree_robot, bad):
    q = torch.zeros(4, 5, dtype=torch.float64)
    q[2, 2] = bad
    with pytest.raises(ValueError) as e:
        tree_robot.fk(q)
    msg = str(e.value)
    assert "NaN or inf" in msg and "slide_joint" in msg
    assert "yaw_joint" not in msg  # only the offending joint is named
    assert "drop or fill" in msg


def test_degrees_warning(tree_robot, no_warnings):
    q = torch.tensor([[90.0, 0.5, 0.1, 0.0, 0.2]], dtype=torch.float64)
    with pytest.warns(UserWarning, match=r"'yaw_joint'.*degrees.*radians"):
        tree_robot.fk(q)
    with pytest.warns(UserWarning, match="degrees"):
        Robot.from_dh([(0.3, 0.1, 0.0), (0.2, 0.0, 0.0)]).fk(torch.tensor([45.0, -30.0]))
    # plausible radians (limits ±2.5, ±2 and a continuous joint past 2π is still allowed once)
    tree_robot.fk(torch.tensor([[2.4, -1.9, 0.3, 6.0, 0.9]], dtype=torch.float64))


def test_millimetres_warning_for_prismatic(tree_robot, no_warnings):
    q = torch.tensor([[0.1, 0.2, 300.0, 0.0, 0.1], [0.1, 0.2, 250.0, 0.0, 0.1]], dtype=torch.float64)
    with pytest.warns(UserWarning, match=r"prismatic joint 'slide_joint'.*millimetres.*metres"):
        tree_robot.fk(q)
    tree_robot.fk(q / 1000)  # metres: quiet


def test_unit_warning_points_at_the_caller(tree_robot):
    with pytest.warns(UserWarning, match="degrees") as rec:
        tree_robot.fk(torch.tensor([90.0, 0.0, 0.0, 0.0, 0.0]))
    assert rec[0].filename == __file__


# ----------------------------------------------------------------------------- URDF
def test_broken_xml_string():
    with pytest.raises(ValueError) as e:
        Robot.from_urdf("<robot name='x'><link name='a'/><joint name='j'", markers=["a"])
    msg = str(e.value)
    assert "could not parse URDF" in msg and "well-formed XML" in msg


def test_broken_xml_string_says_where():
    with pytest.raises(ValueError, match=r"line \d+"):
        Robot.from_urdf("<robot name='x'><link name='a'/><joint name='j'", markers=["a"])


def test_truncated_urdf_file_is_an_error(tree_urdf, tmp_path):
    cut = tree_urdf[: tree_urdf.index('<joint name="finger_a_joint"')]
    path = tmp_path / "truncated.urdf"
    path.write_text(cut)
    with pytest.raises(ValueError, match="could not parse URDF"):
        Robot.from_urdf(path, markers=["tool"])


@pytest.mark.parametrize("jtype", ["planar", "floating"])
def test_unsupported_joint_type(tree_urdf, tree_markers, jtype):
    xml = tree_urdf.replace('<joint name="slide_joint" type="prismatic">', f'<joint name="slide_joint" type="{jtype}">')
    assert xml != tree_urdf
    with pytest.raises(ValueError) as e:
        Robot.from_urdf(xml, markers=tree_markers)
    msg = str(e.value)
    assert "'slide_joint'" in msg and repr(jtype) in msg
    assert "revolute" in msg and "prismatic" in msg and "fixed" in msg  # what is supported
    assert "replace them" in msg  # and what to do


def test_missing_urdf_file(tmp_path):
    path = tmp_path / "nowhere" / "robot.urdf"
    with pytest.raises(FileNotFoundError, match=r"URDF file not found: .*nowhere.*robot\.urdf"):
        Robot.from_urdf(path, markers=["tool"])
    with pytest.raises(FileNotFoundError, match="URDF file not found"):
        Robot.from_urdf(str(path), markers=["tool"])


def test_marker_on_unknown_link_did_you_mean(tree_urdf):
    with pytest.raises(ValueError) as e:
        Robot.from_urdf(tree_urdf, markers=["tool_link"])
    msg = str(e.value)
    assert "'tool_link'" in msg and "not in the URDF" in msg and "did you mean tool?" in msg
    with pytest.raises(ValueError, match=r"marker 'm2' is on link 'LINK4'.*did you mean link4"):
        Robot.from_urdf(tree_urdf, markers=["m2@LINK4=0,0,0.1"])


def test_marker_on_unknown_link_hint_names_a_real_function(tree_urdf):
    with pytest.raises(ValueError) as e:
        Robot.from_urdf(tree_urdf, markers=["m2@zzz=0,0,0"])
    msg = str(e.value)
    assert "'zzz'" in msg and "not in the URDF" in msg
    m = re.search(r"Robot\.(\w+)\(", msg)
    assert m is None or hasattr(Robot, m.group(1)), f"the hint names Robot.{m.group(1)}, which does not exist"


def test_mimic_of_missing_joint(tree_urdf, tree_markers):
    xml = tree_urdf.replace('mimic joint="finger_a_joint"', 'mimic joint="nope_joint"')
    with pytest.raises(ValueError, match="'finger_b_joint' mimics 'nope_joint', which is not in the URDF"):
        Robot.from_urdf(xml, markers=tree_markers)


def test_bad_marker_specs(tree_urdf):
    with pytest.raises(ValueError, match="has 2 numbers, expected 3"):
        Robot.from_urdf(tree_urdf, markers=["m1@link4=0.1,0.2"])
    with pytest.raises(ValueError, match="three numbers in metres"):
        Robot.from_urdf(tree_urdf, markers=["m1@link4=a,b,c"])
    with pytest.raises(ValueError, match="marker names must be unique"):
        Robot.from_urdf(tree_urdf, markers=["tool", "tool@link4"])
    with pytest.raises(ValueError, match="no movable joint"):
        Robot.from_urdf(tree_urdf, markers=["base"])


def test_dh_table_errors():
    with pytest.raises(ValueError, match="convention must be 'classic' or 'modified'"):
        Robot.from_dh([(0.1, 0.2, 0.0)], convention="craig")
    with pytest.raises(ValueError, match=r"DH row 2 must be \(a, d, alpha\[, theta\]\)"):
        Robot.from_dh([(0.1, 0.2, 0.0), (0.1, 0.2)])
    with pytest.raises(ValueError, match=r"DH row 1 has unknown keys \['alfa'\]"):
        Robot.from_dh([dict(a=0.1, d=0.2, alfa=0.0)])


# ----------------------------------------------------------------------------- parameters
def test_params_with_wrong_k(tree_robot, kr5):
    q = torch.zeros(5, dtype=torch.float64)
    K = tree_robot.n_params
    for bad in (torch.zeros(K - 1), torch.zeros(3, K + 2), torch.zeros(2, 3, K)):
        with pytest.raises(ValueError) as e:
            tree_robot.fk(q, bad)
        msg = str(e.value)
        assert f"K = {K}" in msg and "robot.param_names" in msg and str(tuple(bad.shape)) in msg
    with pytest.raises(ValueError, match=f"K = {K}"):
        tree_robot.param_jacobian(q, torch.zeros(K + 1))


def test_paramset_from_another_robot(tree_robot, kr5, modified_arm):
    with pytest.raises(ValueError, match=r"made for another robot.*robot\.params\(\)"):
        tree_robot.fk(torch.zeros(5), kr5.params())
    with pytest.raises(ValueError, match="made for another robot"):
        kr5.export_urdf(modified_arm.params(), "/nonexistent/never_written.urdf")
    with pytest.raises(KeyError, match=r"no parameter named 'joint_1\.dz'; similar: joint_1\.da"):
        kr5.params()["joint_1.dz"]


# ----------------------------------------------------------------------------- measurement files
JOINTS = ["yaw_joint", "pitch_joint", "slide_joint", "roll_joint", "finger_a_joint"]


@pytest.fixture
def tree_two(tree_urdf):
    """The tree robot with the two markers the files below measure (a declared marker without
    columns is an error)."""
    return Robot.from_urdf(tree_urdf, markers=["tool", "m1@finger_a=0.01,0.02,0.03"])


def _csv(tmp_path, header, rows, name="meas.csv"):
    path = tmp_path / name
    path.write_text("\n".join([",".join(header)] + [",".join(map(str, r)) for r in rows]) + "\n")
    return path


def _good_rows():
    return [
        [0.1, 0.2, 0.05, 0.3, 0.1, 0.51, 0.12, 0.43, 0.30, -0.02, 0.41, 20.5, 0],
        [-0.2, 0.4, 0.10, -0.5, 0.0, 0.48, -0.10, 0.47, "", "", "", 20.7, 1],
        [0.3, -0.1, 0.00, 1.0, -0.2, 0.55, 0.20, 0.40, 0.33, 0.01, 0.38, 20.9, 0],
    ]


GOOD_HEADER = JOINTS + ["tool.x", "tool.y", "tool.z", "m1.x", "m1.y", "m1.z", "temperature", "direction"]


def test_good_measurement_file(tree_two, tmp_path, no_warnings):
    path = _csv(tmp_path, GOOD_HEADER, _good_rows())
    data = load_measurements(path, tree_two)
    assert len(data) == 3
    assert data.joint_names == tree_two.joint_names
    assert data.marker_names == ["tool", "m1"]
    torch.testing.assert_close(data.q[1], torch.tensor([-0.2, 0.4, 0.10, -0.5, 0.0], dtype=torch.float64))
    assert data.positions.shape == (3, 2, 3)
    assert bool(torch.isnan(data.positions[1, 1]).all())
    assert not bool(torch.isnan(data.positions[[0, 2]]).any())
    assert data.seen.tolist() == [[True, True], [True, False], [True, True]]
    assert sorted(data.covariates) == ["direction", "temperature"]
    torch.testing.assert_close(data.covariates["temperature"], torch.tensor([20.5, 20.7, 20.9], dtype=torch.float64))
    assert data.quaternions is None


def test_missing_joint_column_suggests_close_name(tree_two, tmp_path):
    header = [("pitch_jnt" if c == "pitch_joint" else c) for c in GOOD_HEADER]
    with pytest.raises(ValueError) as e:
        load_measurements(_csv(tmp_path, header, _good_rows()), tree_two)
    msg = str(e.value)
    assert "no column for joint(s) 'pitch_joint'" in msg
    assert "is 'pitch_jnt' meant?" in msg
    assert "exactly as in the URDF" in msg


def test_unknown_marker_column(tree_two, tmp_path):
    """m1 renamed m7 in the file: the declared m1 has no columns, and the message names m7."""
    header = [c.replace("m1.", "m7.") for c in GOOD_HEADER]
    with pytest.raises(ValueError) as e:
        load_measurements(_csv(tmp_path, header, _good_rows()), tree_two)
    msg = str(e.value)
    assert "['m1'] are declared but the file has no columns" in msg and "['tool', 'm7']" in msg
    assert "--marker tool@LINK" in msg  # how to declare what the file has


def test_columns_of_undeclared_markers_are_left_out(tree_two, tmp_path, caplog):
    header = GOOD_HEADER + ["m7.x", "m7.y", "m7.z", "m7.qw", "m7.qx", "m7.qy", "m7.qz", "tool.dist.m7"]
    rows = [r + ["0.1", "0.2", "0.3", "1", "0", "0", "0", "0.25"] for r in _good_rows()]
    with caplog.at_level(logging.WARNING, logger="torchcal"):
        data = load_measurements(_csv(tmp_path, header, rows), tree_two)
    ref = load_measurements(_csv(tmp_path, GOOD_HEADER, _good_rows(), name="ref.csv"), tree_two)
    assert len(caplog.records) == 1 and "['m7']" in caplog.records[0].getMessage()
    assert data.marker_names == ref.marker_names and torch.allclose(data.positions, ref.positions, equal_nan=True)
    assert sorted(data.covariates) == sorted(ref.covariates) and not data.distances  # nothing of m7 is kept


def test_non_numeric_cell_gives_line_and_column(tree_two, tmp_path):
    rows = _good_rows()
    rows[1][6] = "0.1O"  # a letter O typed for a zero
    with pytest.raises(ValueError) as e:
        load_measurements(_csv(tmp_path, GOOD_HEADER, rows), tree_two)
    msg = str(e.value)
    assert "line 3" in msg and "column 'tool.y'" in msg and "'0.1O' is not a number" in msg


@pytest.mark.parametrize("cell", ["", "nan", "inf"])
def test_nan_in_joint_column(tree_two, tmp_path, cell):
    rows = _good_rows()
    rows[2][2] = cell
    with pytest.raises(ValueError) as e:
        load_measurements(_csv(tmp_path, GOOD_HEADER, rows), tree_two)
    msg = str(e.value)
    assert "line 4" in msg and "'slide_joint'" in msg and "drop the row" in msg


def test_partial_marker_coordinates_are_kept_per_axis(tree_two, tmp_path):
    rows = _good_rows()
    rows[0][9] = ""  # m1.y missing in the first data row: the other two axes still count
    d = load_measurements(_csv(tmp_path, GOOD_HEADER, rows), tree_two)
    k = d.marker_names.index("m1")
    assert d.axes_seen[0, k].tolist() == [True, False, True]
    assert not bool(d.seen[0, k]) and bool(d.observed[0, k])
    assert not d.positions_only and "1 partial" in repr(d)
    full = load_measurements(_csv(tmp_path, GOOD_HEADER, _good_rows()), tree_two)
    assert d.n_values == full.n_values - 1


def test_partial_marker_columns(tree_two, tmp_path):
    header = [c for c in GOOD_HEADER if c != "tool.z"]
    rows = [r[:7] + r[8:] for r in _good_rows()]
    with pytest.raises(ValueError, match=r"marker 'tool' has position columns .* but not \['tool\.z'\]"):
        load_measurements(_csv(tmp_path, header, rows), tree_two)


def test_millimetre_coordinates_stop_unless_declared(tree_two, tmp_path):
    rows = _good_rows()
    for r in rows:
        r[2] = 1000 * r[2]  # the prismatic slide, in mm like the positions
        for k in range(5, 11):
            if r[k] != "":
                r[k] = 1000 * r[k]
    path = _csv(tmp_path, GOOD_HEADER, rows)
    with pytest.raises(UnitsError, match="millimetres.*divide by 1000.*--units mm"):
        load_measurements(path, tree_two)
    mm = load_measurements(path, tree_two, units=["mm"])
    ref = load_measurements(_csv(tmp_path, GOOD_HEADER, _good_rows(), name="m.csv"), tree_two)
    torch.testing.assert_close(mm.positions, ref.positions, equal_nan=True)
    torch.testing.assert_close(mm.q, ref.q)


def test_degree_joint_values_stop_unless_declared(tree_two, tmp_path):
    rows = _good_rows()
    for r in rows:
        r[0] = round(math.degrees(r[0]) * 5, 3)  # yaw in degrees: 28.6, -57.3, 85.9
    path = _csv(tmp_path, GOOD_HEADER, rows)
    with pytest.raises(UnitsError, match=r"'yaw_joint'.*degrees.*π/180.*--units deg"):
        load_measurements(path, tree_two)
    deg = load_measurements(path, tree_two, units=["deg"])
    # revolute columns converted, the prismatic slide untouched
    assert deg.q[:, 0].tolist() == pytest.approx([math.radians(r[0]) for r in rows])
    assert deg.q[:, 2].tolist() == pytest.approx([r[2] for r in rows])


def test_measurement_file_problems(tree_two, tmp_path):
    with pytest.raises(FileNotFoundError, match="measurement file not found"):
        load_measurements(tmp_path / "absent.csv", tree_two)
    with pytest.raises(ValueError, match="header but no rows"):
        load_measurements(_csv(tmp_path, GOOD_HEADER, [], name="empty.csv"), tree_two)
    rows = _good_rows()
    rows[1] = rows[1][:-1]
    with pytest.raises(ValueError, match="line 3: 12 cells but the header has 13 columns"):
        load_measurements(_csv(tmp_path, GOOD_HEADER, rows, name="short.csv"), tree_two)
    with pytest.raises(ValueError, match=r"duplicate column names \['tool\.x'\]"):
        load_measurements(_csv(tmp_path, GOOD_HEADER + ["tool.x"], [r + [0] for r in _good_rows()],
                               name="dup.csv"), tree_two)
    header = JOINTS + ["temperature"]
    with pytest.raises(ValueError, match=r"no marker columns; expected '<marker>\.x'"):
        load_measurements(_csv(tmp_path, header, [r[:5] + [20.0] for r in _good_rows()], name="nomk.csv"),
                          tree_two)
