"""Text columns as levels: a tool name, an operator, a fixture, a day.

A text column of a measurement file is a factor: its categories are levels, as in a regression
with a factor. It is held as one 0/1 covariate per level, named ``<column>=<level>``, so that
every row operation (subsets, folds, saving) carries it as it carries a number; writing a file
joins those covariates back into the text column they came from.
"""
from __future__ import annotations

import math

import numpy as np

__all__ = ["LEVEL_SEP", "is_level_column", "factor_levels", "level_covariates", "join_levels", "is_text_column"]

LEVEL_SEP = "="


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
