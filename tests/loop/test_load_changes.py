"""A load that changed mid-session with nothing logged, found by its own shape
(:mod:`torchcal.pipelines.loop.loadscan`): the scan's explained power against each break's projected
columns computed directly. The loop on a payload swapped beside a tracker knocked in one session
(``swap_and_knock``) is checked in ``tests/loop/test_loop_physsim_data.py``, on the run its
case-by-case test makes."""
from __future__ import annotations

import pytest
import torch

from torchcal.effects.shapes import step_breaks
from torchcal.pipelines.loop.loadscan import step_power

D = torch.float64


def test_the_step_scan_matches_each_projected_least_squares_fit():
    """Every break's explained power equals ``‖P r‖²`` of its own columns (``G`` past the break,
    projected off the model's columns) fitted by least squares directly, and its rank the columns'."""
    g = torch.Generator().manual_seed(7)
    n_obs, P = 30, 4
    x = torch.arange(n_obs, dtype=D)[torch.randperm(n_obs, generator=g)]  # the rows in any order
    b = step_breaks(x)
    at = torch.tensor(b, dtype=D)
    G = torch.randn(3 * n_obs, P, generator=g, dtype=D)
    G[:, 3] = G[:, 0] + G[:, 1]  # one column a combination of two others: rank 3
    Q, _ = torch.linalg.qr(torch.randn(3 * n_obs, 5, generator=g, dtype=D))
    r = torch.randn(3 * n_obs, generator=g, dtype=D)
    rp = r - Q @ (Q.T @ r)
    x3 = x.repeat_interleave(3)
    power, rank = step_power(G, x3, at, Q, rp)
    for i, br in enumerate(b):
        C = G * (x3 >= br).to(D)[:, None]
        C = C - Q @ (Q.T @ C)
        coef = torch.linalg.lstsq(C, rp[:, None], driver="gelsd").solution
        fit = C @ coef[:, 0]
        assert float(power[i]) == pytest.approx(float(fit @ fit), rel=1e-8)
        assert int(rank[i]) == 3
