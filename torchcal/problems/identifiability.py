"""Which error parameters can a pose set identify, and how well?

The measurement model is linearised about ``params``: a small parameter change ``dp`` moves the
markers by ``J dp``, with ``J`` the stacked analytic Jacobian (:func:`stacked_jacobian`). A
parameter is *identifiable* from the pose set when its column is not a linear combination of the
columns of the other identified parameters; the rest are *dropped* and their effect is absorbed
by the identified ones.

Column scaling. Columns carry different units (m/m for lengths, m/rad for angles) and different
sizes, so every rank decision here is made on the **column-normalised** Jacobian ``Ĵ``: each
column divided by its 2-norm. This makes the decision independent of units (mm vs m, rad vs deg)
and of how far a parameter's lever arm reaches. A column whose norm is below ``rtol`` times the
largest column norm is zero: that parameter does not move any marker and is unidentifiable outright.

Selection. A column-pivoted QR (``scipy.linalg.qr(..., pivoting=True)``) on ``Ĵ`` chooses a base
set greedily; the numerical rank is the number of R-diagonal entries above ``rtol`` times the
first one, and it is cross-checked against the SVD of the same matrix. Interchangeable
parameters (``joint_1.dz`` and ``base.z``) tie exactly after normalisation, so the QR is run in
*tiers*: the columns matching the first preference tier are pivoted first, the next tier is
pivoted against the span of what was kept, and so on (:data:`DEFAULT_PREFER`: base frame, then
marker points, then DH errors and joint offsets, then joint-origin errors).

Observability indices (Borm & Menq 1991; Driels & Pathre 1990; Nahvi & Hollerbach 1996), from
the singular values ``σ1 ≥ … ≥ σk`` of the Jacobian of the ``k`` identifiable parameters:

* ``O1 = (σ1 σ2 … σk)^(1/k) / √m``  (Borm & Menq; volume of the error ellipsoid),
* ``O2 = σk / σ1``                   (inverse condition number; ``condition = σ1 / σk``),
* ``O3 = σk``                        (minimum singular value, Nahvi & Hollerbach),
* ``O4 = σk² / σ1``                  (noise amplification index, Nahvi & Hollerbach).

Normalisation used for them: the identifiable columns are scaled to unit RMS (each column divided
by ``‖column‖ / √m``, dimensionless), ``m = N·M·r`` is the number of stacked rows (poses × markers
× 3 or 6 components), and the literature formulas are applied as written. Singular values of this
matrix grow like ``√m`` as a raw Jacobian's do, so ``O1`` is a per-row figure comparable across
pose-set sizes while ``O3`` and ``O4`` grow with more data; ``O1`` equals the geometric mean of the
singular values of the unit-norm ``Ĵ``. (Papers that take ``m`` as the number of poses get an
``O1`` larger by ``√(M·r)``.) Because the scaling depends on the pose set, compare pose sets on the
same ``free`` columns, or pass ``scale`` to :func:`observability`.
"""
from __future__ import annotations

import fnmatch
import math
import warnings
from typing import Mapping, Sequence

import numpy as np
import torch
from torch import Tensor

from torchcal.params import ParamSet
from torchcal.problems.identifiability_report import (IdentifiabilityReport, dependency_reason,
                                                      zero_column_reason)

__all__ = ["stacked_jacobian", "identifiability", "analyse_jacobian", "observability", "DEFAULT_PREFER",
           "resolve_free", "normalise_columns", "preference_tiers", "TIE_BOOST", "observability_indices",
           "jacobian_observability"]

# Preference tiers (glob patterns), earliest kept first when parameters are interchangeable.
# The base frame comes first, with the other unknowns of the set-up (touched planes, fixed points):
# with measurements in an instrument frame it must always be identified, and first-joint errors
# duplicate it. Then the marker points, unknowns of the set-up too: a point's place about the last
# joint's axis is exactly that joint's zero offset, and it is the point, placed anywhere on its
# link, that takes it (a zero offset taking it would be as large as the point's unknown angle).
# Then DH errors and joint zero offsets (the textbook parameters), and last the six-per-joint
# origin errors of URDF robots, which duplicate the others most often.
DEFAULT_PREFER: list[list[str]] = [
    ["base.*", "plane.*", "pivot.*"],
    ["<markers>"],  # placeholder: replaced by "<marker>.*" for each of the robot's markers
    ["*.da", "*.dd", "*.dalpha", "*.dtheta", "*.offset"],
]

