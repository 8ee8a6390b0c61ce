"""The 3-RRRU's error parameters (seed 004).

Error parameters (14, as the seed counts them; nominal value 0, order of its Tables 5-6)::

    dtheta_11, dtheta_21, dtheta_31         drive offsets (rad): actual θ_i1 = commanded + Δθ_i1
    dL_i1, dL_i2, dL_i3  for i = 1, 2, 3    link-length errors per branch (m)
    dR, dr                                  static / moving platform radius errors (m)

``R`` and ``r`` enter only as ``r - R`` (the platform translates, so every branch sees the same
difference); ``dR`` and ``dr`` are therefore never separately identifiable from positions.
See :mod:`torchcal.problems.rrru` for the identifiability analysis.
"""
from __future__ import annotations

__all__ = ["PARAM_NAMES", "PARAM_UNITS", "N_PARAMS"]

PARAM_NAMES: tuple[str, ...] = (
    "dtheta_11", "dtheta_21", "dtheta_31",
    "dL_11", "dL_12", "dL_13", "dL_21", "dL_22", "dL_23", "dL_31", "dL_32", "dL_33",
    "dR", "dr")
PARAM_UNITS: tuple[str, ...] = ("rad",) * 3 + ("m",) * 11
N_PARAMS = len(PARAM_NAMES)
