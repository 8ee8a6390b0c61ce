"""Gravity wrenches of a rigid tree for the independent simulator (numpy only): each joint carries
the weight of everything downstream of it."""
from __future__ import annotations

import numpy as np

from torchcal.sim.physsim_urdf import UrdfJoint

__all__ = ["subtree_wrenches"]


def subtree_wrenches(T: dict, order: list[UrdfJoint], below: dict[str, list[str]], root: str,
                     bodies: dict[str, list], gravity: np.ndarray) -> dict:
    """``T``: link -> ``(N, 4, 4)`` poses in the base frame; ``order``: joints parent before
    child; ``below``: link -> links of its subtree; ``bodies``: link -> [(mass kg, COM (3,) m in
    the link frame)], payloads included (a mass may be ``(N,)``, one per row); ``gravity (3,)`` m/s² in
    the base frame.

    Returns ``{"joints": {name: {"F_N": (N, 3), "M_Nm": (N, 3) about the joint's child frame
    origin, "tau_Nm": (N,) M . axis (revolute joints)}}, "base": {"F_N", "M_Nm" about the base
    origin}}``, each the wrench of the weights downstream."""
    N = len(T[root])
    m_link, s_link = {}, {}  # mass and first mass moment sum(m c) per link
    for link, bs in bodies.items():
        if link in T and bs:
            R, p = T[link][:, :3, :3], T[link][:, :3, 3]
            m_link[link] = sum(np.broadcast_to(b[0], (N,)) for b in bs)
            s_link[link] = sum(np.asarray(b[0])[..., None] * (R @ b[1] + p) for b in bs)
    out: dict = {"joints": {}}
    for j in order + [None]:
        sub = below[j.child if j else root]
        m = sum((m_link[ln] for ln in sub if ln in m_link), np.zeros(N))
        s = sum((s_link[ln] for ln in sub if ln in s_link), np.zeros((N, 3)))
        o = T[j.child][:, :3, 3] if j else np.zeros((N, 3))
        # sum (c - o) x m g = (sum m c - m_tot o) x g
        w = {"F_N": m[:, None] * gravity, "M_Nm": np.cross(s - m[:, None] * o, gravity)}
        if j is None:
            out["base"] = w
            continue
        if j.type in ("revolute", "continuous"):
            w["tau_Nm"] = np.einsum("ni,ni->n", w["M_Nm"], T[j.child][:, :3, :3] @ j.axis)
        out["joints"][j.name] = w
    return out
