"""The 3-RRRU translational parallel robot of seed 004: geometry, closed-form inverse kinematics,
Newton forward kinematics with implicit-function gradients, and the 14 error parameters.

Geometry (reconstructed from the seed's eqs. 2-8; lengths in metres, angles in radians)
-----------------------------------------------------------------------------------------
Base frame at the centre of the static platform, ``z`` perpendicular to it and pointing towards
the moving platform, which hangs *below* the static platform: workspace points have ``z > 0``
(the seed's line runs at ``P_z = +600 mm``). Branch ``i`` (``i = 1, 2, 3``) sits at azimuth
``phi_i = 0°, 120°, 240°`` with radial unit vector ``e_i = (cos phi_i, sin phi_i, 0)`` and
tangential unit vector ``t_i = (-sin phi_i, cos phi_i, 0)``.

Orientation. The seed's eq. 8 fixes the three branches 120° apart, with the tangential offset of
branch 2 equal to ``(√3 P_x + P_y)/2``, but its constants ``a_1, b_1, c_1`` leave the sign of ``e_i``
open; its eq. 2 (``T_1R``) puts ``A_11`` on ``-x``. With that sign the seed's line from
(-800, 0, 600) mm runs through a parallel (type II) singularity at ``x ≈ -780 mm`` in the elbow-out
working mode below (the three ``L_i3`` links become parallel to the ``xz`` plane), so the robot
could not track it; the only modes without it fold every arm in towards the centre, where the
three elbows collide. We therefore put branch 1 on ``+x`` (the other sign of eq. 8): the seed's
lines then lie between branches 2 and 3, at least 0.2 (smallest singular value of ``∂h/∂p``)
from any singularity. ``branch_angles=(π, 5π/3, π/3)`` gives the eq. 2 orientation.

* ``A_i1`` (active revolute) at ``R e_i``; its axis is ``t_i`` (parallel to the static platform,
  perpendicular to the branch's radial plane). Link ``L_i1`` points along
  ``u_i = cos θ_i1 e_i + sin θ_i1 z``, so ``θ_i1 = 0`` is horizontal and outward and positive
  ``θ_i1`` swings the link down, towards the moving platform.
* ``A_i2`` (passive, parallel to ``A_i1``) at the end of ``L_i1``; link ``L_i2`` stays in the radial
  plane ``(e_i, z)`` at angle ``θ_i1 + θ_i2``.
* ``A_i3`` (passive, perpendicular to ``A_i2`` and to ``L_i2``, in the radial plane); link
  ``L_i3`` leaves the radial plane by ``θ_i3 ∈ [-π/2, π/2]`` (the seed's ``cos θ_i3 ≥ 0``).
* A universal joint (``A_i4``, ``A_i5``, zero link lengths as in the seed's Table 1) joins
  ``L_i3`` to the moving platform at ``B_i = p + r e_i``; the platform only translates.

Loop closure (the seed's eq. 8, one scalar per branch). The tangential component of
``B_i - A_i2`` is ``y_i = t_i·p`` and equals ``L_i3 sin θ_i3``; its in-plane part has length
``L_i2 + L_i3 cos θ_i3 = L_i2 + sqrt(L_i3² - y_i²)``. With ``ρ_i = e_i·p + (r - R) -
L_i1 cos θ_i1`` and ``ζ_i = p_z - L_i1 sin θ_i1`` (in-plane coordinates of ``B_i`` seen from
``A_i2``)::

    h_i(p, θ) = sqrt(ρ_i² + ζ_i²) - L_i2 - sqrt(L_i3² - y_i²) = 0          (metres)

Squaring gives the seed's polynomial form ``|B_i - A_i2|² = L_i2² + L_i3² + 2 L_i2
sqrt(L_i3² - y_i²)``; the distance form keeps the residual in metres and well scaled.

Working mode (stated once, used everywhere):

* **IK branch, "elbow out"**: of the two solutions of ``h_i = 0`` for ``θ_i1`` (the seed's ``±``
  in eq. 6) we take ``θ_i1 = atan2(b, a) - arccos(K / sqrt(a² + b²))`` with ``a = e_i·p + r - R``,
  ``b = p_z``, ``K = (a² + b² + L_i1² - c_i²) / (2 L_i1)``, ``c_i = L_i2 + sqrt(L_i3² - y_i²)`` (eq. 6
  in atan2 form; its tan-half-angle quadratic has the same two roots): the elbow ``A_i2`` lies on the outer/upper side of the line ``A_i1 → B_i``, so
  the three elbows stay apart (the other root folds every link in towards the centre, where
  they would collide). Equivalently ``∂h_i/∂θ_i1 < 0``.
* **FK assembly mode**: the moving platform below the static one (``p_z > 0``), every branch
  elbow-out, ``cos θ_i3 ≥ 0`` (built into ``h``). Newton starts from ``p0`` (default the
  workspace centre ``(0, 0, 0.7)`` m, or a caller's warm start such as the commanded target)
  and the solution is checked against this mode, so ``ik(fk(θ)) = θ``.

Error parameters: the 14 of :mod:`torchcal.kinematics.rrru_params`. Batching: ``params`` is ``None`` (nominal), ``(14,)`` or a population ``(P, 14)``; poses
(positions or drive angles) are ``(..., 3)``. A ``(P, 14)`` population with ``(N, 3)`` poses gives
``(P, N, 3)`` (every vector at every pose); ``(P, N, 3)`` poses are paired with the population
(vector ``k`` at poses ``k``), as :meth:`torchcal.Robot.positions` does.
"""
from __future__ import annotations

