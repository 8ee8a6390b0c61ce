"""The linear CV's solves through the base block's Schur complement against the pseudo-inverse of
each set's whole normal matrix (pinv's cut at PINV_RTOL), on sets that are regular, exactly
singular (a candidate column repeated, a candidate column inside the base's span) and near the cut."""
import pytest
import torch

from torchcal.pipelines.loop.linear_cv import LinearCV
from torchcal.pipelines.loop.schur import BaseSchur
from torchcal.problems.uncertainty import PINV_RTOL

F64 = torch.float64


def _systems(seed: int, prior_on: int, kb: int = 12, g: int = 8, rows: int = 40, E: int = 3):
    """``E`` normal matrices over ``kb`` base and ``g`` candidate columns, each on its own rows; the
    candidates 5 and 6 repeat 4 and a base column, 7 mixes two base columns; a prior on the first
    ``prior_on`` base columns."""
    gen = torch.Generator().manual_seed(seed)
    A = torch.randn(rows, kb + g, generator=gen, dtype=F64)
    A[:, kb + 5] = A[:, kb + 4]
    A[:, kb + 6] = A[:, 2]
    A[:, kb + 7] = 0.5 * A[:, 0] - 2.0 * A[:, 1]
    A = A / A.norm(dim=0)
    y = torch.randn(rows, generator=gen, dtype=F64)
    P2 = torch.zeros(kb + g, dtype=F64)
    P2[:prior_on] = 0.3 ** 2
    x0 = torch.randn(kb + g, generator=gen, dtype=F64)
    Gs, bs = [], []
    for e in range(E):
        keep = torch.rand(rows, generator=gen) > 0.2 * e  # the whole data, then folds
        Ae, ye = A[keep], y[keep]
        Gs.append(Ae.T @ Ae + torch.diag(P2))
        bs.append(Ae.T @ ye + P2 * x0)
    return torch.stack(Gs), torch.stack(bs), P2


SETS = [[0, 1], [4, 5], [6], [7, 3], [4, 5, 6, 7], [0, 1, 2, 3, 4, 5, 6, 7], []]


def _pinv_solve(G, b, cols):
    return torch.linalg.pinv(G[:, cols][:, :, cols], rtol=PINV_RTOL, hermitian=True) @ b[:, cols, None]


@pytest.mark.parametrize("prior_on", [0, 5, 12])
def test_solves_match_the_pseudo_inverse(prior_on):
    kb = 12
    G, b, _ = _systems(0, prior_on, kb=kb)
    sch = BaseSchur(G, b, kb)
    assert sch.usable
    e = torch.arange(G.shape[0])
    for s in SETS:
        J = torch.tensor([s], dtype=torch.long).reshape(1, len(s))
        assert bool(sch._solve(J, e)[1].all()), f"{s} went to the whole solve"
        cols = list(range(kb)) + [kb + j for j in s]
        x = sch.solve(torch.tensor([cols]), e)
        ref = _pinv_solve(G, b, cols)[..., 0]
        assert torch.allclose(x[:, 0], ref, rtol=0, atol=1e-9 * float(ref.abs().max())), s


@pytest.mark.parametrize("prior_on, lost", [(0, 3), (5, 1)])
def test_pinv_diagonal_and_rank(prior_on, lost):
    kb = 12
    G, b, P2 = _systems(1, prior_on, kb=kb)
    sch = BaseSchur(G, b, kb)
    J = torch.tensor([[4, 5, 6, 7], [0, 1, 2, 3]])
    d, rank, ok = sch._pinv_diagonal(J, torch.arange(G.shape[0]))
    assert bool(ok.all())
    for i, s in enumerate(J.tolist()):
        cols = list(range(kb)) + [kb + j for j in s]
        H = torch.linalg.pinv(G[:, cols][:, :, cols], rtol=PINV_RTOL, hermitian=True)
        assert torch.allclose(d[:, i], H.diagonal(dim1=-2, dim2=-1), rtol=0, atol=1e-9 * float(H.abs().max()))
        ref_rank = torch.linalg.matrix_rank(G[:, cols][:, :, cols], rtol=PINV_RTOL, hermitian=True)
        assert rank[:, i].tolist() == ref_rank.to(F64).tolist()
        # the effective parameters under the prior: trace(pinv(G) Gd) with Gd the data's part
        Gd = G[0] - torch.diag(P2)
        k = sch.effective(torch.tensor([cols]), Gd)
        assert float(k[0]) == pytest.approx(float((H[0] * Gd[cols][:, cols]).sum()), abs=1e-9)
    # 5 repeats 4: a rank lost; 6 (a base column) and 7 (in the base's span) lose one each only
    # where the prior does not hold those base columns
    assert rank[:, 0].tolist() == [float(kb + 4 - lost)] * G.shape[0]


