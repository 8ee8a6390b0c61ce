"""The loop's linearised mode selection: the batched rank-one scoring of single-mode additions equals
scoring each addition on its own, and the selection can drop and exchange modes it took earlier."""
from __future__ import annotations

import torch

from torchcal.pipelines.crossval.models import folds_of
from torchcal.pipelines.loop.linear_cv import LinearCV

D = torch.float64


def _problem(n_rows=60, kb=5, L=12, seed=0, prior=True, truth=()):
    g = torch.Generator().manual_seed(seed)
    base = torch.randn(3 * n_rows, kb, generator=g, dtype=D)
    groups = [torch.randn(3 * n_rows, 1, generator=g, dtype=D) for _ in range(L)]
    r = 0.01 * torch.randn(n_rows, 3, generator=g, dtype=D)
    for j, c in truth:  # model - measured: the residual a missing mode leaves
        r = r - c * groups[j].reshape(n_rows, 3)
    w = torch.ones(n_rows, dtype=D)
    x0 = 0.1 * torch.randn(kb, generator=g, dtype=D)
    pr = torch.full((kb,), 0.3, dtype=D) if prior else None
    rows = torch.arange(n_rows)
    return LinearCV(r, w, base, x0, pr, groups, rows, n_rows, folds_of(n_rows, 5, seed), 0.02)


def test_batched_single_additions_equal_one_at_a_time():
    for prior in (True, False):
        lcv = _problem(prior=prior)
        chosen = [1, 4]
        pool = [g for g in range(12) if g not in chosen]
        sc, k = lcv.add_one(chosen, pool)
        for i, g in enumerate(pool):
            torch.testing.assert_close(sc[:, i], lcv.scores(chosen + [g]), rtol=1e-9, atol=1e-15)
            assert abs(float(k[i]) - lcv.k_eff(chosen + [g])) < 1e-8


def test_a_column_the_set_spans_adds_nothing():
    lcv = _problem()
    lcv_dup = LinearCV(lcv.r, torch.ones(60, dtype=D), lcv.A[:, :5] * lcv.scale[:5], lcv._x0[:5] / lcv.scale[:5],
                       lcv.prior, [lcv.A[:, 5:6] * lcv.scale[5], lcv.A[:, 5:6] * lcv.scale[5] * 2.0],
                       lcv.rows, 60, folds_of(60, 5, 0), 0.02)
    sc, k = lcv_dup.add_one([0], [1])
    torch.testing.assert_close(sc[:, 0], lcv_dup.scores([0]), rtol=1e-9, atol=1e-15)
    assert abs(float(k[0]) - lcv_dup.k_eff([0])) < 1e-8


def test_a_mode_that_later_ones_make_redundant_leaves():
    """Mode 2 mixes modes 0 and 1, so forward selection takes it first; once 0 and 1 are in, it
    explains nothing of its own and the backward pass drops it."""
    g = torch.Generator().manual_seed(3)
    n_rows = 120
    cols = [torch.randn(3 * n_rows, 1, generator=g, dtype=D) for _ in range(6)]
    cols[2] = (cols[0] + 0.8 * cols[1]) / 1.28 + 0.05 * torch.randn(3 * n_rows, 1, generator=g, dtype=D)
    r = 1e-3 * torch.randn(n_rows, 3, generator=g, dtype=D) - (0.05 * cols[0] + 0.03 * cols[1]).reshape(n_rows, 3)
    base = torch.randn(3 * n_rows, 4, generator=g, dtype=D)
    lcv = LinearCV(r, torch.ones(n_rows, dtype=D), base, torch.zeros(4, dtype=D), None, cols, torch.arange(n_rows),
                   n_rows, folds_of(n_rows, 5, 0), None)
    chosen, hist, _, _ = lcv.forward([], n_rows)
    assert hist[0]["added"] == [2]  # forward alone would keep the mixture
    assert sorted(chosen) == [0, 1], hist
    assert any("removed" in h for h in hist)


def test_modes_the_data_cannot_tell_apart_are_named_together():
    g = torch.Generator().manual_seed(4)
    n_rows = 80
    cols = [torch.randn(3 * n_rows, 1, generator=g, dtype=D) for _ in range(5)]
    cols[3] = cols[1] * 1.01 + 0.01 * torch.randn(3 * n_rows, 1, generator=g, dtype=D)
    r = 1e-3 * torch.randn(n_rows, 3, generator=g, dtype=D) - 0.02 * cols[1].reshape(n_rows, 3)
    lcv = LinearCV(r, torch.ones(n_rows, dtype=D), torch.randn(3 * n_rows, 3, generator=g, dtype=D),
                   torch.zeros(3, dtype=D), None, cols, torch.arange(n_rows), n_rows, folds_of(n_rows, 5, 0), None)
    chosen, _, _, _ = lcv.forward([], n_rows)
    assert len(chosen) == 1 and chosen[0] in (1, 3)
    assert lcv.aliases(chosen) == {chosen[0]: [4 - chosen[0]]}


def test_wide_sets_score_as_through_the_normal_matrix(monkeypatch):
    """A set with more columns than rows is solved through the rows' Gram (BBᵀ): the same
    minimum-norm steps, scores and effective sizes as the pseudo-inverse of the normal matrix."""
    for prior in (True, False):
        lcv = _problem(n_rows=8, kb=5, L=40, seed=4, prior=prior)
        idx = torch.stack([lcv._cols(list(range(40))), lcv._cols(list(range(1, 40)) + [0])])
        assert lcv._wide(idx)
        assert not lcv.set_prior(lcv.prior, 0.05)._wide(idx)  # a ridge row per column: no fewer rows
        lcv.set_prior(lcv.prior)
        wide = lcv._scores_batch(idx), lcv._k_eff_batch(idx)
        monkeypatch.setattr(LinearCV, "_wide", lambda self, idx: False)
        normal = lcv._scores_batch(idx), lcv._k_eff_batch(idx)
        monkeypatch.undo()
        torch.testing.assert_close(wide[0], normal[0], rtol=1e-8, atol=1e-14)
        torch.testing.assert_close(wide[1], normal[1], rtol=1e-8, atol=1e-10)
        assert float(wide[1][0]) > 5  # more than the base's parameters: the groups count
