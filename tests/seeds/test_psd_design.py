"""Seed 003 worst case: expected spot errors, beam weights and the D-optimal design (small cases)."""
from __future__ import annotations

import pytest
import torch

from torchcal.pipelines.psd import calibrate_psd
from torchcal.problems.psd import SpotResidual
from torchcal.measure.psd import PSDData, spot_covariance, spot_sensitivity, spot_whitening
from torchcal.measure.laser import Laser, laser_beams, plane_intersection, psd_frame
from torchcal.pipelines.psd_design import _greedy, information, predicted_max_error, select_design
from torchcal.sim.psd import measure_psd
from torchcal.kinematics.robots import shipped

F64 = dict(dtype=torch.float64)
HOME = torch.tensor([0.0, -1.4, 2.4, 0.0, 0.5, 0.0], **F64)
UNSEEN = ("joint_a1.dd", "joint_a1.dtheta", "joint_a3.dd", "joint_a2.da")  # gauge, d2/d3, and the scale


@pytest.fixture(scope="module")
def setup():
    """Three PSD placements, each facing the beam of a reference pose 0.35 m away, and eight
    candidate aims per placement near that pose (FK only: no aiming IK, so the fixture is fast;
    spots land within a few cm of the centres, which the spot model does not mind)."""
    robot = shipped("kuka_kr5_arc", source="dh")
    laser = Laser()
    free = robot.params()
    free.only("joint_a*")
    free.fix(*UNSEEN)
    zero = torch.zeros(robot.n_params, **F64)
    refs = HOME + torch.tensor([[0.0, 0.0, 0.0, 0.0, 0.0, 0.0], [0.6, 0.2, -0.3, 0.5, 0.3, 0.4],
                                [-0.5, 0.3, -0.5, -0.4, 0.6, -0.7]], **F64)
    p, w = laser_beams(robot, laser, refs, zero)
    C = p + 0.35 * w
    R = torch.stack([psd_frame(-w[j], 0.4 * j) for j in range(3)])
    g = torch.Generator().manual_seed(4)
    q = (refs[:, None] + 0.06 * torch.randn(3, 8, robot.dof, generator=g, **F64)).reshape(-1, robot.dof)
    loc = torch.arange(3).repeat_interleave(8)
    _, uv = plane_intersection(*laser_beams(robot, laser, q, zero), C[loc], R[loc])
    cand = PSDData(q, uv, loc, 3)
    true = torch.zeros(robot.n_params, **F64)
    idx = free.free_index
    true[idx] = torch.where(torch.tensor([robot.param_units[i] == "m" for i in idx.tolist()]), 0.5e-3, 1e-3) \
        * torch.randn(idx.numel(), generator=g, **F64)
    return dict(robot=robot, laser=laser, R=R, C=C, free=free, cand=cand, zero=zero, true=true)


def test_spot_sensitivity_matches_finite_differences(setup):
    s = setup
    robot, laser, d = s["robot"], s["laser"], s["cand"]
    q, loc = d.q[:5], d.loc[:5]
    G = spot_sensitivity(robot, laser, q, loc, s["R"], s["C"], s["true"])
    h = 1e-7
    cols = []
    for j in range(robot.dof):
        e = torch.zeros(robot.dof, **F64)
        e[j] = h
        uv = [plane_intersection(*laser_beams(robot, laser, q + sgn * e, s["true"]), s["C"][loc], s["R"][loc])[1]
              for sgn in (1, -1)]
        cols.append((uv[0] - uv[1]) / (2 * h))
    torch.testing.assert_close(G, torch.stack(cols, -1), atol=1e-7, rtol=1e-6)


def test_whitening_and_weighted_spot_residual(setup):
    s = setup
    robot, laser, d = s["robot"], s["laser"], s["cand"]
    cov = spot_covariance(robot, laser, d.q, d.loc, s["R"], s["C"], s["zero"], q_noise=10e-6, uv_noise=1e-6)
    W = spot_whitening(cov)
    eye = torch.eye(2, **F64).expand_as(cov)
    torch.testing.assert_close(W @ cov @ W.transpose(-1, -2), eye, atol=1e-9, rtol=0)
    # a 10 µrad encoder moves a spot by about 10 µm, far above the 1 µm PSD noise
    sd = torch.sqrt(torch.linalg.eigvalsh(cov)[:, -1])
    assert 5e-6 < float(sd.min()) and float(sd.max()) < 30e-6
    plain = SpotResidual(robot, laser, d, s["free"], s["R"], s["C"])
    weighted = SpotResidual(robot, laser, d, s["free"], s["R"], s["C"], whiten=W)
    x = plain.start() + 1e-4
    r, rw = plain.residuals(x[None])[0].reshape(-1, 2), weighted.residuals(x[None])[0].reshape(-1, 2)
    torch.testing.assert_close(rw, (W @ r[..., None])[..., 0], atol=1e-15, rtol=1e-12)
    J, Jw = plain.jacobian(x).reshape(-1, 2, x.numel()), weighted.jacobian(x).reshape(-1, 2, x.numel())
    torch.testing.assert_close(Jw, W @ J, atol=1e-12, rtol=1e-12)
    with pytest.raises(ValueError, match="whiten"):
        SpotResidual(robot, laser, d, s["free"], s["R"], s["C"], whiten=W[:3])


