"""Pruning judges its removals together: a mode whose removal the refit shows the data need stays,
however redundant its own judgement (the linearised "added last" rule) made it look.

The case: a KR5 arc whose joints are compliant (simulated, 60 poses, 0.05 mm noise), the joint
compliance fitted with a twist mode per joint. ``weakest_mode`` is replaced by a judge that calls a
given list of modes redundant in turn (as modes that stand in for one another each look), so that
what the guard decides is seen alone. Independent reference: the truth of the simulation, in which
joint_a2 and joint_a3 carry the arm's weight and the wrist joints almost none."""
from __future__ import annotations

import pytest

import torchcal.pipelines.loop.prune as prune_mod
from torchcal.pipelines.crossval.evaluate import evaluate
from torchcal.pipelines.crossval.scores import T_EXIT, compare

from .test_batched_folds import _case

# each test fits and prunes a loop's model (2-5 s each on a slow 2-core machine): make test runs them,
# the fast lane does not
pytestmark = pytest.mark.slow


def _judge(monkeypatch, order):
    """The guard alone: the judge of :func:`_judge_redundant`, and no idle mode (the model's first
    joint, whose axis is vertical, has a twist mode gravity never loads: its own test is below)."""
    monkeypatch.setattr(prune_mod, "weakest_mode", _judge_redundant(order))
    monkeypatch.setattr(prune_mod, "idle_modes", lambda *a, **k: [])


def _judge_redundant(order):
    """A stand-in for :func:`weakest_mode` that calls the first mode of ``order`` still in the model
    redundant (t = 0), and none once they are all gone."""
    def judge(ctx, m, protect=frozenset()):
        present = [lab for _, lab, _ in prune_mod._mode_columns(ctx, m)]
        left = [lab for lab in order if lab in present]
        if not left:
            return None
        k = next(i for i, e in enumerate(m.effects) if any(lab == left[0] for lab, _ in e.modes()))
        return k, left[0], 0.0
    return judge


def _model():
    ctx, start, effects = _case(n=60)
    m = evaluate(ctx, "joint compliance", start, effects, None)
    assert [lab for _, lab, _ in prune_mod._mode_columns(ctx, m)] == [
        "joint_a2.twist", "joint_a3.twist", "joint_a4.twist", "joint_a5.twist", "joint_a6.twist"]
    return ctx, m


def test_a_removal_the_data_need_does_not_happen(monkeypatch):
    ctx, m = _model()
    said = []
    _judge(monkeypatch, ["joint_a2.twist"])
    out, gone = prune_mod.prune(ctx, m, say=said.append)
    assert gone == [] and out is m
    assert "joint_a2.twist stays" in said[0]
    # what the guard read: the refit without it is clearly worse than the model with it
    forced = prune_mod.without_mode(ctx, m, 0, "joint_a2.twist")
    t, pen_ok, _ = compare(forced.scores, m.scores, forced.k, m.k, ctx.n_obs)
    assert t > T_EXIT and pen_ok


def test_a_removal_the_data_do_not_need_happens(monkeypatch):
    ctx, m = _model()
    _judge(monkeypatch, ["joint_a6.twist"])
    out, gone = prune_mod.prune(ctx, m)
    assert [g["mode"] for g in gone] == ["joint_a6.twist"]
    assert [lab for _, lab, _ in prune_mod._mode_columns(ctx, out)] == [
        "joint_a2.twist", "joint_a3.twist", "joint_a4.twist", "joint_a5.twist"]


def test_removals_stop_where_together_they_cost_what_the_data_need(monkeypatch):
    """The wrist twists go one after another (the model barely changes), then the shoulder's stays:
    pruning ends with the model before it, and the wrist removals kept."""
    ctx, m = _model()
    order = ["joint_a6.twist", "joint_a5.twist", "joint_a4.twist", "joint_a2.twist", "joint_a3.twist"]
    said = []
    _judge(monkeypatch, order)
    out, gone = prune_mod.prune(ctx, m, say=said.append)
    assert [g["mode"] for g in gone] == order[:3]
    assert [lab for _, lab, _ in prune_mod._mode_columns(ctx, out)] == ["joint_a2.twist", "joint_a3.twist"]
    assert "joint_a2.twist stays" in said[-1]
    # the guard's rule, checked on what came out: the model before pruning does not pass the exit rule
    # against the pruned one (three wrist twists less cost nothing the data need) ...
    t, pen_ok, _ = compare(out.scores, m.scores, out.k, m.k, ctx.n_obs)
    assert not (t > T_EXIT and pen_ok)
    # ... while against the model without the shoulder's twist too, it does
    forced = prune_mod.without_mode(ctx, out, 0, "joint_a2.twist")
    t, pen_ok, _ = compare(forced.scores, m.scores, forced.k, m.k, ctx.n_obs)
    assert t > T_EXIT and pen_ok


def test_a_mode_the_rank_judgement_dropped_leaves_first(monkeypatch):
    """The first joint's twist, whose axis is vertical, is one mode of the fitted compliance that
    gravity never loads: the rank judgement drops all its parameters (held at zero). It carries
    nothing, and leaves before any judgement; the model's predictions stay what they were."""
    ctx, m = _model()
    assert prune_mod.idle_modes(ctx, m) == [(0, "joint_a1.twist")]
    monkeypatch.setattr(prune_mod, "weakest_mode", _judge_redundant([]))
    said = []
    out, gone = prune_mod.prune(ctx, m, say=said.append)
    assert gone == [{"effect": "joint_compliance", "mode": "joint_a1.twist", "t": None}]
    assert "joint_a1.twist leaves" in said[0]
    assert [lab for lab, _ in out.effects[0].modes()] == [lab for lab, _ in m.effects[0].modes()][1:]
    # the same fit without the idle mode: the cross-validated scores agree to the fits' tolerance (each
    # refit stops within xtol of the same minimum; removing a mode that carries anything moves them by
    # far more than this)
    assert float((out.scores - m.scores).abs().max()) < 1e-6 * float(m.scores.abs().max())
