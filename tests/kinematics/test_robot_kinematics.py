"""Kinematics of :class:`torchcal.Robot`: analytic Jacobians against autograd and finite
differences, population batching, shapes, differentiability, float32, and both DH conventions
against an independent numpy product.

Relative errors are ``max|A - B| / max|B|``. Pose rows 3..5 of the parameter Jacobian are the
angular velocity ω with ``dR = skew(ω) R``; they are checked through ``skew(ω) ≈ dR Rᵀ``.
"""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from torch.autograd.functional import jacobian

from torchcal import Robot
from torchcal.kinematics.transforms import skew

H = 1e-6  # central-difference step (m and rad)


def rel(a: torch.Tensor, b: torch.Tensor) -> float:
    return float((a - b).abs().max() / b.abs().max())


# ----------------------------------------------------------------------------- robots
ROBOTS = ["kr5", "modified_arm", "scara", "tree_robot"]


@pytest.fixture(params=ROBOTS)
def robot(request) -> Robot:
    return request.getfixturevalue(request.param)


def _fd_params(robot: Robot, q: torch.Tensor, p: torch.Tensor):
    """Central differences of fk_rt w.r.t. every parameter: dR (N,M,3,3,K), dt (N,M,3,K)."""
    dR, dt = [], []
    for k in range(robot.n_params):
        e = torch.zeros_like(p)
        e[k] = H
        Rp, tp = robot.fk_rt(q, p + e)
        Rm, tm = robot.fk_rt(q, p - e)
        dR.append((Rp - Rm) / (2 * H))
        dt.append((tp - tm) / (2 * H))
    return torch.stack(dR, -1), torch.stack(dt, -1)


def _omega_matrix(dR: torch.Tensor, R: torch.Tensor) -> torch.Tensor:
    """dR Rᵀ for derivative stacks dR (N,M,3,3,K), R (N,M,3,3) -> (N,M,K,3,3)."""
    return dR.movedim(-1, 2) @ R.transpose(-1, -2)[:, :, None]


def test_param_jacobian_matches_autograd_and_fd(robot, make_params, make_q):
    p = make_params(robot, seed=11)
    q = make_q(robot, 6, seed=12)
    assert float(p[3:6].norm()) == pytest.approx(2.5)
    J_pos = robot.param_jacobian(q, p, kind="position")
    J_pose = robot.param_jacobian(q, p, kind="pose")
    N, M, K = q.shape[0], len(robot.marker_names), robot.n_params
    assert J_pos.shape == (N, M, 3, K) and J_pose.shape == (N, M, 6, K)
    # the pose Jacobian's position rows are the position Jacobian, computed in a wider batch of
    # products: equal to the rounding of those products
    torch.testing.assert_close(J_pose[..., :3, :], J_pos, rtol=0, atol=1e-14 * float(J_pos.abs().max()))

    R, _ = robot.fk_rt(q, p)
    dR_fd, dt_fd = _fd_params(robot, q, p)
    # every parameter moves something (no all-zero FD column), so the checks below have teeth
    assert bool((dt_fd.abs().amax((0, 1, 2)) + dR_fd.abs().amax((0, 1, 2, 3)) > 1e-8).all())
    assert rel(J_pos, dt_fd) < 1e-6
    W_fd = _omega_matrix(dR_fd, R)
    W = skew(J_pose[..., 3:, :].movedim(-1, 2))  # (N, M, K, 3, 3)
    assert rel(W, W_fd) < 1e-6

    # autograd through fk_rt (both the small-batch 4x4 path and the column path)
    for qq in (q, make_q(robot, 20, seed=13)):
        Ja_t = jacobian(lambda x: robot.fk_rt(qq, x)[1], p)
        Ja_R = jacobian(lambda x: robot.fk_rt(qq, x)[0], p)
        Jq = robot.param_jacobian(qq, p, kind="pose")
        Rq, _ = robot.fk_rt(qq, p)
        assert rel(Jq[..., :3, :], Ja_t) < 1e-10
        assert rel(skew(Jq[..., 3:, :].movedim(-1, 2)), _omega_matrix(Ja_R, Rq)) < 1e-10


