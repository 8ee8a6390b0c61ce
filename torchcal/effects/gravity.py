"""Gravity wrenches: the force and moment gravity puts on everything beyond each frame.

For a body of mass ``m`` with centre of mass ``c = o_b + R_b s`` (link origin ``o_b``, rotation
``R_b``, ``s`` in the link frame), the wrench it exerts about the origin ``o_f`` of a frame
upstream of it is ``F = m g`` and ``M = m (o_b − o_f) × g + R_b (m s) × g``: linear in the mass
moments ``μ = (m, m s)``. Summed over the bodies beyond the frame (URDF inertials) and an unknown
payload, the wrench is ``W_URDF(q) + A(q) μ_payload``.

Wrenches are computed once per data set at the commanded configurations and a stated geometry:
the deflections they cause are micro-radians, which change the wrench only to second order.
"""
from __future__ import annotations

import weakref
from dataclasses import dataclass
from functools import lru_cache

import numpy as np
import torch
from torch import Tensor

from torchcal.effects.shapes import shape_column
from torchcal.kinematics.robot import Robot
from torchcal.kinematics.tree import Marker
from torchcal.kinematics.urdf import load_joints, read_inertials
from torchcal.measure.levels import LEVEL_SEP

__all__ = ["GRAVITY", "Frames", "Wrenches", "body_inertials", "kinematic_frames", "frames_beyond", "gravity_wrenches",
           "gravity_features", "load_values", "row_payload"]

GRAVITY = (0.0, 0.0, -9.81)  # m/s², robot base frame with z up
# The gravity features and wrenches of the last commands seen, per robot: the loop builds hundreds of
# problems on the same rows (fits, folds, rounds), and these kinematics are a large part of its time
# when recomputed
_KEPT: "weakref.WeakKeyDictionary[Robot, list]" = weakref.WeakKeyDictionary()
_KEPT_PER_ROBOT = 32


def body_inertials(robot) -> dict[str, tuple[float, np.ndarray]]:
    """``link -> (mass kg, COM (3,) m in the link frame)`` for the links of ``robot``'s tree.

    Parts of the URDF the robot does not model (links beyond the markers, branches no marker
    is on) still weigh on its joints: each such subtree is lumped onto the modelled link it
    hangs from, at its zero configuration, since nobody measured where it was."""
    text = robot.urdf_text
    if not text:
        return {}
    # each effect built on the robot asks again, and parsing the URDF each time cost a tenth of a
    # small loop: the answer depends only on the text and the modelled links, so it is kept
    kept = _inertials_of(text, tuple(robot.link_frame))
    return {k: (m, com.copy()) for k, (m, com) in kept.items()}


@lru_cache(maxsize=8)
def _inertials_of(text: str, modelled: tuple[str, ...]) -> dict[str, tuple[float, np.ndarray]]:
    inert = read_inertials(text)
    _, joints, _ = load_joints(text)
    kids: dict[str, list] = {}
    for jt in joints:
        kids.setdefault(jt.parent, []).append(jt)
    # modelled is in frame order: sums are the same in every process
    out: dict[str, list] = {}

    def add(link: str, m: float, com: np.ndarray) -> None:
        if link in out:
            m0, c0 = out[link]
            out[link] = [m0 + m, (m0 * c0 + m * com) / (m0 + m)]
        else:
            out[link] = [m, com]

    def lump(link: str, T: np.ndarray, into: str) -> None:
        if link in inert:
            add(into, inert[link]["mass"], T[:3, :3] @ inert[link]["com"] + T[:3, 3])
        for jt in kids.get(link, []):
            lump(jt.child, T @ jt.origin, into)

    for link in modelled:
        if link in inert:
            add(link, inert[link]["mass"], np.asarray(inert[link]["com"], dtype=float))
        for jt in kids.get(link, []):
            if jt.child not in modelled:
                lump(jt.child, jt.origin, link)
    return {k: (float(v[0]), np.asarray(v[1], dtype=float)) for k, v in out.items() if v[0] > 0}