def test_a_set_near_the_cut_goes_to_the_full_solve():
    """A candidate whose part beyond the base is 1e-6 of its norm puts an eigenvalue near 1e-12 of
    the largest: no bound can say on which side of the cut pinv puts it, so the set is solved whole,
    and the answer is pinv's."""
    kb = 12
    gen = torch.Generator().manual_seed(2)
    A = torch.randn(40, kb + 2, generator=gen, dtype=F64)
    A[:, kb + 1] = A[:, 3] + 1e-6 * torch.randn(40, generator=gen, dtype=F64)
    A = A / A.norm(dim=0)
    G, b = (A.T @ A)[None], (A.T @ torch.randn(40, generator=gen, dtype=F64))[None]
    sch = BaseSchur(G, b, kb)
    _, ok = sch._solve(torch.tensor([[0], [1]]), torch.arange(1))
    assert ok.tolist() == [[True, False]]
    cols = list(range(kb)) + [kb + 1]
    ref = _pinv_solve(G, b, cols)[0, :, 0]
    assert torch.allclose(sch.solve(torch.tensor([cols]), torch.arange(1))[0, 0], ref, rtol=0,
                          atol=1e-9 * float(ref.abs().max()))


def test_a_singular_base_is_solved_whole():
    kb = 6
    G, b, _ = _systems(3, 0, kb=kb)
    G, b = G.clone(), b.clone()
    G[:, 1, :] = 0.0
    G[:, :, 1] = 0.0
    b[:, 1] = 0.0
    sch = BaseSchur(G, b, kb)
    assert not sch.usable
    cols = list(range(kb)) + [kb + 2, kb + 4, kb + 5]
    ref = _pinv_solve(G, b, cols)[..., 0]
    assert torch.allclose(sch.solve(torch.tensor([cols]), torch.arange(G.shape[0]))[:, 0], ref, rtol=0,
                          atol=1e-9 * float(ref.abs().max()))


def test_linear_cv_fold_solves_equal_the_full_pseudo_inverse():
    """Through LinearCV: the folds' steps and the effective parameter counts of sets with singular
    candidates, as the whole matrices' pseudo-inverses give them."""
    gen = torch.Generator().manual_seed(4)
    n_obs, kb = 30, 7
    base = torch.randn(3 * n_obs, kb, generator=gen, dtype=F64)
    groups = [torch.randn(3 * n_obs, 1, generator=gen, dtype=F64) for _ in range(4)]
    groups.append(groups[0].clone())            # a repeated mode
    groups.append(base[:, 2:3] * 3.0)           # a mode the base already has
    groups.append(torch.randn(3 * n_obs, 3, generator=gen, dtype=F64))
    r = 1e-4 * torch.randn(n_obs, 3, generator=gen, dtype=F64)
    rows = torch.arange(n_obs)
    folds = [torch.arange(i, n_obs, 5) for i in range(5)]
    prior = torch.tensor([0.0, 2.0, 0.0, 5.0, 1.0, 0.0, 3.0], dtype=F64)
    cv = LinearCV(r, torch.ones(n_obs, dtype=F64), base, torch.zeros(kb, dtype=F64), prior, groups, rows, n_obs,
                  folds, c=3e-4)
    assert cv._schur.usable
    for chosen in ([0, 4], [1, 5], [0, 4, 5, 6], [2, 3], []):
        idx = cv._cols(chosen)[None]
        ii, jj = idx[:, :, None], idx[:, None, :]
        ref = (torch.linalg.pinv(cv._Gf[:, ii, jj], rtol=PINV_RTOL, hermitian=True) @ cv._bf[:, idx][..., None])[..., 0]
        got = cv._schur.solve(idx, torch.arange(1, 6))
        assert torch.allclose(got, ref, rtol=0, atol=1e-9 * float(ref.abs().max())), chosen
        H = torch.linalg.pinv(cv._all[0][ii, jj], rtol=PINV_RTOL, hermitian=True)
        k_ref = float((H * cv._data_all[0][ii, jj].mT).sum((-1, -2)))
        assert cv.k_eff(chosen) == pytest.approx(k_ref, abs=1e-8), chosen


def test_no_base_columns_solves_whole():
    G, b, _ = _systems(5, 0, kb=4)
    sch = BaseSchur(G, b, 0)
    assert not sch.usable
    cols = [0, 2, 5, 9]
    ref = _pinv_solve(G, b, cols)[..., 0]
    assert torch.allclose(sch.solve(torch.tensor([cols]), torch.arange(G.shape[0]))[:, 0], ref, rtol=0,
                          atol=1e-9 * float(ref.abs().max()))


def test_an_ill_conditioned_base_still_finds_an_exact_dependence():
    """Two base columns 3e-4 apart (a base block conditioned near 1e7) and a candidate that is exactly
    a sum of base columns: the Schur complement, formed through the base's factor, leaves that
    dependence at rounding level, so the set is pinv's minimum-norm solve and not a division by rounding."""
    gen = torch.Generator().manual_seed(6)
    kb = 6
    A = torch.randn(50, kb + 2, generator=gen, dtype=F64)
    A[:, 1] = A[:, 0] + 3e-4 * torch.randn(50, generator=gen, dtype=F64)
    A[:, kb] = A[:, 0] - 0.5 * A[:, 3]
    A = A / A.norm(dim=0)
    y = torch.randn(50, generator=gen, dtype=F64)
    G, b = (A.T @ A)[None], (A.T @ y)[None]
    sch = BaseSchur(G, b, kb)
    assert sch.usable
    cols = list(range(kb + 1))
    _, ok = sch._solve(torch.tensor([[0]]), torch.arange(1))
    assert bool(ok.all())
    ref = _pinv_solve(G, b, cols)[0, :, 0]
    got = sch.solve(torch.tensor([cols]), torch.arange(1))[0, 0]
    assert torch.allclose(got, ref, rtol=0, atol=1e-6 * float(ref.abs().max()))
