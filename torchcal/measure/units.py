"""Units of a measurement file: torchcal reads radians and metres; ``--units deg`` / ``--units mm``
(``units=[...]``) converts, and values that look like degrees or millimetres are refused, as are
declared units whose converted values are implausible."""
from __future__ import annotations

import numpy as np

from torchcal.advice import advice

__all__ = ["UNITS", "UnitsError", "convert_units"]

UNITS = ("deg", "mm")


class UnitsError(ValueError):
    """Values that look like degrees or millimetres where torchcal expects radians and metres."""


def convert_units(path, robot, Q: np.ndarray, P: np.ndarray, D: dict, units) -> tuple[np.ndarray, np.ndarray, dict]:
    """Convert declared units; refuse values that look like degrees or millimetres otherwise, and
    declared units whose converted values are implausible (degrees declared on radians)."""
    rev = np.array([u == "rad" for u in robot.joint_units])
    if "deg" in units:
        Q = np.where(rev, np.deg2rad(Q), Q)
        reach = float(np.abs(Q[:, rev]).max()) if rev.any() else 1.0
        if reach < 0.15:
            raise UnitsError(f"{path}: with the joint columns read as degrees, no revolute joint moves more than "
                             f"{np.rad2deg(reach):.3g}° ({reach:.3g} rad) from zero; they look like radians already: "
                             + advice("leave out units=['deg']", "leave out --units deg"))
    if "mm" in units:
        Q = np.where(rev, Q, Q / 1000.0)
        P = P / 1000.0
        D = {k: v / 1000.0 for k, v in D.items()}
    lo, hi = (x.cpu().numpy() for x in robot.joint_limits)
    for j, n in enumerate(robot.joint_names):
        v = float(np.abs(Q[:, j]).max())
        bounded = bool(np.isfinite(lo[j]) and np.isfinite(hi[j]))
        span = max(abs(lo[j]), abs(hi[j])) if bounded else 0.0
        # a continuous joint may turn many times: its values alone cannot say degrees (the bounded
        # joints of the same file do)
        if rev[j] and bounded and v > max(2.2 * np.pi, 1.5 * span):
            raise UnitsError(f"{path}: joint column {n!r} reaches |q| = {v:.4g}, beyond its limits "
                             f"[{lo[j]:.4g}, {hi[j]:.4g}] rad, which looks like degrees; torchcal expects radians: "
                             "convert (rad = deg × π/180) or declare the unit ("
                             + advice("load_measurements(..., units=['deg']), or --units deg on the command line",
                                      "--units deg") + ")")
        if not rev[j] and v > max(5.0, 3 * span):
            raise UnitsError(f"{path}: prismatic joint column {n!r} reaches |q| = {v:.4g}, which looks like "
                             "millimetres; torchcal expects metres: divide by 1000 or declare the unit ("
                             + advice("units=['mm'], or --units mm on the command line", "--units mm") + ")")
    for what, vals in (("marker coordinates", P[np.isfinite(P)]),
                       ("distances", np.concatenate([v[np.isfinite(v)] for v in D.values()] or [np.zeros(0)]))):
        med = float(np.median(np.abs(vals))) if vals.size else 0.0
        if med > 20.0:
            raise UnitsError(f"{path}: {what} have median |value| {med:.4g}, which looks like millimetres; torchcal "
                             "expects metres: divide by 1000 or declare the unit ("
                             + advice("load_measurements(..., units=['mm']), or --units mm on the command line",
                                      "--units mm") + ")")
    return Q, P, D