# Relative boost per position that breaks exact ties in favour of earlier columns (see _tiered_qr).
# (public: the fleet's batched selection breaks ties the same way)
TIE_BOOST = 1e-10


# ---------------------------------------------------------------------------- helpers
def resolve_free(robot, free=None) -> list[int]:
    """Indices (into ``robot.param_names``) of the columns to analyse.

    Args:
        free: ``None`` (all ``K`` parameters), a :class:`~torchcal.params.ParamSet` (its free
            mask), a ``(K,)`` bool tensor/array, or a list of names or glob patterns
            (``"joint_2.*"``). Parameter order is always the robot's.
    """
    names = list(robot.param_names)
    K = len(names)
    if free is None:
        return list(range(K))
    if isinstance(free, ParamSet):
        if free.names != names:
            raise ValueError("this ParamSet was made for another robot (parameter names differ); use robot.params()")
        return [i for i, f in enumerate(free.free.tolist()) if f]
    if isinstance(free, (Tensor, np.ndarray)) and free.dtype in (torch.bool, np.bool_):
        mask = np.asarray(free.cpu() if isinstance(free, Tensor) else free).reshape(-1)
        if mask.shape != (K,):
            raise ValueError(f"a free mask must have shape ({K},), got {tuple(mask.shape)}")
        return [int(i) for i in np.flatnonzero(mask)]
    if isinstance(free, str):
        free = [free]
    chosen = set()
    for pat in free:
        hit = [i for i, n in enumerate(names) if fnmatch.fnmatchcase(n, pat)]
        if not hit:
            raise KeyError(f"no parameter matches {pat!r}; names look like {names[:4]} … (robot.param_names)")
        chosen.update(hit)
    return sorted(chosen)


