"""Experiment design and beam weights for the PSD calibration (seed 003).

With a 1 µm PSD, the joint encoders set the error budget: 10 µrad of encoder noise moves a spot
by 10-16 µm through the arm and the laser's lever (:func:`spot_covariance`), so the identified
errors scatter with the encoder noise and the worst fresh pose shows it first
(:func:`torchcal.pipelines.psd.spot_covariance`). Two remedies:

* **beam weights**: each beam's spot residual is whitened by its expected spot covariance
  ``Σ = σ_q² G Gᵀ + σ_uv² I`` (``G = ∂(u, v)/∂q``, from the model, never the truth), i.e.
  generalised least squares (:func:`torchcal.pipelines.psd.spot_covariance`,
  ``calibrate_psd(..., noise=...)``);
* **design**: choose the PSD locations and the ``k`` aims per location from simulated candidates
  (nominal model) by a greedy D-optimal criterion (:func:`select_design`).

The criterion is Ds-optimality: ``log det`` of the information matrix of the robot errors with
the PSD poses (6 unknowns per location, nuisance) profiled out, i.e. of the Schur complement
``S = M_θθ - M_θψ M_ψψ⁻¹ M_ψθ`` of the whitened spot model's information ``M = Jᵀ Σ⁻¹ J``. A
beam adds a rank-2 term ``U Uᵀ`` (``U = (W J_b)ᵀ``, two rows); with ``A = M⁻¹ U``,
``C = (I + Uᵀ A)⁻¹`` and ``V`` the robot-error rows of ``A``, Woodbury gives
``log det S' - log det S = -log det(I - C Vᵀ S V)``, evaluated for every candidate at once.

Scope: this greedy selection is written for the PSD residual only. It should move to the
general pose planner (the D-optimal pose-selection issue) once that exists.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Sequence

import torch
from torch import Tensor

from torchcal.kinematics.transforms import skew
from torchcal.measure.laser import Laser
from torchcal.measure.psd import PSDData, spot_covariance, spot_whitening
from torchcal.options import Options
from torchcal.params import ParamSet
from torchcal.problems.psd import SpotResidual

__all__ = ["PSDDesign", "DesignOptions", "whitened_rows", "information", "predicted_max_error", "select_design"]


@dataclass
class PSDDesign:
    """Outcome of :func:`select_design`.

    Attributes:
        locations: chosen candidate locations, in the order chosen (slot ``s`` is ``locations[s]``).
        rows: ``(m k,)`` indices into the candidate data, slot-major (``k`` per slot).
        logdet: Ds criterion ``log det S`` after each slot (units of the free parameters).
        considered: per slot, the criterion reached by every candidate location tried.
    """

    locations: list[int]
    rows: Tensor
    logdet: list[float] = field(default_factory=list)
    considered: list[dict] = field(default_factory=list)

    def data(self, cand: PSDData) -> PSDData:
        """The chosen samples of ``cand``, locations renumbered ``0 .. m-1`` in slot order."""
        q, uv = cand.q[self.rows], cand.uv[self.rows]
        remap = {c: s for s, c in enumerate(self.locations)}
        loc = torch.tensor([remap[int(c)] for c in cand.loc[self.rows].tolist()], dtype=torch.long,
                           device=cand.q.device)
        return PSDData(q, uv, loc, len(self.locations))


def _greedy(M: Tensor, U: Tensor, k: int, kd: int) -> tuple[Tensor, list[int]]:
    """Add ``k`` of the candidates ``U (n_c, n, 2)`` to the information ``M (n, n)``, each time the
    one with the largest Ds gain (module docstring). Returns the new ``M`` and the picks."""
    eye = torch.eye(2, dtype=M.dtype, device=M.device)
    avail = torch.ones(U.shape[0], dtype=torch.bool, device=M.device)
    Ut = U.transpose(1, 2)
    picks = []
    for _ in range(k):
        Mi = torch.linalg.inv(M)
        S = torch.linalg.inv(Mi[:kd, :kd])
        A = Mi @ U  # (n_c, n, 2)
        C = torch.linalg.inv(eye + Ut @ A)
        V = A[:, :kd]
        gain = -torch.logdet(eye - C @ (V.transpose(1, 2) @ S @ V))
        gain = torch.where(avail & torch.isfinite(gain), gain, torch.full_like(gain, -torch.inf))
        b = int(torch.argmax(gain))
        picks.append(b)
        avail[b] = False
        M = M + U[b] @ Ut[b]
    return M, picks


def _ds_logdet(M: Tensor, kd: int) -> float:
    return -float(torch.logdet(torch.linalg.inv(M)[:kd, :kd]))


def whitened_rows(robot, laser: Laser, data: PSDData, psd_R: Tensor, psd_c: Tensor, free: ParamSet, *,
                  q_noise: float, uv_noise: float, params: Tensor | None = None) -> tuple[Tensor, int]:
    """``(N, 2, kd + 6 m)`` rows of the spot model's Jacobian (free robot errors, then 6 pose
    unknowns per location, :class:`~torchcal.pipelines.psd.SpotResidual`), each beam whitened by its expected
    spot covariance, at the model ``params`` (default ``free.values``); and ``kd``."""
    params = free.values if params is None else params
    blk = SpotResidual(robot, laser, data, free, psd_R, psd_c)
    J = blk.jacobian(blk.start()).reshape(data.q.shape[0], 2, -1)
    cov = spot_covariance(robot, laser, data.q, data.loc, psd_R, psd_c, params, q_noise=q_noise, uv_noise=uv_noise)
    return spot_whitening(cov) @ J, blk.kr


@dataclass(frozen=True)
class DesignOptions(Options):
    """The noise model and settings of the PSD design (:func:`information`, :func:`select_design`).

    Attributes:
        q_noise, uv_noise: encoder (rad) and PSD (m) noise std, for the beam weights (required).
        distances: slot pairs whose centre distance will be measured, ``distance_noise`` m std.
        params: ``(K,)`` the model the rows are computed at (default ``free.values``: the
            nominal model, never the truth).
        ridge: (:func:`select_design`) ``ridge ×`` the mean diagonal of the candidates'
            information is added to ``M`` so that it is invertible before the data identify
            everything.
    """

    q_noise: float | None = None
    uv_noise: float | None = None
    distances: Sequence[tuple[int, int]] = ((0, 1),)
    distance_noise: float = 2e-6
    params: Tensor | None = None
    ridge: float = 1e-9

    def checked(self) -> "DesignOptions":
        if self.q_noise is None or self.uv_noise is None:
            raise TypeError("give q_noise (encoder noise std, rad) and uv_noise (PSD noise std, m): the beam weights "
                            "need both")
        return self


def information(robot, laser: Laser, data: PSDData, psd_R: Tensor, psd_c: Tensor, free: ParamSet, *,
                settings: DesignOptions | None = None, **kw) -> tuple[Tensor, int]:
    """Information matrix ``Jᵀ Σ⁻¹ J`` ``(n, n)`` of the whitened spot model for ``data`` (its
    locations ``0 .. m-1`` at ``psd_R``, ``psd_c``) plus the known centre distances; and ``kd``,
    the number of robot errors (the first ``kd`` unknowns). ``settings``, ``kw``: a
    :class:`DesignOptions` and/or its fields as keywords (``q_noise`` and ``uv_noise`` required)."""
    o = DesignOptions.build(settings, **kw).checked()
    WJ, kd = whitened_rows(robot, laser, data, psd_R, psd_c, free, q_noise=o.q_noise, uv_noise=o.uv_noise,
                           params=o.params)
    n = WJ.shape[-1]
    m = (n - kd) // 6
    M = torch.einsum("bri,brj->ij", WJ, WJ)
    for s in range(m):
        M = M + _distance_info(list(range(m)), psd_c, o.distances, s, kd, n, o.distance_noise)
    return M, kd


def predicted_max_error(robot, M: Tensor, kd: int, free: ParamSet, q_fresh: Tensor, *, draws: int,
                        generator: torch.Generator) -> Tensor:
    """``(draws,)`` worst position error (m) over the poses ``q_fresh (n, dof)`` for robot-error
    estimates scattered as ``N(0, [M⁻¹]_θθ)`` (the linearised least-squares covariance), after the
    best rigid fit, as the fresh-pose figures are scored: the spread the noise alone leaves."""
    C = torch.linalg.inv(M)[:kd, :kd]
    C = 0.5 * (C + C.T)
    zero = torch.zeros(robot.n_params, dtype=M.dtype, device=M.device)
    Jf = robot.param_jacobian(q_fresh, zero)[:, 0][..., free.free_index].reshape(-1, kd)  # (3 n, kd)
    p = robot.positions(q_fresh, zero)[:, 0]
    B = torch.zeros(p.shape[0], 3, 6, dtype=M.dtype, device=M.device)
    B[..., :3] = torch.eye(3, dtype=M.dtype, device=M.device)
    B[..., 3:] = -skew(p)  # a small rigid motion (t, ω) moves p by t + ω × p
    B = B.reshape(-1, 6)
    Q, _ = torch.linalg.qr(B)
    th = torch.randn(draws, kd, generator=generator, dtype=M.dtype).to(M.device) @ torch.linalg.cholesky(C).T
    e = th @ Jf.T
    e = e - (e @ Q) @ Q.T  # what the rigid fit cannot absorb (first order)
    return e.reshape(draws, -1, 3).norm(dim=-1).amax(1)


def select_design(robot, laser: Laser, cand: PSDData, psd_R: Tensor, psd_c: Tensor, free: ParamSet, *, m: int,
                  k: int, settings: DesignOptions | None = None, **kw) -> PSDDesign:
    """Greedy Ds-optimal choice of ``m`` PSD locations and ``k`` aims per location.

    Args:
        cand: candidate aims, simulated with the model at ``params`` (default ``free.values``;
            the nominal model, never the truth); ``cand.loc`` indexes the candidate locations.
        psd_R, psd_c: ``(L, 3, 3)``, ``(L, 3)`` (m) the candidate PSD poses.
        free: the robot errors to identify (its free flags).
        m, k: locations to choose and aims per location.
        settings, kw: a :class:`DesignOptions` and/or its fields as keywords (``q_noise`` and
            ``uv_noise`` required; ``distances``, ``distance_noise``, ``params``, ``ridge``).

    Slots are filled in turn: for each remaining candidate location the ``k`` best aims are
    chosen greedily, and the location whose aims reach the largest criterion takes the slot.
    """
    o = DesignOptions.build(settings, **kw).checked()
    WJ, kd = whitened_rows(robot, laser, cand, psd_R, psd_c, free, q_noise=o.q_noise, uv_noise=o.uv_noise,
                           params=o.params)
    n = kd + 6 * m
    M = torch.eye(n, dtype=WJ.dtype, device=WJ.device) * o.ridge * float((WJ * WJ).sum((0, 1)).mean())
    design = PSDDesign(locations=[], rows=torch.empty(0, dtype=torch.long, device=WJ.device))
    rows = []
    for s in range(m):
        best = None
        tried = {}
        for c in range(psd_R.shape[0]):
            idx = torch.nonzero(cand.loc == c).flatten()
            if c in design.locations or idx.numel() < k:
                continue
            U = torch.zeros(idx.numel(), n, 2, dtype=WJ.dtype, device=WJ.device)
            U[:, :kd] = WJ[idx, :, :kd].transpose(1, 2)
            U[:, kd + 6 * s: kd + 6 * s + 6] = WJ[idx, :, kd + 6 * c: kd + 6 * c + 6].transpose(1, 2)
            Ms = M + _distance_info(design.locations + [c], psd_c, o.distances, s, kd, n, o.distance_noise)
            Mc, picks = _greedy(Ms, U, k, kd)
            tried[c] = _ds_logdet(Mc, kd)
            if best is None or tried[c] > best[0]:
                best = (tried[c], c, Mc, idx[picks])
        if best is None:
            raise ValueError(f"no candidate location left with {k} aims for slot {s}")
        ld, c, M, r = best
        design.locations.append(c)
        design.logdet.append(ld)
        design.considered.append(tried)
        rows.append(r)
    design.rows = torch.cat(rows)
    return design


def _distance_info(locs: list[int], psd_c: Tensor, pairs, s: int, kd: int, n: int, sigma: float) -> Tensor:
    """Information of the known centre distances that slot ``s`` completes (slots ``locs``)."""
    out = torch.zeros(n, n, dtype=psd_c.dtype, device=psd_c.device)
    for a, b in pairs:
        if max(a, b) != s:
            continue
        u = psd_c[locs[a]] - psd_c[locs[b]]
        u = u / u.norm()
        row = torch.zeros(n, dtype=psd_c.dtype, device=psd_c.device)
        row[kd + 6 * a + 3: kd + 6 * a + 6] = u / sigma
        row[kd + 6 * b + 3: kd + 6 * b + 6] = -u / sigma
        out += row[:, None] * row[None]
    return out