@dataclass
class Frames:
    """Frames of a robot over ``N`` configurations, in the robot base frame: the base, then each
    of ``robot.joints``' frames after its motion (= its child link's frame).

    Attributes:
        names: ``"base"`` then joint names.
        R: ``(N, F, 3, 3)`` rotations; ``o``: ``(N, F, 3)`` origins (m).
        markers: ``(N, M, 3)`` marker positions (m); ``beyond``: ``(F, M)`` bool, the marker moves
            with the frame (lies on the frame's link or beyond it).
    """

    names: list[str]
    R: Tensor
    o: Tensor
    markers: Tensor
    beyond: Tensor


@dataclass
class Wrenches(Frames):
    """:class:`Frames` with the gravity wrench at each frame, in that frame's own axes.

    Attributes:
        urdf: ``(N, F, 6)`` force (N) then moment (N·m) from the URDF inertials.
        payload: ``(N, F, 6, 4)`` the same per unit payload mass moment ``(m kg, m·s kg·m)``.
    """

    urdf: Tensor = None
    payload: Tensor = None


def _aux(robot, links: list[str]):
    """A robot with a marker on each of ``links`` (same joints); where each of its parameters sits
    in ``robot``'s parameter vector (-1: a marker parameter of its own); and the columns of
    ``robot``'s ``q`` in its own joint order (a tree's joints may come in another order)."""
    aux = Robot(robot.name, robot.joints, [Marker(f"__g{i}", l) for i, l in enumerate(links)], dtype=robot.dtype,
                device=robot.device)
    pos = {n: i for i, n in enumerate(robot.param_names)}
    take = torch.tensor([pos.get(n, -1) for n in aux.param_names], device=robot.device)
    qcols = torch.tensor([robot.joint_names.index(n) for n in aux.joint_names], device=robot.device)
    return aux, take, qcols


def _robot_geometry(robot, geometry) -> Tensor | None:
    """Joint geometry without the instrument registration: gravity is -z in the robot base
    frame, whatever frame the instrument measures in."""
    if geometry is None:
        return None
    g = torch.as_tensor(geometry, dtype=robot.dtype, device=robot.device).clone()
    g[:6] = 0
    return g


def kinematic_frames(robot, q: Tensor, geometry: Tensor | None = None) -> Frames:
    """The base and every joint frame of ``robot`` at commands ``q (N, dof)`` with ``geometry``
    (``(K,)`` robot parameters; the base frame part is ignored), and the markers."""
    links = [robot.root] + [jt.child for jt in robot.joints]
    aux, take, qcols = _aux(robot, links)
    g = torch.zeros(aux.n_params, dtype=robot.dtype, device=robot.device)
    geo = _robot_geometry(robot, geometry)
    if geo is not None:
        g = torch.where(take >= 0, geo[take.clamp(min=0)], g)
    R, o = aux.fk_rt(q[:, qcols], g, check=False)  # (N, F, 3, 3), (N, F, 3)
    pm = robot.positions(q, geo, check=False, base=False)
    mk_frame = [robot.link_frame[mk.link] for mk in robot.markers]
    beyond = torch.stack([_beyond(robot, f, mk_frame) for f in range(len(links))])
    return Frames(["base"] + [jt.name for jt in robot.joints], R, o, pm, beyond)


def frames_beyond(robot) -> Tensor:
    """``(F, F)`` bool: frame ``j`` lies at or beyond frame ``i`` (frames as in :class:`Frames`)."""
    F = len(robot.joints) + 1
    out = torch.zeros(F, F, dtype=torch.bool, device=robot.device)
    for j in range(F):
        f = j
        while True:
            out[f, j] = True
            if f == 0:
                break
            f = robot.parent_frame[f - 1]
    return out