def test_weighted_spots_recover_the_truth_from_noise_free_data(setup):
    s = setup
    robot, laser = s["robot"], s["laser"]
    data, keep = measure_psd(robot, s["true"], laser, s["cand"].q, s["cand"].loc, s["R"], s["C"],
                             generator=torch.Generator().manual_seed(0), psd_half=1.0)
    assert bool(keep.all())
    D = [(0, 1, float((s["C"][0] - s["C"][1]).norm()))]
    res = calibrate_psd(robot, laser, data, s["free"], method="spots", distances=D, noise=(10e-6, 1e-6, 2e-6))
    idx = s["free"].free_index
    torch.testing.assert_close(res.params[idx], s["true"][idx], atol=1e-9, rtol=0)
    with pytest.raises(ValueError, match="noise"):  # the weights are for the spot residual only
        calibrate_psd(robot, laser, data, s["free"], method="pm", distances=D, noise=(10e-6, 1e-6, 2e-6))


def test_measure_psd_drops_spots_off_the_detector(setup):
    s = setup
    robot, laser, d = s["robot"], s["laser"], s["cand"]
    data, keep = measure_psd(robot, s["zero"], laser, d.q, d.loc, s["R"], s["C"],
                             generator=torch.Generator().manual_seed(0), psd_half=0.02)
    assert 0 < int(keep.sum()) < keep.numel()
    torch.testing.assert_close(keep, (d.uv.abs() <= 0.02).all(-1))  # the candidates' own spots, nominal model
    assert data.q.shape[0] == int(keep.sum()) and torch.allclose(data.uv, d.uv[keep], atol=1e-12)


def test_design_picks_valid_rows_and_the_best_location(setup):
    s = setup
    robot, laser, cand, free = s["robot"], s["laser"], s["cand"], s["free"]
    des = select_design(robot, laser, cand, s["R"], s["C"], free, m=2, k=3, q_noise=10e-6, uv_noise=1e-6)
    assert len(des.locations) == 2 and len(set(des.locations)) == 2 and des.rows.numel() == 6
    assert len(set(des.rows.tolist())) == 6
    for slot, c in enumerate(des.locations):
        assert bool((cand.loc[des.rows[3 * slot: 3 * slot + 3]] == c).all())
    assert des.logdet[1] > des.logdet[0]
    assert all(ld == max(tried.values()) for ld, tried in zip(des.logdet, des.considered))
    sub = des.data(cand)
    assert sub.n_locations == 2 and sub.loc.tolist() == [0, 0, 0, 1, 1, 1]


def _ds(M, kd):
    """log det of the Schur complement of the nuisance block, computed directly."""
    A, B, C = M[:kd, :kd], M[:kd, kd:], M[kd:, kd:]
    return float(torch.logdet(A - B @ torch.linalg.solve(C, B.T)))


def test_greedy_gain_is_the_ds_increase():
    """Each greedy pick is the candidate whose two rows raise log det of the Schur complement most,
    checked against the direct computation for every candidate."""
    g = torch.Generator().manual_seed(0)
    n, kd = 9, 5
    A = torch.randn(n, 3 * n, generator=g, **F64)
    M = A @ A.T / n
    U = torch.randn(12, n, 2, generator=g, **F64)
    M1, picks = _greedy(M.clone(), U, 2, kd)
    gains = [_ds(M + U[i] @ U[i].T, kd) - _ds(M, kd) for i in range(12)]
    assert picks[0] == max(range(12), key=lambda i: gains[i])
    M_after = M + U[picks[0]] @ U[picks[0]].T
    gains2 = [_ds(M_after + U[i] @ U[i].T, kd) if i != picks[0] else -1e300 for i in range(12)]
    assert picks[1] == max(range(12), key=lambda i: gains2[i])
    torch.testing.assert_close(M1, M_after + U[picks[1]] @ U[picks[1]].T)


def test_predicted_max_error_scales_with_the_noise(setup):
    s = setup
    robot, laser, cand, free = s["robot"], s["laser"], s["cand"], s["free"]
    M, kd = information(robot, laser, cand, s["R"], s["C"], free, q_noise=10e-6, uv_noise=1e-6)
    q = cand.q[:10]
    a = predicted_max_error(robot, M, kd, free, q, draws=50, generator=torch.Generator().manual_seed(1))
    b = predicted_max_error(robot, 4 * M, kd, free, q, draws=50, generator=torch.Generator().manual_seed(1))
    assert a.shape == (50,) and bool((a > 0).all())
    torch.testing.assert_close(b, a / 2, atol=0, rtol=1e-9)  # 4x the information: half the scatter
