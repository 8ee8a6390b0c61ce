"""Target paths for the 3-RRRU (seed 004): the seed's seven straight lines and a helix, in the
robot base frame (m)."""
from __future__ import annotations

import math
from typing import Sequence

import torch
from torch import Tensor

from torchcal.kinematics.rrru import RRRU

__all__ = ["line_trajectories", "spiral_trajectory", "LINE_OFFSETS"]


#: Offsets of the seed's 7 lines from line 1 (m). Line 1 runs in the ``xoz`` plane through the
#: workspace centre; lines 2-3 are nearest to it, lines 6-7 near the boundary (the seed's
#: section 3.2). Reconstruction: all at the seed's height ``z = 0.6`` m, stepped in ``y`` by
#: ±0.05 m; at ``x = -0.8`` m the workspace ends near ``|y| = 0.18`` m (``|y| = 0.2`` is out of
#: reach of branches 2/3), so ``±0.15`` m is "near the boundary".
LINE_OFFSETS: tuple[tuple[float, float, float], ...] = (
    (0.0, 0.0, 0.0), (0.0, 0.05, 0.0), (0.0, -0.05, 0.0), (0.0, 0.10, 0.0), (0.0, -0.10, 0.0),
    (0.0, 0.15, 0.0), (0.0, -0.15, 0.0))


def line_trajectories(n_points: int = 26, start: Sequence[float] = (-0.8, 0.0, 0.6),
                      end: Sequence[float] = (-0.3, 0.0, 0.6),
                      offsets: Sequence[Sequence[float]] = LINE_OFFSETS, *,
                      dtype: torch.dtype = torch.float64) -> Tensor:
    """The seed's straight lines: ``n_points`` equally spaced points from ``start`` to ``end``
    (m), shifted by each of ``offsets`` (m).

    Returns:
        ``(n_lines, n_points, 3)`` positions (m); line ``k`` is ``start + offsets[k] + s (end - start)``.
    """
    a = torch.as_tensor(start, dtype=dtype)
    b = torch.as_tensor(end, dtype=dtype)
    off = torch.as_tensor(offsets, dtype=dtype).reshape(-1, 1, 3)
    s = torch.linspace(0.0, 1.0, n_points, dtype=dtype)[:, None]
    return off + a + s * (b - a)


def spiral_trajectory(n_points: int = 40, centre: Sequence[float] = (-0.5, 0.0),
                      radius: float = 0.25, z: Sequence[float] = (0.45, 0.9), turns: float = 2.5,
                      phase: float = math.pi, *, dtype: torch.dtype = torch.float64) -> Tensor:
    """A helix about a vertical axis (the seed's "spiral", Fig. 11a; its size is not given).

    Default (reconstruction): axis through ``(-0.5, 0)`` m, radius 0.25 m, so that it covers the
    lines' patch (``x`` from -0.75 to -0.25 m, ``|y| ≤ 0.25`` m), climbing from ``z = 0.45`` to
    ``0.9`` m in 2.5 turns, i.e. over the height the lines (all at ``z = 0.6`` m) never leave;
    40 points equally spaced in angle, starting at azimuth ``phase = π`` (``x = -0.75`` m).

    Returns:
        ``(n_points, 3)`` positions (m).
    """
    u = torch.linspace(0.0, 1.0, n_points, dtype=dtype)
    ang = phase + 2 * math.pi * turns * u
    return torch.stack([centre[0] + radius * ang.cos(), centre[1] + radius * ang.sin(),
                        z[0] + (z[1] - z[0]) * u], -1)