def test_param_jacobian_population_matches_members(tree_robot, make_params, make_q):
    P = torch.stack([make_params(tree_robot, seed=s) for s in range(3)])
    q = make_q(tree_robot, 4, seed=1)
    J = tree_robot.param_jacobian(q, P, kind="pose")
    assert J.shape == (3, 4, 4, 6, tree_robot.n_params)
    for i in range(3):
        torch.testing.assert_close(J[i], tree_robot.param_jacobian(q, P[i], kind="pose"), atol=1e-13, rtol=0)


def test_param_jacobian_kind_is_checked(kr5):
    with pytest.raises(ValueError, match="kind must be 'position' or 'pose'"):
        kr5.param_jacobian(torch.zeros(6), kind="orientation")


def test_joint_jacobian(robot, make_params, make_q):
    p = make_params(robot, seed=21)
    q = make_q(robot, 5, seed=22)
    Jq = robot.joint_jacobian(q, p)
    N, M = q.shape[0], len(robot.marker_names)
    assert Jq.shape == (N, M, 6, robot.dof)
    # position rows: autograd w.r.t. q, one configuration at a time
    for n in range(N):
        Ja = jacobian(lambda x: robot.fk_rt(x, p)[1], q[n])  # (M, 3, dof)
        assert rel(Jq[n, :, :3], Ja) < 1e-10
    # angular rows: central differences of R
    R, _ = robot.fk_rt(q, p)
    dR = []
    for j in range(robot.dof):
        e = torch.zeros(robot.dof, dtype=q.dtype)
        e[j] = H
        dR.append((robot.fk_rt(q + e, p)[0] - robot.fk_rt(q - e, p)[0]) / (2 * H))
    W_fd = _omega_matrix(torch.stack(dR, -1), R)
    W = skew(Jq[..., 3:, :].movedim(-1, 2))
    assert rel(W, W_fd) < 1e-6
    # the angular column of a prismatic joint is zero, of a revolute one a unit vector
    for j, u in enumerate(robot.joint_units):
        norms = Jq[..., 3:, j].norm(dim=-1)
        if u == "m":
            assert float(norms.max()) == 0.0
        else:
            assert float(norms.max()) > 1 - 1e-12


def test_joint_columns_from_the_parameter_pass(robot, make_params, make_q):
    """``param_jacobian(..., joints=True)`` gives the joint Jacobian of the same pass: for one vector,
    and for a population paired with its own joint values, per member."""
    p = make_params(robot, seed=23)
    q = make_q(robot, 4, seed=24)
    for kind, rows in (("position", 3), ("pose", 6)):
        J, Jq = robot.param_jacobian(q, p, kind=kind, joints=True)
        torch.testing.assert_close(J, robot.param_jacobian(q, p, kind=kind), rtol=0, atol=0)
        torch.testing.assert_close(Jq, robot.joint_jacobian(q, p)[:, :, :rows], rtol=1e-12, atol=1e-14)
    P = torch.stack([p, make_params(robot, seed=25)])
    Q = torch.stack([q, make_q(robot, 4, seed=26)])
    _, JqP, pos = robot.param_jacobian(Q, P, kind="pose", joints=True, return_positions=True)
    for b in range(2):
        torch.testing.assert_close(JqP[b], robot.joint_jacobian(Q[b], P[b]), rtol=1e-12, atol=1e-14)
        torch.testing.assert_close(pos[b], robot.positions(Q[b], P[b]), rtol=1e-12, atol=1e-14)