def normalise_columns(A: np.ndarray, rtol: float = 1e-9) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Divide each column of ``A`` (n_rows, k) by its 2-norm.

    Returns ``(Â, norms, zero)``: ``Â`` with unit-norm columns (zero columns stay zero),
    ``norms`` (k,) in the column's units (m per unit parameter), and ``zero`` (k,) bool: columns
    whose norm is at most ``rtol`` times the largest one — parameters that move no marker.
    """
    norms = np.linalg.norm(A, axis=0)
    big = float(norms.max()) if norms.size else 0.0
    zero = norms <= rtol * big if big > 0 else np.ones_like(norms, dtype=bool)
    An = np.zeros_like(A)
    An[:, ~zero] = A[:, ~zero] / norms[~zero]
    return An, norms, zero


def stacked_jacobian(robot, q, params=None, kind: str = "position", free=None, weights=None) -> Tensor:
    """The parameter Jacobian of all poses and markers as one matrix.

    Args:
        robot: a :class:`~torchcal.kinematics.robot.Robot`.
        q: joint values ``(N, dof)`` (rad or m).
        params: linearisation point, ``(K,)`` tensor or ParamSet (default: nominal, all zero).
        kind: ``"position"`` (3 rows per marker, m per unit) or ``"pose"`` (6 rows: position,
            then angular velocity in rad per unit).
        free: which columns, see :func:`resolve_free` (default: all ``K``).
        weights: optional row weights multiplied into the rows (e.g. ``1/σ`` of each measured
            component), broadcast against ``(N, M, r)`` by torch rules: a scalar, ``(r,)`` per
            component, ``(N, 1, 1)`` per pose, ``(N, M, 1)`` per pose and marker. Weighting the
            position rows against the rotation rows matters for ``kind="pose"`` (m vs rad).

    Returns:
        ``(N*M*r, k)`` float64 tensor, rows ordered pose-major (pose, marker, component) and
        columns in the robot's parameter order. Unscaled: rank decisions elsewhere use the
        column-normalised form (:func:`normalise_columns`).
    """
    return _stacked(robot, q, params, kind, resolve_free(robot, free), weights)


def _stacked(robot, q, params, kind: str, idx: list[int], weights) -> Tensor:
    if isinstance(params, (Tensor, np.ndarray)) and params.ndim == 2:
        raise ValueError("give one parameter vector (K,), not a population (P, K)")
    J = robot.param_jacobian(q, params, kind=kind)
    if J.ndim == 3:  # a single pose given as (dof,)
        J = J[None]
    if J.ndim != 4:
        raise ValueError("give one parameter vector (K,), not a population (P, K)")
    J = J.to(torch.float64)
    if weights is not None:
        w = torch.as_tensor(weights, dtype=J.dtype, device=J.device)
        try:
            J = J * w.expand(J.shape[:-1])[..., None]
        except RuntimeError as e:
            raise ValueError(f"weights of shape {tuple(w.shape)} do not broadcast to (N, M, r) = "
                             f"{tuple(J.shape[:-1])}") from e
    return J.reshape(-1, J.shape[-1])[:, idx]


def preference_tiers(marker_names: Sequence[str], names: list[str], prefer) -> list[list[int]]:
    """Split column positions into preference tiers: the caller's patterns (each entry a glob or a
    list of globs = one tier) in order, then :data:`DEFAULT_PREFER`, then everything else."""
    spec: list = list(prefer or []) + DEFAULT_PREFER
    tiers, taken = [], set()
    for entry in spec:
        pats = [entry] if isinstance(entry, str) else list(entry)
        if "<markers>" in pats:
            pats = [p for p in pats if p != "<markers>"] + [f"{m}.*" for m in marker_names]
        t = [i for i, n in enumerate(names) if i not in taken and any(fnmatch.fnmatchcase(n, p) for p in pats)]
        if t:
            tiers.append(t)
            taken.update(t)
    rest = [i for i in range(len(names)) if i not in taken]
    if rest:
        tiers.append(rest)
    return tiers


def _tiered_qr(An: np.ndarray, tiers: list[list[int]], rtol: float) -> tuple[list[int], list[float]]:
    """Greedy base-column selection: pivoted QR tier by tier, each tier against the span of the
    columns already kept. Returns kept column positions in pivot order and their R diagonals
    (residual norms when chosen; 1 for the first, since columns have unit norm)."""

    n = An.shape[0]
    Q = np.zeros((n, 0))
    kept: list[int] = []
    diag: list[float] = []
    tol = None
    for tier in tiers:
        if Q.shape[1] >= n:
            break
        B = An[:, tier]
        # project out the kept span twice: one Gram-Schmidt pass loses orthogonality when
        # columns are nearly dependent, which is exactly the case being decided here
        for _ in range(2):
            B = B - Q @ (Q.T @ B)
        # Exact duplicates (joint_2.dd / joint_3.dd) tie, and rounding would pick one at random;
        # a tiny boost, largest for the earliest column, makes the earlier one win every time.
        # Scaling a column changes neither the span nor (at 1e-10) any rank decision.
        boost = 1.0 + TIE_BOOST * np.arange(len(tier), 0, -1, dtype=float)
        import scipy.linalg  # scipy costs start-up time; only a rank decision needs it

        Qt, Rt, piv = scipy.linalg.qr(B * boost, mode="economic", pivoting=True)
        d = np.abs(np.diag(Rt)) / boost[piv[: min(Rt.shape)]]
        if tol is None:  # relative to the first R-diagonal entry overall
            tol = rtol * (d[0] if d.size and d[0] > 0 else 1.0)
        nk = int(np.argmax(d <= tol)) if np.any(d <= tol) else d.size
        kept += [tier[int(p)] for p in piv[:nk]]
        diag += [float(x) for x in d[:nk]]
        Q = np.hstack([Q, Qt[:, :nk]])
    return kept, diag


def observability_indices(s: np.ndarray, n_rows: int) -> dict[str, float]:
    """O1..O4 and the condition number from singular values ``s`` of the unit-RMS Jacobian."""
    k = s.size
    if k == 0:
        return dict(O1=0.0, O2=0.0, O3=0.0, O4=0.0, condition=math.inf)
    smax, smin = float(s[0]), float(s[-1])
    with np.errstate(divide="ignore"):
        O1 = float(np.exp(np.mean(np.log(s)))) / math.sqrt(n_rows) if smin > 0 else 0.0  # log: no overflow
    return dict(O1=O1, O2=smin / smax if smax > 0 else 0.0, O3=smin, O4=smin ** 2 / smax if smax > 0 else 0.0,
                condition=smax / smin if smin > 0 else math.inf)


def jacobian_observability(J: Tensor, scale: Tensor | None = None) -> dict[str, float]:
    """O1-O4 and the condition number of a stacked Jacobian ``(m, k)`` with its columns divided by
    ``scale (k,)`` (default: their own RMS, as the analysis does). Pass one ``scale``
    (e.g. the column RMS of all data together) to compare data sets on the same footing; ``O1`` is
    then per measured row, ``O3``, ``O4`` grow with ``√m`` (:func:`observability_indices`)."""
    J = torch.as_tensor(J, dtype=torch.float64)
    m = J.shape[0]
    if scale is None:
        scale = torch.linalg.vector_norm(J, dim=0) / math.sqrt(m)
    s = torch.linalg.svdvals(J / scale).cpu().numpy()
    out = observability_indices(s, m)
    out["n_rows"] = m
    return out



# ---------------------------------------------------------------------------- analysis
def identifiability(robot, q, params=None, kind: str = "position", free=None, rtol: float = 1e-9, *,
                    prefer: Sequence[str | Sequence[str]] | None = None, weights=None) -> IdentifiabilityReport:
    """Which free parameters a pose set identifies, which it cannot, and why.

    Args:
        robot, q, params, kind, free, weights: as for :func:`stacked_jacobian`.
        rtol: relative rank tolerance on the column-normalised Jacobian: an R-diagonal entry of
            the pivoted QR at most ``rtol`` times the first (1) means the column lies in the span
            of those already kept; a column norm at most ``rtol`` times the largest means the
            parameter moves no marker. The SVD cross-check counts ``σ > rtol·σ1``.
        prefer: glob patterns kept first when parameters are interchangeable; each entry is one
            tier (a pattern, or a list of patterns), earlier tiers win. :data:`DEFAULT_PREFER`
            is appended, so ``prefer=["joint_1.dz"]`` keeps ``joint_1.dz`` over ``base.z`` and
            otherwise behaves as the default; ``prefer=["*"]`` gives a plain pivoted QR.

    Returns:
        An :class:`IdentifiabilityReport`.
    """
    idx = resolve_free(robot, free)
    names = [robot.param_names[i] for i in idx]
    units = [robot.param_units[i] for i in idx]
    A = _stacked(robot, q, params, kind, idx, weights).detach().cpu().numpy()
    return analyse_jacobian(A, names, units, markers=robot.marker_names, kind=kind, rtol=rtol, prefer=prefer)


def analyse_jacobian(A, names: list[str], units: list[str], *, markers: Sequence[str] = (), kind: str = "position",
                     rtol: float = 1e-9, prefer: Sequence[str | Sequence[str]] | None = None) -> IdentifiabilityReport:
    """:func:`identifiability` on a Jacobian you already have (rows = whatever residuals you fit,
    columns = ``names`` with ``units``); ``markers`` names the marker-offset preference tier."""
    A = A.detach().cpu().numpy() if isinstance(A, Tensor) else np.asarray(A, dtype=float)
    m, k = A.shape
    if len(names) != k or len(units) != k:
        raise ValueError(f"{k} Jacobian columns but {len(names)} names and {len(units)} units")
    An, norms, zero = normalise_columns(A, rtol)
    if m > k:
        # Column relations, singular values, least-squares coefficients and residual norms are
        # all invariant under an orthogonal transform of the rows: work on the k x k R factor of
        # a thin QR instead of the tall m x k matrix (hundreds of poses cost no more than ten).
        An = torch.linalg.qr(torch.from_numpy(An), mode="r").R.numpy()

    # base subset: tiered pivoted QR over the non-zero columns
    tiers = [[i for i in t if not zero[i]] for t in preference_tiers(markers, names, prefer)]
    tiers = [t for t in tiers if t]
    kept_pivot, _ = _tiered_qr(An, tiers, rtol) if tiers else ([], [])
    kept = sorted(kept_pivot)
    rank = len(kept)

    # cross-check: the SVD of the same matrix should see the same rank
    s_all = np.linalg.svd(An, compute_uv=False) if k and m else np.zeros(0)
    svd_rank = int(np.sum(s_all > rtol * s_all[0])) if s_all.size and s_all[0] > 0 else 0
    if svd_rank != rank:
        warnings.warn(f"the poses nearly fail to identify some parameters: whether {min(rank, svd_rank)} or "
                      f"{max(rank, svd_rank)} of them are seen depends on rounding (pivoted QR keeps {rank}, the SVD "
                      f"counts {svd_rank} at rtol={rtol:g}); poses that move every joint further apart settle it",
                      RuntimeWarning, stacklevel=2)

    # reasons: each dropped column as a least-squares combination of the identifiable columns
    reasons, relations, residuals = {}, {}, {}
    B = An[:, kept]
    kept_set = set(kept)
    todo = [i for i in range(k) if i not in kept_set and not zero[i]]
    # one least-squares solve with every dropped column as a right-hand side
    coef = (np.linalg.lstsq(B, An[:, todo], rcond=None)[0] if kept and todo
            else np.zeros((len(kept), len(todo))))
    coef_of = {i: coef[:, t] for t, i in enumerate(todo)}
    for i in range(k):
        if i in kept_set:
            continue
        n = names[i]
        if zero[i]:
            reasons[n] = zero_column_reason(n, kind)
            relations[n], residuals[n] = {}, 1.0
            continue
        c = coef_of[i]
        res = float(np.linalg.norm(An[:, i] - B @ c)) if kept else 1.0
        reasons[n], relations[n] = dependency_reason(i, c, res, kept, names, units, norms, rtol)
        residuals[n] = res

    # observability of the identifiable columns, scaled to unit RMS (see module docstring)
    rms = norms / math.sqrt(m) if m else norms
    obs = observability_indices(np.linalg.svd(An[:, kept] * math.sqrt(m), compute_uv=False) if kept
                                 else np.zeros(0), m)
    return IdentifiabilityReport(
        rank=rank, svd_rank=svd_rank, n_params=k, n_rows=m,
        identifiable=[names[i] for i in kept], dropped=[names[i] for i in range(k) if i not in kept],
        reasons=reasons, relations=relations, residuals=residuals,
        singular_values=[float(x) for x in s_all], kind=kind, rtol=rtol,
        column_rms={names[i]: float(rms[i]) for i in range(k)},
        pivot_order=[names[i] for i in kept_pivot], **obs)


def observability(robot, q, params=None, kind: str = "position", free=None, *, weights=None, reduce: bool = True,
                  rtol: float = 1e-9, prefer=None, scale: Mapping[str, float] | None = None) -> dict:
    """Observability indices of a pose set: a thin wrapper over the same machinery.

    Args:
        robot, q, params, kind, free, weights: as for :func:`stacked_jacobian`.
        reduce: first reduce ``free`` to the parameters this pose set identifies (as
            :func:`identifiability` does); with ``False`` the columns are used as given, so an
            unidentifiable set gives ``O1 = O2 = O3 = O4 = 0`` and an infinite condition.
        scale: per-parameter column scales (m per unit) to use instead of this pose set's column
            RMS, e.g. ``report.column_rms`` of a reference set: then two pose sets are compared
            with the same, fixed column scaling.

    Returns:
        ``dict(O1, O2, O3, O4, condition, rank, n_params, n_rows, params)``; definitions in the
        module docstring; ``params`` lists the columns the indices were computed on.
    """
    idx = resolve_free(robot, free)
    if reduce:
        rep = identifiability(robot, q, params, kind, free=[robot.param_names[i] for i in idx], rtol=rtol,
                              prefer=prefer, weights=weights)
        idx = [robot.param_names.index(n) for n in rep.identifiable]
    names = [robot.param_names[i] for i in idx]
    A = _stacked(robot, q, params, kind, idx, weights).detach().cpu().numpy()
    m = A.shape[0]
    if scale is None:
        # same zero-column rule as identifiability(): a rounding-level column is zero, not a
        # unit column of noise
        _, norms, zero = normalise_columns(A, rtol)
        sc = np.where(zero, 0.0, norms / math.sqrt(m))
    else:
        missing = [n for n in names if n not in scale]
        if missing:
            raise KeyError(f"scale has no entry for {missing[:5]}")
        sc = np.array([float(scale[n]) for n in names])
    with np.errstate(divide="ignore", invalid="ignore"):
        As = np.where(sc > 0, A / np.where(sc > 0, sc, 1.0), 0.0)
    s = np.linalg.svd(As, compute_uv=False) if As.size else np.zeros(0)
    rank = int(np.sum(s > rtol * s[0])) if s.size and s[0] > 0 else 0
    out = observability_indices(s, m)
    if s.size and rank < len(names):  # a deficient column set: σ_min is (numerically) zero
        out.update(O1=0.0, O2=0.0, O3=0.0, O4=0.0, condition=math.inf)
    out.update(rank=rank, n_params=len(names), n_rows=m, params=names)
    return out
