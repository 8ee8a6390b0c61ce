"""Text columns as levels: a tool name, an operator, a fixture, a day.

A text column of a measurement file is a factor: its categories are levels, as in a regression
with a factor. It is held as one 0/1 covariate per level, named ``<column>=<level>``, so that
every row operation (subsets, folds, saving) carries it as it carries a number; writing a file
joins those covariates back into the text column they came from.

A numeric column may be a factor too: tools, stations or fixtures logged by number (``tool_id``
1, 2, 3). A column of few whole numbers (:func:`code_levels`) is also read as levels
(``tool_id=2``), beside its numeric reading: whether an error follows the number or the
category is the data's to tell, by cross-validation.
"""
from __future__ import annotations

import math

import numpy as np
import torch
from torch import Tensor

__all__ = ["LEVEL_SEP", "MAX_CODES", "is_level_column", "factor_levels", "level_covariates", "join_levels",
           "is_text_column", "code_levels", "code_indicator"]

LEVEL_SEP = "="
#: A numeric column with at most this many distinct whole-number values (and at most a quarter as
#: many as it has rows), each on two rows or more, may hold codes (a tool, a station, a fixture by
#: number; a rack of ten or twenty tools is common). More values read as a quantity only.
MAX_CODES = 24


def is_level_column(name: str) -> bool:
    """A covariate that holds one level of a text column (``tool=probe``)."""
    return LEVEL_SEP in name


def factor_levels(covariates: dict) -> dict[str, list[str]]:
    """Text column -> its levels (sorted), from the ``<column>=<level>`` covariates."""
    out: dict[str, list[str]] = {}
    for k in covariates:
        if is_level_column(k):
            f, lv = k.split(LEVEL_SEP, 1)
            out.setdefault(f, []).append(lv)
    return {f: sorted(v) for f, v in out.items()}


def _is_number(cell: str) -> bool:
    s = cell.strip()
    if s == "" or s.lower() == "nan":
        return True
    try:
        float(s)
        return True
    except ValueError:
        return False


def is_text_column(cells: list[str]) -> bool:
    """A column whose cells are not all numbers (or empty)."""
    return not all(_is_number(c) for c in cells)


def level_covariates(name: str, cells: list[str]) -> dict[str, np.ndarray]:
    """One 0/1 array per level of the text column ``name`` (an empty cell: NaN in every one,
    the level was not recorded)."""
    if LEVEL_SEP in name:
        raise ValueError(f"column {name!r}: a text column's name must not contain '{LEVEL_SEP}'; rename it")
    vals = [c.strip() for c in cells]
    levels = sorted({v for v in vals if v})
    out = {}
    for lv in levels:
        out[f"{name}{LEVEL_SEP}{lv}"] = np.array([math.nan if not v else float(v == lv) for v in vals])
    return out


def join_levels(covariates: dict) -> tuple[dict, dict[str, list[str]]]:
    """(the numeric covariates, text column -> its cell per row) for writing a file: the level
    covariates joined back into their text columns."""
    numeric = {k: v for k, v in covariates.items() if not is_level_column(k)}
    text: dict[str, list[str]] = {}
    for f, levels in factor_levels(covariates).items():
        cols = [covariates[f"{f}{LEVEL_SEP}{lv}"].detach().cpu().double().numpy() for lv in levels]
        n = len(cols[0])
        text[f] = [next((lv for lv, c in zip(levels, cols) if c[i] == 1.0), "") for i in range(n)]
    return numeric, text


def code_levels(values: Tensor) -> list[str] | None:
    """The levels (``"1"``, ``"2"``, …) of a numeric column ``values (N,)`` that may hold codes: whole
    numbers, 2 to :data:`MAX_CODES` distinct values and at most a quarter of the rows, each value on
    two rows or more (NaN: not recorded); None when it does not."""
    v = values[torch.isfinite(values)]
    if v.numel() < 8 or bool((v != torch.round(v)).any()):
        return None
    u, n = torch.unique(v, return_counts=True)
    if not 2 <= u.numel() <= min(MAX_CODES, v.numel() // 4) or int(n.min()) < 2:
        return None
    return [f"{int(x)}" for x in u.tolist()]


def code_indicator(values: Tensor, level: str) -> Tensor:
    """``(N,)`` 1 where the numeric column ``values`` holds the code ``level``, else 0 (NaN where it
    holds NaN: the level was not recorded)."""
    hit = (values == float(level)).to(values.dtype)
    return torch.where(torch.isfinite(values), hit, torch.full_like(values, math.nan))