def gravity_wrenches(robot, q: Tensor, geometry: Tensor | None = None, *, payload_link: str | None = None,
                     gravity=GRAVITY, inertials: dict | None = None) -> Wrenches:
    """Gravity wrenches at the base and at every joint of ``robot`` for commands ``q (N, dof)``.

    Args:
        geometry: ``(K,)`` robot parameters (joint offsets and origin errors) the frames are
            computed at; the base frame (instrument registration) is ignored. Default nominal.
        payload_link: the link an unknown payload hangs on (default: the first marker's link).
        inertials: ``link -> (mass, com)``; default :func:`body_inertials` of the URDF.

    Results are kept per robot (:func:`_kept`) and returned again for equal arguments.
    """
    inert = body_inertials(robot) if inertials is None else inertials
    key = ("wrenches", payload_link, tuple(float(v) for v in gravity),
           tuple(sorted((k, float(m), tuple(float(c) for c in com)) for k, (m, com) in inert.items())))
    geo = None if geometry is None else torch.as_tensor(geometry, dtype=robot.dtype, device=robot.device)
    return _kept(robot, key, (q, geo), lambda: _gravity_wrenches(robot, q, geo, payload_link, gravity, inert))


def _gravity_wrenches(robot, q: Tensor, geometry: Tensor | None, payload_link: str | None, gravity,
                      inert: dict) -> Wrenches:
    dt = dict(dtype=robot.dtype, device=robot.device)
    payload_link = payload_link or robot.markers[0].link
    fr = kinematic_frames(robot, q, geometry)
    R, o = fr.R, fr.o
    N, nF = q.shape[0], R.shape[1]
    inside = frames_beyond(robot).to(robot.dtype)  # (F, F): body frame j counts at frame i
    gv = torch.tensor(gravity, **dt)
    # URDF bodies: F = Σ m g, M = Σ (c − o_f) × m g
    F_u = torch.zeros(N, nF, 3, **dt)
    M_u = torch.zeros(N, nF, 3, **dt)
    for link, (m, com) in inert.items():
        j = robot.link_frame.get(link)
        if j is None:
            continue
        c = o[:, j] + R[:, j] @ torch.as_tensor(com, **dt)  # (N, 3)
        w = inside[:, j][None, :, None]
        F_u = F_u + w * (m * gv)
        M_u = M_u + w * torch.linalg.cross(c[:, None] - o, (m * gv).expand(N, nF, 3))
    # payload basis: column 0 per kg at the link origin, columns 1-3 per kg·m of first moment
    jp = robot.link_frame[payload_link]
    wp = inside[:, jp][None, :, None]
    F_p = torch.zeros(N, nF, 3, 4, **dt)
    F_p[..., 0] = wp * gv
    M_p = torch.zeros(N, nF, 3, 4, **dt)
    M_p[..., 0] = wp * torch.linalg.cross(o[:, jp, None] - o, gv.expand(N, nF, 3))
    for a in range(3):
        M_p[..., a + 1] = wp * torch.linalg.cross(R[:, jp, :, a], gv.expand(N, 3))[:, None]
    RT = R.transpose(-1, -2)  # into each frame's own axes
    urdf = torch.cat([RT @ F_u[..., None], RT @ M_u[..., None]], -2)[..., 0]
    payload = torch.cat([RT @ F_p, RT @ M_p], -2)
    return Wrenches(fr.names, R, o, fr.markers, fr.beyond, urdf, payload)


def _beyond(robot, frame: int, mk_frame: list[int]) -> Tensor:
    """``(M,)`` bool: markers whose link lies at or beyond ``frame``."""
    out = []
    for f in mk_frame:
        hit = False
        while True:
            if f == frame:
                hit = True
                break
            if f == 0:
                break
            f = robot.parent_frame[f - 1]
        out.append(hit)
    return torch.tensor(out, dtype=torch.bool, device=robot.device)


def gravity_features(robot, q: Tensor, links: list[str], gravity=GRAVITY) -> Tensor:
    """``(N, L, dof, 4)`` features: torque (N·m) on each actuated joint from a unit mass at each
    link's origin (feature 0) and from a unit first moment along the link's x, y, z (features 1–3,
    N·m per kg·m). Prismatic joints get the force along their axis (N) in feature 0. Results are
    kept per robot (:func:`_kept`) and returned again for equal commands."""
    return _kept(robot, ("features", tuple(links), tuple(float(v) for v in gravity)), (q,),
                 lambda: _gravity_features(robot, q, links, gravity))


