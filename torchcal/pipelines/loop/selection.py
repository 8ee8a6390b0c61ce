"""How the loop decides: robust per-row scores, the acceptance rule, effective parameter counts,
and the choice of an effect's modes by linearised cross-validation.

**Scores.** Every decision compares cross-validated errors row by row. With outliers in the
data a squared error lets a few rows decide everything, so a row scores the Huber loss of its
observations' Euclidean errors ``e`` (m): ``e²`` up to the threshold ``c``, ``2ce − c²`` beyond
(:func:`row_scores`), held constant past the suspect threshold (``OUTLIER_K √3 σ̂``): a gross
error says nothing about which of two models is better, and would only add noise to the
comparison. ``c = HUBER_K σ̂`` with ``σ̂`` the robust per-axis noise estimate of the current
model (:func:`robust_sigma`). The fits themselves use the plain Huber loss.

**Rule.** Adding something is accepted when, on the per-row cross-validated scores, the paired
one-sided t statistic of the improvement exceeds ``T_ACCEPT`` and the penalised error
``mean · (1 + 2k / n_obs)`` falls (``k``: free parameters, or the effective number under a prior).

**Modes.** A family (bending at every joint in three directions, growth of every link) is
chosen one mode at a time (:class:`LinearCV`): around the fitted model the measurement model is
linear in small changes of its parameters and in each mode's coordinates, so the
cross-validated score of any set of modes costs a few small solves. A mode is added while one
passes the rule with the threshold raised for the number of modes tried (Bonferroni), since the
best of many noise columns passes a plain t > 3 test by chance.
"""
from __future__ import annotations

import math
from statistics import NormalDist

import numpy as np
import torch
from scipy.optimize import least_squares
from torch import Tensor

__all__ = ["T_ACCEPT", "HUBER_K", "OUTLIER_K", "SIGMA_FLOOR", "robust_sigma", "row_scores", "compare", "rmse_mm",
           "effective_params", "selection_threshold", "LinearCV"]

T_ACCEPT = 3.0
HUBER_K = 3.0    # Huber threshold on the 3-D error norm, in units of the per-axis noise σ̂
OUTLIER_K = 5.0  # an observation further than this many σ̂ from the model is a suspect


# the smallest noise estimate (m per axis), far below any instrument's: rows a model fits exactly
# (as many unknowns as values) leave no spread, and a zero Huber threshold would mean nothing
SIGMA_FLOOR = 1e-9


def robust_sigma(r: Tensor, k_params: int = 0) -> float:
    """Per-axis noise estimate (m) from residual vectors ``r (n_obs, 3)``: 1.4826 × the median
    absolute deviation of all components (blind to outliers), scaled up by ``sqrt(n / (n − k))``
    for ``k`` fitted parameters, which pull the residuals of the fitted rows in; never below
    :data:`SIGMA_FLOOR`."""
    x = r.reshape(-1)
    x = x[torch.isfinite(x)]
    if x.numel() == 0:
        return float("nan")
    mad = float((x - x.median()).abs().median())
    n = x.numel()
    return max(1.4826 * mad * math.sqrt(n / max(n - k_params, 1)), SIGMA_FLOOR)


def row_scores(err: Tensor, rows: Tensor, n_rows: int, c: float | None) -> Tensor:
    """``(n_rows,)`` per-row score: the sum over the row's observations of the Huber loss of the
    Euclidean error ``err (n_obs,)`` (m) with threshold ``c`` (m; None: squared error), constant
    beyond the suspect threshold ``OUTLIER_K √3 c / HUBER_K``, in m²."""
    e = err.abs()
    if c is not None:
        e = e.clamp(max=OUTLIER_K * math.sqrt(3) / HUBER_K * c)
    rho = e * e if c is None else torch.where(e <= c, e * e, 2 * c * e - c * c)
    return torch.zeros(n_rows, dtype=err.dtype, device=err.device).index_add_(0, rows, rho)


