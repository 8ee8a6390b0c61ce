"""Issue 36, items 1, 5, 6: a URDF is read by presence and as strictly as a CSV, a byte-order mark
is accepted, and file content is never taken for a path."""
from __future__ import annotations

import re
from pathlib import Path

import pytest
import torch

from torchcal import Robot, load, save
from torchcal.deploy.model import CalibratedModel

REPO = Path(__file__).resolve().parents[2]
UR5E = REPO / "urdf" / "ur5e.urdf"
SMR = "smr@flange=0,0,0.05"


def test_a_mimic_multiplier_of_zero_is_zero(tree_urdf):
    """finger_b mimics finger_a with multiplier 0: finger_b stays at the offset whatever finger_a
    does, exactly as the URDF says (it was read as multiplier 1)."""
    tip = "tip@finger_b=0,0.05,0.02"  # off finger_b's axis (x), so that its turning shows
    still = Robot.from_urdf(tree_urdf.replace('multiplier="-1.5"', 'multiplier="0"'), markers=[tip])
    q = torch.zeros(2, still.dof, dtype=torch.float64)
    q[1, still.joint_names.index("finger_a_joint")] = 0.8  # only the mimicked joint moves
    p = still.positions(q)
    torch.testing.assert_close(p[0], p[1], rtol=0, atol=1e-12)
    # with the file's own multiplier, the same motion moves finger_b: the test can fail
    moving = Robot.from_urdf(tree_urdf, markers=[tip]).positions(q)
    assert float((moving[0] - moving[1]).norm()) > 1e-3


BAD = [
    ("an axis with NaN", lambda s: s.replace('<axis xyz="0.0 0.0 1.0"/>', '<axis xyz="nan 1 0"/>', 1),
     r"<axis> of joint 'shoulder_pan_joint'.*nan 1 0.*3 finite numbers"),
    ("an origin with four numbers", lambda s: re.sub(r'(<joint[^>]*>\s*<parent[^>]*/>\s*<child[^>]*/>\s*<origin xyz=")'
                                                     r'([^"]*)"', r'\1\2 0.5"', s, count=1),
     r"<origin> of joint .*must be 3 finite numbers"),
    ("a link named twice", lambda s: s.replace("</robot>", '<link name="link1"/></robot>'),
     r"link name 'link1' is used again \(first on line \d+\)"),
    ("a zero axis", lambda s: s.replace('<axis xyz="0.0 0.0 1.0"/>', '<axis xyz="0 0 0"/>', 1), "zero axis"),
    ("a limit of inf", lambda s: re.sub(r'lower="[^"]*"', 'lower="-inf"', s, count=1), r"lower=\"-inf\""),
    ("a joint loop", lambda s: s.replace("</robot>", '<joint name="cyc" type="fixed"><parent link="flange"/>'
                                         '<child link="link0"/></joint></robot>'), r"its own ancestor"),
    ("a link that belongs to nothing", lambda s: s.replace("</robot>", '<link name="lonely"/></robot>'),
     r"have no parent joint: the URDF is 2 trees"),
    ("limits the wrong way round", lambda s: re.sub(r'lower="[^"]*" upper="[^"]*"', 'lower="1" upper="-1"', s, count=1),
     r'lower="1" is above upper="-1"'),
    ("a joint without a type", lambda s: re.sub(r'(<joint name="shoulder_pan_joint") type="[^"]*"', r"\1", s, count=1),
     "has no type attribute"),
    ("a link with two parents", lambda s: s.replace("</robot>", '<joint name="extra" type="fixed"><parent link="link0"/>'
                                                    '<child link="link2"/></joint></robot>'),
     r"link 'link2' already has the parent joint"),
]


@pytest.mark.parametrize("what, edit, words", BAD, ids=[b[0] for b in BAD])
def test_a_malformed_urdf_is_refused_at_the_door_naming_its_line(tmp_path, torchcal_cli, ur5e_csv, what, edit, words):
    bad = tmp_path / "bad.urdf"
    bad.write_text(edit(UR5E.read_text()))
    assert bad.read_text() != UR5E.read_text(), what  # the edit took
    rc, _, err = torchcal_cli("calibrate", "--robot", bad, "--marker", SMR, "--data", ur5e_csv, "--out", tmp_path / "o")
    assert rc == 2 and "Traceback" not in err, err
    assert re.search(words, err) and re.search(r"bad\.urdf, line \d+", err), err
    assert not (tmp_path / "o").exists()


@pytest.mark.slow
def test_a_byte_order_mark_is_accepted_by_calibrate(tmp_path, torchcal_cli, ur5e_csv):
    bom = tmp_path / "bom.urdf"
    bom.write_bytes(b"\xef\xbb\xbf" + UR5E.read_bytes())
    rc, _, err = torchcal_cli("calibrate", "--robot", bom, "--marker", SMR, "--data", ur5e_csv, "--out", tmp_path / "o")
    assert rc == 0 and "File name too long" not in err, err
    assert (tmp_path / "o" / "calibrated.urdf").read_bytes()[:3] != b"\xef\xbb\xbf"


def test_a_byte_order_mark_is_accepted_and_content_is_never_a_path(tmp_path):
    bom = tmp_path / "bom.urdf"
    bom.write_bytes(b"\xef\xbb\xbf" + UR5E.read_bytes())
    assert Robot.from_urdf(bom, markers=[SMR]).urdf_text == UR5E.read_text()
    # the API: a robot built from BOM text saves a model that loads, and gives the same positions
    text = "\ufeff" + UR5E.read_text()
    robot = Robot.from_urdf(text, markers=[SMR])
    assert robot.urdf_text == UR5E.read_text()
    save(CalibratedModel(robot), tmp_path / "m")
    again = load(tmp_path / "m")
    q = torch.zeros(1, robot.dof, dtype=torch.float64)
    torch.testing.assert_close(again.robot.positions(q), robot.positions(q))
    # text that is not XML is named as such, never opened as a file name
    with pytest.raises(ValueError, match=r"could not parse URDF string.*line 1"):
        Robot.from_urdf("robot name='x'\n" + "x" * 5000)
