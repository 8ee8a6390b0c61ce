"""A cycle in time (a frame that swings with the air conditioning): its shape, its grid of
frequencies, the screening's search for it, and its words. Independent references: the sine written
out, a signal of known period and phase put into known columns, noise alone."""
from __future__ import annotations

import math
from types import SimpleNamespace

import torch

from torchcal.effects import ParameterDrivers
from torchcal.effects.shapes import (MAX_CYCLES, PERIOD_OVERSAMPLE, cycle_label, period_frequencies, period_parts,
                                     period_tag, shape_column)
from torchcal.kinematics.robots import shipped
from torchcal.pipelines.loop import screen


def test_a_cycle_is_a_sine_of_its_period_from_the_first_time():
    t = torch.linspace(100.0, 9000.0, 50, dtype=torch.float64)
    for phase, fn in (("sin", torch.sin), ("cos", torch.cos)):
        tag = period_tag(phase, 1980.0, 100.0)
        assert period_parts(tag) == (phase, 1980.0, 100.0)
        ref = fn(2 * math.pi * (t - 100.0) / 1980.0)
        assert torch.allclose(shape_column(tag, t, 4550.0, 4450.0), ref, atol=1e-12)


def test_the_frequencies_run_from_one_cycle_over_the_span_to_the_fastest_the_rows_can_show():
    t = torch.linspace(0.0, 8000.0, 300, dtype=torch.float64)
    f = period_frequencies(t)
    assert len(f) == (MAX_CYCLES - 1) * PERIOD_OVERSAMPLE + 1
    assert math.isclose(f[0], 1 / 8000.0) and math.isclose(f[-1], MAX_CYCLES / 8000.0)
    assert math.isclose(f[1] - f[0], 1 / (PERIOD_OVERSAMPLE * 8000.0))
    few = period_frequencies(t[:12])  # 12 distinct times: at most 3 cycles (4 rows each)
    assert math.isclose(few[-1], 3 / float(t[11]))
    assert period_frequencies(t[:3]) == [] and period_frequencies(torch.full((9,), 5.0)) == []


class _Family:
    """The screening's view of a family: terms, copies with other terms, the robot."""

    def __init__(self, robot, terms):
        self.robot, self.terms = robot, terms

    def _copy(self, terms):
        return _Family(self.robot, terms)


def _screening_inputs(signal: bool, seed: int = 0):
    """300 rows over 2.3 h; one parameter's column ``g`` (3 axes per row) seen through a 27-minute
    cycle of phase 0.7 rad (``signal``), plus noise of 1 per axis; a second parameter's column with
    no cycle. The columns of a term are ``g`` times its shape, as the family's are."""
    g = torch.Generator().manual_seed(seed)
    n = 300
    t = torch.sort(torch.rand(n, generator=g, dtype=torch.float64) * 8300.0).values
    G = {"a.offset": torch.randn(3 * n, generator=g, dtype=torch.float64),
         "b.offset": torch.randn(3 * n, generator=g, dtype=torch.float64)}
    x0 = float(t.min())
    r = torch.randn(3 * n, generator=g, dtype=torch.float64)
    if signal:
        r = r + 0.6 * G["a.offset"] * torch.sin(2 * math.pi * (t - x0) / 1620.0 + 0.7).repeat_interleave(3)
    mean, half = float(t.mean()), float(t.max() - t.min()) / 2

    def columns(e):
        return torch.stack([G[p] * shape_column(tag, t, mean, half).repeat_interleave(3) for p, _, tag in e.terms], 1)

    data = SimpleNamespace(q=torch.zeros(n, 6, dtype=torch.float64), covariates={"time": t})
    eff = _Family(shipped("ur5e"), [("a.offset", "time:time", "lin"), ("b.offset", "time:time", "lin")])
    Q = torch.zeros(3 * n, 0, dtype=torch.float64)
    return eff, data, columns, Q, r, torch.ones(3 * n, dtype=torch.float64)


def test_the_screening_finds_a_cycle_and_its_period():
    """A cycle no low-order shape sees passes the screening for its own parameter only, and the
    refined frequency is within 0.3 % of the one put in, both phases offered."""
    eff, data, columns, Q, r, w3 = _screening_inputs(signal=True)
    cyc = screen._Cycles(eff, data, torch.arange(len(data.covariates["time"])), screen._Units(eff, columns, w3))
    stats = dict((pr, pv) for pv, pr in cyc.stats(Q, r, 1.0))
    assert stats[("a.offset", "time:time")] < 1e-12 and stats[("b.offset", "time:time")] > 1e-3, stats
    tags = cyc.best(("a.offset", "time:time"), Q, r)
    assert [period_parts(t)[0] for t in tags] == ["sin", "cos"]
    assert abs(period_parts(tags[0])[1] / 1620.0 - 1) < 3e-3, tags


def test_noise_alone_passes_no_cycle():
    """On noise alone the best of the grid's frequencies, at the level the grid shares, is no finding
    (20 draws: every p-value above the screening's level for one pair)."""
    for seed in range(20):
        eff, data, columns, Q, r, w3 = _screening_inputs(signal=False, seed=seed)
        cyc = screen._Cycles(eff, data, torch.arange(len(data.covariates["time"])), screen._Units(eff, columns, w3))
        pv = min(p for p, _ in cyc.stats(Q, r, 1.0))
        assert pv > screen.ALPHA / 2, (seed, pv)


def test_a_cycle_is_one_finding_whatever_its_phase_and_is_said_with_its_period():
    robot = shipped("ur5e")
    s, c = period_tag("sin", 1980.0, 0.0), period_tag("cos", 1980.0, 0.0)
    terms = [("base.rz", "time:time", s), ("base.rz", "time:time", c), ("elbow_joint.offset", "time:time", s),
             ("elbow_joint.offset", "time:time", c)]
    eff = ParameterDrivers(robot, terms=terms)
    modes = dict(eff.modes())
    assert modes == {f"base.frame~time:time~{cycle_label(s)}": [0, 1],
                     f"elbow_joint.offset~time:time~{cycle_label(s)}": [2, 3]}, modes
    words = [eff.mode_words(m) for m in modes]
    assert any("the instrument frame moves as one rigid body" in w and "with a period of 33 min" in w for w in words), words
    assert any("elbow_joint's zero cycles along time" in w and "33 min" in w for w in words), words
    said = eff.describe(torch.tensor([2e-4, 0.0, -1e-4, 0.0], dtype=torch.float64))
    assert any("swings by ±0.1 mrad (sin phase)" in x and "period of 33 min" in x for x in said), said
