"""Tracker-free calibration with a flange laser and a position-sensitive detector (seed 003, PMPSD).

A laser fixed to a marker frame (the flange) shines on a PSD placed at ``m`` locations; at each
location the robot takes ``k`` poses whose beams land anywhere on the PSD surface, and the PSD
reports the 2-D spot ``(u, v)`` (m) in its own surface frame. Nothing is measured in an
instrument frame: every quantity here lives in the robot base frame, and the PSD poses are
unknown.

Frames and units: a PSD pose is a rotation ``R (3, 3)`` whose columns are the surface axes
``u``, ``v`` and the normal, and its centre ``c (3,)`` (m), both in the robot base frame;
``(u, v) = (Rᵀ (s - c))[:2]`` for a spot ``s`` on the surface. A beam is a point ``p (3,)`` (m,
the laser origin) and a unit direction ``w (3,)``. Joint values are rad.

Two residual blocks, both batched over parameter populations ``(P, k) -> (P, rows)`` (m) with an
analytic Jacobian ``(rows, k)``:

* :class:`PointConstraint`, the seed's *multi-point virtual constraint*: at one location every
  pair of beams gives its intersection or, for skew beams, the midpoint of their common
  perpendicular; the residual is each such point minus the mean of the location's points (3
  rows per pair), so ``Σ rows² = Σ_pairs ‖point − mean‖²`` — the seed's "distance of the points to
  their mean", squared for least squares (a sum of plain distances is not differentiable at the
  solution). The mean moves with the parameters (the seed computes it once at zero errors,
  which leaves a non-zero residual at the true parameters). It needs beams that really meet:
  beams aimed at the PSD centre, or beams made to by :func:`modify_poses`.
* :class:`SpotResidual`: the measured spots used directly; each PSD pose (6 unknowns per
  location) is estimated together with the robot errors, rows = predicted minus measured
  ``(u, v)``.

The seed's *pose modification* (:func:`modify_poses`): with the PSD pose estimated under the
current model (:func:`fit_psd_poses`), rotate each beam about the laser origin so that it would
move its spot by ``-(u, v)`` onto the PSD centre, and replace the recorded joint values by the IK
solution of that virtual beam. Under the true model the virtual beams meet in the centre. Under
the nominal model they do not: the PSD orientation fitted with a model that is off by ~1 mm is
off by tens of mrad, which turns a spot offset of a few mm into ~0.1-1 mm of inconsistency.
:func:`calibrate_psd` repeats the step with the calibrated model (``rounds``); the truth is its
fixed point.

Expected spot errors (:func:`spot_covariance`): encoder noise reaches a spot through the arm and
the laser's lever, ``Σ = σ_q² G Gᵀ + σ_uv² I`` with ``G = ∂(u, v)/∂q``; at 10 µrad it is 10-16 µm
per beam, ten times a 1 µm PSD, and it sets the worst fresh-pose error. ``calibrate_psd(...,
noise=...)`` weights the spot residuals by it; :mod:`torchcal.pipelines.psd_design` chooses the PSD
placements and aims.

Observability (numbers in ``scripts/seed003_pmpsd.py``): a point constraint is blind to rigid
motions of the whole world (the first joint's Δθ and Δd of a DH robot) and to a uniform scale
of all lengths (scaled beams still meet) whenever the last DH row can absorb the scaled laser
offset, as it can for a beam parallel to the flange axis or tilted about flange x with the
offset along flange x. A known distance between two PSD centres (``distances=[(a, b, D)]``)
restores the scale. The direct-spot residual sees the scale weakly through the metric PSD
coordinates (a scale error ``ε`` moves a spot by ``ε ×`` its offset from the centre).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Sequence

import torch
from torch import Tensor

from torchcal.kinematics.ik import solve_ik
from torchcal.kinematics.transforms import so3_exp
from torchcal.measure.laser import Laser, laser_beams, plane_intersection
from torchcal.measure.psd import PSDData, spot_covariance, spot_whitening
from torchcal.optim import Result, get_solver
from torchcal.options import Options
from torchcal.params import ParamSet
from torchcal.problems.psd import PointConstraint, SpotResidual, DISTANCE_WEIGHT

__all__ = ["modify_poses", "calibrate_psd", "PSDOptions", "PSDCalibration", "SEED_LM"]

#: The seed's LM settings for :func:`~torchcal.optim.get_solver` (Δs0 = 0 comes from the start
#: point): μ0 = 0.1 on an identity damping matrix, ν = 2, accept when the gain ratio ρ > 0, else
#: μ ← μν, ν ← 2ν. The seed's formula for shrinking μ did not survive in its text; torchcal's LM
#: uses Nielsen's μ·max(1/3, 1 − (2ρ − 1)³). Its stop test ‖Jᵀr‖ < ε is the scale-free version
#: (largest cosine between r and a column of J below ``gtol``), plus step and decrease tests.
SEED_LM = dict(mu0=0.1, scaling="identity", max_iter=300, gtol=1e-12, xtol=1e-14, ftol=1e-15)

def modify_poses(robot, laser: Laser, data: PSDData, params, psd_R: Tensor, psd_c: Tensor, *,
                 tol: float = 1e-12) -> tuple[Tensor, dict]:
    """The seed's pose modification: joint values of virtual beams through the PSD centres.

    For each sample, with the model at ``params``: the beam ``(p, w)`` meets the estimated PSD
    surface at ``s``; the spot reading says the centre lies at ``h = s − R_j [u, v, 0]``. The
    laser frame is turned about ``p`` by the smallest rotation taking ``w`` to ``(h − p)/|h − p|``
    and IK (started at the recorded joints, so the nearest solution) gives the joints ``q′``.

    Returns ``q′ (N, dof)`` (rad) and ``info`` with ``angle`` ``(N,)`` (rad, the beam corrections),
    ``ik_converged`` ``(N,)`` bool and ``ik_pos_err`` ``(N,)`` (m).
    """
    params = torch.as_tensor(params.values if isinstance(params, ParamSet) else params,
                             dtype=robot.dtype, device=robot.device)
    L = data.loc
    R, t = robot.fk_rt(data.q, params, check=False)
    i = laser.index(robot)
    R, t = R[:, i], t[:, i]
    p, w = laser_beams(robot, laser, data.q, params)
    s, _ = plane_intersection(p, w, psd_c[L], psd_R[L])
    h = s - (psd_R[L][..., :2] @ data.uv[..., None])[..., 0]
    w2 = (h - p) / (h - p).norm(dim=-1, keepdim=True)
    ax = torch.linalg.cross(w, w2)
    ang = torch.atan2(ax.norm(dim=-1), (w * w2).sum(-1))
    n_ax = ax.norm(dim=-1, keepdim=True)
    rv = torch.where(n_ax > 0, ax / n_ax.clamp(min=1e-300), 0.0) * ang[:, None]  # no turn: no axis
    Q = so3_exp(rv)
    T = torch.zeros(p.shape[0], 4, 4, dtype=p.dtype, device=p.device)
    T[:, :3, :3] = Q @ R
    T[:, :3, 3] = p + (Q @ (t - p)[..., None])[..., 0]
    T[:, 3, 3] = 1.0
    ik = solve_ik(robot, params, T, q0=data.q, marker=robot.marker_names[i], tol_pos_m=tol, tol_rot=tol,
                  restarts=0, limits=False)
    return ik.q, {"angle": ang, "ik_converged": ik.converged, "ik_pos_err": ik.pos_err}


# ------------------------------------------------------------------------------- calibration
@dataclass
class PSDCalibration:
    """Outcome of :func:`calibrate_psd`.

    Attributes:
        params: ``(K,)`` identified robot errors (fixed entries as given).
        psd_R, psd_c: ``(m, 3, 3)``, ``(m, 3)`` PSD poses (m): estimated with the errors
            (``"spots"``), used by the last pose modification (``"pm"``), or fitted to the final
            model (``"raw"``).
        method: ``"pm"``, ``"raw"`` or ``"spots"``.
        results: the LM :class:`~torchcal.optim.Result` of every round.
        q_used: joints the last point constraint used (modified ones for ``"pm"``).
        rounds: per round ``{"params", "rms_m"}`` (``rms_m``: RMS residual row at the end, m),
            for the point constraint ``"max_change"`` (largest parameter change of the round);
            ``"psd_rms_m"`` (spot residual per location of the PSD-pose fit at the round's start
            model) for ``"pm"`` and ``"spots"``; for the point constraint also ``"n_pairs"``, and for
            ``"pm"`` ``"correction_max_rad"`` (largest beam correction) and ``"ik_all_converged"``.
    """

    params: Tensor
    psd_R: Tensor
    psd_c: Tensor
    method: str
    results: list[Result] = field(default_factory=list)
    q_used: Tensor | None = None
    rounds: list[dict] = field(default_factory=list)


@dataclass(frozen=True)
class PSDOptions(Options):
    """How :func:`calibrate_psd` identifies.

    Attributes:
        method: ``"pm"`` the seed: PSD poses from the spots (model at the current estimate),
            pose modification, then LM on the point constraint, ``rounds`` times; ``"raw"`` the
            point constraint on the recorded beams (right only when they hit the centre);
            ``"spots"`` LM on :class:`SpotResidual` (robot errors and PSD poses together).
        rounds: pose-modification rounds at most (``"pm"``); round_tol: stop earlier once no
            free parameter moved by more than this in a round (m or rad; 0 runs all rounds).
        distances: known distances between PSD centres ``(a, b, D in m)``; ``distance_weight``:
            their weight (m of residual per m of distance error).
        min_angle_deg: beam pairs of the point constraint at least this far apart (deg).
        lm: LM options on top of :data:`SEED_LM` (the seed's μ0 = 0.1, ν = 2, identity damping).
        noise: ``(q_noise rad, uv_noise m, distance_noise m)`` stds; with ``"spots"``, weight each
            beam by its expected spot covariance (encoder noise through the arm, at the start
            model and PSD poses, plus PSD noise; :func:`spot_covariance`) and each known
            distance by one over its std: generalised least squares.
    """

    method: str = "pm"
    rounds: int = 1
    round_tol: float = 0.0
    distances: Sequence[tuple[int, int, float]] = ()
    distance_weight: float = DISTANCE_WEIGHT
    min_angle_deg: float = 5.0
    lm: dict | None = None
    noise: tuple[float, float, float] | None = None


def calibrate_psd(robot, laser: Laser, data: PSDData, free: ParamSet, *, settings: PSDOptions | None = None,
                  **kw) -> PSDCalibration:
    """Identify robot errors from PSD data.

    Args:
        free: ``robot.params()`` with the unknowns free and everything else at its known value
            (start point = its values, Δs0 = 0 for zeros). Free only identifiable parameters: a
            point constraint cannot fix the gauge (see the module docstring).
        settings, kw: a :class:`PSDOptions` and/or its fields as keywords (``method="spots"``,
            ``rounds=3``, ``distances=…``, ``noise=…``).
    """
    opt = PSDOptions.build(settings, **kw)
    if opt.method not in ("pm", "raw", "spots"):
        raise ValueError(f"method must be 'pm', 'raw' or 'spots', got {opt.method!r}")
    if opt.noise is not None and (opt.method != "spots" or (opt.distances and not opt.noise[2] > 0)):
        raise ValueError("noise weights the spot residuals: it needs method='spots', and a positive distance "
                         "noise std when distances are given")
    if opt.method == "spots":
        return _calibrate_spots(robot, laser, data, free.clone(), opt)
    return _calibrate_points(robot, laser, data, free.clone(), opt)


def _calibrate_spots(robot, laser: Laser, data: PSDData, cur: ParamSet, opt: PSDOptions) -> PSDCalibration:
    """Robot errors and PSD poses together by LM on the spots (``method="spots"``)."""
    out = PSDCalibration(params=cur.values.clone(), psd_R=torch.empty(0), psd_c=torch.empty(0), method=opt.method)
    R0, c0, rms0 = fit_psd_poses(robot, laser, data, cur.values)
    W, distance_weight = None, opt.distance_weight
    if opt.noise is not None:
        cov = spot_covariance(robot, laser, data.q, data.loc, R0, c0, cur.values, q_noise=opt.noise[0],
                              uv_noise=opt.noise[1])
        W, distance_weight = spot_whitening(cov), 1.0 / opt.noise[2]
    blk = SpotResidual(robot, laser, data, cur, R0, c0, distances=opt.distances, distance_weight=distance_weight,
                       whiten=W)
    res = get_solver("lm", **{**SEED_LM, **(opt.lm or {})}).minimize(blk)
    out.params = blk.robot_params(res.x)
    out.psd_R, out.psd_c = blk.psd_poses(res.x)
    out.results.append(res)
    out.rounds.append({"params": out.params.detach().clone(), "psd_rms_m": rms0.tolist(),
                       "rms_m": float(torch.sqrt((res.extra["residuals"] ** 2).mean()))})
    return out


def _calibrate_points(robot, laser: Laser, data: PSDData, cur: ParamSet, opt: PSDOptions) -> PSDCalibration:
    """LM on the point constraint, on the recorded beams (``"raw"``) or on the beams pose
    modification turns through the PSD centres, round after round (``"pm"``)."""
    method = opt.method
    out = PSDCalibration(params=cur.values.clone(), psd_R=torch.empty(0), psd_c=torch.empty(0), method=method)
    opts = {**SEED_LM, **(opt.lm or {})}
    n_rounds = 1 if method == "raw" else int(opt.rounds)
    for _ in range(n_rounds):
        info: dict = {}
        q = data.q
        if method == "pm":
            R, c, rms = fit_psd_poses(robot, laser, data, cur.values)
            q, mi = modify_poses(robot, laser, data, cur.values, R, c)
            out.psd_R, out.psd_c = R, c
            info = {"psd_rms_m": rms.tolist(), "correction_max_rad": float(mi["angle"].max()),
                    "ik_all_converged": bool(mi["ik_converged"].all())}
        blk = PointConstraint(robot, laser, q, data.loc, cur, distances=opt.distances,
                              distance_weight=opt.distance_weight, min_angle_deg=opt.min_angle_deg)
        res = get_solver("lm", **opts).minimize(blk)
        step = float((blk.robot_params(res.x).detach() - cur.values).abs().max())
        cur.values = blk.robot_params(res.x).detach()
        info["rms_m"] = float(torch.sqrt((res.extra["residuals"] ** 2).mean()))
        info["n_pairs"] = int(blk.ia.numel())
        info["params"] = cur.values.clone()
        info["max_change"] = step
        out.results.append(res)
        out.rounds.append(info)
        out.q_used = q
        if step <= opt.round_tol:
            break
    out.params = cur.values.clone()
    if method == "raw":
        out.psd_R, out.psd_c, _ = fit_psd_poses(robot, laser, data, cur.values)
    return out


# ------------------------------------------------------------------------------- PSD poses and pose modification
def _initial_psd_poses(p: Tensor, w: Tensor, uv: Tensor, loc: Tensor, m: int) -> tuple[Tensor, Tensor]:
    """Linear start: ``c + u r1 + v r2 − λ_i w_i = p_i`` for ``c, r1, r2`` and the ``λ_i``, then the
    nearest rotation with ``r1, r2`` as its first columns."""
    Rs, cs = [], []
    for j in range(m):
        i = torch.nonzero(loc == j).flatten()
        n = i.numel()
        if n < 5:
            raise ValueError(f"PSD location {j} has {n} samples; a PSD pose needs at least 5")
        A = p.new_zeros(3 * n, 9 + n)
        eye = torch.eye(3, dtype=p.dtype, device=p.device)
        for s in range(n):
            A[3 * s: 3 * s + 3, 0:3] = eye
            A[3 * s: 3 * s + 3, 3:6] = uv[i[s], 0] * eye
            A[3 * s: 3 * s + 3, 6:9] = uv[i[s], 1] * eye
            A[3 * s: 3 * s + 3, 9 + s] = -w[i[s]]
        sol = torch.linalg.lstsq(A, p[i].reshape(-1, 1)).solution[:, 0]
        c, B = sol[:3], torch.stack([sol[3:6], sol[6:9]], 1)
        U, _, Vh = torch.linalg.svd(B, full_matrices=False)
        Q = U @ Vh  # nearest matrix with orthonormal columns
        r3 = torch.linalg.cross(Q[:, 0], Q[:, 1])
        Rs.append(torch.stack([Q[:, 0], Q[:, 1], r3], 1))
        cs.append(c)
    return torch.stack(Rs), torch.stack(cs)


def fit_psd_poses(robot, laser: Laser, data: PSDData, params, *, R0: Tensor | None = None,
                  c0: Tensor | None = None) -> tuple[Tensor, Tensor, Tensor]:
    """PSD poses that best explain the spots with the robot model held at ``params``.

    A linear start (unless ``R0``, ``c0`` are given) refined by LM on :class:`SpotResidual` with
    no free robot parameter. Returns rotations ``(m, 3, 3)``, centres ``(m, 3)`` (m) and the RMS
    spot residual per location ``(m,)`` (m) — model errors show up there.
    """
    params = torch.as_tensor(params.values if isinstance(params, ParamSet) else params,
                             dtype=robot.dtype, device=robot.device)
    if R0 is None or c0 is None:
        p, w = laser_beams(robot, laser, data.q, params)
        R0, c0 = _initial_psd_poses(p, w, data.uv, data.loc, data.n_locations)
    none = robot.params(params)
    none.free[:] = False
    blk = SpotResidual(robot, laser, data, none, R0, c0)
    res = get_solver("lm", max_iter=100, gtol=1e-13, xtol=1e-15, ftol=1e-16).minimize(blk)
    R, c = blk.psd_poses(res.x)
    r = blk.residuals(res.x[None])[0].reshape(-1, 2)
    ss = torch.zeros(data.n_locations, dtype=r.dtype, device=r.device).index_add_(0, data.loc, (r * r).sum(-1))
    rms = torch.sqrt(ss / torch.bincount(data.loc, minlength=data.n_locations).to(r.dtype))
    return R, c, rms
