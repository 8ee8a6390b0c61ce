"""One fit's rank and precision judgements at the same values share one Jacobian and one rank
analysis (:func:`~torchcal.pipelines.fitting.rank_judged`, kept by ``fit_identified`` per free set
and values). Independent reference: the same judgements made from scratch each time."""
from __future__ import annotations

import copy

import torch

from torchcal.pipelines import fitting
from torchcal.pipelines.crossval.models import Context, effect_problem, fit_noise
from torchcal.pipelines.fitting import fit_identified, rank_judged, reduce_free
from torchcal.problems.template import geometric_start

from .test_creeping_fit import _seventeen_poses


def _make(robot, data, counter=None):
    ctx = Context(robot, data, [], None, 1.0)

    def make(p):
        prob = effect_problem(ctx, p, [], data, None)
        if counter is not None:
            plain = prob.jacobian

            def counted(x):
                counter.append(1)
                return plain(x)
            prob.jacobian = counted
        return prob
    return ctx, make


def test_a_kept_rank_judgement_gives_the_same_reduction_and_is_not_changed():
    robot, data = _seventeen_poses()
    ctx, make = _make(robot, data)
    p = geometric_start(robot, data, None)
    noise = 5e-3  # m: so coarse that some of the start's full-rank parameters are too vague to keep
    ranked = rank_judged(make, p, markers=robot.marker_names)
    kept = copy.deepcopy(ranked[2])
    fresh, rep_fresh = reduce_free(make, p, markers=robot.marker_names, noise=noise, plausible=ctx.plausible)
    reused, rep_reused = reduce_free(make, p, noise=noise, plausible=ctx.plausible, ranked=ranked)
    assert rep_fresh.imprecise, "the case must drop a parameter for imprecision, or the precision half is untested"
    assert reused.free_names == fresh.free_names
    assert rep_reused.dropped == rep_fresh.dropped and rep_reused.imprecise == rep_fresh.imprecise
    assert rep_reused.reasons == rep_fresh.reasons
    # the precision judgement appended to its own copy: the kept rank judgement is as it was
    assert ranked[2] == kept and not ranked[2].imprecise


def test_fit_identified_judges_each_solution_from_one_jacobian(monkeypatch):
    robot, data = _seventeen_poses()
    start = geometric_start(robot, data, None)
    kw = dict(reduce=True, markers=robot.marker_names, options={"max_iter": 200}, noise=fit_noise)

    def fit(counter):
        ctx, make = _make(robot, data, counter)
        return fit_identified(make, start, plausible=ctx.plausible, **kw)

    n_kept: list = []
    kept = fit(n_kept)
    # the reference: every judgement from scratch
    monkeypatch.setattr(fitting._OneProblem, "reduce", lambda self, p, noise: reduce_free(
        self.make, p, markers=self.opt.markers, kind=self.opt.kind, prefer=self.opt.prefer, noise=noise,
        plausible=self.opt.plausible))
    n_fresh: list = []
    fresh = fit(n_fresh)
    assert kept[0].free_names == fresh[0].free_names
    # exact on any processor: both runs make the same operations on the same values in one process, the
    # kept judgements only skip computing again what was computed
    assert torch.equal(kept[0].values, fresh[0].values)
    assert kept[2].dropped == fresh[2].dropped and kept[2].reasons == fresh[2].reasons
    assert len(n_kept) < len(n_fresh), (len(n_kept), len(n_fresh))