def compare(old: Tensor, new: Tensor, k_old: float, k_new: float, n_obs: int) -> tuple[float, bool, bool]:
    """``(t, penalised error fell, accepted)`` for replacing per-row scores ``old`` by ``new``."""
    d = old - new
    n = d.numel()
    sd = float(d.std()) if n > 1 else 0.0
    t = float(d.mean()) / (sd / math.sqrt(n)) if sd > 0 else (math.inf if float(d.mean()) > 0 else 0.0)
    pen_old = float(old.mean()) * (1 + 2 * k_old / n_obs)
    pen_new = float(new.mean()) * (1 + 2 * k_new / n_obs)
    return t, pen_new < pen_old, t > T_ACCEPT and pen_new < pen_old


def penalised(scores: Tensor, k: float, n_obs: int) -> float:
    return float(scores.mean()) * (1 + 2 * k / n_obs)


def rmse_mm(scores: Tensor, n_obs: int) -> float:
    """Root of the mean score per observation, mm (the RMSE when no observation is beyond ``c``)."""
    return 1e3 * math.sqrt(float(scores.sum()) / max(n_obs, 1))


def effective_params(J: Tensor, prior: Tensor | None = None) -> float:
    """Effective number of parameters ``tr((JᵀJ + W²)⁻¹ JᵀJ)`` of a fit with Jacobian ``J (m, k)``
    and prior weights ``W = diag(prior)`` (``(k,)``, 0 = no prior): ``k`` without a prior, less
    as the prior holds parameters the data barely sees."""
    A = J.T @ J
    if prior is None or not bool((prior > 0).any()):
        return float(torch.linalg.matrix_rank(A))
    s = torch.sqrt(torch.clamp(A.diagonal(), min=1e-300))  # unit-free: scale columns alike
    An = A / s[:, None] / s[None, :]
    Pn = torch.diag((prior / s) ** 2)
    return float(torch.trace(torch.linalg.solve(An + Pn + 1e-12 * torch.eye(len(s), dtype=A.dtype), An)))


def selection_threshold(n_tried: int) -> float:
    """The t a mode must beat when ``n_tried`` modes compete: the one-sided level of
    :data:`T_ACCEPT`, shared among them (Bonferroni)."""
    nd = NormalDist()
    p = (1 - nd.cdf(T_ACCEPT)) / max(n_tried, 1)
    return max(T_ACCEPT, nd.inv_cdf(1 - p))


