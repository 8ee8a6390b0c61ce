"""The greedy column selection behind every rank decision: a column-pivoted QR run tier by tier.

:func:`~torchcal.problems.identifiability.analyse_jacobian` keeps, among the columns of a
column-normalised Jacobian, those that are not (to ``rtol``) combinations of columns kept before,
the columns of the earlier preference tiers first; the fleet makes the same decision batched over
robots (:mod:`torchcal.pipelines.fleet.identify`), with the same tie-breaking boost.
"""
from __future__ import annotations

import numpy as np

__all__ = ["TIE_BOOST", "pivoted_qr", "tiered_selection"]

# Relative boost per position that breaks exact ties in favour of earlier columns (see tiered_selection).
# (public: the fleet's batched selection breaks ties the same way)
TIE_BOOST = 1e-10


def pivoted_qr(B: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Column-pivoted QR of ``B (n, p)`` (Businger & Golub): at each step the column with the
    largest norm orthogonal to those already taken. Returns the orthonormal directions ``Q (n, r)``,
    ``|diag R| (r,)`` (non-increasing) and the pivot order ``(p,)``, ``r = min(n, p)``.

    Written here rather than taken from LAPACK (``scipy.linalg.qr(pivoting=True)``): torch has no
    pivoted QR, and importing scipy for one rank decision cost a loop 0.14 s. The matrices are small
    (the ``k x k`` R factor), and the norms are recomputed at every step instead of downdated, so no
    cancellation needs watching."""
    n, p = B.shape
    r = min(n, p)
    W = np.array(B, dtype=float, copy=True)
    Q = np.zeros((n, r))
    d = np.zeros(r)
    piv = np.arange(p)
    for j in range(r):
        rest = W[:, j:]
        i = j + int(np.argmax(np.einsum("ij,ij->j", rest, rest)))
        if i != j:
            W[:, [j, i]] = W[:, [i, j]]
            piv[[j, i]] = piv[[i, j]]
        w = W[:, j] - Q[:, :j] @ (Q[:, :j].T @ W[:, j])  # once more: keeps Q orthogonal near dependence
        d[j] = np.linalg.norm(w)
        if d[j] == 0.0:
            break
        Q[:, j] = w / d[j]
        W[:, j + 1:] -= np.outer(Q[:, j], Q[:, j] @ W[:, j + 1:])
    return Q, d, piv


def tiered_selection(An: np.ndarray, tiers: list[list[int]], rtol: float) -> tuple[list[int], list[float]]:
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
        Qt, dt, piv = pivoted_qr(B * boost)
        d = dt / boost[piv[: dt.size]]
        if tol is None:  # relative to the first R-diagonal entry overall
            tol = rtol * (d[0] if d.size and d[0] > 0 else 1.0)
        nk = int(np.argmax(d <= tol)) if np.any(d <= tol) else d.size
        kept += [tier[int(p)] for p in piv[:nk]]
        diag += [float(x) for x in d[:nk]]
        Q = np.hstack([Q, Qt[:, :nk]])
    return kept, diag
