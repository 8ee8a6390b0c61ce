"""A load that changed mid-session with nothing logged, found by its own shape
(:mod:`torchcal.pipelines.loop.loadscan`): the scan's explained power against each break's projected
columns computed directly, and the loop on a payload swapped beside a tracker knocked in one session."""
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


@pytest.mark.slow
def test_a_payload_swapped_beside_a_knocked_tracker_is_found_at_its_own_row():
    """``swap_and_knock``: 6 kg from row 150 on and the tracker knocked at row 240, nothing logged.
    The knock's step is the easier to see; the payload's change is found at its own row (a load tied
    to the knock's step would explain nothing of the swap), its mass within a quarter, and the
    held-out error ends within a fifth of the noise floor (2.3 times it before: the load never found,
    a step of the shoulder's origin in its place)."""
    from torchcal import Robot
    from torchcal.pipelines.loop.run import run_loop
    from torchcal.sim.cases import make_case

    c = make_case("swap_and_knock", 1)
    robot = Robot.from_urdf(c.urdf, markers=c.markers)
    res = run_loop(robot, c.train.to_measurements(), c.test.to_measurements(), seed=1, log=None,
                   candidates=["joint_compliance", "load_compliance", "parameter_drivers"], elm=False)
    load = next(e for e in res.model().effects if e.name == "load_compliance")
    steps = [float(s.split("~step")[1]) for s in load.loads if "~step" in s]
    assert any(abs(s - 149.5) <= 1.0 for s in steps), load.loads
    i = load.loads.index(next(s for s in load.loads if abs(float(s.split("~step")[1]) - 149.5) <= 1.0))
    mass = float(load.theta[load.param_names.index(f"load_compliance.load~{load.loads[i]}.m")])
    assert abs(mass - 6.0) < 1.5, mass
    assert res.stages[-1]["test"]["mean_mm"] < 1.2 * c.floor_mm, (res.stages[-1]["test"], c.floor_mm)
