"""A compact position-only forward-kinematics path for population fitness calls.

Swarm solvers call the fitness with a population ``(P, k)`` of free-parameter vectors every
iteration, on the same joint values. :meth:`Robot.positions` is general but spends most of a
small call on work that does not depend on ``P``: about a hundred tensor operations, each with a
fixed dispatch cost. :class:`PositionKernel` is built once for fixed joint values and a fixed set
of free parameters, precomputes everything that does not depend on the free values, and leaves
per call a short sequence of operations whose work is proportional to ``P``:

* the free values enter every slot (DH values, offsets, marker points, base) through one
  ``addmm`` with a 0/1 scatter matrix each (exact: every output is one input plus zeros);
* every entry of a DH origin is a product of two of ten per-joint values whose trigonometric
  ones all come from one cosine call (``sin x = cos(x - π/2)``), so the origins of all DH joints
  are one ``cos``, one ``gather`` and one product; a free zero offset of a revolute DH joint is
  folded into the origin's ``φ`` (``Rz(φ) Rz(δ + q) = Rz(φ + δ) Rz(q)``);
* a revolute joint turns about its (aligned) z axis, so the per-pose rotation ``Rz(q)`` is one
  complex multiplication of the ``x + iy`` pairs by ``exp(iq)``, precomputed per pose, and the
  origin is one batched matrix product on homogeneous points;
* origins, offsets, markers and the base that no free parameter moves are constants, built once.

The result equals :meth:`Robot.positions` to rounding (the tests check 1e-12 m). Work buffers
are kept between calls and grown only when ``P`` exceeds every earlier call, so a shrinking
population (LDPSO-BT) never allocates them again.
"""
from __future__ import annotations

import math

import torch
from torch import Tensor

from torchcal.kinematics.transforms import rpy_to_matrix, so3_exp

__all__ = ["PositionKernel"]

# DH values per joint, ten rows of a (10, Jd) block: the cosines of rows 0-6 give
# cos α, sin α, -sin α, 1, cos φ, sin φ, -sin φ (sin x = cos(x - π/2), -sin x = cos(x + π/2),
# 1 = cos 0); rows 7-9 stay a, d, 0.
_N_COS = 7
_SHIFT = (0.0, -math.pi / 2, math.pi / 2)
# Every entry of a DH origin A (torchcal.kinematics.tree.DHOrigin: rotation Rx(α) Rz(φ), translation
# (a, 0, d) classic or (a, -d sin α, d cos α) modified) is a product of two of those rows:
# A[r][c] -> (row, row). Entries not listed are 0 * 1.
_PAIRS = {(0, 0): (4, 3), (0, 1): (6, 3), (0, 3): (7, 3), (1, 0): (0, 5), (1, 1): (0, 4), (1, 2): (2, 3),
          (2, 0): (1, 5), (2, 1): (1, 4), (2, 2): (0, 3), (3, 3): (3, 3)}
_PAIRS_T = {"classic": {(2, 3): (8, 3)}, "modified": {(1, 3): (8, 2), (2, 3): (8, 0)}}


def _dh_pairs(conventions: list[str], device) -> Tensor:
    """``(32, Jd)`` row indices: ``A^T`` flattened (entry ``4 c + r`` is ``A[r][c]``) is the
    product of rows ``[:16]`` and ``[16:]``."""
    out = torch.empty(32, len(conventions), dtype=torch.long, device=device)
    for j, conv in enumerate(conventions):
        pairs = {**_PAIRS, **_PAIRS_T[conv]}
        for c in range(4):
            for r in range(4):
                i1, i2 = pairs.get((r, c), (9, 3))
                out[4 * c + r, j], out[16 + 4 * c + r, j] = i1, i2
    return out


def _hom_T(R: Tensor, t: Tensor) -> Tensor:
    """``(..., 3, 3), (..., 3) -> (..., 4, 4)`` transposed homogeneous matrix ``[[R^T, 0], [t, 1]]``:
    a row vector ``[x y z 1]`` times it is ``(R v + t, 1)``."""
    top = torch.cat([R.transpose(-1, -2), torch.zeros_like(R[..., :1])], -1)
    bottom = torch.cat([t, torch.ones_like(t[..., :1])], -1)[..., None, :]
    return torch.cat([top, bottom], -2)


