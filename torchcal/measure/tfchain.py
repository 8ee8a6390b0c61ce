"""Poses along a chain of tf transforms (ROS ``/tf``, ``/tf_static``): the pose of one frame in
another, composed edge by edge whichever way each edge points. Static edges are constant; the
chain is sampled at the times of its most frequent dynamic edge, and its other dynamic edges are
interpolated there (position linearly, orientation by normalised linear interpolation), never
extrapolated."""
from __future__ import annotations

import difflib
from collections import defaultdict, deque

import numpy as np
import torch

from torchcal.kinematics.transforms import matrix_to_quat, quat_to_matrix

__all__ = ["chain_samples"]

Edge = tuple[str, str]  # (parent frame, child frame)


def _tf_path(edges, parent: str, child: str) -> list[tuple[Edge, bool]] | None:
    """Edges ``((parent, child), forward)`` from frame ``parent`` to frame ``child`` (breadth first)."""
    nbr = defaultdict(list)
    for a, b in edges:
        nbr[a].append((b, (a, b), True))
        nbr[b].append((a, (a, b), False))
    prev = {parent: None}
    todo = deque([parent])
    while todo:
        f = todo.popleft()
        for g, key, fwd in nbr[f]:
            if g not in prev:
                prev[g] = (f, key, fwd)
                todo.append(g)
    if child not in prev:
        return None
    path, f = [], child
    while prev[f] is not None:
        f, key, fwd = prev[f]
        path.append((key, fwd))
    return path[::-1]


def _at(t_e: np.ndarray, p_e: np.ndarray, r_e: np.ndarray, t: np.ndarray) -> tuple[torch.Tensor, np.ndarray]:
    """``(n, 4, 4)`` poses of a ``/tf`` edge interpolated at times ``t`` (position linearly,
    orientation by normalised linear interpolation), and which ``t`` lie within its samples."""
    o = np.argsort(t_e, kind="stable")
    t_e, p_e, r_e = t_e[o], p_e[o], r_e[o]
    r_e = r_e * np.cumprod(np.r_[1.0, np.sign(np.sum(r_e[1:] * r_e[:-1], 1) + 1e-300)])[:, None]
    p = np.stack([np.interp(t, t_e, p_e[:, k]) for k in range(3)], 1)
    r = np.stack([np.interp(t, t_e, r_e[:, k]) for k in range(4)], 1)
    return _pose(p, r), (t >= t_e[0]) & (t <= t_e[-1])


def _pose(p: np.ndarray, r: np.ndarray) -> torch.Tensor:
    T = torch.eye(4, dtype=torch.float64).repeat(len(p), 1, 1)
    T[:, :3, :3] = quat_to_matrix(torch.as_tensor(r))
    T[:, :3, 3] = torch.as_tensor(p)
    return T


def chain_samples(dynamic: dict[Edge, tuple], static: dict[Edge, tuple], parent: str, child: str,
                  what: str = "marker") -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Pose of frame ``child`` in frame ``parent`` over time.

    Args:
        dynamic: edge -> ``(times (n,) s, translations (n, 3) m, quaternions (n, 4) w,x,y,z)``
            (sequences), from ``/tf``.
        static: edge -> ``(translation (3,), quaternion (4,))``, from ``/tf_static``.
    Returns ``(t (n,) s, p (n, 3) m, quaternion (n, 4))``, sorted by time. Raises ``ValueError``
    (naming ``what``) when no chain joins the frames or the chain is static only.
    """
    path = _tf_path(set(dynamic) | set(static), parent, child)
    if path is None:
        frames = sorted({f for k in set(dynamic) | set(static) for f in k})
        close = [difflib.get_close_matches(f, frames, n=1) for f in (parent, child)]
        hint = "; ".join(f"is {m[0]!r} meant for {f!r}?" for f, m in zip((parent, child), close) if m and m[0] != f)
        raise ValueError(f"{what}: no chain of /tf, /tf_static transforms joins frame {parent!r} to {child!r}; "
                         f"frames in the bag: {frames}" + (f" ({hint})" if hint else ""))
    moving = [k for k, _ in path if k in dynamic]
    if not moving:
        raise ValueError(f"{what}: {parent!r} -> {child!r} comes from /tf_static alone, a constant, not a "
                         "measurement; give the instrument's frames")
    t = np.sort(np.asarray(dynamic[max(moving, key=lambda k: len(dynamic[k][0]))][0], dtype=np.float64))
    T, ok = torch.eye(4, dtype=torch.float64).repeat(len(t), 1, 1), np.ones(len(t), dtype=bool)
    for key, fwd in path:
        if key in dynamic:
            Te, inside = _at(*(np.asarray(v, dtype=np.float64) for v in dynamic[key]), t)
            ok &= inside
        else:
            Te = _pose(*(np.asarray(v, dtype=np.float64)[None] for v in static[key])).expand(len(t), 4, 4)
        T = T @ (Te if fwd else torch.linalg.inv(Te))
    return t[ok], T[ok, :3, 3].numpy(), matrix_to_quat(T[ok, :3, :3]).numpy()


