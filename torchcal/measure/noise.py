"""The one robust noise estimator: 1.4826 × the median absolute deviation, a normal distribution's
standard deviation that a few gross errors do not move.

Every stage estimates noise with it: ``calibrate``'s Huber scale, the loop's per-axis noise
(:func:`robust_sigma`, which also corrects for the fitted parameters), the fleet's spread of a
parameter over sibling robots. Here, beside the measurements, so every stage may import it.
"""
from __future__ import annotations

import math

import numpy as np
import torch
from torch import Tensor

__all__ = ["MAD_SIGMA", "SIGMA_FLOOR", "mad_sigma", "robust_sigma"]

#: 1 / Φ⁻¹(3/4): the median absolute deviation of a normal distribution times this is its σ.
MAD_SIGMA = 1.4826
#: The smallest noise estimate (m per axis), far below any instrument's: rows a model fits exactly
#: (as many unknowns as values) leave no spread, and a zero Huber threshold would mean nothing.
SIGMA_FLOOR = 1e-9


def mad_sigma(x: Tensor | np.ndarray, center: float | None = None) -> float:
    """``1.4826 · median |x − center|`` over the finite entries of ``x`` (any shape; ``center``
    default: their median; 0 for the size of errors around zero); NaN when none is finite.

    The median is torch's (the lower middle value) for a tensor and numpy's (the mean of the two
    middle values) for an array, as each caller has always used it."""
    if isinstance(x, np.ndarray):
        v = x.reshape(-1)
        v = v[np.isfinite(v)]
        if v.size == 0:
            return float("nan")
        c = float(np.median(v)) if center is None else center
        return MAD_SIGMA * float(np.median(np.abs(v - c)))
    v = x.reshape(-1)
    v = v[torch.isfinite(v)]
    if v.numel() == 0:
        return float("nan")
    c = v.median() if center is None else center
    return MAD_SIGMA * float((v - c).abs().median())


def robust_sigma(r: Tensor, k_params: int = 0) -> float:
    """Per-axis noise estimate (m) from residual vectors ``r (n_obs, 3)``: :func:`mad_sigma` of all
    components (blind to outliers), scaled up by ``sqrt(n / (n − k))`` for ``k`` fitted parameters,
    which pull the residuals of the fitted rows in; never below :data:`SIGMA_FLOOR`."""
    n = int(torch.isfinite(r).sum())
    s = mad_sigma(r)
    if math.isnan(s):
        return s
    return max(s * math.sqrt(n / max(n - k_params, 1)), SIGMA_FLOOR)
