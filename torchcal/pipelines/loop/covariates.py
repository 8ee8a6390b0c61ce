"""The loop's covariates: directions of approach derived from the time order of the rows, the row
order, a numeric column of codes read as levels too, and the covariates whose held-out values leave
their training range (the effects reading them would extrapolate there)."""
from __future__ import annotations

import torch

from torchcal.effects.base import TIME_COVARIATES
from torchcal.effects.terms import driver_columns
from torchcal.measure.data import Measurements
from torchcal.measure.levels import LEVEL_SEP, code_indicator, code_levels, factor_levels

__all__ = ["derive_directions", "derive_row_order", "derive_code_levels", "extrapolation", "fold_groups"]


def derive_directions(data: Measurements) -> str | None:
    """Add ``dir.<joint>`` covariates (+1/-1: direction from which each joint reached the
    posture) from the time order of the rows, when the data has a time column and no direction
    columns. The first posture in time counts as approached from below. Returns the time column
    used, or None. A covariate, not a measurement: it is derived for test data the same way."""
    if any(k.startswith("dir.") for k in data.covariates):
        return None
    key = next((k for k in TIME_COVARIATES if k in data.covariates), None)
    if key is None or len(data) < 2:
        return None
    order = torch.argsort(data.covariates[key])
    q = data.q[order]
    steps = torch.diff(q, dim=0, prepend=q[:1])
    d = torch.where(steps >= 0, torch.ones_like(q), -torch.ones_like(q))
    inv = torch.empty_like(order)
    inv[order] = torch.arange(len(order), device=order.device)
    for j, n in enumerate(data.joint_names):
        data.covariates[f"dir.{n}"] = d[inv, j]
    return key


def derive_row_order(train: Measurements, test: Measurements | None) -> bool:
    """Add the ``row`` covariate (0, 1, … in file order; the held-out rows after the training
    ones) when the data has no time column: what changed during a session without a clock (a
    joint re-mastered, a fixture knocked) still follows the order the rows were measured in.
    Returns whether it was added."""
    from torchcal.effects.drivers import ROW

    if ROW in train.covariates or any(k in train.covariates for k in TIME_COVARIATES) or len(train) < 2:
        return False
    train.covariates[ROW] = torch.arange(len(train), dtype=train.q.dtype, device=train.q.device)
    if test is not None and ROW not in test.covariates:
        test.covariates[ROW] = len(train) + torch.arange(len(test), dtype=test.q.dtype, device=test.q.device)
    return True


def derive_code_levels(train: Measurements, test: Measurements | None) -> list[str]:
    """Add ``<column>=<code>`` levels (0/1) for each numeric column of the training rows that may hold
    codes (:func:`~torchcal.measure.levels.code_levels`: a tool, a station, a fixture logged by number),
    to the training and the held-out rows; the numeric column stays. A held-out code the training
    rows never show reads 0 in every level, as an unseen text level does. Returns the columns."""
    texts = set(factor_levels(train.covariates))
    out = []
    for c in driver_columns(train.covariates):
        levels = None if c in TIME_COVARIATES or c in texts else code_levels(train.covariates[c])
        if levels is None:
            continue
        for d in (train, test):
            if d is not None and c in d.covariates:
                for lv in levels:
                    d.covariates[f"{c}{LEVEL_SEP}{lv}"] = code_indicator(d.covariates[c], lv)
        out.append(c)
    return out


def fold_groups(data: Measurements, duplicates: torch.Tensor) -> torch.Tensor:
    """A group id per row for the folds: rows with identical commands (``duplicates``, one id
    per row) and rows sharing a time stamp stay together, so that a step in time is never
    "found" by rows of one instant on both sides of a fold."""
    key = next((k for k in TIME_COVARIATES if k in data.covariates), None)
    if key is None or torch.unique(data.covariates[key]).numel() == len(data):
        return duplicates  # no instant holds two rows: the folds stay what they were
    parent = list(range(len(data)))

    def root(i: int) -> int:
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i
    cols = [duplicates] + ([] if key is None else [torch.unique(data.covariates[key], return_inverse=True)[1]])
    for g in cols:
        first: dict[int, int] = {}
        for i, v in enumerate(g.tolist()):
            if v in first:
                parent[root(i)] = root(first[v])
            else:
                first[v] = i
    _, out = torch.unique(torch.tensor([root(i) for i in range(len(data))]), return_inverse=True)
    return out.to(duplicates.device)


def extrapolation(eff, test: Measurements | None) -> list[dict]:
    """Covariates an effect reads whose held-out values leave the training range."""
    out = []
    if test is None:
        return out
    for c, (lo, hi) in eff.covariate_range.items():
        if c not in test.covariates:
            continue
        v = test.covariates[c]
        tol = 0.01 * (hi - lo)
        outside = float(((v < lo - tol) | (v > hi + tol)).double().mean())
        if outside > 0:
            out.append({"effect": eff.name, "covariate": c, "train_range": [lo, hi],
                        "test_range": [float(v.min()), float(v.max())], "fraction_outside": outside,
                        "note": "the held-out rows lie outside the training range of this covariate: the "
                                "effect would extrapolate there" + (" (time covariates are clamped to the "
                                                                    "training range in the deployed model)"
                                                                    if c in TIME_COVARIATES else "")})
    return out

