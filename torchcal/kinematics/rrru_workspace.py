"""Where the 3-RRRU cannot go, in words: the error raised for a point outside the workspace (IK)
or actuated angles with no solution in the working mode (FK), naming the first offending pose."""
from __future__ import annotations

import torch
from torch import Tensor

__all__ = ["WorkspaceError", "check_reach", "raise_fk_failure", "pick"]


class WorkspaceError(ValueError):
    """A position (IK) or a set of drive angles (FK) outside the robot's working mode."""


def pick(x: Tensor, idx: tuple, n_batch: int) -> Tensor:
    """``x[idx]`` where ``x`` has only the trailing ``n_batch`` of ``idx``'s batch axes (a
    pose tensor indexed with a (population, pose) index)."""
    idx = idx[len(idx) - n_batch:] if n_batch else ()
    return x[idx] if idx else x


def check_reach(p: Tensor, a: Tensor, b: Tensor, y: Tensor, L1: Tensor, L2: Tensor, L3: Tensor) -> None:
    """Raise :class:`WorkspaceError`, naming the first offending point and why, when a point ``p
    (..., 3)`` (m) is not reachable: ``a, b, y`` its in-plane and tangential coordinates per branch
    ``(..., 3)`` and ``L1, L2, L3`` the link lengths (m)."""
    z_bad = p[..., 2] <= 0
    y_bad = y.abs() >= L3
    c = L2 + torch.sqrt(torch.clamp(L3 * L3 - y * y, min=0.0))
    rho = torch.sqrt(a * a + b * b)
    far = (rho > L1 + c) | (rho < (L1 - c).abs())
    bad = z_bad[..., None].expand_as(y_bad) | y_bad | far
    if not bool(bad.any()):
        return
    k = torch.nonzero(bad)[0].tolist()
    idx, br = tuple(k[:-1]), k[-1]
    at = f" {list(idx)}" if idx else ""
    where = f"point{at} p = {[round(v, 6) for v in pick(p, idx, p.ndim - 1).tolist()]} m"
    n_bad = int(bad.any(-1).sum())
    if bool(pick(z_bad, idx, z_bad.ndim)):
        why = "is not below the static platform (p_z <= 0; the moving platform hangs below, z > 0)"
    elif bool(y_bad[idx + (br,)]):
        why = (f"has a tangential offset |t_{br + 1}·p| = {float(y[idx + (br,)].abs()):.4f} m >= "
               f"L_{br + 1}3 = {float(L3.expand_as(y)[idx + (br,)]):.4f} m for branch {br + 1}")
    else:
        why = (f"is out of reach of branch {br + 1}: distance {float(rho[idx + (br,)]):.4f} m from "
               f"A_{br + 1}1 outside [{float((L1 - c).abs()[idx + (br,)]):.4f}, "
               f"{float((L1 + c)[idx + (br,)]):.4f}] m")
    raise WorkspaceError(f"outside the workspace: {where} {why} ({n_bad} point(s) in all)")


def raise_fk_failure(theta: Tensor, p: Tensor, ok: Tensor, h: Tensor, Ht: Tensor) -> None:
    """Raise :class:`WorkspaceError` for the first pose whose FK failed (``ok`` False), saying why:
    no convergence, the other assembly mode, a branch not elbow-out, or the workspace boundary.
    ``theta (..., 3)`` rad, ``p (..., 3)`` m, ``h`` the closure residuals (m), ``Ht`` their
    derivatives by the actuated angles."""
    bad = ~ok
    idx = tuple(torch.nonzero(bad)[0].tolist())
    th = [round(v, 6) for v in theta[idx].tolist()]
    if not bool(torch.isfinite(p[idx]).all()) or float(h[idx].abs().max()) > 1e-6:
        why = ("the loop-closure equations have no solution near the start (Newton did not converge:"
               f" max |h| = {float(h[idx].abs().max()):.3g} m); the angles are outside the workspace")
    elif float(p[idx][2]) <= 0:
        why = "the solution found has the platform above the static platform (another assembly mode)"
    elif bool((Ht[idx] >= 0).any()):
        br = int(torch.nonzero(Ht[idx] >= 0)[0]) + 1
        why = (f"at the solution found branch {br} is not elbow-out (the IK's working mode), or the "
               "pose is singular; pass p0 near the expected position")
    else:
        why = "a branch reaches |t_i·p| = L_i3 (θ_i3 = ±90°, the workspace boundary)"
    at = f"[{list(idx)}]" if idx else ""
    raise WorkspaceError(f"FK: no solution in the working mode for θ{at} = {th} rad: {why} "
                         f"({int(bad.sum())} of {bad.numel()} in all)")
