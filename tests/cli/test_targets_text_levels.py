"""``torchcal correct`` reads a level of a text column the model needs (``load=pallet``) from the text
column itself, as the training file had it, or from its own 0/1 column, and a level of a column of
codes (``tool_id=2``) from the numeric column (:func:`torchcal.cli.correct.read_targets`)."""
from __future__ import annotations

import pytest
import torch

from torchcal.cli.correct import read_targets
from torchcal.kinematics.robots import shipped


def test_a_level_comes_from_its_text_column(tmp_path):
    f = tmp_path / "targets.csv"
    f.write_text("x,y,z,load,temperature\n0.5,0.1,0.6,box,21\n0.4,-0.2,0.7, pallet ,22\n0.45,0.0,0.65,empty,23\n")
    _, _, cov, _ = read_targets(f, shipped("ur5e"), ["load=empty", "load=pallet", "temperature"])
    assert cov["load=empty"].tolist() == [0.0, 0.0, 1.0]
    assert cov["load=pallet"].tolist() == [0.0, 1.0, 0.0]  # the cell's spaces aside, as the training reader
    assert torch.equal(cov["temperature"], torch.tensor([21.0, 22.0, 23.0], dtype=torch.float64))


def test_a_level_may_also_be_given_as_its_own_column(tmp_path):
    f = tmp_path / "targets.csv"
    f.write_text("x,y,z,load=pallet\n0.5,0.1,0.6,1\n0.4,-0.2,0.7,0\n")
    _, _, cov, _ = read_targets(f, shipped("ur5e"), ["load=pallet"])
    assert cov["load=pallet"].tolist() == [1.0, 0.0]


def test_a_level_of_codes_comes_from_its_numeric_column(tmp_path):
    f = tmp_path / "targets.csv"
    f.write_text("x,y,z,tool_id\n0.5,0.1,0.6,2\n0.4,-0.2,0.7,3.0\n0.45,0.0,0.65,1\n")
    _, _, cov, _ = read_targets(f, shipped("ur5e"), ["tool_id=2", "tool_id=3"])
    assert cov["tool_id=2"].tolist() == [1.0, 0.0, 0.0]
    assert cov["tool_id=3"].tolist() == [0.0, 1.0, 0.0]  # 3.0 is the code 3


def test_a_missing_level_says_where_it_may_come_from(tmp_path):
    f = tmp_path / "targets.csv"
    f.write_text("x,y,z\n0.5,0.1,0.6\n")
    with pytest.raises(ValueError, match=r"needs covariate column\(s\) \['tool=probe'\]; a level .* text column"):
        read_targets(f, shipped("ur5e"), ["tool=probe"])
