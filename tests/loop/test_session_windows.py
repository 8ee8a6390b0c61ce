"""A set-up that changed and changed back during the session (a tool swapped for a while): the
screening's scan of steps and windows against the projected columns themselves, the window shape,
and the loop on a simulated tool swapped for rows 100-199."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from torchcal.effects.shapes import shape_column, window_grid, window_parts, window_tag
from torchcal.pipelines.loop.screen import step_window_power

D = torch.float64


def test_the_scan_matches_each_projected_column():
    """Every step's and window's explained power from the steps' products equals ``(cᵀr)² / |c|²`` of
    its own column projected off the model's columns, computed directly."""
    g = torch.Generator().manual_seed(3)
    n_obs = 40
    x = torch.arange(n_obs, dtype=D)
    x = x[torch.randperm(n_obs, generator=g)]  # the rows in any order
    breaks, ok = window_grid(x)
    at = torch.tensor(breaks, dtype=D)
    S = (x[:, None] >= at[None]).to(D).repeat_interleave(3, dim=0)  # each step's shape, directly
    col = torch.randn(3 * n_obs, generator=g, dtype=D)
    Q, _ = torch.linalg.qr(torch.randn(3 * n_obs, 5, generator=g, dtype=D))
    r = torch.randn(3 * n_obs, generator=g, dtype=D)
    rp = r - Q @ (Q.T @ r)
    step, win = step_window_power(col, x.repeat_interleave(3), at, ok, Q, rp)

    def explained(c):
        c = c - Q @ (Q.T @ c)
        return float((c @ rp) ** 2 / (c @ c))

    B = len(breaks)
    for a in range(B):
        assert step[a] == pytest.approx(explained(col * S[:, a]), rel=1e-9)
        for b in range(B):
            if ok[a, b]:
                assert win[a, b] == pytest.approx(explained(col * (S[:, a] - S[:, b])), rel=1e-9)
            else:
                assert win[a, b] == 0.0
    # windows hold three rows at least, and run forward
    assert bool(ok.any()) and all(b - a >= 3 for a, b in zip(*torch.nonzero(ok).T.tolist()))


def test_a_window_is_one_inside_and_zero_outside():
    tag = window_tag(99.5, 199.5)
    assert window_parts(tag) == (99.5, 199.5)
    x = torch.tensor([0.0, 99.0, 100.0, 199.0, 200.0, 400.0], dtype=D)
    assert shape_column(tag, x, 0.0, 1.0).tolist() == [0.0, 0.0, 1.0, 1.0, 0.0, 0.0]


@pytest.mark.slow
def test_a_tool_swapped_for_a_while_is_found_as_one_window():
    """A tool 40 mm longer for rows 100-199 of 300, then the first one back, nothing logged; the held-out
    rows come after (rows 300-379, the first tool). A bow in the row order fits the middle and, held at
    the session's end, would move every held-out point by centimetres; the window is one rigid change
    and its return, and the held-out error ends within a tenth of the noise."""
    from .test_driver_findings import _samples, Drift, run_loop

    swap = Drift("marker:tool", "row", lambda rows: ((rows >= 100) & (rows < 200)).astype(float)[:, None]
                 * np.array([0.0, 0.01, 0.04]))
    robot, train, test = _samples([swap], 300, 80, seed=5)
    res = run_loop(robot, train.to_measurements(), test.to_measurements(), seed=5, log=None,
                   candidates=["parameter_drivers"], elm=False)
    modes = [m for a in res.accepted for m in a["modes"]]
    assert len(modes) == 1 and modes[0].startswith("tool.point~row~win"), modes
    a, b = window_parts(modes[0].split("~")[2])
    assert 97 < a < 102 and 197 < b < 202
    floor = float(np.linalg.norm(test.true_positions - test.positions, axis=-1).mean()) * 1e3
    assert res.stages[-1]["test"]["mean_mm"] < 1.1 * floor, (res.stages[-1]["test"], floor)