class PositionKernel:
    """Marker positions ``(P, n_obs, 3)`` (m) for one set of joint values and one free set.

    Args:
        robot: the :class:`~torchcal.kinematics.robot.Robot`.
        q: ``(N, dof)`` joint values (rad / m).
        values: ``(K,)`` full parameter vector; its entries outside ``free_index`` are the fixed
            values (read once, here).
        free_index: ``(k,)`` indices of the free parameters, the columns of a call's ``x``.
        rows, cols: ``(n_obs,)`` pose row and robot marker index of each observation; ``None``
            for every marker in every pose (``n_obs = N M``, pose-major).
        base: include the base frame (instrument frame), as ``Robot.positions(base=True)``.

    Call with ``x (P, k)``. The returned tensor may share memory with the work buffers and is
    valid until the next call (clone it to keep it).
    """

    def __init__(self, robot, q: Tensor, values: Tensor, free_index: Tensor, rows: Tensor | None = None,
                 cols: Tensor | None = None, base: bool = True):
        dt = dict(dtype=robot.dtype, device=robot.device)
        self.robot = r = robot
        self.layout = lay = robot.layout()
        q = robot.check_q(q)
        free_index = torch.as_tensor(free_index, device=r.device).long()
        self.N, self.k, self.J = int(q.shape[0]), int(free_index.numel()), len(r.joints)
        fixed = torch.as_tensor(values, **dt).clone()
        fixed[free_index] = 0
        slots0 = lay.slots(fixed[None])[0]  # fixed values per slot, 0 where a free value goes
        E = torch.zeros(self.k, r.n_slots, **dt)  # free value -> the slots it fills
        for i, p in enumerate(free_index.tolist()):
            E[i, lay.slot_gather == p] = 1

        def group(name: str) -> tuple[Tensor, Tensor, bool]:
            sl = lay.slices[name]
            return slots0[sl], E[:, sl].contiguous(), bool(E[:, sl].any())

        Eo_j, dh_rev = self._joint_values(q, group)
        dh_c = self._dh_origins(group, Eo_j, dh_rev)
        urdf_c = self._urdf_origins(group)
        self._dh_c, self._urdf_c = dh_c, urdf_c
        self._AT_c = None
        if self._dh is None and self._urdf is None:
            self._AT_c = self._origins_T(dh_c, urdf_c).unbind(1)
        self._marker_points(group)
        self._base_c = self._base = None
        if base:
            b0, Eb, b_var = group("base")
            if b_var:
                self._base = (b0, Eb)
            elif bool(b0.any()):
                self._base_c = _hom_T(so3_exp(b0[3:]), b0[:3])
        self._chains(rows, cols)
        self._cap = 0
        self._views: dict[int, tuple] = {}

    # ------------------------------------------------------------------ what a call needs, built once
    def _joint_values(self, q: Tensor, group) -> tuple[Tensor, Tensor]:
        """``exp(i q)`` per pose and joint, the prismatic travel, and the map of free offsets that
        stay per pose; free offsets of revolute DH joints go into φ instead. Returns the map of
        free values to joint values ``(k, J)`` and which DH joints are revolute."""
        r, lay = self.robot, self.layout
        o0, Eo, _ = group("offset")
        Eo_j = Eo @ lay.Mmap.T  # (k, J) free value -> joint angle / travel
        qj0 = (q + o0) @ lay.Mmap.T + lay.moff  # (N, J) with the fixed offsets
        dh_rev = torch.tensor([lay.kinds[j] == 1 for j in lay.dh_idx], device=r.device)
        per_pose = torch.ones(self.J, device=r.device, **{"dtype": r.dtype})
        per_pose[[j for j, v in zip(lay.dh_idx, dh_rev.tolist()) if v]] = 0
        self._off = (Eo_j * per_pose) if bool((Eo_j * per_pose).any()) else None
        self._th = qj0  # prismatic travel per pose
        self._Eq = torch.polar(torch.ones_like(qj0), qj0)  # (N, J)
        self._rot = list(self._Eq.T.contiguous())  # per joint (N,) complex
        self._any_pri = 2 in lay.kinds
        return Eo_j, dh_rev

    def _dh_origins(self, group, Eo_j: Tensor, dh_rev: Tensor) -> Tensor | None:
        """DH origins from a ``(10, Jd)`` block of values per parameter vector (see ``_N_COS``): kept
        as ``self._dh`` when a free value moves them, else returned as constants ``(1, Jd, 4, 4)``."""
        r, lay = self.robot, self.layout
        dt = dict(dtype=r.dtype, device=r.device)
        self._dh = None
        if not lay.dh_idx:
            return None
        Jd = len(lay.dh_idx)
        d0, Ed, _ = group("dh")
        v0 = (lay.dh_nom.reshape(-1) + d0).reshape(Jd, 4)  # a, d, α, φ
        Ed = Ed.reshape(self.k, Jd, 4)
        Ephi = Ed[..., 3] + Eo_j[:, lay.dh_idx] * dh_rev
        al, ph, zero = v0[:, 2], v0[:, 3], torch.zeros(Jd, **dt)
        w0 = torch.stack([al + _SHIFT[0], al + _SHIFT[1], al + _SHIFT[2], zero, ph + _SHIFT[0],
                          ph + _SHIFT[1], ph + _SHIFT[2], v0[:, 0], v0[:, 1], zero]).reshape(-1)
        Z = torch.zeros_like(Ephi)
        Ew = torch.stack([Ed[..., 2]] * 3 + [Z] + [Ephi] * 3 + [Ed[..., 0], Ed[..., 1], Z], 1).reshape(self.k, -1)
        pairs = _dh_pairs([r.joints[j].dh.convention for j in lay.dh_idx], r.device)
        if bool(Ew.any()):
            self._dh = (w0, Ew.contiguous(), pairs)
            return None
        return self._dh_T(w0[None].clone(), pairs).transpose(1, 2).unflatten(-1, (4, 4))

    def _urdf_origins(self, group) -> Tensor | None:
        """URDF origins: kept as ``self._urdf`` when a free value moves them, else returned as
        constants. Also the alignment matrices the origins are wrapped in when axes are not z."""
        lay = self.layout
        dt = dict(dtype=self.robot.dtype, device=self.robot.device)
        # the DH origins go straight into a work buffer unless other joints must be merged in
        self._dh_direct = self._dh is not None and not lay.urdf_idx
        self._urdf = urdf_c = None
        if lay.urdf_idx:
            u0, Eu, u_var = group("urdf")
            if u_var:
                self._urdf = (u0, Eu)
            else:
                urdf_c = self._urdf_T(u0.reshape(1, -1, 6))
        if not lay.aligned:
            # A_aligned = diag(Cp^T, 1) A diag(C, 1), so A_aligned^T = diag(C^T, 1) A^T diag(Cp, 1)
            self._left_C = torch.eye(4, **dt).repeat(self.J, 1, 1)
            self._left_C[:, :3, :3] = lay.C.transpose(-1, -2)
            self._right_C = torch.eye(4, **dt).repeat(self.J, 1, 1)
            self._right_C[:, :3, :3] = lay.CpT.transpose(-1, -2)
        return urdf_c

    def _marker_points(self, group) -> None:
        """Homogeneous marker points on their links ``(M, 4)``: only the point matters for
        positions, and it is linear in its offsets."""
        lay = self.layout
        dt = dict(dtype=self.robot.dtype, device=self.robot.device)
        m0, Em, mk_var = group("marker")
        M = len(self.robot.markers)
        CmT = lay.CmT if not lay.aligned else torch.eye(3, **dt).expand(M, 3, 3)
        mt0 = lay.mk_t + (lay.mk_R @ m0.reshape(M, 6)[:, :3, None])[..., 0]
        self._mk0 = torch.cat([(CmT @ mt0[..., None])[..., 0], torch.ones(M, 1, **dt)], -1)  # (M, 4)
        self._mk = None
        if mk_var:
            Em3 = torch.einsum("kmj,mij->kmi", Em.reshape(self.k, M, 6)[..., :3], CmT @ lay.mk_R)
            self._mk = (self._mk0.reshape(-1), torch.cat([Em3, torch.zeros(self.k, M, 1, **dt)], -1).reshape(self.k, -1))

    def _chains(self, rows: Tensor | None, cols: Tensor | None) -> None:
        """Per marker, the joints from its link up to the root; and which (pose, marker) pairs a
        call returns."""
        r = self.robot
        M = len(r.markers)
        self._paths = []
        for f in self.layout.mk_frame:
            path = []
            while f != 0:
                path.append(f - 1)
                f = r.parent_frame[f - 1]
            self._paths.append(path)
        self._gather = None
        self.n_obs = self.N * M
        if rows is not None:
            rows = torch.as_tensor(rows, device=r.device).long()
            cols = torch.as_tensor(cols, device=r.device).long()
            self.n_obs = int(rows.numel())
            if not (M == 1 and torch.equal(rows, torch.arange(self.N, device=r.device))):
                self._gather = (rows, cols)

    # ------------------------------------------------------------------ origins
    @staticmethod
    def _dh_T(W: Tensor, pairs: Tensor, out: Tensor | None = None) -> Tensor:
        """``(P, 10 Jd)`` DH values (see ``_N_COS``; overwritten) -> ``(P, 16, Jd)`` transposed
        origins, flattened (written into ``out`` when given)."""
        P = W.shape[0]
        W[:, : _N_COS * pairs.shape[1]].cos_()
        g = torch.gather(W.view(P, -1, pairs.shape[1]), 1, pairs.expand(P, -1, -1))
        return torch.mul(g[:, :16], g[:, 16:], out=out)

    def _urdf_T(self, e: Tensor) -> Tensor:
        lay = self.layout
        R = lay.U_R @ rpy_to_matrix(e[..., 3:])
        t = lay.U_t + (lay.U_R @ e[..., :3, None])[..., 0]
        return _hom_T(R, t)

    def _origins_T(self, dh_T: Tensor | None, urdf_T: Tensor | None) -> Tensor:
        """``(P|1, J, 4, 4)`` transposed origins in the axis-aligned frames the chain works in."""
        lay = self.layout
        parts = [t for t in (urdf_T, dh_T) if t is not None]
        if len(parts) == 2:
            P = max(parts[0].shape[0], parts[1].shape[0])
            parts = [t.expand(P, -1, -1, -1) for t in parts]
        AT = parts[0] if len(parts) == 1 else torch.cat(parts, 1)
        if lay.perm is not None:
            AT = AT[:, lay.perm]
        if not lay.aligned:
            AT = self._left_C @ AT @ self._right_C
        return AT

    def _origins(self, x: Tensor, work: tuple) -> tuple:
        """Per joint ``(P|1, 4, 4)`` transposed origins for ``x (P, k)``."""
        if self._AT_c is not None:
            return self._AT_c
        if self._dh_direct:
            w0, Ew, pairs = self._dh
            self._dh_T(torch.addmm(w0, x, Ew), pairs, out=work[2])
            return work[3]
        dh_T = self._dh_c
        if self._dh is not None:
            w0, Ew, pairs = self._dh
            dh_T = self._dh_T(torch.addmm(w0, x, Ew), pairs).transpose(1, 2).unflatten(-1, (4, 4))
        urdf_T = self._urdf_c
        if self._urdf is not None:
            urdf_T = self._urdf_T(torch.addmm(self._urdf[0], x, self._urdf[1]).unflatten(-1, (-1, 6)))
        return self._origins_T(dh_T, urdf_T).unbind(1)

    # ------------------------------------------------------------------ buffers
    def _work(self, P: int) -> tuple:
        """Views of buffers sized for the largest population seen: two ``(P, N, 4)`` point
        buffers with their ``(P, N)`` complex ``x + iy`` views and ``(P N, 4)`` flat views; the
        DH origins ``(P, 16, Jd)`` as written and as per-joint ``(P, 4, 4)`` matrices."""
        v = self._views.get(P)
        if v is None:
            Jd = len(self.layout.dh_idx)
            if P > self._cap:
                dt = dict(dtype=self.robot.dtype, device=self.robot.device)
                self._bufs = ([torch.empty(P, self.N, 4, **dt) for _ in range(2)], torch.empty(P, Jd, 16, **dt))
                self._cap, self._views = P, {}
            pts = []
            for b in self._bufs[0]:
                h = b[:P]
                pts.append((h, torch.view_as_complex(h.view(P, self.N, 2, 2))[..., 0], h.view(P * self.N, 4)))
            A = self._bufs[1][:P]
            v = self._views[P] = (pts[0], pts[1], A.transpose(1, 2), tuple(a.view(P, 4, 4) for a in A.unbind(1)))
        return v

    # ------------------------------------------------------------------ the call
    def __call__(self, x: Tensor) -> Tensor:
        """``x (P, k)`` free values -> ``(P, n_obs, 3)`` positions (m)."""
        P = int(x.shape[0])
        work = self._work(P)
        AT = self._origins(x, work)
        BT = self._base_c
        if self._base is not None:
            b = torch.addmm(self._base[0], x, self._base[1])
            BT = _hom_T(so3_exp(b[:, 3:]), b[:, :3])
        rot, th = self._rot, self._th
        if self._off is not None:  # offsets that stay per pose (URDF revolute, prismatic)
            d = x @ self._off  # (P, J)
            rot = (torch.polar(torch.ones_like(d), d)[:, None] * self._Eq).unbind(2)
            if self._any_pri:
                th = th + d[:, None]
        mk = self._mk0[None]
        if self._mk is not None:
            mk = torch.addmm(self._mk[0], x, self._mk[1]).view(P, -1, 4)
        if len(self._paths) == 1:
            pos = self._chain(P, work, self._paths[0], AT, rot, th, mk[:, 0], BT)[:, :, None]
        else:
            # each chain reuses the work buffers: copy its result out before the next one
            pos = torch.empty(P, self.N, len(self._paths), 3, dtype=x.dtype, device=x.device)
            for m, path in enumerate(self._paths):
                pos[:, :, m] = self._chain(P, work, path, AT, rot, th, mk[:, m], BT)
        if self._gather is None:
            return pos[:, :, 0] if pos.shape[2] == 1 else pos.flatten(1, 2)
        return pos[:, self._gather[0], self._gather[1]]

    def _chain(self, P: int, work: tuple, path: list[int], AT: tuple, rot, th: Tensor, u: Tensor,
               BT: Tensor | None) -> Tensor:
        """Carry the homogeneous marker point ``u (P|1, 4)`` from its link to the base through the
        joints of ``path`` (leaf first), ``v <- A_j M_j(q_j) v``, then the base. ``(P, N, 3)``."""
        kinds = self.layout.kinds
        i = 0
        # fixed joints next to the marker act on one point per parameter vector, not per pose
        while i < len(path) and kinds[path[i]] == 0:
            u = (u[:, None, :] @ AT[path[i]])[:, 0]
            i += 1
        if i == len(path):
            if BT is not None:
                u = (u[:, None, :] @ BT)[:, 0]
            return u[:, None, :3].expand(P, self.N, 3)
        (H, Hc, Hf), (H2, Hc2, Hf2) = work[0], work[1]
        H.copy_(u[:, None, :].expand(P, self.N, 4))
        for j in path[i:]:
            if kinds[j] == 1:
                Hc.mul_(rot[j])
            elif kinds[j] == 2:
                H[..., 2].add_(th[..., j])
            A = AT[j]
            if A.ndim == 2 or A.shape[0] == 1:
                torch.mm(Hf, A.reshape(4, 4), out=Hf2)
            else:
                torch.bmm(H, A, out=H2)
            (H, Hc, Hf), (H2, Hc2, Hf2) = (H2, Hc2, Hf2), (H, Hc, Hf)
        if BT is not None:
            if BT.ndim == 2:
                torch.mm(Hf, BT, out=Hf2)
            else:
                torch.bmm(H, BT, out=H2)
            H = H2
        return H[..., :3]
