"""Optimal experiment design for calibration poses: the information matrix of a pose set, the
criteria, greedy selection with rank-1 updates, an exchange pass, approach directions for
backlash, and gradient refinement through the differentiable kinematics.

Information matrix. A pose contributes the block ``A`` (``r = 3·M`` rows: every marker's x, y,
z; ``k`` columns: the identifiable parameters), each column divided by a fixed scale (its RMS
over the candidate set, the column scaling of :mod:`torchcal.problems.identifiability`), and a plan of
``S`` poses has ``Mᵢ = Σ AᵀA + εI`` over ``m = S·r`` rows. The tiny ridge ``ε`` keeps the
Cholesky factor defined while the first poses leave ``Mᵢ`` rank-deficient; against the ``≈ r``
a pose adds to each diagonal entry it is negligible.

Criteria, all maximised, all in log form (smooth for gradients):

* ``"D"``: ``log det Mᵢ``. The scaling shifts it by a constant and changes nothing else;
* ``"O1"``: ``log O1 = (log det Mᵢ − Σ log Mᵢ,jj) / 2k``, Borm and Menq's index as
  :func:`torchcal.problems.identifiability.observability` reports it for the plan (columns scaled to unit
  RMS over the plan's own rows);
* ``"O4"``: ``log O4 = log λ_min − ½ log λ_max`` of ``m·D^-½ Mᵢ D^-½`` (``D = diag Mᵢ``), the
  noise amplification index ``σ_min² / σ_max`` in the same convention.

Greedy selection starts from nothing and adds the candidate that raises the criterion most. For
D and O1 all candidates are scored at once by the matrix determinant lemma,
``log det(M + AᵀA) = log det M + log det(I_r + A M⁻¹ Aᵀ)``; O4 has no such update and is
evaluated exactly, in chunks. O1 and O4 need a full-rank matrix to discriminate, so the first
``⌈k / r⌉`` poses are chosen by D. The exchange pass then swaps each chosen pose for the best
candidate while that raises the criterion.
"""
from __future__ import annotations

import math

import torch
from torch import Tensor

from torchcal.effects import Effect

__all__ = ["CRITERIA", "DesignColumns", "criterion_value", "information", "candidate_values", "greedy_select", "exchange",
           "balanced_signs", "column_signs", "tune_directions", "refine_poses"]

CRITERIA = ("D", "O1", "O4")
RIDGE = 1e-9          # ε above, in units where a pose adds about r to each diagonal entry
_CHUNK = 1024         # candidates per batched O4 evaluation (memory: chunk·k² floats)


class DesignColumns:
    """The unscaled columns of the information matrix at any poses.

    Args:
        robot: the :class:`~torchcal.kinematics.robot.Robot`.
        params: ``(K,)`` parameters the model is linearised at (m, rad).
        geo_idx: the geometric parameters (indices into ``robot.param_names``) analysed.
        effects: effects whose linear-basis columns join them (:meth:`Effect.linear_basis`,
            joint deflections carried to the markers by the joint Jacobian).

    Attributes:
        names, units: of all ``k_all`` columns, geometric first.
        flip: ``(k_all,)`` for each column the actuated joint whose approach direction flips its
            sign (a backlash column), else -1.
    """

    def __init__(self, robot, params: Tensor, geo_idx: list[int], effects: list[Effect]):
        self.robot, self.params, self.geo_idx, self.effects = robot, params, list(geo_idx), list(effects)
        self.names = [robot.param_names[i] for i in geo_idx] + [n for e in effects for n in e.param_names]
        self.units = [robot.param_units[i] for i in geo_idx] + [u for e in effects for u in e.param_units]
        flip = [-1] * len(geo_idx)
        for e in effects:
            flip += e.direction_flips()
        self.flip = torch.tensor(flip, dtype=torch.long, device=robot.device)

    def __call__(self, q: Tensor, directions: Tensor | None = None) -> Tensor:
        """``(N, r, k_all)`` columns at poses ``q (N, dof)`` (m per unit parameter, instrument
        frame), backlash columns for approach ``directions (N, dof)`` (±1; default +1).
        Differentiable in ``q``."""
        robot = self.robot
        N = q.shape[0]
        J = robot.param_jacobian(q, self.params, check=False)[..., self.geo_idx]  # (N, M, 3, kg)
        if not self.effects:
            return J.reshape(N, -1, J.shape[-1])
        d = torch.ones_like(q) if directions is None else directions.to(q)
        Jq = robot.joint_jacobian(q, self.params, check=False)[:, :, :3, :]  # (N, M, 3, dof)
        Rb, _ = robot.base_transform(self.params)
        cols = [J]
        for e in self.effects:
            cov = {f"dir.{j}": d[:, i] for i, j in enumerate(robot.joint_names)} if "direction" in e.reads else {}
            basis = e.linear_basis(e.prepare(q, cov))
            L = sum(len(g) for g in basis.groups)
            c = J.new_zeros(N, J.shape[1], 3, L)
            if basis.dq is not None:
                c = c + Jq @ basis.dq[:, None]
            if basis.dp is not None:  # robot-base displacements, turned into the instrument frame
                c = c + Rb @ basis.dp
            cols.append(c)
        A = torch.cat(cols, -1)
        return A.reshape(N, -1, A.shape[-1])