def _kept(robot, key: tuple, tensors: tuple, compute):
    """``compute()``, or the result kept from an earlier call with an equal ``key`` and equal
    ``tensors`` (None or tensors) for ``robot`` (the last :data:`_KEPT_PER_ROBOT`). Nothing that
    carries an autograd graph is kept: a later call must not share this call's graph."""
    if any(t is not None and t.requires_grad for t in tensors):
        return compute()
    seen = _KEPT.setdefault(robot, [])
    for k, ts, out in seen:
        if k == key and all(_same(a, b) for a, b in zip(ts, tensors)):
            return out
    out = compute()
    seen.append((key, tuple(None if t is None else t.detach().clone() for t in tensors), out))
    del seen[:-_KEPT_PER_ROBOT]
    return out


def _same(a: Tensor | None, b: Tensor | None) -> bool:
    if a is None or b is None:
        return a is b
    return a.shape == b.shape and a.device == b.device and a.dtype == b.dtype and torch.equal(a, b)


def _gravity_features(robot, q: Tensor, links: list[str], gravity) -> Tensor:
    aux, _, qcols = _aux(robot, links)
    cols = [aux.joint_names.index(n) for n in robot.joint_names]
    J = aux.joint_jacobian(q[:, qcols], check=False)[..., cols]  # (N, L, 6, dof)
    R, _ = aux.fk_rt(q[:, qcols], check=False)  # (N, L, 3, 3)
    g = torch.tensor(gravity, dtype=robot.dtype, device=robot.device)
    f0 = torch.einsum("i,nlij->nlj", g, J[..., :3, :])  # gᵀ J_v
    gx = torch.linalg.cross(g.expand_as(J[..., 3:, :].transpose(-1, -2)), J[..., 3:, :].transpose(-1, -2))  # (N,L,dof,3)
    f1 = torch.einsum("nlij,nlki->nlkj", R, gx)  # Rᵀ (g × ω_j)
    return torch.cat([f0[..., None], f1], -1)


def load_values(loads: list[str], covariates: dict, q: Tensor) -> list[Tensor]:
    """Each logged load's value per row ``(N,)``: its column (a payload in kg, a level's 0/1
    indicator ``<column>=<level>``), or ``<column>~<shape>`` that shape of it (a step of the row
    order or of time: a payload changed where a set-up change was found)."""
    missing = [c for c in dict.fromkeys(c.split("~", 1)[0] for c in loads) if c not in covariates]
    if missing:
        raise ValueError(f"the load per row needs the covariate(s) {missing}: pass them with the commands")
    out = []
    for c in loads:
        col, _, tag = c.partition("~")
        x = covariates[col].to(q)
        # a level's 0/1 column reads NaN where the text was not recorded: the first level's load then
        out.append(shape_column(tag, x, 0.0, 1.0) if tag else torch.nan_to_num(x, nan=0.0) if LEVEL_SEP in c else x)
    return out


def row_payload(payload, loads: dict | None, covariates: dict | None, q: Tensor) -> Tensor:
    """The payload's mass moments ``(m kg, m·sx, m·sy, m·sz kg·m)``: ``(4,)`` the constant ``payload``,
    or ``(N, 4)`` per row ``μ + Σ_c L_c ν_c`` with the loads ``{load: ν_c (4,)}`` logged row by row
    (:func:`load_values` of ``covariates``)."""
    mu = torch.as_tensor(payload, dtype=q.dtype, device=q.device)
    if not loads:
        return mu
    nu = torch.tensor(list(loads.values()), dtype=q.dtype, device=q.device)  # (loads, 4)
    L = torch.stack(load_values(list(loads), covariates or {}, q), 1)  # (N, loads)
    return mu + L @ nu
