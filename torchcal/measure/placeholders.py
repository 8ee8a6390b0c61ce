"""Columns an instrument fills without measuring: an orientation that never changes.

A position-only tracker still writes orientation fields (``import-bag`` from a ``PoseStamped``
topic writes its identity quaternions). A robot that moves its wrist turns its marker, so an
orientation identical in every row is the instrument's placeholder, not a measurement: fitted, it
would ask the marker to turn with nothing, and the fit has no parameter left to say so.
"""
from __future__ import annotations

import torch

from torchcal.measure.data import Measurements

__all__ = ["constant_orientations", "without_constant_orientations"]

_SAME_RAD = 1e-6  # turns below this (0.2 arcsec) are a file's rounding, not a measured change


def constant_orientations(data: Measurements) -> list[str]:
    """The markers whose measured orientation is the same in every row where it is given (two or
    more rows): placeholders."""
    if data.quaternions is None:
        return []
    out = []
    for k, m in enumerate(data.marker_names):
        qq = data.quaternions[:, k]
        qq = qq[torch.isfinite(qq).all(-1)]
        if len(qq) < 2:
            continue
        # the angle between each quaternion and the first (q and -q are one turn)
        dot = (qq @ qq[0]).abs().clamp(max=1.0)
        if float(2 * torch.acos(dot).max()) < _SAME_RAD:
            out.append(m)
    return out


def without_constant_orientations(data: Measurements, markers: list[str]) -> Measurements:
    """``data`` with the orientations of ``markers`` marked not measured (all of them gone when no
    marker keeps one)."""
    if not markers or data.quaternions is None:
        return data
    qt = data.quaternions.clone()
    for m in markers:
        qt[:, data.marker_names.index(m)] = float("nan")
    keep = bool(torch.isfinite(qt).all(-1).any())
    return data._with(data.q, data.positions, list(data.marker_names), qt if keep else None, dict(data.covariates),
                      data.planes, dict(data.distances))
