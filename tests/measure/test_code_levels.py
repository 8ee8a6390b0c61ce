"""A numeric column of codes (a tool, a station logged by number) is also read as levels: which
columns qualify, the 0/1 levels the loop derives for training and held-out rows, and a saved
model given the numeric column where it reads a level."""
from __future__ import annotations

import math

import pytest
import torch

from torchcal.effects.compliance import load_columns
from torchcal.measure.levels import MAX_CODES, code_indicator, code_levels
from torchcal.pipelines.loop.covariates import derive_code_levels
from torchcal.sim.cases import make_case

T = lambda *v: torch.tensor(v, dtype=torch.float64)  # noqa: E731


@pytest.mark.parametrize("values, levels", [
    ((1, 2, 3, 1, 2, 3, 1, 2, 3, 1, 2, 3), ["1", "2", "3"]),
    ((0, 5, 0, 5, 0, 5, 0, 5, math.nan), ["0", "5"]),    # a cell not recorded does not count
    ((1.0, 2.5) * 4, None),                               # not whole numbers: a quantity
    ((1, 2) * 4 + (3,), None),                            # a code on one row only
    ((4,) * 8, None),                                     # one value: nothing to tell apart
    ((1, 2, 3) * 3, None),                                # three values on nine rows: too few rows each
    (tuple(range(MAX_CODES + 1)) * 4, None),              # too many values for codes
    (tuple(range(MAX_CODES)) * 4, [str(i) for i in range(MAX_CODES)]),
])
def test_which_columns_hold_codes(values, levels):
    assert code_levels(T(*values)) == levels


def test_a_code_indicator_keeps_what_was_not_recorded():
    out = code_indicator(T(1, 2, math.nan, 2), "2")
    assert out[[0, 1, 3]].tolist() == [0.0, 1.0, 1.0] and math.isnan(float(out[2]))


def test_the_loop_reads_a_column_of_codes_as_levels_beside_its_number():
    c = make_case("tool_codes", 1)
    train, test = c.train.to_measurements(), c.test.to_measurements()
    assert derive_code_levels(train, test) == ["tool_id"]
    for d in (train, test):
        ids = d.covariates["tool_id"]
        for lv in "1234":
            assert torch.equal(d.covariates[f"tool_id={lv}"], (ids == float(lv)).double())
    # the number logs a load already: its levels are no loads of their own
    assert load_columns(train.covariates) == ["tool_id"]


def test_time_and_text_columns_are_not_read_as_codes():
    c = make_case("tool_codes", 1)
    train = c.train.to_measurements()
    n = len(train)
    train.covariates["time"] = torch.arange(n, dtype=torch.float64) % 3  # a clock is never a code
    train.covariates["tool_id"] = train.covariates["tool_id"] * 1.5      # 1.5, 3.0, ...: a quantity
    assert derive_code_levels(train, None) == []
