"""Identifiability for a fleet: the decision of :func:`~torchcal.problems.identifiability.analyse_jacobian`
made for many robots at once.

Every robot's Jacobian is judged on its own, as :func:`torchcal.pipelines.calibrate` judges it: columns
normalised to unit length, reduced to the ``k x k`` R factor of a thin QR, then a greedy pivoted
selection run tier by tier (:data:`~torchcal.problems.identifiability.DEFAULT_PREFER`), each tier against
the span of the columns already kept, with the same tie-breaking boost for earlier columns. The
greedy steps are batched over robots, so a fleet costs ``k`` small batched products instead of one
LAPACK call and a Python report per robot. The reasons in words come from the same helpers as the
single-robot report, with one batched least-squares solve per distinct kept set.
"""
from __future__ import annotations

import warnings
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from torchcal.problems.identifiability import TIE_BOOST, preference_tiers
from torchcal.problems.identifiability_report import dependency_reason, zero_column_reason

__all__ = ["FleetDecision", "decide", "explain", "check_rank"]

_CPU_CHUNK = 256  # robots per greedy selection on a CPU


@dataclass
class FleetDecision:
    """Which columns each robot identifies.

    Attributes:
        kept: ``(B, k)`` bool, identifiable; ``zero``: ``(B, k)`` bool, columns that move nothing.
        An: ``(B, n, k)`` the column-normalised Jacobians (reduced to their R factors when tall);
        norms: ``(B, k)`` column norms (m per unit parameter).
    """

    kept: Tensor
    zero: Tensor
    An: Tensor
    norms: Tensor


def _greedy(An: Tensor, tiers: list[list[int]], valid: Tensor, rtol: float) -> Tensor:
    """Tiered greedy column selection, batched: in each tier pick the column with the largest
    (boosted) residual norm while its residual norm exceeds ``rtol`` times the first pick's.

    A column within that tolerance of the kept span stays there (its residual only shrinks) and is
    never picked: columns so for every robot still picking leave the tier's working set, so that
    each step costs what the columns still in play cost (most of a URDF robot's origin errors
    duplicate the joint offsets, base and marker kept before them, or the tier's first picks)."""
    Bn, n, k = An.shape
    dev = An.device
    # columns as rows (B, k, n): every norm and projection then runs along contiguous memory
    Ar = An.transpose(-1, -2).contiguous()
    kept = torch.zeros(Bn, k, dtype=torch.bool, device=dev)
    Q = An.new_zeros(Bn, k, n)  # the kept directions as rows (zero where a robot picked nothing)
    nq = 0
    tol = An.new_zeros(Bn)
    tol_set = torch.zeros(Bn, dtype=torch.bool, device=dev)
    rows = torch.arange(Bn, device=dev)
    for tier in tiers:
        T = Ar[:, tier]
        if nq:
            # project out the kept span twice: once loses orthogonality for nearly dependent columns
            Qk = Q[:, :nq]
            for _ in range(2):
                T = T - (T @ Qk.transpose(-1, -2)) @ Qk
        boost = 1.0 + TIE_BOOST * torch.arange(len(tier), 0, -1, dtype=An.dtype, device=dev)
        T = T * boost[:, None]
        avail = valid[:, tier].clone()
        cols = torch.as_tensor(tier, device=dev)
        going = avail.any(-1)
        for _ in range(len(tier)):
            nrm = torch.linalg.vector_norm(T, dim=-1)
            best, j = torch.where(avail, nrm, -1.0).max(-1)
            d = best / boost[j]
            fresh = going & ~tol_set
            tol = torch.where(fresh, rtol * torch.where(d > 0, d, torch.ones_like(d)), tol)
            tol_set |= fresh
            going = going & (d > tol)
            live = avail & going[:, None] & (nrm / boost > tol[:, None])
            flags = torch.cat([going.any()[None], live.any(0)]).tolist()  # the step's one wait for the device
            if not flags[0]:
                break
            v = T[rows, j]
            v = v * (going / torch.linalg.vector_norm(v, dim=-1).clamp(min=1e-300))[:, None]
            T.addcmul_(T @ v[:, :, None], v[:, None, :], value=-1.0)
            Q[:, nq] = v
            nq += 1
            avail[rows, j] &= ~going
            kept[rows, cols[j]] |= going
            going = going & avail.any(-1)
            alive = [i for i, a in enumerate(flags[1:]) if a]
            if len(alive) < cols.numel():
                at = torch.as_tensor(alive, dtype=torch.long, device=dev)
                T, avail, cols, boost = T[:, at], avail[:, at], cols[at], boost[at]
    return kept


