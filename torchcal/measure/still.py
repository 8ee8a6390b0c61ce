"""Static poses in streams of joint values: where a robot stood still long enough to be measured,
and the mean orientation of samples taken there."""
from __future__ import annotations

import numpy as np

__all__ = ["still_windows", "mean_quaternion"]


def still_windows(t: np.ndarray, q: np.ndarray, still_s: float, still_tol: float) -> list[tuple[int, int]]:
    """``[(i, j)]``: sample ranges ``q[i:j]`` (``t (N,)`` s, sorted; ``q (N, dof)``) in which every
    joint stays within ``still_tol`` (max − min) for at least ``still_s`` seconds; maximal, from
    the earliest start, not overlapping. A gap between samples over ``still_s`` ends a window."""
    out: list[tuple[int, int]] = []
    # a single step over the tolerance (motion) or a gap cannot lie inside a window: cut there first
    cut = np.flatnonzero((np.abs(np.diff(q, axis=0)) > still_tol).any(1) | (np.diff(t) > still_s)) + 1
    for a, b in zip(np.r_[0, cut], np.r_[cut, len(t)]):
        i = int(a)
        while i < b and t[b - 1] - t[i] >= still_s:
            j = _still_until(q, i, int(b), still_tol)
            if t[j - 1] - t[i] >= still_s:
                out.append((i, j))
                i = j
            elif j == b:
                break
            else:  # the earliest start from which q stays within the tolerance up to sample j
                back = q[i:j + 1][::-1]
                over = ((np.maximum.accumulate(back) - np.minimum.accumulate(back)) > still_tol).any(1)
                i = j + 1 - int(np.argmax(over))
    return out


def _still_until(q: np.ndarray, i: int, b: int, tol: float) -> int:
    """First ``j`` in ``(i, b]`` with ``q[i:j+1]`` out of tolerance (``b``: none), looking ahead in
    growing chunks so that a long window costs O(length)."""
    lo, hi, start, n = q[i].copy(), q[i].copy(), i, 64
    while start < b:
        seg = q[start:min(b, start + n)]
        mx, mn = np.maximum(np.maximum.accumulate(seg), hi), np.minimum(np.minimum.accumulate(seg), lo)
        over = np.flatnonzero(((mx - mn) > tol).any(1))
        if len(over):
            return start + int(over[0])
        hi, lo, start, n = mx[-1], mn[-1], start + len(seg), 2 * n
    return b



def mean_quaternion(r: np.ndarray) -> np.ndarray:
    """``(n, 4)`` unit quaternions (w, x, y, z) of nearby orientations -> their mean ``(4,)``
    (signs aligned to the first, averaged, normalised: exact to second order in the spread)."""
    r = r * np.where(r @ r[0] < 0, -1.0, 1.0)[:, None]  # q and -q are one rotation
    m = r.mean(0)
    return m / np.linalg.norm(m)