import math
from typing import Sequence

import torch
from torch import Tensor

from torchcal.kinematics.rrru_params import N_PARAMS, PARAM_NAMES, PARAM_UNITS
from torchcal.kinematics.rrru_workspace import WorkspaceError, check_reach, raise_fk_failure

__all__ = ["RRRU"]

# Relative margin kept from the boundary |y_i| = L_i3 while Newton iterates: sqrt(L3² - y²)
# has an infinite slope there, and an iterate that overshoots it must not produce NaN.
_Y_MARGIN = 1e-9
# Step lengths tried per Newton iteration: 1, 1/2, ..., 1/2^7 (the last is taken even if |h| grows).
_BACKTRACK = 8


def _wrap(a: Tensor) -> Tensor:
    """Angles to ``(-π, π]``."""
    return torch.remainder(a + math.pi, 2 * math.pi) - math.pi


class RRRU:
    """Kinematic model of the 3-RRRU translational parallel robot (module docstring).

    Args:
        L1, L2, L3: nominal link lengths ``L_i1, L_i2, L_i3`` (m), a scalar for all three
            branches or three values. Seed 004: 0.4, 0.1, 0.8.
        R, r: nominal circumradii of the static and moving platforms (m). Seed 004: 0.4, 0.4.
        branch_angles: azimuths ``phi_i`` of the branches (rad); default ``(0, 2π/3, 4π/3)`` (module
            docstring: why not the seed's eq. 2 orientation ``(π, 5π/3, π/3)``).
        p0: default Newton start for :meth:`fk` (m).
        dtype, device: of every tensor the model makes (float64 by default).
    """

    param_names: tuple[str, ...] = PARAM_NAMES
    param_units: tuple[str, ...] = PARAM_UNITS
    n_params: int = N_PARAMS

    def __init__(self, L1: float | Sequence[float] = 0.4, L2: float | Sequence[float] = 0.1,
                 L3: float | Sequence[float] = 0.8, R: float = 0.4, r: float = 0.4,
                 branch_angles: Sequence[float] = (0.0, 2 * math.pi / 3, 4 * math.pi / 3),
                 p0: Sequence[float] = (0.0, 0.0, 0.7), *, dtype: torch.dtype = torch.float64,
                 device: torch.device | str | None = None):
        kw = dict(dtype=dtype, device=device)
        self.dtype, self.device = dtype, torch.device(device) if device is not None else torch.device("cpu")
        self.L = torch.stack([torch.as_tensor(L, **kw).expand(3) for L in (L1, L2, L3)])  # (3 links, 3 branches)
        self.R = float(R)
        self.r = float(r)
        phi = torch.as_tensor(branch_angles, **kw)
        if phi.shape != (3,):
            raise ValueError(f"branch_angles must hold 3 angles, got shape {tuple(phi.shape)}")
        zero = torch.zeros_like(phi)
        self.E = torch.stack([phi.cos(), phi.sin(), zero], -1)    # (3, 3): row i = e_i
        self.T = torch.stack([-phi.sin(), phi.cos(), zero], -1)   # (3, 3): row i = t_i
        self._zhat = torch.zeros_like(self.E)
        self._zhat[:, 2] = 1.0
        self.p0 = torch.as_tensor(p0, **kw)
        if bool((self.L <= 0).any()):
            raise ValueError("link lengths must be positive")

    def __repr__(self) -> str:
        L = self.L[:, 0].tolist()
        return (f"RRRU(L1={L[0]:g}, L2={L[1]:g}, L3={L[2]:g}, R={self.R:g}, r={self.r:g} m, "
                f"{self.n_params} error parameters)")

    # ---------------------------------------------------------------- parameters and shapes
    def zero_params(self) -> Tensor:
        """``(14,)`` zeros: the nominal robot."""
        return torch.zeros(self.n_params, dtype=self.dtype, device=self.device)

    def _params(self, params) -> Tensor:
        if params is None:
            return self.zero_params()
        p = torch.as_tensor(params, dtype=self.dtype, device=self.device)
        if p.ndim not in (1, 2) or p.shape[-1] != self.n_params:
            raise ValueError(f"params must have shape (14,) or (P, 14), got {tuple(p.shape)}; "
                             f"order: {', '.join(self.param_names)}")
        return p

    def _xyz(self, x, what: str) -> Tensor:
        x = torch.as_tensor(x, dtype=self.dtype, device=self.device)
        if x.ndim == 0 or x.shape[-1] != 3:
            raise ValueError(f"{what} must have shape (..., 3), got {tuple(x.shape)}")
        return x

    @staticmethod
    def _lift(params: Tensor, x: Tensor) -> Tensor:
        """Make ``params`` broadcast against poses ``x (..., 3)``: ``(14,)`` as is; ``(P, 14)``
        against ``x (N, 3)`` (or any shared pose batch) -> ``(P, 1.., 14)``, output
        ``(P,) + batch``; against ``x (P, N, 3)`` paired (the same convention as
        :meth:`torchcal.Robot.positions`) -> ``(P, 1, 14)``."""
        if params.ndim == 1:
            return params
        if x.ndim == 3:
            if x.shape[0] not in (1, params.shape[0]):
                raise ValueError(f"poses of shape {tuple(x.shape)} are paired with a population of "
                                 f"{params.shape[0]} parameter vectors: the first axis must be "
                                 f"{params.shape[0]} (or give (N, 3) poses shared by all)")
            return params[:, None, :]
        return params.reshape(params.shape[:1] + (1,) * (x.ndim - 1) + params.shape[1:])

    def geometry(self, params: Tensor) -> dict[str, Tensor]:
        """Actual geometry of a parameter vector / population ``(..., 14)``.

        Returns ``dtheta, L1, L2, L3`` of shape ``(..., 3)`` (one entry per branch; rad, m) and
        ``d = r - R`` of shape ``(..., 1)`` (m).
        """
        return dict(dtheta=params[..., 0:3],
                    L1=self.L[0] + params[..., 3:12:3],
                    L2=self.L[1] + params[..., 4:12:3],
                    L3=self.L[2] + params[..., 5:12:3],
                    d=(self.r + params[..., 13:14]) - (self.R + params[..., 12:13]))

    # ---------------------------------------------------------------- loop closure
    def _terms(self, p: Tensor, theta_act: Tensor, g: dict[str, Tensor], clamp: bool = False):
        """Loop-closure pieces at ``p (..., 3)`` and actual drive angles ``θ (..., 3)``."""
        c, s = theta_act.cos(), theta_act.sin()
        rho = p @ self.E.mT + g["d"] - g["L1"] * c          # (..., 3) radial, from A_i2 to B_i
        zeta = p[..., 2:3] - g["L1"] * s                   # (..., 3) vertical
        y = p @ self.T.mT                                  # (..., 3) tangential
        L3 = g["L3"]
        y2 = y * y
        if clamp:
            y2 = torch.minimum(y2, (L3 * (1 - _Y_MARGIN)) ** 2)
        sq = torch.sqrt(L3 * L3 - y2)
        n = torch.sqrt(rho * rho + zeta * zeta)
        h = n - g["L2"] - sq
        return dict(c=c, s=s, rho=rho, zeta=zeta, y=y, sq=sq, n=n, h=h)

    def constraint(self, p, theta, params=None) -> Tensor:
        """Loop-closure residuals ``h_i`` (m), ``(..., 3)``: zero when ``p`` is the platform
        position for commanded drive angles ``theta`` (rad). Broadcasts like :meth:`fk`."""
        params = self._params(params)
        p, theta = self._xyz(p, "p"), self._xyz(theta, "theta")
        g = self.geometry(self._lift(params, p if p.ndim >= theta.ndim else theta))
        return self._terms(p, theta + g["dtheta"], g)["h"]

    def _partials(self, p: Tensor, theta: Tensor, g: dict[str, Tensor], params: bool = True):
        """Analytic partial derivatives of ``h`` at ``(p, θ)``.

        Returns ``(h, Hp, Ht, Hq)``: ``h (..., 3)``, ``Hp = ∂h/∂p (..., 3, 3)``,
        ``Ht = ∂h_i/∂θ_i1 (..., 3)`` (``h_i`` depends on its own drive only; equals
        ``∂h_i/∂Δθ_i1``), ``Hq = ∂h/∂params (..., 3, 14)`` (``None`` unless ``params``: the
        Newton loop needs only ``h`` and ``Hp``).
        """
        t = self._terms(p, theta + g["dtheta"], g, clamp=True)
        rho, zeta, n, sq, y, c, s = t["rho"], t["zeta"], t["n"], t["sq"], t["y"], t["c"], t["s"]
        L1, L3 = g["L1"], g["L3"]
        ur, uz = rho / n, zeta / n                         # unit vector A_i2 -> B_i, in-plane
        # row i of Hp is the direction of link L_i3 divided by cos θ_i3: the constraint normal
        Hp = ur[..., None] * self.E + uz[..., None] * self._zhat + (y / sq)[..., None] * self.T
        Ht = L1 * (ur * s - uz * c)
        if not params:
            return t["h"], Hp, Ht, None
        dL1 = -(ur * c + uz * s)
        dL3 = -L3 / sq
        batch = torch.broadcast_shapes(Ht.shape, dL1.shape, ur.shape)   # (..., 3 branches)
        Hq = torch.zeros(batch + (self.n_params,), dtype=self.dtype, device=self.device)  # (..., 3, 14)
        idx = torch.arange(3, device=self.device)
        Hq[..., idx, idx] = Ht.expand(batch)
        Hq[..., idx, 3 + 3 * idx] = dL1.expand(batch)
        Hq[..., idx, 4 + 3 * idx] = -1.0
        Hq[..., idx, 5 + 3 * idx] = dL3.expand(batch)
        Hq[..., 12] = -ur.expand(batch)                    # d = r - R, in every branch
        Hq[..., 13] = ur.expand(batch)
        return t["h"], Hp, Ht, Hq

    # ---------------------------------------------------------------- inverse kinematics
    def ik(self, p, params=None, *, return_passive: bool = False):
        """Commanded drive angles that place the platform at ``p`` (closed form, elbow out).

        Args:
            p: platform positions ``(..., 3)`` (m), base frame.
            params: ``None``, ``(14,)`` or ``(P, 14)`` error parameters (the robot whose drives
                are commanded); the result is what to command, i.e. the actual angle minus
                ``Δθ_i1``.
            return_passive: also return ``(θ_i2, θ_i3)``.

        Returns:
            ``θ`` of shape ``params.shape[:-1] + p.shape[:-1] + (3,)`` (rad, in ``(-π, π]``), and
            with ``return_passive`` the passive angles ``θ_i2, θ_i3`` of the same shape.

        Raises:
            WorkspaceError: a point above the static platform (``p_z ≤ 0``), with a tangential
                offset ``|t_i·p| ≥ L_i3``, or out of reach of a branch; the message names the first
                such point and branch.
        """
        params = self._params(params)
        p = self._xyz(p, "p")
        g = self.geometry(self._lift(params, p))
        L1, L2, L3 = g["L1"], g["L2"], g["L3"]
        y = p @ self.T.mT
        a = p @ self.E.mT + g["d"]                         # B_i relative to A_i1, radial
        b = p[..., 2:3].expand_as(a)                       # ... and vertical
        a, b, y = torch.broadcast_tensors(a, b, y)
        check_reach(p, a, b, y, L1, L2, L3)
        c = L2 + torch.sqrt(L3 * L3 - y * y)               # in-plane length A_i2 -> B_i
        rho2 = a * a + b * b
        K = (rho2 + L1 * L1 - c * c) / (2 * L1)            # a cos θ + b sin θ = K (seed's eq. 6)
        # elbow out: θ = atan2(b, a) - arccos(K / ρ), written with atan2 for accuracy near ±1
        th_act = torch.atan2(b, a) - torch.atan2(torch.sqrt(torch.clamp(rho2 - K * K, min=0.0)), K)
        theta = _wrap(th_act - g["dtheta"])
        if not return_passive:
            return theta
        th3 = torch.asin(y / L3)
        th12 = torch.atan2(b - L1 * th_act.sin(), a - L1 * th_act.cos())
        return theta, (_wrap(th12 - th_act), th3)

    # ---------------------------------------------------------------- forward kinematics
    def fk(self, theta, params=None, *, p0=None, tol: float = 1e-13, max_iter: int = 50,
           on_failure: str = "raise") -> Tensor:
        """Platform position for commanded drive angles: the three loop-closure equations solved
        by batched Newton iterations; differentiable in ``theta`` and ``params`` by the implicit
        function theorem (not by unrolling the iterations).

        Args:
            theta: commanded drive angles ``(..., 3)`` (rad).
            params: ``None``, ``(14,)`` or ``(P, 14)``.
            p0: Newton start ``(..., 3)`` (m) broadcastable to the output (e.g. the targets the
                angles were computed for); default the workspace centre ``self.p0``.
            tol: stop when every ``|h_i|`` is below ``tol`` (m).
            max_iter: Newton iterations at most.
            on_failure: ``"raise"`` (default): :class:`WorkspaceError` for angles with no solution
                in the working mode; ``"nan"``: those outputs become NaN instead (for optimisers,
                which treat NaN as a failed evaluation).

        Returns:
            ``p`` of shape ``params.shape[:-1] + theta.shape[:-1] + (3,)`` (m).
        """
        if on_failure not in ("raise", "nan"):
            raise ValueError(f"on_failure must be 'raise' or 'nan', got {on_failure!r}")
        params = self._params(params)
        theta = self._xyz(theta, "theta")
        pl = self._lift(params, theta)
        batch = torch.broadcast_shapes(pl.shape[:-1], theta.shape[:-1])
        start = self.p0 if p0 is None else self._xyz(p0, "p0")
        start = start.expand(batch + (3,))
        return _ImplicitFK.apply(self, theta.expand(batch + (3,)), pl.expand(batch + (self.n_params,)),
                                 start.detach(), float(tol), int(max_iter), on_failure)

    def _newton(self, theta: Tensor, params: Tensor, p: Tensor, tol: float, max_iter: int):
        """Newton on ``h(p) = 0``; all tensors already broadcast to one batch shape. Returns
        ``(p, ok, h, Ht)`` with ``ok (...,)`` bool: converged, in the working mode."""
        g = self.geometry(params)
        # a step is at most this long (m): far from the solution the linearisation of the
        # square roots is poor, and a full step could jump to another assembly mode
        max_step = 0.1 * float(self.L.sum(0).max())
        h, Hp, Ht, _ = self._partials(p, theta, g, params=False)
        for _ in range(max_iter):
            hn = torch.linalg.vector_norm(h, dim=-1)
            # failed members (NaN) must not keep the others iterating, nor stop them early
            if h.numel() == 0 or float(torch.where(torch.isfinite(hn), hn, 0.0).max()) < tol:
                break
            step = torch.linalg.solve(Hp, h.unsqueeze(-1)).squeeze(-1)
            norm = torch.linalg.vector_norm(step, dim=-1, keepdim=True)
            step = torch.where(norm > max_step, step * (max_step / norm), step)
            step = torch.where(torch.isfinite(step), step, torch.zeros_like(step))
            # backtracking on |h| (halve the step where it does not decrease): near the workspace
            # boundary the plain iteration cycles between two points instead of converging. The
            # partials at the accepted point serve the next iteration.
            alpha = torch.ones_like(hn)
            for j in range(_BACKTRACK):
                p_try = p - alpha[..., None] * step
                h_try, Hp_try, Ht_try, _ = self._partials(p_try, theta, g, params=False)
                worse = ~(torch.linalg.vector_norm(h_try, dim=-1) <= (1 - 1e-4 * alpha) * hn) & (hn > tol)
                if j == _BACKTRACK - 1 or not bool(worse.any()):
                    break
                alpha = torch.where(worse, 0.5 * alpha, alpha)
            p, h, Hp, Ht = p_try, h_try, Hp_try, Ht_try
        y_ok = ((p @ self.T.mT).abs() < g["L3"] * (1 - _Y_MARGIN)).all(-1)
        ok = ((h.abs() < max(1e3 * tol, 1e-10)).all(-1) & (p[..., 2] > 0) & (Ht < 0).all(-1)
              & y_ok & torch.isfinite(p).all(-1))
        return p, ok, h, Ht

    def param_jacobian(self, theta, params=None, *, p=None, p0=None) -> Tensor:
        """``∂p/∂params`` at the FK solution: ``-Hp⁻¹ Hq`` (implicit function theorem).

        Args:
            theta, params, p0: as for :meth:`fk`.
            p: the FK solution if already known (skips the Newton solve).

        Returns:
            ``(..., 3, 14)`` (m per rad for the drive offsets, m/m for lengths).
        """
        _, Hp, _, Hq = self._partials_at_solution(theta, params, p, p0, with_params=True)
        return -torch.linalg.solve(Hp, Hq)

    def joint_jacobian(self, theta, params=None, *, p=None, p0=None) -> Tensor:
        """``∂p/∂θ`` (m/rad), ``(..., 3, 3)``: the platform's velocity per drive rate."""
        _, Hp, Ht, _ = self._partials_at_solution(theta, params, p, p0, with_params=False)
        return -torch.linalg.solve(Hp, torch.diag_embed(Ht))

    def _partials_at_solution(self, theta, params, p, p0, *, with_params: bool):
        """Loop-closure partials at the FK solution (solved here unless ``p`` is given); the
        implicit-function Jacobians are ``-Hp⁻¹ H_x``."""
        params = self._params(params)
        theta = self._xyz(theta, "theta")
        if p is None:
            with torch.no_grad():
                p = self.fk(theta, params, p0=p0)
        g = self.geometry(self._lift(params, theta))
        return self._partials(p, theta, g, params=with_params)


