"""Tests of the identifiability analysis (rank, base-parameter selection, reasons, observability)."""
from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch

from torchcal import Robot
from torchcal.problems.identifiability import identifiability, observability, stacked_jacobian
from torchcal.kinematics.robot_data import get_robot

D = torch.float64
DH_ERRORS = ["joint_*.da", "joint_*.dd", "joint_*.dalpha", "joint_*.dtheta"]
D6 = 0.115  # KR5 arc: flange distance beyond the wrist centre (m)


def kr5_table():
    return [dict(a=j["a"], d=j["d"], alpha=j["alpha"], theta=j["theta"], name=f"joint_{i + 1}")
            for i, j in enumerate(get_robot("kuka_kr5_arc")["joints"])]


@pytest.fixture(scope="module")
def kr5():
    return Robot.from_dh(kr5_table())


@pytest.fixture(scope="module")
def q30():
    g = torch.Generator().manual_seed(0)
    return (torch.rand(30, 6, generator=g, dtype=D) * 2 - 1) * math.pi


@pytest.fixture(scope="module")
def rep(kr5, q30):
    return identifiability(kr5, q30, free=DH_ERRORS)


def normalised(A: np.ndarray, rtol: float = 1e-9) -> np.ndarray:
    """Columns divided by their norms (computed independently of the module). Columns at most
    rtol x the largest norm are zero: e.g. joint_6.dtheta's column is ~1e-17 (the flange sits on
    axis 6), and dividing that rounding noise by its own norm would invent a unit column."""
    n = np.linalg.norm(A, axis=0)
    zero = n <= rtol * n.max()
    return np.where(zero, 0.0, A / np.where(zero, 1.0, n))


def direct_jacobian(robot, q, names, kind="position"):
    """The stacked Jacobian straight from robot.param_jacobian, for cross-checks."""
    J = robot.param_jacobian(q, kind=kind).numpy()
    idx = [robot.param_names.index(n) for n in names]
    return J.reshape(-1, J.shape[-1])[:, idx]


# ----------------------------------------------------------------------------- stacked Jacobian
def test_stacked_jacobian_columns_rows_and_weights(kr5, q30):
    A = stacked_jacobian(kr5, q30, free=["joint_2.*"])
    assert A.shape == (30 * 1 * 3, 4) and A.dtype == D
    np.testing.assert_allclose(A.numpy(), direct_jacobian(kr5, q30, ["joint_2.da", "joint_2.dd", "joint_2.dalpha",
                                                                    "joint_2.dtheta"]), atol=0)
    ps = kr5.params().only("joint_2.*")  # a ParamSet's free mask selects the same columns
    assert torch.equal(stacked_jacobian(kr5, q30, free=ps), A)
    Aw = stacked_jacobian(kr5, q30, free=["joint_2.*"], weights=torch.tensor([1.0, 2.0, 0.0], dtype=D))
    np.testing.assert_allclose(Aw[1::3].numpy(), 2 * A[1::3].numpy())
    assert float(Aw[2::3].abs().max()) == 0.0
    with pytest.raises(KeyError):
        stacked_jacobian(kr5, q30, free=["joint_9.*"])


# ----------------------------------------------------------------------------- KR5 rank
def test_kr5_dh_rank_matches_direct_svd(kr5, q30, rep):
    names = [n for n in kr5.param_names if n.startswith("joint_")]
    assert rep.n_params == len(names) == 24
    An = normalised(direct_jacobian(kr5, q30, names))
    assert rep.rank == np.linalg.matrix_rank(An) == 19
    assert rep.svd_rank == rep.rank
    s = np.linalg.svd(An, compute_uv=False)
    np.testing.assert_allclose(rep.singular_values, s, atol=1e-12)


def test_kr5_dropped_set_and_span(kr5, q30, rep):
    assert sorted(rep.identifiable + rep.dropped) == sorted(n for n in kr5.param_names if n.startswith("joint_"))
    assert not set(rep.identifiable) & set(rep.dropped)
    assert set(rep.dropped) == set(rep.reasons)
    # the expected structure of the KR5 (equal ties go to the earlier parameter)
    assert set(rep.dropped) == {"joint_3.dd", "joint_5.dalpha", "joint_5.dtheta", "joint_6.dalpha", "joint_6.dtheta"}
    names = rep.identifiable + rep.dropped
    An = normalised(direct_jacobian(kr5, q30, names))
    k = len(rep.identifiable)
    assert np.linalg.matrix_rank(An[:, :k]) == rep.rank == k  # the kept columns are independent
    for j in range(k, len(names)):  # every dropped column lies in their span
        assert np.linalg.matrix_rank(np.column_stack([An[:, :k], An[:, j]])) == rep.rank


def test_kr5_reasons(kr5, q30, rep):
    for n in ("joint_6.dalpha", "joint_6.dtheta"):
        assert "does not move any marker" in rep.reasons[n]
        assert rep.relations[n] == {}
    r = rep.reasons["joint_3.dd"]
    assert "joint_2.dd" in r and "cannot be told apart" in r
    np.testing.assert_allclose(rep.relations["joint_3.dd"]["joint_2.dd"], 1.0, atol=1e-9)
    # wrist: a5 and theta5 couple through d6, as do d5 and alpha5 (m per rad = d6)
    np.testing.assert_allclose(rep.relations["joint_5.dtheta"]["joint_5.da"], -D6, rtol=1e-9)
    np.testing.assert_allclose(rep.relations["joint_5.dalpha"]["joint_5.dd"], D6, rtol=1e-9)
    assert "1 mrad of joint_5.dtheta acts like -0.115 mm of joint_5.da" in rep.reasons["joint_5.dtheta"]


