"""The full-data step of a bilinear effect (a compliance with an unknown payload: each mode's column
is ``u + Σ s_i v_i`` for shared parameters ``s``), by variable projection: for given ``s`` the rest
is the linear CV's minimum-norm solve, so only ``s`` is searched."""
from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from torchcal.pipelines.loop.linear_cv import LinearCV
from torchcal.problems.uncertainty import PINV_RTOL

__all__ = ["bilinear_step"]


def bilinear_step(lcv: LinearCV, chosen: list[int], starts: list[Tensor]) -> tuple[Tensor, Tensor, Tensor]:
    """The full-data step for the groups ``chosen`` of ``lcv`` (each group ``[u, v_1 … v_S]``), the
    shared parameters searched from each of ``starts`` (``(S,)`` each). Returns (base step ``(kb,)``,
    each mode's coefficient ``(K,)``, ``s`` ``(S,)``)."""
    w3, rw, x_base = lcv.weighted_data()
    kb = lcv.kb
    Au = lcv.A * lcv.scale
    base = Au[:, :kb]
    U = torch.stack([Au[:, lcv.slices[g][0]] for g in chosen], 1)  # (3n, K)
    V = torch.stack([Au[:, lcv.slices[g][1:]] for g in chosen], 1)  # (3n, K, S)
    P = torch.zeros(kb + len(chosen), dtype=Au.dtype, device=Au.device)
    x0 = torch.zeros_like(P)
    if lcv.prior is not None:
        P[:kb] = lcv.prior
        x0[:kb] = x_base

    def solve(sv: Tensor) -> tuple[Tensor, Tensor]:
        cols = torch.cat([base, U + V @ sv], 1)
        n = cols.norm(dim=0).clamp(min=1e-300)
        Aw = cols * w3[:, None] / n
        Pn = P / n
        G = Aw.T @ Aw + torch.diag(Pn * Pn)
        x = -(torch.linalg.pinv(G, rtol=PINV_RTOL, hermitian=True) @ (Aw.T @ rw + Pn * Pn * (x0 * n)))
        res = torch.cat([rw + Aw @ x, Pn * (x0 * n + x)])
        return x / n, res

    from scipy.optimize import least_squares  # scipy costs start-up time; only this fit needs it

    best = None
    for s0 in starts:
        fit = least_squares(lambda v: solve(torch.as_tensor(v, dtype=Au.dtype, device=Au.device))[1].cpu().numpy(),
                            np.asarray(s0.cpu(), dtype=float), method="lm", x_scale="jac", max_nfev=200)
        if best is None or fit.cost < best.cost:
            best = fit
    sv = torch.as_tensor(best.x, dtype=Au.dtype, device=Au.device)
    x, _ = solve(sv)
    return x[:kb], x[kb:], sv