class LinearCV:
    """Cross-validated scores of adding column groups to a fitted model, to first order.

    Around the fitted parameters ``x0``, the model's position errors are ``r + A δ`` for a small
    change ``δ`` of the base parameters and of candidate coordinates. For each fold, ``δ`` is
    fitted on the training observations (with the fit's IRLS weights and the base's prior, which
    pulls ``x0 + δ`` to zero), and the validation rows are scored on ``r + A δ``. The prior can be
    changed (:meth:`set_prior`): the same linearisation then scores the model under another prior.

    Args:
        r: ``(n_obs, 3)`` errors of the fitted model (model − measured, m).
        w: ``(n_obs,)`` IRLS factor of each observation (1 without a robust loss).
        base: ``(3 n_obs, kb)`` Jacobian of the fitted model's free parameters; ``x0``: their values.
        prior: ``(kb,)`` prior weights of the base parameters (0 or None: none).
        groups: candidate column groups, each ``(3 n_obs, g)``.
        rows: ``(n_obs,)`` the row of each observation; ``n_rows``; ``folds``: row indices per fold.
        c: Huber threshold of the scores (m).
    """

    def __init__(self, r: Tensor, w: Tensor, base: Tensor, x0: Tensor, prior: Tensor | None, groups: list[Tensor],
                 rows: Tensor, n_rows: int, folds: list[Tensor], c: float | None):
        self.r, self.rows, self.n_rows, self.c = r, rows, n_rows, c
        A = torch.cat([base] + list(groups), 1)
        norm = A.norm(dim=0)
        self.scale = torch.where(norm > 0, norm, torch.ones_like(norm))
        A = A / self.scale  # unit columns (coordinates δ·scale): the jitter means the same everywhere
        self.A = A
        self.kb = kb = base.shape[1]
        self.slices, o = [], kb
        for g in groups:
            self.slices.append(list(range(o, o + g.shape[1])))
            o += g.shape[1]
        self.usable = [float(norm[sl].max()) > 0 for sl in self.slices]
        self._x0 = torch.zeros(A.shape[1], dtype=A.dtype, device=A.device)
        self._x0[:kb] = x0 * self.scale[:kb]
        w3 = w.repeat_interleave(3)
        self._w3, self._rw = w3, r.reshape(-1) * w3
        Aw = A * w3[:, None]
        self._data_all = (Aw.T @ Aw, Aw.T @ self._rw)
        self._data_folds = []
        for f in folds:
            in_val = torch.zeros(n_rows, dtype=torch.bool, device=A.device)
            in_val[f] = True
            val_obs = in_val[rows]
            tr3 = (~val_obs).repeat_interleave(3)
            self._data_folds.append((val_obs, Aw[tr3].T @ Aw[tr3], Aw[tr3].T @ self._rw[tr3]))
        self.set_prior(prior)

    def set_prior(self, prior: Tensor | None) -> "LinearCV":
        """Score under base prior weights ``prior`` (``(kb,)``, raw units; None: no prior)."""
        P = torch.zeros_like(self._x0)
        if prior is not None:
            P[: self.kb] = prior / self.scale[: self.kb]
        self.prior = None if prior is None else prior.clone()
        P2 = P * P

        def add(G, b):  # the prior residual P (x0 + δ): curvature P², gradient P² x0
            return G + torch.diag(P2), b + P2 * self._x0
        self._all = add(*self._data_all)
        self.folds = [(v, *add(G, b)) for v, G, b in self._data_folds]
        return self

    def k_eff(self, chosen: list[int]) -> float:
        """Effective parameters of the base plus ``chosen`` under the current prior."""
        idx = self._cols(chosen)
        Gd = self._data_all[0][idx][:, idx]
        G = self._all[0][idx][:, idx]
        return float(torch.trace(torch.linalg.pinv(G, rtol=1e-12, hermitian=True) @ Gd))

    @staticmethod
    def _solve(G: Tensor, b: Tensor, idx: Tensor) -> Tensor:
        """Minimum-norm step: directions the columns (unit norm) cannot tell apart, to 1e-6 of
        the largest singular value, get no share of it, rather than huge values that cancel."""
        return -(torch.linalg.pinv(G[idx][:, idx], rtol=1e-12, hermitian=True) @ b[idx])

    def _cols(self, chosen: list[int]) -> Tensor:
        return torch.tensor(list(range(self.kb)) + [i for g in chosen for i in self.slices[g]], device=self.A.device)

    def scores(self, chosen: list[int]) -> Tensor:
        """``(n_rows,)`` cross-validated per-row scores with the groups ``chosen`` added."""
        idx = self._cols(chosen)
        out_err = torch.zeros(self.r.shape[0], dtype=self.A.dtype, device=self.A.device)
        A3 = self.A.reshape(-1, 3, self.A.shape[1])
        for val_obs, G, b in self.folds:
            d = self._solve(G, b, idx)
            pred = self.r[val_obs] + A3[val_obs][..., idx] @ d
            out_err[val_obs] = pred.norm(dim=-1)
        return row_scores(out_err, self.rows, self.n_rows, self.c)

    def coefficients(self, chosen: list[int]) -> Tensor:
        """The full-data linear step for the groups ``chosen``: ``(kb + Σ g,)`` in the columns'
        own units (base parameters first, then each chosen group's coordinates)."""
        idx = self._cols(chosen)
        return self._solve(*self._all, idx) / self.scale[idx]

    def bilinear(self, chosen: list[int], starts: list[Tensor]) -> tuple[Tensor, Tensor, Tensor]:
        """The full-data step for chosen groups of a bilinear effect (each group ``[u, v_1 … v_S]``,
        the mode's column ``u + Σ s_i v_i``), by variable projection: for shared parameters ``s``
        the rest is linear and solved exactly, and only ``s`` is searched, from each of ``starts``.
        Returns (base step ``(kb,)``, each mode's coefficient ``(K,)``, ``s`` ``(S,)``)."""

        Au = self.A * self.scale
        base = Au[:, : self.kb]
        U = torch.stack([Au[:, self.slices[g][0]] for g in chosen], 1)  # (3n, K)
        V = torch.stack([Au[:, self.slices[g][1:]] for g in chosen], 1)  # (3n, K, S)
        P = torch.zeros(self.kb + len(chosen), dtype=Au.dtype, device=Au.device)
        x0 = torch.zeros_like(P)
        if self.prior is not None:
            P[: self.kb] = self.prior
            x0[: self.kb] = self._x0[: self.kb] / self.scale[: self.kb]

        def solve(sv: Tensor) -> tuple[Tensor, Tensor]:
            cols = torch.cat([base, U + V @ sv], 1)
            n = cols.norm(dim=0).clamp(min=1e-300)
            Aw = cols * self._w3[:, None] / n
            Pn = P / n
            G = Aw.T @ Aw + torch.diag(Pn * Pn)
            x = -(torch.linalg.pinv(G, rtol=1e-12, hermitian=True) @ (Aw.T @ self._rw + Pn * Pn * (x0 * n)))
            res = torch.cat([self._rw + Aw @ x, Pn * (x0 * n + x)])
            return x / n, res

        best = None
        for s0 in starts:
            fit = least_squares(lambda v: solve(torch.as_tensor(v, dtype=Au.dtype))[1].cpu().numpy(),
                                np.asarray(s0.cpu(), dtype=float), method="lm", x_scale="jac", max_nfev=200)
            if best is None or fit.cost < best.cost:
                best = fit
        sv = torch.as_tensor(best.x, dtype=Au.dtype, device=Au.device)
        x, _ = solve(sv)
        return x[: self.kb], x[self.kb:], sv

    def forward(self, start: list[int], n_obs: int, baseline: tuple[Tensor, float] | None = None,
                max_modes: int | None = None) -> tuple[list[int], list[dict], Tensor, float]:
        """Forward selection from the groups ``start``: add what passes the rule (at the Bonferroni
        threshold for the candidates tried) with the lowest penalised score, until nothing does.
        The candidates of a step are each remaining group, and, when none of them passes, all of
        them at once: an effect spread thinly over many joints can be clear as a whole and in no
        joint alone.

        Args:
            baseline: (scores, parameter count) to beat at the first step (default: ``start``'s
                own under the current prior); counts are effective ones (:meth:`k_eff`).
        Returns (chosen groups, per step each candidate's t (the whole under -1), the final
        scores, the final parameter count)."""
        chosen = list(start)
        cur, k_cur = (self.scores(chosen), self.k_eff(chosen)) if baseline is None else baseline
        history = []
        pool = [g for g in range(len(self.slices)) if g not in chosen and self.usable[g]]
        t_sel = selection_threshold(len(pool) + (len(pool) > 1))
        while pool and (max_modes is None or len(chosen) - len(start) < max_modes):
            tried, passing = {}, []
            # each remaining group on its own; only when none passes, all of them at once
            for options in ([[g] for g in pool], [list(pool)] if len(pool) > 1 else []):
                for opt in options:
                    s = self.scores(chosen + opt)
                    k = self.k_eff(chosen + opt)
                    t, pen_ok, _ = compare(cur, s, k_cur, k, n_obs)
                    tried[opt[0] if len(opt) == 1 else -1] = t
                    if t > t_sel and pen_ok:
                        passing.append((penalised(s, k, n_obs), opt, s, k, t))
                if passing:
                    break
            best = min(passing, key=lambda p: p[0]) if passing else None
            if best is not None:
                # options that gain within 2 % of the best's gain are ties (a base that tilts and a
                # first joint that bends, pivots 16 cm apart): take the first in the catalogue's
                # order, which runs from the base outwards
                gain = float(cur.mean() - best[2].mean())
                ties = [p for p in passing if float(cur.mean() - p[2].mean()) >= 0.98 * gain]
                best = min(ties, key=lambda p: p[1][0])
            history.append({"tried": tried, "threshold": t_sel, "added": None if best is None else best[1]})
            if best is None:
                break
            _, opt, cur, k_cur, _ = best
            chosen += opt
            pool = [g for g in pool if g not in opt]
        return chosen, history, cur, k_cur