def test_relations_reproduce_raw_columns(kr5, q30):
    """Unscaled coefficients: 1 unit of a dropped parameter = sum(coef * 1 unit of each partner)."""
    rep = identifiability(kr5, q30)  # all 36 parameters: base, DH errors, flange offsets
    assert rep.rank == np.linalg.matrix_rank(normalised(direct_jacobian(kr5, q30, kr5.param_names)))
    for n, rel in rep.relations.items():
        col = direct_jacobian(kr5, q30, [n])[:, 0]
        fit = sum(c * direct_jacobian(kr5, q30, [p])[:, 0] for p, c in rel.items()) if rel else 0 * col
        np.testing.assert_allclose(fit, col, atol=1e-9)
    # base first: joint_1's d and theta duplicate base.z and base.rz
    assert "base.z" in rep.reasons["joint_1.dd"] and "base.rz" in rep.reasons["joint_1.dtheta"]
    assert {f"base.{c}" for c in ("x", "y", "z", "rx", "ry", "rz")} <= set(rep.identifiable)


def test_prefer_changes_which_of_a_pair_is_kept(kr5, q30, rep):
    alt = identifiability(kr5, q30, free=DH_ERRORS, prefer=["joint_3.dd", "joint_5.dtheta"])
    assert alt.rank == rep.rank
    assert "joint_3.dd" in alt.identifiable and "joint_2.dd" in alt.dropped
    assert "joint_3.dd" in alt.reasons["joint_2.dd"]
    assert "joint_5.dtheta" in alt.identifiable and "joint_5.da" in alt.dropped
    np.testing.assert_allclose(alt.relations["joint_5.da"]["joint_5.dtheta"], -1 / D6, rtol=1e-9)


# ----------------------------------------------------------------------------- URDF, base free
def test_urdf_first_joint_origin_duplicates_base(kr5, q30):
    ru = Robot.from_urdf(kr5.to_urdf_string(), markers=["flange"])
    rep = identifiability(ru, q30, free=ru.params())  # base, all origin errors, offsets, flange xyz
    assert rep.rank == np.linalg.matrix_rank(normalised(direct_jacobian(ru, q30, ru.params().free_names)))
    assert {f"base.{c}" for c in ("x", "y", "z", "rx", "ry", "rz")} <= set(rep.identifiable)
    assert "joint_1.dz" in rep.dropped
    assert "base.z" in rep.reasons["joint_1.dz"] and "cannot be told apart" in rep.reasons["joint_1.dz"]
    np.testing.assert_allclose(rep.relations["joint_1.dz"]["base.z"], 1.0, atol=1e-9)
    assert "base.rz" in rep.reasons["joint_1.offset"]
    # asking for the joint error first keeps it and drops base.z instead
    alt = identifiability(ru, q30, free=ru.params(), prefer=["joint_1.dz"])
    assert "joint_1.dz" in alt.identifiable and "base.z" in alt.dropped and alt.rank == rep.rank


# ----------------------------------------------------------------------------- observability
def test_observability_indices_match_numpy(kr5, q30, rep):
    A = direct_jacobian(kr5, q30, rep.identifiable)
    m, k = A.shape
    s = np.linalg.svd(normalised(A) * math.sqrt(m), compute_uv=False)  # unit-RMS columns
    want = dict(O1=np.prod(s) ** (1 / k) / math.sqrt(m), O2=s[-1] / s[0], O3=s[-1], O4=s[-1] ** 2 / s[0],
                condition=s[0] / s[-1])
    got = observability(kr5, q30, free=DH_ERRORS)
    assert got["params"] == rep.identifiable and got["n_rows"] == m == rep.n_rows
    for key, v in want.items():
        assert rep.__getattribute__(key) == pytest.approx(v, rel=1e-10), key
        assert got[key] == pytest.approx(v, rel=1e-10), key


def test_random_poses_beat_clustered_poses(kr5, q30, rep):
    g = torch.Generator().manual_seed(1)
    qc = q30[0] + (torch.rand(30, 6, generator=g, dtype=D) * 2 - 1) * 0.05
    spread = observability(kr5, q30, free=rep.identifiable)
    clustered = observability(kr5, qc, free=rep.identifiable)
    assert spread["rank"] == clustered["rank"] == 19
    assert spread["O1"] > 5 * clustered["O1"]
    assert spread["condition"] < clustered["condition"] / 100
    fixed = observability(kr5, qc, free=rep.identifiable, scale=rep.column_rms)  # same column scaling
    assert spread["O1"] > 5 * fixed["O1"]
    # used as given, a deficient column set is unobservable
    raw = observability(kr5, q30, free=DH_ERRORS, reduce=False)
    assert raw["rank"] == 19 and raw["O1"] == raw["O3"] == 0.0 and math.isinf(raw["condition"])


def test_summary_and_dict(rep):
    text = rep.summary()
    assert "rank 19 of 24" in text
    for n in rep.dropped:
        assert rep.reasons[n] in text
    d = json.loads(json.dumps(rep.to_dict()))
    assert d["rank"] == 19 and d["dropped"] == rep.dropped and d["O1"] == pytest.approx(rep.O1)