def _logdet_chol(M: Tensor) -> Tensor:
    L, info = torch.linalg.cholesky_ex(M)
    out = 2 * torch.log(torch.diagonal(L, dim1=-2, dim2=-1)).sum(-1)
    return torch.where(info == 0, out, torch.full_like(out, -math.inf))


def criterion_value(M: Tensor, m: int, kind: str) -> Tensor:
    """The criterion (log form, module docstring) of information matrices ``M (..., k, k)``
    built from ``m`` rows; ``-inf`` where ``M`` is not positive definite."""
    k = M.shape[-1]
    if kind == "D":
        return _logdet_chol(M)
    dg = torch.diagonal(M, dim1=-2, dim2=-1)
    if kind == "O1":
        return (_logdet_chol(M) - torch.log(dg).sum(-1)) / (2 * k)
    if kind == "O4":
        s = dg.rsqrt()
        lam = torch.linalg.eigvalsh(m * s[..., :, None] * M * s[..., None, :])
        lo = lam[..., 0]
        return torch.where(lo > 0, torch.log(lo.clamp(min=1e-300)) - 0.5 * torch.log(lam[..., -1]),
                           torch.full_like(lo, -math.inf))
    raise ValueError(f"criterion must be one of {CRITERIA}, got {kind!r}")


def information(A: Tensor) -> Tensor:
    """``Σ AᵀA + εI`` of blocks ``A (S, r, k)`` (scaled columns)."""
    k = A.shape[-1]
    return torch.einsum("srk,srl->kl", A, A) + RIDGE * torch.eye(k, dtype=A.dtype, device=A.device)


def candidate_values(M: Tensor, A: Tensor, m: int, kind: str) -> Tensor:
    """The criterion after adding each candidate block ``A (N, r, k)`` to ``M (k, k)``: ``(N,)``.
    D and O1 by the determinant lemma (one triangular solve for all candidates), O4 exactly."""
    if kind in ("D", "O1"):
        N, r, k = A.shape
        L = torch.linalg.cholesky(M)
        # one solve with every candidate's rows side by side: a batch of N small solves is far slower
        X = torch.linalg.solve_triangular(L, A.reshape(N * r, k).T, upper=False).T.reshape(N, r, k)  # A L⁻ᵀ
        G = X @ X.transpose(1, 2) + torch.eye(r, dtype=A.dtype, device=A.device)
        val = 2 * torch.log(torch.diagonal(L)).sum() + _logdet_chol(G)
        if kind == "O1":
            val = (val - torch.log(torch.diagonal(M) + (A * A).sum(1)).sum(-1)) / (2 * M.shape[-1])
        return val
    return torch.cat([criterion_value(M + torch.einsum("nrk,nrl->nkl", a, a), m, kind)
                      for a in A.split(_CHUNK)])


# ----------------------------------------------------------------------------- approach directions
def balanced_signs(A_plus: Tensor, sel: list[int], D: Tensor, flip: Tensor) -> Tensor:
    """``(k,)`` column signs for a new pose: each backlash column approached against the side
    its joint leans to so far (``Σ d·‖column‖²`` over the chosen poses; +1 when even), so that
    both directions are measured about equally, weighted by how far each moves the markers."""
    s = torch.ones(A_plus.shape[-1], dtype=A_plus.dtype, device=A_plus.device)
    cols = torch.nonzero(flip >= 0).flatten()
    if not len(sel) or not len(cols):
        return s
    w = (A_plus[sel][:, :, cols] ** 2).sum(1)  # (S, c)
    lean = (D[:, flip[cols]] * w).sum(0)
    s[cols] = torch.where(lean > 0, -1.0, 1.0).to(s)
    return s


def column_signs(D: Tensor, flip: Tensor) -> Tensor:
    """``(S, k)`` sign of every column at poses approached from ``D (S, dof)``."""
    sg = torch.ones(D.shape[0], flip.numel(), dtype=D.dtype, device=D.device)
    b = flip >= 0
    sg[:, b] = D[:, flip[b]]
    return sg


def greedy_select(A_plus: Tensor, n: int, kind: str, flip: Tensor, dof: int) -> tuple[list[int], Tensor]:
    """Greedy selection of ``n`` poses from scaled candidate blocks ``A_plus (N, r, k)`` (backlash
    columns at direction +1; ``flip`` as :attr:`DesignColumns.flip` for these columns). Returns
    the indices and ``D (n, dof)`` their approach directions (±1; +1 for joints without
    backlash)."""
    N, r, k = A_plus.shape
    M = RIDGE * torch.eye(k, dtype=A_plus.dtype, device=A_plus.device)
    sel: list[int] = []
    D = torch.ones(0, dof, dtype=A_plus.dtype, device=A_plus.device)
    n_d = math.ceil(k / r)  # until M has full rank, only D tells candidates apart
    for t in range(n):
        s = balanced_signs(A_plus, sel, D, flip)
        A = A_plus * s
        v = candidate_values(M, A, (t + 1) * r, kind if t >= n_d else "D")
        v[sel] = -math.inf
        i = int(torch.argmax(v))
        sel.append(i)
        M = M + A[i].T @ A[i]
        d = torch.ones(1, D.shape[1], dtype=A.dtype, device=A.device)
        b = flip >= 0
        d[0, flip[b]] = s[b]
        D = torch.cat([D, d])
    return sel, D