class _ImplicitFK(torch.autograd.Function):
    """FK as an autograd node. Forward: Newton (no graph). Backward: with ``h(p*, θ, q) = 0``,
    ``dp* = -Hp⁻¹ (Ht dθ + Hq dq)``, so for an incoming gradient ``g`` the adjoint
    ``λ = Hp⁻ᵀ g`` gives ``∂L/∂θ = -λ ⊙ Ht`` and ``∂L/∂q = -Hqᵀ λ``: one 3x3 solve per pose,
    whatever the number of Newton iterations. First derivatives only (``once_differentiable``).
    """

    @staticmethod
    def forward(ctx, model: RRRU, theta: Tensor, params: Tensor, p0: Tensor, tol: float,
                max_iter: int, on_failure: str) -> Tensor:
        with torch.no_grad():
            p, ok, h, Ht = model._newton(theta.detach(), params.detach(), p0, tol, max_iter)
        if not bool(ok.all()):
            if on_failure == "raise":
                raise_fk_failure(theta, p, ok, h, Ht)
            p = torch.where(ok[..., None], p, torch.full_like(p, float("nan")))
        ctx.model = model
        ctx.save_for_backward(theta, params, p)
        return p

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, gp: Tensor):
        theta, params, p = ctx.saved_tensors
        model: RRRU = ctx.model
        _, Hp, Ht, Hq = model._partials(p, theta, model.geometry(params))
        lam = torch.linalg.solve(Hp.mT, gp.unsqueeze(-1)).squeeze(-1)      # (..., 3)
        g_theta = -lam * Ht if ctx.needs_input_grad[1] else None
        g_params = -(lam.unsqueeze(-1) * Hq).sum(-2) if ctx.needs_input_grad[2] else None
        return None, g_theta, g_params, None, None, None, None