def test_a_column_subset_is_the_full_jacobians_columns(robot, make_params, make_q):
    """``param_jacobian(..., columns=c)`` computes c's columns alone, in c's order: the full Jacobian's
    columns, with the joint Jacobian of the same pass; for one vector and for a paired population."""
    p = make_params(robot, seed=31)
    q = make_q(robot, 5, seed=32)
    K, names = robot.n_params, robot.param_names
    g = torch.Generator().manual_seed(33)
    subsets = [torch.randperm(K, generator=g)[: max(1, K // 3)], torch.arange(K - 1, -1, -1),
               torch.tensor([i for i, n in enumerate(names) if n.startswith("base.") or n.split(".")[0] in
                             robot.marker_names])]
    offsets = robot._slot_gather[robot._slices["offset"]]  # the parameters that move joint zeros (URDF robots)
    if bool((offsets < K).any()):
        subsets.append(offsets[offsets < K])
    P = torch.stack([p, make_params(robot, seed=34)])
    Q = torch.stack([q, make_q(robot, 5, seed=35)])
    for kind in ("position", "pose"):
        J, Jq = robot.param_jacobian(q, p, kind=kind, joints=True)
        JP, JqP = robot.param_jacobian(Q, P, kind=kind, joints=True)
        scale = float(J.abs().max())
        for c in subsets:
            assert c.numel()
            sub, sub_q = robot.param_jacobian(q, p, kind=kind, joints=True, columns=c)
            torch.testing.assert_close(sub, J[..., c], rtol=0, atol=1e-14 * scale)
            torch.testing.assert_close(sub_q, Jq, rtol=0, atol=1e-14 * scale)
            torch.testing.assert_close(robot.param_jacobian(q, p, kind=kind, columns=c), J[..., c], rtol=0,
                                       atol=1e-14 * scale)
            subP, subP_q = robot.param_jacobian(Q, P, kind=kind, joints=True, columns=c)
            torch.testing.assert_close(subP, JP[..., c], rtol=0, atol=1e-14 * scale)
            torch.testing.assert_close(subP_q, JqP, rtol=0, atol=1e-14 * scale)
        # no parameter column at all (a fit of effects alone): the joint Jacobian still comes
        none, none_q = robot.param_jacobian(q, p, kind=kind, joints=True, columns=())
        assert none.shape == J.shape[:-1] + (0,)
        torch.testing.assert_close(none_q, Jq, rtol=0, atol=1e-14 * scale)


def test_joint_jacobian_mimic_column(tree_robot, make_q):
    """finger_b mimics finger_a with multiplier -1.5: its angular velocity per unit of finger_a is
    1.5 times the (unit) joint axis."""
    q = make_q(tree_robot, 3, seed=5)
    J = tree_robot.joint_jacobian(q)
    ja = tree_robot.joint_names.index("finger_a_joint")
    mb = tree_robot.marker_names.index("finger_b")
    torch.testing.assert_close(J[:, mb, 3:, ja].norm(dim=-1), torch.full((3,), 1.5, dtype=torch.float64))
    with pytest.raises(ValueError, match="population"):
        tree_robot.joint_jacobian(q, torch.zeros(2, tree_robot.n_params))


# ----------------------------------------------------------------------------- batching
@pytest.mark.parametrize("N,P", [(1, 3), (2, 7), (50, 7), (10, 2)])
def test_population_equals_loop(tree_robot, make_params, make_q, N, P):
    """(P, K) populations equal a loop over members; N*P <= 16 uses 4x4 products, larger batches
    the column form (and (10, 2) batched vs. a loop of (10,) crosses the two)."""
    pop = torch.stack([make_params(tree_robot, seed=100 + i) for i in range(P)])
    q = make_q(tree_robot, N, seed=N)
    T = tree_robot.fk(q, pop)
    assert T.shape == (P, N, 4, 4, 4)
    loop = torch.stack([tree_robot.fk(q, pop[i]) for i in range(P)])
    torch.testing.assert_close(T, loop, atol=1e-14, rtol=0)
    R, t = tree_robot.fk_rt(q, pop)
    torch.testing.assert_close(R, T[..., :3, :3], atol=1e-14, rtol=0)
    torch.testing.assert_close(t, T[..., :3, 3], atol=1e-14, rtol=0)
    torch.testing.assert_close(tree_robot.positions(q, pop), t, atol=1e-13, rtol=0)
    # members really differ, so equality above is not vacuous
    if P > 1:
        assert float((T[0] - T[-1]).abs().max()) > 1e-3


def test_population_kr5_both_paths(kr5, make_params, make_q):
    pop = torch.stack([make_params(kr5, seed=i) for i in range(7)])
    for N in (1, 2, 50):
        q = make_q(kr5, N, seed=N)
        T = kr5.fk(q, pop)
        loop = torch.stack([kr5.fk(q, pop[i]) for i in range(7)])
        torch.testing.assert_close(T, loop, atol=1e-14, rtol=0)
        torch.testing.assert_close(kr5.positions(q, pop), kr5.fk_rt(q, pop)[1], atol=1e-13, rtol=0)


def test_unbatched_shapes(tree_robot, make_params, make_q):
    r = tree_robot
    M, K = len(r.marker_names), r.n_params
    q = make_q(r, 3, seed=0)
    p = make_params(r, seed=0)
    pop = torch.stack([p, 0.5 * p])
    assert r.fk(q[0]).shape == (M, 4, 4)
    assert r.fk(q).shape == (3, M, 4, 4)
    assert r.fk(q[0], p).shape == (M, 4, 4)
    assert r.fk(q, p).shape == (3, M, 4, 4)
    assert r.fk(q[0], pop).shape == (2, M, 4, 4)
    assert r.fk(q, pop).shape == (2, 3, M, 4, 4)
    R, t = r.fk_rt(q[0], p)
    assert R.shape == (M, 3, 3) and t.shape == (M, 3)
    assert r.positions(q[0], p).shape == (M, 3)
    assert r.positions(q[0], pop).shape == (2, M, 3)
    assert r.param_jacobian(q[0], p, kind="pose").shape == (M, 6, K)
    assert r.param_jacobian(q[0], pop).shape == (2, M, 3, K)
    assert r.joint_jacobian(q[0], p).shape == (M, 6, r.dof)
    # values agree with the batched call
    torch.testing.assert_close(r.fk(q[1], p), r.fk(q, p)[1], atol=1e-14, rtol=0)
    torch.testing.assert_close(r.fk(q[1], pop), r.fk(q, pop)[:, 1], atol=1e-14, rtol=0)
    # a ParamSet works like its values
    ps = r.params(p)
    torch.testing.assert_close(r.fk(q, ps), r.fk(q, p), atol=0, rtol=0)
    # nominal = zero parameters
    torch.testing.assert_close(r.fk(q), r.fk(q, torch.zeros(K, dtype=torch.float64)), atol=1e-15, rtol=0)


def test_gradients_flow_to_q_and_params(tree_robot, make_params, make_q):
    r = tree_robot
    q = make_q(r, 4, seed=3).requires_grad_(True)
    p = make_params(r, seed=3).requires_grad_(True)
    T = r.fk(q, p)
    T[..., :3, 3].sum().backward()
    assert q.grad is not None and p.grad is not None
    assert bool(torch.isfinite(q.grad).all()) and bool(torch.isfinite(p.grad).all())
    # the gradients are the analytic Jacobians summed over rows and markers
    with torch.no_grad():
        gq = r.joint_jacobian(q.detach(), p.detach())[..., :3, :].sum((1, 2))
        gp = r.param_jacobian(q.detach(), p.detach()).sum((0, 1, 2))
    torch.testing.assert_close(q.grad, gq, atol=1e-12, rtol=0)
    torch.testing.assert_close(p.grad, gp, atol=1e-12, rtol=0)
    assert float(q.grad.abs().max()) > 0.1 and float(p.grad.abs().max()) > 0.1
    # population, column path, positions(): gradients too
    pop = torch.stack([p.detach(), 0.5 * p.detach()]).requires_grad_(True)
    q2 = make_q(r, 20, seed=4).requires_grad_(True)
    (r.positions(q2, pop) ** 2).sum().backward()
    assert bool(torch.isfinite(pop.grad).all()) and float(pop.grad.abs().max()) > 0
    assert bool(torch.isfinite(q2.grad).all()) and float(q2.grad.abs().max()) > 0


@pytest.mark.parametrize("name", ["kr5", "modified_arm"])
def test_float32_robot(dh_tables, make_params, make_q, name):
    rows, conv = dh_tables[name]
    r64 = Robot.from_dh(rows, convention=conv)
    r32 = Robot.from_dh(rows, convention=conv, dtype=torch.float32)
    assert r32.dtype == torch.float32
    q = make_q(r64, 30, seed=7)
    p = make_params(r64, seed=7, base_rot=0.3, base_trans=0.2)
    for qq, pp in ((q, None), (q, p), (q[:2], p), (q, torch.stack([p, -p]))):
        T32 = r32.fk(qq.float(), None if pp is None else pp.float())
        assert T32.dtype == torch.float32
        T64 = r64.fk(qq, pp)
        assert float((T32.double() - T64).abs().max()) < 1e-5
    pos32 = r32.positions(q.float(), p.float())
    assert pos32.dtype == torch.float32
    assert float((pos32.double() - r64.positions(q, p)).abs().max()) < 1e-5
    J32 = r32.param_jacobian(q.float(), p.float(), kind="pose")
    assert J32.dtype == torch.float32
    assert rel(J32.double(), r64.param_jacobian(q, p, kind="pose")) < 1e-5


# ----------------------------------------------------------------------------- DH conventions
def _rz(t):
    c, s = math.cos(t), math.sin(t)
    return np.array([[c, -s, 0, 0], [s, c, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1.0]])


def _rx(t):
    c, s = math.cos(t), math.sin(t)
    return np.array([[1.0, 0, 0, 0], [0, c, -s, 0], [0, s, c, 0], [0, 0, 0, 1]])


def _tz(d):
    T = np.eye(4)
    T[2, 3] = d
    return T


def _tx(a):
    T = np.eye(4)
    T[0, 3] = a
    return T


def numpy_dh(rows: list[dict], convention: str, q: np.ndarray, err: dict) -> np.ndarray:
    """Independent DH product; ``err[i]`` = (Δa, Δd, Δα, Δθ) of row i (0-based). Prismatic rows
    add q to d, revolute rows to θ. Craig (modified) rows list α_{i-1}, a_{i-1} as alpha, a."""
    T = np.eye(4)
    for i, (r, qi) in enumerate(zip(rows, q)):
        da, dd, dal, dth = err[i]
        a, d, al, th = r["a"] + da, r["d"] + dd, r["alpha"] + dal, r.get("theta", 0.0) + dth
        if r.get("type", "revolute") == "prismatic":
            d += qi
        else:
            th += qi
        if convention == "classic":
            A = _rz(th) @ _tz(d) @ _tx(a) @ _rx(al)
        else:
            A = _rx(al) @ _tx(a) @ _rz(th) @ _tz(d)
        T = T @ A
    return T


@pytest.mark.parametrize("name,seed", [("kr5", 1), ("scara", 2), ("modified_arm", 3), ("modified_prismatic", 4)])
def test_dh_against_numpy(dh_tables, make_q, name, seed):
    rows, conv = dh_tables[name]
    robot = Robot.from_dh(rows, convention=conv)
    n = len(rows)
    g = np.random.default_rng(seed)
    err = g.uniform(-0.05, 0.05, size=(n, 4))
    ps = robot.params()
    for i in range(n):
        for k, slot in enumerate(("da", "dd", "dalpha", "dtheta")):
            ps[f"joint_{i + 1}.{slot}"] = float(err[i, k])
    assert float(ps.values.abs().sum()) == pytest.approx(float(np.abs(err).sum()))
    q = make_q(robot, 8, seed=seed)
    T = robot.fk(q, ps)
    T_nom = robot.fk(q)
    for qq, Tn, Tn_nom in zip(q.numpy(), T, T_nom):
        ref = numpy_dh(rows, conv, qq, err)
        np.testing.assert_allclose(Tn[0].numpy(), ref, atol=1e-12, rtol=0)
        np.testing.assert_allclose(Tn_nom[0].numpy(), numpy_dh(rows, conv, qq, np.zeros((n, 4))), atol=1e-12, rtol=0)
    # the errors matter: calibrated and nominal differ by much more than the tolerance
    assert float((T - T_nom).abs().max()) > 1e-3


def test_dh_prismatic_row_parameter_names(scara, dh_tables):
    """A prismatic DH row's zero offset is its Δd and its Δθ a fixed rotation; no separate
    .offset parameter exists."""
    names = scara.param_names
    assert "joint_3.dd" in names and "joint_3.dtheta" in names
    assert not any(n.endswith(".offset") for n in names)
    assert scara.joint_units == ["rad", "rad", "m", "rad"]
    i = names.index("joint_3.dd")
    assert scara.param_units[i] == "m"
    # moving joint_3.dd is the same as moving q_3
    q = torch.tensor([[0.3, -0.4, 0.1, 0.2]], dtype=torch.float64)
    p = torch.zeros(scara.n_params, dtype=torch.float64)
    p[i] = 0.05
    dq = torch.tensor([0.0, 0.0, 0.05, 0.0], dtype=torch.float64)
    torch.testing.assert_close(scara.fk(q, p), scara.fk(q + dq), atol=1e-14, rtol=0)


def test_markers_on_one_link_carried_together_equal_one_at_a_time(make_params, make_q):
    """positions() carries the markers of one link through the chain together: the same points as
    the marker frames of fk_rt (another code path), one vector and a paired population."""
    from torchcal import Robot

    pts = ["a@flange=0.01,0,0.1", "b@flange=-0.02,0.03,0.05", "c@link3=0,0.1,0", "d@flange=0,0,0.2"]
    many = Robot.from_urdf("urdf/kuka_kr5_arc.urdf", markers=pts)
    assert sorted(len(ms) for ms in many._mk_groups.values()) == [1, 3]
    p = make_params(many, seed=31)
    q = make_q(many, 6, seed=32)
    torch.testing.assert_close(many.positions(q, p), many.fk_rt(q, p)[1], rtol=0, atol=1e-14)
    P = torch.stack([p, make_params(many, seed=33)])
    Q = torch.stack([q, make_q(many, 6, seed=34)])
    got = many.positions(Q, P)
    for b in range(2):
        torch.testing.assert_close(got[b], many.fk_rt(Q[b], P[b])[1], rtol=0, atol=1e-14)


def test_points_moved_per_row_are_the_marker_parameters_moved_per_row(robot, make_params, make_q):
    """``points`` moves each row's marker points exactly as the markers' own ``dx/dy/dz``
    parameters moved on that row would (per-row parameter vectors, an independent path through the
    kinematics); ``param_jacobian(points=)`` is the derivative of those moved points by every
    parameter (central differences)."""
    p = make_params(robot, seed=31)
    q = make_q(robot, 5, seed=32)
    M = len(robot.marker_names)
    pts = torch.randn(5, M, 3, generator=torch.Generator().manual_seed(33), dtype=torch.float64) * 0.05
    idx = torch.tensor([[robot.param_names.index(f"{m}.{a}") for a in ("dx", "dy", "dz")] for m in robot.marker_names])
    per_row = p.repeat(5, 1)
    per_row[:, idx.flatten()] += pts.reshape(5, -1)
    want = robot.positions(q[:, None], per_row)[:, 0]  # each row its own parameter vector
    torch.testing.assert_close(robot.positions(q, p, points=pts), want, rtol=0, atol=1e-12)
    R, t = robot.fk_rt(q, p, points=pts)
    torch.testing.assert_close(t, want, rtol=0, atol=1e-12)
    torch.testing.assert_close(R, robot.fk_rt(q, p)[0], rtol=0, atol=1e-14)  # points turn no frame
    torch.testing.assert_close(robot.positions(q[None].expand(2, -1, -1), torch.stack([p, p]), points=pts[None]),
                               want[None].expand(2, -1, -1, -1), rtol=0, atol=1e-12)
    J = robot.param_jacobian(q, p, points=pts)
    fd = torch.stack([(robot.positions(q, p + H * e, points=pts) - robot.positions(q, p - H * e, points=pts)) / (2 * H)
                      for e in torch.eye(robot.n_params, dtype=torch.float64)], -1)
    assert rel(J, fd) < 1e-6
    assert rel(J, robot.param_jacobian(q, p)) > 1e-4  # the moved points change the columns
    cols = [0, robot.n_params - 1, 3]
    torch.testing.assert_close(robot.param_jacobian(q, p, points=pts, columns=cols), J[..., cols], rtol=0, atol=1e-13)