def exchange(A_plus: Tensor, sel: list[int], D: Tensor, kind: str, flip: Tensor, passes: int = 3,
             tol: float = 1e-9) -> tuple[list[int], Tensor, int]:
    """Swap chosen poses for better candidates while the criterion rises (at most ``passes``
    sweeps over the plan). Returns the plan, its directions and the number of swaps."""
    sel, D = list(sel), D.clone()
    r = A_plus.shape[1]
    m = len(sel) * r
    A_sel = A_plus[sel] * column_signs(D, flip)[:, None]
    cur = float(criterion_value(information(A_sel), m, kind))
    swaps = 0
    for _ in range(passes):
        changed = False
        for p in range(len(sel)):
            rest = sel[:p] + sel[p + 1:]
            Dr = torch.cat([D[:p], D[p + 1:]])
            M_minus = information(torch.cat([A_sel[:p], A_sel[p + 1:]]))  # not M − AᵀA: no cancellation
            s = balanced_signs(A_plus, rest, Dr, flip)
            v = candidate_values(M_minus, A_plus * s, m, kind)
            v[rest] = -math.inf
            i = int(torch.argmax(v))
            if float(v[i]) > cur + tol * max(1.0, abs(cur)) and i != sel[p]:
                sel[p] = i
                b = flip >= 0
                D[p, flip[b]] = s[b]
                A_sel[p] = A_plus[i] * s
                cur, changed = float(v[i]), True
                swaps += 1
        if not changed:
            break
    return sel, D, swaps


def tune_directions(A_plus_sel: Tensor, D: Tensor, kind: str, flip: Tensor, passes: int = 3) -> Tensor:
    """Flip single approach directions (pose, joint) while the criterion rises."""
    D = D.clone()
    joints = sorted(set(flip[flip >= 0].tolist()))
    m = A_plus_sel.shape[0] * A_plus_sel.shape[1]

    def value(Dx):
        return float(criterion_value(information(A_plus_sel * column_signs(Dx, flip)[:, None]), m, kind))

    cur = value(D)
    for _ in range(passes if joints else 0):
        changed = False
        for p in range(D.shape[0]):
            for j in joints:
                D[p, j] = -D[p, j]
                v = value(D)
                if v > cur + 1e-12 * max(1.0, abs(cur)):
                    cur, changed = v, True
                else:
                    D[p, j] = -D[p, j]
        if not changed:
            break
    return D


# ----------------------------------------------------------------------------- gradient refinement
def refine_poses(columns: DesignColumns, q0: Tensor, D: Tensor | None, keep: list[int], scale: Tensor,
                 bounds: tuple[Tensor, Tensor], kind: str, feasible, steps: int = 100,
                 lr: float = 0.1) -> tuple[Tensor, list[float]]:
    """Gradient ascent of the criterion over the joint values of a plan.

    The joints are ``lo + (hi − lo)·sigmoid(u)`` for ``bounds = (lo, hi)`` (``(dof,)`` each), so
    every step stays strictly inside the bounds; Adam moves ``u``. A step that takes a pose out of ``feasible`` (a callable
    ``q (S, dof) -> (S,) bool``: reachability box, self-collision) is undone for that pose.
    Returns the best plan seen (never worse than ``q0``) and the criterion per step."""
    lo, hi = bounds
    span = (hi - lo).to(q0)
    lo = lo.to(q0)
    x = ((q0 - lo) / span).clamp(1e-6, 1 - 1e-6)
    u = torch.log(x / (1 - x)).detach().requires_grad_(True)
    mom, var = torch.zeros_like(u), torch.zeros_like(u)
    m = q0.shape[0] * 3 * len(columns.robot.marker_names)
    best_q, best_v, hist = q0.clone(), -math.inf, []
    for t in range(1, steps + 2):
        q = lo + span * torch.sigmoid(u)
        A = columns(q, D)[:, :, keep] / scale  # backlash columns already signed by D
        v = criterion_value(information(A), m, kind)
        hist.append(float(v.detach()))
        if hist[-1] > best_v:
            best_v, best_q = hist[-1], q.detach().clone()
        if t > steps or not math.isfinite(hist[-1]):
            break
        (grad,) = torch.autograd.grad(v, u)
        with torch.no_grad():
            # Adam, written out: torch.optim imports torch._dynamo, seconds at its first use
            mom.mul_(0.9).add_(grad, alpha=0.1)
            var.mul_(0.999).addcmul_(grad, grad, value=0.001)
            step = lr * (mom / (1 - 0.9 ** t)) / ((var / (1 - 0.999 ** t)).sqrt() + 1e-12)
            ok = feasible(lo + span * torch.sigmoid(u + step))
            u += step * ok[:, None]
    return best_q, hist
