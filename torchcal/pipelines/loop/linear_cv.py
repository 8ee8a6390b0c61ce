"""Cross-validated scores of adding modes to a fitted model, to first order, and the selection of
a family's modes by them: forward steps, then exchanges and removals under the same rule, and
the modes the data cannot tell apart from each chosen one.

Around the fitted model the measurement model is linear in small changes of its parameters and
in each mode's coordinates, so the cross-validated score of any set of modes costs a few small
solves (:class:`LinearCV`); adding one single-column mode to a set is a rank-one update of the
set's solve, so every candidate of a step is scored in one batched pass.
"""
from __future__ import annotations

import torch
from torch import Tensor

from torchcal.pipelines.crossval.scores import T_ACCEPT, T_EXIT, compare, penalised, row_scores, selection_threshold
from torchcal.pipelines.loop.schur import BaseSchur
from torchcal.problems.uncertainty import PINV_RTOL

__all__ = ["LinearCV", "ALIAS_COS"]

# Two modes whose columns, beyond what the rest of the model explains, have a cosine above this
# are candidates for one finding (the rule then says whether the data can tell them apart)
ALIAS_COS = 0.9


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
        self.n_searched = 0  # columns a screening searched before these groups (0: only these)
        self.allow_whole = True  # forward may try every group at once when none passes alone
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
        self._Aw = Aw
        self._data_all = (Aw.T @ Aw, Aw.T @ self._rw)
        self._data_folds, train = [], []
        for f in folds:
            in_val = torch.zeros(n_rows, dtype=torch.bool, device=A.device)
            in_val[f] = True
            val_obs = in_val[rows]
            tr3 = (~val_obs).repeat_interleave(3)
            train.append(tr3)
            self._data_folds.append((val_obs, Aw[tr3].T @ Aw[tr3], Aw[tr3].T @ self._rw[tr3]))
        self._train = torch.stack(train).to(A.dtype) if train else None  # (F, 3 n_obs): 1 on a fold's training rows
        self.set_prior(prior)

    def set_prior(self, prior: Tensor | None, ridge: float | None = None) -> "LinearCV":
        """Score under base prior weights ``prior`` (``(kb,)``, raw units; None: no prior) and a
        Gaussian prior of weight ``ridge`` on every group coordinate (each column of unit norm, so
        ``ridge = σ_noise / (σ_mode √(3 n_obs))`` for a mode's RMS displacement ``σ_mode``; None:
        none)."""
        P = torch.zeros_like(self._x0)
        if prior is not None:
            P[: self.kb] = prior / self.scale[: self.kb]
        if ridge is not None:
            P[self.kb:] = ridge
        self.prior = None if prior is None else prior.clone()
        self.ridge = ridge
        self._P = P
        P2 = P * P

        def add(G, b):  # the prior residual P (x0 + δ): curvature P², gradient P² x0
            return G + torch.diag(P2), b + P2 * self._x0
        self._all = add(*self._data_all)
        self.folds = [(v, *add(G, b)) for v, G, b in self._data_folds]
        # the folds' normal equations stacked, so that every fold (and option) is one batched solve
        self._Gf = torch.stack([G for _, G, _ in self.folds]) if self.folds else None
        self._bf = torch.stack([b for _, _, b in self.folds]) if self.folds else None
        self._schur_at = None  # built when a set is first solved under this prior
        return self

    @property
    def _schur(self) -> BaseSchur:
        """Every set's solve through the base's Schur complement: the whole data first, then the folds."""
        if self._schur_at is None:
            G, b = self._all[0][None], self._all[1][None]
            if self.folds:
                G, b = torch.cat([G, self._Gf]), torch.cat([b, self._bf])
            self._schur_at = BaseSchur(G, b, self.kb)
        return self._schur_at

    def k_eff(self, chosen: list[int]) -> float:
        """Effective parameters of the base plus ``chosen`` under the current prior."""
        return float(self._k_eff_batch(self._cols(chosen)[None])[0])

    def _wide(self, idx: Tensor) -> bool:
        """Whether column sets ``idx (L, k)`` have more columns than the rows (observations and prior
        rows) that determine them: then their pseudo-inverse is cheaper through the rows' Gram."""
        return idx.shape[1] > self._Aw.shape[0] + int((self._P[idx[0]] != 0).sum())

    def _rows(self, idx: Tensor, train: Tensor | None) -> tuple[Tensor, Tensor]:
        """The stacked rows ``B (…, L, r, k)`` whose Gram ``BᵀB`` is the normal matrix of the column sets
        ``idx (L, k)`` (observations, zero outside ``train (F, 3 n_obs)``, then a prior row per column
        that has one), and the right-hand side ``y`` with ``Bᵀy`` the normal equations' ``b``."""
        Aw = self._Aw[:, idx].permute(1, 0, 2)  # (L, 3n, k)
        rw = self._rw.expand(idx.shape[0], -1)
        P = self._P[idx]  # (L, k): the same prior columns in every set (the base), and the ridge if any
        has = torch.nonzero(P[0] != 0).flatten()
        prows = torch.diag_embed(P)[:, has]  # (L, p, k)
        py = (P * self._x0[idx])[:, has]  # (L, p)
        if train is not None:
            Aw = Aw[None] * train[:, None, :, None]
            rw = rw[None] * train[:, None, :]
            prows, py = prows.expand(train.shape[0], -1, -1, -1), py.expand(train.shape[0], -1, -1)
        return torch.cat([Aw, prows], -2), torch.cat([rw, py], -1)

    def _k_eff_batch(self, idx: Tensor) -> Tensor:
        """:meth:`k_eff` of ``L`` column sets of one size, ``idx (L, k)``: ``(L,)``."""
        if self._wide(idx):  # trace((BᵀB)⁺ AᵀA) = ‖(BBᵀ)⁺ B Aᵀ‖²_F, with the rows' smaller Gram
            B, _ = self._rows(idx, None)
            M = torch.linalg.pinv(B @ B.mT, rtol=PINV_RTOL, hermitian=True)
            C = B @ self._Aw[:, idx].permute(1, 2, 0)  # (L, r, 3n)
            return ((M @ C) ** 2).sum((-1, -2))
        return self._schur.effective(idx, self._data_all[0])

    @staticmethod
    def _solve(G: Tensor, b: Tensor, idx: Tensor) -> Tensor:
        """Minimum-norm step: directions the columns (unit norm) cannot tell apart, to 1e-6 of
        the largest singular value, get no share of it, rather than huge values that cancel."""
        return -(torch.linalg.pinv(G[idx][:, idx], rtol=PINV_RTOL, hermitian=True) @ b[idx])

    def _cols(self, chosen: list[int]) -> Tensor:
        return torch.tensor(list(range(self.kb)) + [i for g in chosen for i in self.slices[g]], device=self.A.device)

    def scores(self, chosen: list[int]) -> Tensor:
        """``(n_rows,)`` cross-validated per-row scores with the groups ``chosen`` added."""
        return self._scores_batch(self._cols(chosen)[None])[:, 0]

    def _scores_batch(self, idx: Tensor) -> Tensor:
        """:meth:`scores` of ``L`` column sets of one size, ``idx (L, k)``: ``(n_rows, L)``; every fold
        and set is one batched solve (the same minimum-norm step as :meth:`_solve`)."""
        L = idx.shape[0]
        out_err = torch.zeros(self.r.shape[0], L, dtype=self.A.dtype, device=self.A.device)
        A3 = self.A.reshape(-1, 3, self.A.shape[1])
        if not self.folds:
            return torch.stack([row_scores(out_err[:, i], self.rows, self.n_rows, self.c) for i in range(L)], 1)
        if self._wide(idx):  # (BᵀB)⁺Bᵀ = Bᵀ(BBᵀ)⁺: the same minimum-norm step through the rows' Gram
            B, y = self._rows(idx, self._train)  # (F, L, r, k), (F, L, r)
            M = torch.linalg.pinv(B @ B.mT, rtol=PINV_RTOL, hermitian=True)
            D = -(B.mT @ (M @ y[..., None]))[..., 0]
        else:
            D = -self._schur.solve(idx, torch.arange(1, 1 + len(self.folds), device=idx.device))  # (F, L, k)
        # each set's step spread over all columns, so that a fold's predictions are one product
        # (gathering every set's columns per validation row costs more than the product's zeros)
        steps = D.new_zeros(D.shape[0], L, self.A.shape[1]).scatter_(2, idx.expand(D.shape[0], -1, -1), D)
        for (val_obs, _, _), d in zip(self.folds, steps):
            pred = self.r[val_obs][..., None] + A3[val_obs] @ d.T  # (n_v, 3, L)
            out_err[val_obs] = pred.norm(dim=1)
        return torch.stack([row_scores(out_err[:, i], self.rows, self.n_rows, self.c) for i in range(L)], 1)

    def coefficients(self, chosen: list[int]) -> Tensor:
        """The full-data linear step for the groups ``chosen``: ``(kb + Σ g,)`` in the columns'
        own units (base parameters first, then each chosen group's coordinates)."""
        idx = self._cols(chosen)
        return self._solve(*self._all, idx) / self.scale[idx]

    def weighted_data(self) -> tuple[Tensor, Tensor, Tensor]:
        """The IRLS factor per residual entry ``(3 n_obs,)``, the weighted residuals ``(3 n_obs,)`` (m)
        and the base parameters' fitted values ``(kb,)`` (their own units): what a solve beside this
        one (:func:`~torchcal.pipelines.loop.bilinear.bilinear_step`) starts from."""
        return self._w3, self._rw, self._x0[: self.kb] / self.scale[: self.kb]

    def add_one(self, chosen: list[int], pool: list[int]) -> tuple[Tensor, Tensor]:
        """Scores ``(n_rows, L)`` and effective parameter counts ``(L,)`` of ``chosen`` plus each
        single-column group of ``pool`` (``L`` of them), as :meth:`scores` and :meth:`k_eff` give
        them one at a time: each addition is a rank-one update of the set's solve (a column the
        set already spans adds nothing)."""
        S = self._cols(chosen)
        J = torch.tensor([self.slices[g][0] for g in pool], device=self.A.device)
        A3 = self.A.reshape(-1, 3, self.A.shape[1])
        err = torch.zeros(self.r.shape[0], len(pool), dtype=self.A.dtype, device=self.A.device)
        for val_obs, G, b in self.folds:
            x, U, _ = self._rank_one(G, b, S, J)
            d = self._solve(G, b, S)
            Av = A3[val_obs]  # (n_v, 3, n_cols)
            base = self.r[val_obs] + Av[..., S] @ d  # (n_v, 3)
            E = Av[..., J] - Av[..., S] @ U  # (n_v, 3, L)
            err[val_obs] = (base[..., None] + E * x).norm(dim=1)
        scores = torch.stack([row_scores(err[:, i], self.rows, self.n_rows, self.c) for i in range(len(pool))], 1)
        G, b = self._all
        Gd = self._data_all[0]
        _, U, sch = self._rank_one(G, b, S, J)
        Hinv = torch.linalg.pinv(G[S][:, S], rtol=PINV_RTOL, hermitian=True)
        k0 = float(torch.trace(Hinv @ Gd[S][:, S]))
        g = G[S][:, J]
        h = G[J, J]
        quad = ((U * (Gd[S][:, S] @ U)).sum(0) - 2 * (U * g).sum(0) + h) / sch.clamp(min=1e-300)
        return scores, torch.where(sch > 1e-12 * h.clamp(min=1e-300), k0 + quad, torch.full_like(h, k0))

    def soft(self, start: list[int], n_obs: float, ridges: list[float]) -> dict | None:
        """Every usable group at once under the ridge (of ``ridges``) with the lowest penalised
        score: ``{"ridge", "chosen", "scores", "k", "pen"}``; None with fewer than two groups. The
        ridge stays set as found; :meth:`set_prior` resets it."""
        pool = [g for g in range(len(self.slices)) if self.usable[g] and g not in start]
        if len(pool) < 2:
            return None
        best = None
        for lam in ridges:
            self.set_prior(self.prior, lam)
            sc, k = self.scores(start + pool), self.k_eff(start + pool)
            pen = penalised(sc, k, n_obs)
            if best is None or pen < best["pen"]:
                best = {"ridge": lam, "chosen": start + pool, "scores": sc, "k": k, "pen": pen}
        self.set_prior(self.prior, best["ridge"])
        return best

    def _rank_one(self, G: Tensor, b: Tensor, S: Tensor, J: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """For each column ``j`` of ``J`` added to the set ``S``: its coefficient ``x_j``, the
        set's change per unit of it (``U[:, j]``, the set's solve of ``j``'s column) and the Schur
        complement ``s_j`` (0 when the set spans it: then ``x_j = 0``)."""
        Hinv = torch.linalg.pinv(G[S][:, S], rtol=PINV_RTOL, hermitian=True)
        g = G[S][:, J]  # (k, L)
        U = Hinv @ g
        h = G[J, J]
        sch = h - (g * U).sum(0)
        ok = sch > 1e-12 * h.clamp(min=1e-300)
        x = torch.where(ok, -(b[J] - U.T @ b[S]) / torch.where(ok, sch, torch.ones_like(sch)), torch.zeros_like(sch))
        return x, U, sch

    def _score_options(self, chosen: list[int], options: list[list[int]]) -> list[tuple[Tensor, float]]:
        """(scores, effective parameters) of ``chosen`` plus each option (a list of groups)."""
        single = [o for o in options if len(o) == 1 and len(self.slices[o[0]]) == 1]
        out: dict[int, tuple[Tensor, float]] = {}
        if len(single) > 1:
            sc, k = self.add_one(chosen, [o[0] for o in single])
            for i, o in enumerate(single):
                out[id(o)] = (sc[:, i], float(k[i]))
        # the rest batched by size: one solve for every option and fold of a size
        by_size: dict[int, list] = {}
        for o in options:
            if id(o) not in out:
                idx = self._cols(chosen + o)
                by_size.setdefault(idx.numel(), []).append((o, idx))
        for group in by_size.values():
            idx = torch.stack([i for _, i in group])
            sc, k = self._scores_batch(idx), self._k_eff_batch(idx).tolist()
            for j, (o, _) in enumerate(group):
                out[id(o)] = (sc[:, j], k[j])
        return [out[id(o)] for o in options]

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
        blocks: list[list[int]] = []
        cur, k_cur = (self.scores(chosen), self.k_eff(chosen)) if baseline is None else baseline
        history = []
        pool = [g for g in range(len(self.slices)) if g not in chosen and self.usable[g]]
        t_sel = selection_threshold(max(len(pool) + (len(pool) > 1), self.n_searched))
        while pool and (max_modes is None or len(chosen) - len(start) < max_modes):
            tried, passing = {}, []
            # each remaining group on its own; only when none passes, all of them at once
            for options in ([[g] for g in pool], [list(pool)] if len(pool) > 1 and self.allow_whole else []):
                for opt, (s, k) in zip(options, self._score_options(chosen, options)):
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
            blocks.append(list(opt))
            pool = [g for g in pool if g not in opt]
        chosen, cur, k_cur = self._refine(blocks, list(start), n_obs, cur, k_cur, t_sel, history)
        return chosen, history, cur, k_cur

    def _refine(self, blocks: list[list[int]], start: list[int], n_obs: float, cur: Tensor, k_cur: float, t_sel: float,
                history: list) -> tuple[list[int], Tensor, float]:
        """Selection that can change its mind: after the forward steps, a mode (or a block added at
        once) that no longer passes the rule against the set without it (at the exit threshold
        :data:`~torchcal.pipelines.crossval.scores.T_EXIT`) leaves, and a mode is
        exchanged for one outside when the rule prefers the set with the other; until neither
        applies. ``start`` stays."""
        for _ in range(4 * len(self.slices) + 4):
            chosen = start + [g for b in blocks for g in b]
            drop = None
            for b in blocks:
                rest = [g for g in chosen if g not in b]
                s, k = self.scores(rest), self.k_eff(rest)
                t, pen_ok, _ = compare(s, cur, k, k_cur, n_obs)
                if not (t > T_EXIT and pen_ok) and (drop is None or t < drop[0]):
                    drop = (t, b, s, k)
            if drop is not None:
                blocks.remove(drop[1])
                cur, k_cur = drop[2], drop[3]
                history.append({"removed": list(drop[1]), "t": drop[0], "threshold": t_sel})
                continue
            swap = None
            pool = [g for g in range(len(self.slices)) if g not in chosen and self.usable[g]]
            for b in [b for b in blocks if len(b) == 1]:
                rest = [g for g in chosen if g not in b]
                for h, (s, k) in zip(pool, self._score_options(rest, [[h] for h in pool])):
                    t, pen_ok, _ = compare(cur, s, k_cur, k, n_obs)
                    if t > t_sel and pen_ok and (swap is None or penalised(s, k, n_obs) < swap[0]):
                        swap = (penalised(s, k, n_obs), b, h, s, k, t)
            if swap is None:
                break
            _, b, h, cur, k_cur, t = swap
            blocks[blocks.index(b)] = [h]
            history.append({"exchanged": [b[0], h], "t": t, "threshold": t_sel})
        return start + [g for b in blocks for g in b], cur, k_cur

    def aliases(self, chosen: list[int], pool: list[int] | None = None) -> dict[int, list[int]]:
        """For each chosen single-column group, the other single-column groups the data cannot tell
        from it: beyond what the base and the other chosen groups explain, their columns (weighted
        as the fit weighs them) are nearly collinear (cosine above :data:`ALIAS_COS`), and put in
        its place, the rule would not prefer the chosen set over the exchanged one (paired t of the
        chosen set's gain below :data:`T_ACCEPT`)."""
        pool = [g for g in range(len(self.slices)) if g not in chosen and self.usable[g]] if pool is None else pool
        singles = [g for g in pool if len(self.slices[g]) == 1]
        cur = self.scores(chosen)
        Aw = self.A * self._w3[:, None]
        out = {}
        for g in [g for g in chosen if len(self.slices[g]) == 1]:
            rest = [h for h in chosen if h != g]
            Q = torch.linalg.qr(Aw[:, self._cols(rest)]).Q
            C = Aw[:, [self.slices[h][0] for h in [g] + singles]]
            C = C - Q @ (Q.T @ C)
            n = C.norm(dim=0).clamp(min=1e-300)
            cos = ((C[:, 1:] * C[:, :1]).sum(0) / (n[1:] * n[0])).abs()
            near = [h for h, c in zip(singles, cos.tolist()) if c > ALIAS_COS]
            keep = []
            for h, (sc, _) in zip(near, self._score_options(rest, [[h] for h in near])):
                if compare(sc, cur, 0.0, 0.0, 1)[0] < T_ACCEPT:
                    keep.append(h)
            if keep:
                out[g] = keep
        return out