def decide(J: Tensor, names: list[str], markers=(), prefer=None, rtol: float = 1e-9,
           out: Tensor | None = None) -> FleetDecision:
    """The identifiable columns of each robot's Jacobian.

    Args:
        J: ``(B, m, k)`` Jacobians (rows: each robot's residuals, padded rows zero; columns: the
            candidate parameters ``names``, m per unit).
        markers, prefer, rtol: as for :func:`~torchcal.problems.identifiability.analyse_jacobian` (whose
            SVD cross-check of the rank is :func:`check_rank`).
        out: ``(B, k)`` bool, columns to leave out (judged as zero columns), without a masked copy of ``J``.
    """
    J = J.to(torch.float64)
    Bn, m, k = J.shape
    norms = J.norm(dim=1)
    if out is not None:
        norms = norms.masked_fill(out, 0.0)
    big = norms.amax(-1, keepdim=True)
    zero = torch.where(big > 0, norms <= rtol * big, torch.ones_like(norms, dtype=torch.bool))
    An = J * torch.where(zero, 0.0, 1.0 / torch.where(zero, 1.0, norms))[:, None, :]
    if m > k:
        An = torch.linalg.qr(An, mode="r").R
    tiers = [t for t in preference_tiers(markers, names, prefer) if t]
    # a few hundred robots at a time on a CPU: a step's working set then stays in cache
    step = _CPU_CHUNK if An.device.type == "cpu" else max(Bn, 1)
    kept = torch.cat([_greedy(An[a:a + step], tiers, ~zero[a:a + step], rtol) for a in range(0, max(Bn, 1), step)])
    return FleetDecision(kept, zero, An, norms)


def _rank_unsure(dec: FleetDecision, rows: Tensor, rtol: float) -> Tensor:
    """``(b,)`` bool: the decision rows ``rows`` whose SVD rank the Cholesky factor of their kept
    columns' Gram matrix cannot prove equal to the number kept.

    With unit columns ``1 ≤ σ1 ≤ ‖An‖_F``; the kept columns bound ``σ_r`` from below by
    ``1 / sqrt(tr((A_KᵀA_K)⁻¹))``, and the residual of the other columns on their span bounds
    ``σ_{r+1}`` from above. Where both bounds clear ``rtol σ1`` by a margin the Cholesky factor's
    rounding cannot close (a well-conditioned kept set: every robot of a usable pose set), the
    SVD would count the same rank."""
    An, kept, zero = dec.An[rows], dec.kept[rows], dec.zero[rows]
    use = torch.nonzero(kept.any(0)).flatten()  # the columns some robot keeps: the others are out everywhere
    A, f = An[:, :, use], kept[:, use].to(An.dtype)
    u = use.numel()
    L, info = torch.linalg.cholesky_ex((A.transpose(-1, -2) @ A) * f[:, :, None] * f[:, None, :]
                                       + torch.diag_embed(1.0 - f))
    eye = torch.eye(u, dtype=An.dtype, device=An.device)
    Li = torch.linalg.solve_triangular(L, eye.expand_as(L), upper=False)
    trace = ((Li * Li).sum((-2, -1)) - (u - f.sum(-1))).clamp(min=1e-300)  # Σ 1/σ² of the kept columns
    s1_hi = (~zero).sum(-1).to(An.dtype).sqrt()
    cond = s1_hi * trace.sqrt()  # at least the kept columns' condition number
    eps = torch.finfo(An.dtype).eps
    accurate = (info == 0) & (u * eps * cond * cond <= 1e-2)
    low = trace.rsqrt() > 2.0 * rtol * s1_hi
    # the other columns minus their projection on the kept span (semi-normal equations: an error of
    # about eps·cond per unit column, added to the residual below)
    Af = A * f[:, None, :]
    res = An - Af @ torch.cholesky_solve(Af.transpose(-1, -2) @ An, L)
    res = torch.linalg.vector_norm(res * (~kept).to(An.dtype)[:, None, :], dim=(-2, -1))
    high = res + 16.0 * eps * cond * An.shape[-1] ** 0.5 <= 0.5 * rtol
    return ~((accurate & low & high) | zero.all(-1))


def check_rank(dec: FleetDecision, rows=None, labels=None, rtol: float = 1e-9) -> None:
    """Warn, as :func:`~torchcal.problems.identifiability.analyse_jacobian` does, where the SVD of a robot's
    Jacobian counts another rank than the selection kept (the rank is ambiguous at ``rtol``).

    No SVD runs on a fleet whose kept columns are well conditioned: the Cholesky factor of their Gram
    matrix proves the rank (:func:`_rank_unsure`); only the rows it cannot decide (a pose set on
    the edge of identifying a parameter) get their singular values, on the host.

    Args:
        rows: decision rows to check (a list or tensor; default all); ``labels``: ``row -> robot``
            name (a mapping or a callable).
    """
    dev = dec.kept.device
    rows = torch.arange(dec.kept.shape[0], device=dev) if rows is None else torch.as_tensor(rows, device=dev)
    if not rows.numel():
        return
    unsure = rows[_rank_unsure(dec, rows, rtol)].tolist()
    if not unsure:
        return
    s = torch.linalg.svdvals(dec.An[unsure].cpu())
    svd_rank = (s > rtol * s[:, :1]).sum(-1) * (s[:, 0] > 0)
    odd = [b for b, a, c in zip(unsure, svd_rank.tolist(), dec.kept[unsure].sum(-1).tolist()) if a != c]
    if odd:
        name = labels if callable(labels) else (lambda b: labels[b]) if labels else str
        who = [name(b) for b in odd[:5]]
        warnings.warn(f"numerical rank is ambiguous at rtol={rtol:g} for robot(s) {who}: the pose set nearly fails "
                      "to identify some parameters", RuntimeWarning, stacklevel=2)


def explain(dec: FleetDecision, names: list[str], units: list[str], kind: str = "position",
            rtol: float = 1e-9, rows: list[int] | None = None) -> list[dict[str, str]]:
    """A sentence per dropped parameter for robots ``rows`` (default all), as
    :func:`~torchcal.problems.identifiability.analyse_jacobian` words them."""
    rows = list(range(dec.kept.shape[0])) if rows is None else list(rows)
    out: dict[int, dict[str, str]] = {b: {} for b in rows}
    if not rows:
        return []
    sel = torch.as_tensor(rows, device=dec.kept.device)
    patterns, inverse = torch.unique(dec.kept[sel], dim=0, return_inverse=True)
    for p, pat in enumerate(patterns):
        members = sel[inverse == p]
        kept = torch.nonzero(pat).flatten().tolist()
        An, zero, norms = dec.An[members], dec.zero[members], dec.norms[members]
        todo = [i for i in range(len(names)) if i not in set(kept)]
        if kept and todo:
            Bk, rhs = An[:, :, kept], An[:, :, todo]
            coef = torch.linalg.lstsq(Bk, rhs, driver="gelsd" if Bk.device.type == "cpu" else None).solution
            # to numpy once: indexing a tensor element by element costs more than the sentence
            res = (rhs - Bk @ coef).norm(dim=1).cpu().numpy()
            coef = coef.transpose(-1, -2).cpu().numpy()  # (members, todo, kept)
            order = np.argsort(-np.abs(coef), axis=-1, kind="stable")
        zero_np, norms_np = zero.cpu().numpy(), norms.cpu().numpy()
        for r, b in enumerate(members.tolist()):
            zr, nr = zero_np[r], norms_np[r]
            for t, i in enumerate(todo):
                if zr[i]:
                    out[b][names[i]] = zero_column_reason(names[i], kind)
                elif kept:
                    out[b][names[i]] = dependency_reason(i, coef[r, t], float(res[r, t]), kept, names, units, nr,
                                                         rtol, order[r, t])[0]
                else:
                    out[b][names[i]] = f"{names[i]} is numerically dependent on the identifiable parameters"
    return [out[b] for b in rows]
