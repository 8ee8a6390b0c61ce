"""Analytic Jacobians of a :class:`~torchcal.kinematics.robot.Robot`: by the error parameters
(every parameter moves the chain like a virtual revolute or prismatic joint at a known frame, so
its column is ``axis × (p − point)`` or ``axis``) and by the joints; m per unit of the parameter.
"""
from __future__ import annotations

from types import SimpleNamespace

import torch
from torch import Tensor

from torchcal.kinematics.transforms import rot_y, rot_z, so3_left_jacobian

__all__ = ["Jacobians"]

_KEPT_PLANS = 64  # column plans kept per robot


class Jacobians:
    """The Jacobian half of :class:`~torchcal.kinematics.robot.Robot` (a mixin over its forward
    kinematics and layout)."""

    def param_jacobian(self, q, params=None, *, kind: str = "position", check: bool = True,
                       return_positions: bool = False, joints: bool = False, columns=None,
                       points: Tensor | None = None):
        """Analytic derivative of the marker poses w.r.t. all K parameters (or ``columns`` of them).

        Args:
            kind: ``"position"``: rows are d(p_x, p_y, p_z) (m per unit); ``"pose"``: three more rows,
                the angular velocity ω (rad per unit, instrument frame) with ``dR = skew(ω) R`` —
                the Jacobian of a rotation-vector residual ``log(R R_meas^T)`` at zero.
            return_positions: also return the marker positions ``(…, M, 3)`` (m) computed on the
                way, which saves a second kinematics pass in least-squares solvers.
            joints: also return the Jacobian by the joints ``(…, M, 3|6, dof)`` (as
                :meth:`joint_jacobian`, here with ``kind``'s rows), from the same pass.
            columns: ``c`` parameter indices (a sequence of ints, or a tensor, which is read on the
                host): only their columns, in this order, are computed (a fit of a few of the K
                parameters pays for those few).
            points: each row's marker points moved, as in
                :meth:`~torchcal.kinematics.fk.ForwardKinematics.positions`: every column is then
                taken at the moved points.
        Returns:
            ``(N, M, 3|6, K)`` (``(P, N, M, 3|6, K)`` for a population, or for ``q (P, N, dof)``
            paired with ``params (P, K)`` as in :meth:`positions`; ``c`` columns with ``columns``);
            then the joint Jacobian when ``joints``, then the positions when ``return_positions``.
        """
        if kind not in ("position", "pose"):
            raise ValueError(f"kind must be 'position' or 'pose', got {kind!r}")
        paired = isinstance(q, Tensor) and q.ndim == 3
        q, slots, pop, q1 = (self._prepare_paired if paired else self._prepare)(q, params, check)
        if slots is None:
            slots = self._slots(torch.zeros(1, self.n_params, dtype=self.dtype, device=self.device))
        if columns is not None:
            plan = self.column_plan(columns, joints)
            Jac, pw, Jq = self._slot_jacobian(q, slots, kind, plan, points)  # (P, N, M, r, slots of the columns)
            out = Jac.new_zeros(*Jac.shape[:-1], plan.n_columns)
            out.index_add_(-1, plan.param_pos, Jac)
        else:
            Jac, pw = self._slot_jacobian(q, slots, kind, points=points)  # (P, N, M, r, S)
            # a parameter's column is the sum over the slots it moves
            K = self.n_params
            out = Jac.new_zeros(*Jac.shape[:-1], K + 1)
            out.index_add_(-1, self._slot_gather, Jac)
            out, Jq = out[..., :K], Jac[..., self._slices["offset"]]
        J = self._unbatch(out, pop, q1, 3)
        extra = ((self._unbatch(Jq, pop, q1, 3),) if joints else ()) \
            + ((self._unbatch(pw, pop, q1, 2),) if return_positions else ())
        return (J, *extra) if extra else J

    def column_plan(self, columns, joints: bool = False) -> SimpleNamespace:
        """What :meth:`param_jacobian` computes for the parameter ``columns`` (with ``joints``), laid
        out once per column set and kept: a problem that knows its columns lays it out when it is
        built, so that no solver step waits for it on a GPU.

        Fields: ``v`` the slot columns of :meth:`_slot_columns` they need (their layout ``lay``),
        ``mov`` where the movable joints' columns sit among them and ``Mm`` their map to the offsets
        (every actuated joint when ``joints``), ``take`` each wanted slot's place among ``[base (6),
        the v columns, the offsets]`` and ``param_pos`` its parameter's place among ``columns``."""
        key = (tuple(int(c) for c in (columns.tolist() if isinstance(columns, Tensor) else columns)), joints)
        plan = self._column_plans.get(key)
        if plan is not None:
            return plan
        sl, lay, Jn = self._slices, self._jac_layout, len(self.joints)
        pos = {c: i for i, c in enumerate(key[0])}
        wanted = [(s, pos[p]) for s, p in enumerate(self._slot_gather.tolist()) if p in pos]
        n_orig, o0, m0 = sl["offset"].start - 6, sl["offset"].start, sl["marker"].start
        dofs = list(range(self.dof)) if joints else [s - o0 for s, _ in wanted if o0 <= s < m0]
        Mmap = self._Mmap[:, dofs]
        movj = [j for j in range(Jn) if bool((Mmap[j] != 0).any())]
        v = sorted({s - 6 for s, _ in wanted if 6 <= s < o0} | {n_orig + j for j in movj}
                   | {n_orig + Jn + s - m0 for s, _ in wanted if s >= m0})
        # translations first, then rotations: the columns are then two blocks, each written once
        is_rot = lay.rot_f.tolist()
        v = [c for c in v if not is_rot[c]] + [c for c in v if is_rot[c]]
        n_trans = sum(1 for c in v if not is_rot[c])
        at = {c: i for i, c in enumerate(v)}
        take = []
        for s, _ in wanted:
            take.append(s if s < 6 else 6 + at[s - 6] if s < o0 else 6 + len(v) + dofs.index(s - o0) if s < m0
                        else 6 + at[n_orig + Jn + s - m0])
        ix = lambda x: torch.tensor(x, dtype=torch.long, device=self.device)  # noqa: E731
        vt = ix(v)
        in_ri = {c: i for i, c in enumerate(lay.ri.tolist())}  # a rotational column's place in pidx
        plan = SimpleNamespace(
            v=vt, lay=SimpleNamespace(rot_f=lay.rot_f[vt], n_trans=n_trans, off=lay.off, mask=lay.mask[:, vt],
                                      pidx=lay.pidx[ix([in_ri[c] for c in v[n_trans:]])]),
            mov=ix([at[n_orig + j] for j in movj]), Mm=Mmap[movj], take=ix(take), param_pos=ix([i for _, i in wanted]),
            n_columns=len(key[0]))
        if len(self._column_plans) >= _KEPT_PLANS:  # a loop tries many sets: keep the recent ones
            self._column_plans.pop(next(iter(self._column_plans)))
        self._column_plans[key] = plan
        return plan

    def joint_jacobian(self, q, params=None, *, check: bool = True) -> Tensor:
        """Geometric Jacobian of every marker w.r.t. the commands ``q``: ``(N, M, 6, dof)``
        (rows: linear velocity m/unit, then angular velocity rad/unit, instrument frame)."""
        q, slots, pop, q1 = self._prepare(q, params, check)
        if pop:
            raise ValueError("joint_jacobian takes one parameter vector (K,), not a population")
        if slots is None:
            slots = self._slots(torch.zeros(1, self.n_params, dtype=self.dtype, device=self.device))
        Jac = self._slot_jacobian(q, slots, "pose")[0][..., self._slices["offset"]]
        return self._unbatch(Jac, False, q1, 3)

    @staticmethod
    def _rpy_directions(e: Tensor, R0: Tensor) -> Tensor:
        """``(P, n, 3, 6)``: ``R0 @ [x, y, z, Rz Ry x, Rz y, z]`` for rpy errors ``e (P, n, 6)`` about
        frames ``R0 (n, 3, 3)``: the directions of the three translations and of the roll, pitch and
        yaw rotation axes of an error ``T(xyz) Rz Ry Rx`` (the last three at the error's value)."""
        eye = torch.eye(3, dtype=e.dtype, device=e.device)
        Rz, Ry = rot_z(e[..., 5]), rot_y(e[..., 4])
        roll = Rz @ (Ry @ eye[:, 0])[..., None]
        pitch = Rz @ eye[:, 1:2]
        I3 = eye.expand(*e.shape[:-1], 3, 3)
        return R0 @ torch.cat([I3, roll, pitch, I3[..., 2:3]], -1)

    @staticmethod
    def _turn(R: Tensor, D: Tensor) -> Tensor:
        """``R (P, N, n, 3, 3)`` frames times ``D (P, n, 3, k)`` directions given in them, laid out
        ``(P, 3, N, n·k)``. One ``(N·3, 3) @ (3, k)`` product per parameter vector and frame: the
        same product as ``R @ D[:, None]`` without ``P·N·n`` tiny 3 x 3 ones."""
        P, N, n = R.shape[:3]
        k = D.shape[-1]
        D = D.expand(P, n, 3, k)
        out = torch.bmm(R.permute(0, 2, 1, 3, 4).reshape(P * n, N * 3, 3), D.reshape(P * n, 3, k))
        return out.reshape(P, n, N, 3, k).permute(0, 3, 2, 1, 4).reshape(P, 3, N, n * k)

    def _jacobian_layout(self) -> SimpleNamespace:
        """What the slot columns of :meth:`_slot_jacobian` take from the robot's structure alone,
        built once (:meth:`Robot._build`) so that a Jacobian copies no index list to the device:
        ``rot_f (V,)`` 1 for the columns that are rotations (in the robot's dtype), ``ri`` their
        indices, ``pidx`` the point each turns about (joint origins ``J``, DH parent origins ``J``,
        then markers ``M``), ``off`` where the markers start among those points, ``mask (M, V)``
        which columns move which marker. Columns: URDF origins (6 each), DH rows (4 each), joint
        offsets (J), markers (6 each). Also the frame indices the Jacobian gathers, as device
        tensors (a Python list as an index is copied to the device at every call): ``parent_urdf``
        (parent frame of each URDF joint), ``parent`` (of every joint), ``dh`` (the DH joints),
        ``mk_frame`` (each marker's frame)."""
        Jn, M, anc = len(self.joints), len(self.markers), self._anc
        is_rot, pidx, masks = [], [], []
        if self._urdf_idx:
            U = self._urdf_idx
            is_rot += [False, False, False, True, True, True] * len(U)
            pidx += [j for j in U for _ in range(3)]
            masks.append(anc[U].repeat_interleave(6, 0))
        if self._dh_idx:
            D = self._dh_idx
            is_rot += [False, False, True, True] * len(D)
            for j, c in zip(D, self._dh_classic.tolist()):
                pidx += [j if c else Jn + j, j]
            masks.append(anc[D].repeat_interleave(4, 0))
        rev = self._is_rev.tolist()
        is_rot += rev
        pidx += [j for j, r in enumerate(rev) if r]
        masks.append(anc)
        off = Jn * (2 if self._dh_idx else 1)
        is_rot += [False, False, False, True, True, True] * M
        pidx += [off + m for m in range(M) for _ in range(3)]
        masks.append(torch.eye(M, dtype=torch.bool, device=self.device).repeat_interleave(6, 0))
        rot = torch.tensor(is_rot, device=self.device)
        ix = lambda v: torch.tensor(v, dtype=torch.long, device=self.device)  # noqa: E731
        return SimpleNamespace(parent_urdf=ix([self.parent_frame[j] for j in self._urdf_idx]),
                               parent=ix(self.parent_frame), dh=ix(self._dh_idx), mk_frame=ix(self._mk_frame),
                               rot_f=rot.to(self.dtype), ri=torch.nonzero(rot).flatten(),
                               pidx=torch.tensor(pidx, dtype=torch.long, device=self.device), off=off,
                               mask=torch.cat(masks, 0).to(self.dtype).T)

    def _slot_jacobian(self, q: Tensor, slots: Tensor, kind: str, plan: SimpleNamespace | None = None,
                       points: Tensor | None = None):
        """Derivatives of the marker poses by every slot: ``(P, N, M, r, S)`` (``r`` 3 rows for
        ``kind="position"``, 6 for ``"pose"``), and the marker positions ``(P, N, M, 3)`` (m,
        instrument frame). With a :meth:`column_plan`, by its slots only, then also the joint
        Jacobian ``(P, N, M, r, dof)`` (None unless the plan has every joint)."""
        Rs, ts, JR, Jt = self._chain(q, slots, keep_joint_frames=True)
        mR, mt = self._marker_frames(Rs, ts, slots, self._point_shift(points))  # robot-base frame, (P, N, M, ...)
        axes, pts = self._slot_axes(slots, Rs, ts, JR, Jt, mt)
        Jv, mw, m_inst = self._slot_columns(slots, axes, pts, kind, plan)  # (P, r, N, M, V)
        if plan is not None:
            J_off = Jv[..., plan.mov] @ plan.Mm  # (P, r, N, M, offsets)
            Jac = torch.cat([self._base_columns(slots, mw, Jv, kind), Jv, J_off], -1)[..., plan.take]
            Jq = J_off.permute(0, 2, 3, 1, 4) if plan.Mm.shape[1] == self.dof else None
            return Jac.permute(0, 2, 3, 1, 4), m_inst.permute(0, 2, 3, 1), Jq
        # split back into slot groups; offsets per movable joint -> per actuated joint
        Jn = len(self.joints)
        nu, nd = 6 * len(self._urdf_idx), 4 * len(self._dh_idx)
        J_orig = Jv[..., : nu + nd]
        J_mov = Jv[..., nu + nd: nu + nd + Jn] @ self._Mmap  # (P, r, N, M, dof)
        J_mk = Jv[..., nu + nd + Jn:]
        base = self._base_columns(slots, mw, Jv, kind)
        Jac = torch.cat([base, J_orig, J_mov, J_mk], -1)  # (P, r, N, M, S)
        return Jac.permute(0, 2, 3, 1, 4), m_inst.permute(0, 2, 3, 1)  # (P, N, M, r, S), (P, N, M, 3)

    def _slot_axes(self, slots: Tensor, Rs: list, ts: list, JR: list, Jt: list, mt: Tensor
                   ) -> tuple[list[Tensor], list[Tensor]]:
        """The axis (rotations) or direction (translations) of every non-base slot, in the robot-base
        frame, as ``(P, 3, N, n)`` blocks (URDF origins, DH rows, zero offsets per movable joint,
        markers); and the points the rotational ones turn about, as ``(P, N, n, 3)`` blocks (joint
        origins, DH parent origins, markers)."""
        P, N = mt.shape[0], mt.shape[1]
        dt = dict(dtype=self.dtype, device=self.device)
        eye = torch.eye(3, **dt)
        # internal (axis-aligned) frames; root = identity. The URDF frame is RFi·Cᵀ: the Cᵀ is folded
        # into the small per-parameter-vector direction matrices, not into every pose's frames
        RFi = torch.stack([eye.expand(P, N, 3, 3) if R is None else R.expand(P, N, 3, 3) for R in Rs], 2)
        RJ = torch.stack([x.expand(P, N, 3, 3) for x in JR], 2)  # internal (aligned) joint frames
        CJ = None if self._aligned else self._CfT[1:]
        pts = [torch.stack([x.expand(P, N, 3) for x in Jt], 2)]
        axes = []
        if self._urdf_idx:
            pU = self._jac_layout.parent_urdf
            e = slots[:, self._slices["urdf"]].reshape(P, -1, 6)
            # x, y, z, roll, pitch, yaw directions of each origin frame F0 = RP·U_R: F0 times
            # small per-parameter-vector matrices, so one batched product per pose
            B = self._rpy_directions(e, self._U_R)  # (P, U, 3, 6), URDF parent frames
            if not self._aligned:
                B = self._CfT[pU] @ B
            axes.append(self._turn(RFi[:, :, pU], B))
        if self._dh_idx:
            D, parent = self._jac_layout.dh, self._jac_layout.parent
            RP = RFi[:, :, parent] if self._aligned else RFi[:, :, parent] @ self._CpT
            pts.append(torch.stack([torch.zeros(P, N, 3, **dt) if ts[f] is None else ts[f].expand(P, N, 3)
                                    for f in self.parent_frame], 2))
            RJ_urdf = RJ if CJ is None else RJ @ CJ
            Rp, Rj = RP[:, :, D], RJ_urdf[:, :, D]
            cls = self._dh_classic[:, None]
            x_p, z_p, z_j = Rp[..., 0], Rp[..., 2], Rj[..., 2]
            # classic Tz(d)Tx(a)Rx(α)Rz(φ): a along x_p, d along z_p, α about x_p at t_J
            # modified Rx(α)Tx(a)Tz(d)Rz(φ): α about x_p at t_p, a along x_p, d along z_J
            a_d = torch.where(cls, z_p, z_j)
            ax = torch.stack([x_p, a_d, x_p, z_j], -2)
            axes.append(ax.reshape(P, N, -1, 3).permute(0, 3, 1, 2))
        # zero offsets: one virtual joint per movable joint, mapped to actuated columns later
        mov_dir = self._axis[..., None] if CJ is None else CJ @ self._axis[..., None]  # (J, 3, 1)
        mov_ax = (RJ @ mov_dir)[..., 0]  # (P, N, J, 3)
        axes.append(mov_ax.permute(0, 3, 1, 2))
        # marker offsets: like a fixed joint on the marker's link
        e = slots[:, self._slices["marker"]].reshape(P, -1, 6)
        dirs = self._rpy_directions(e, self._mk_R)
        if not self._aligned:
            dirs = self._CmT @ dirs
        axes.append(self._turn(RFi[:, :, self._jac_layout.mk_frame], dirs))
        pts.append(mt)
        return axes, pts

    def _slot_columns(self, slots: Tensor, axes: list[Tensor], pts: list[Tensor], kind: str,
                      plan: SimpleNamespace | None = None) -> tuple[Tensor, Tensor, Tensor]:
        """The non-base columns ``(P, r, N, M, V)`` in the instrument frame (the plan's ``v`` of them
        with a :meth:`column_plan`): a translation moves a marker along its direction, a rotation
        by ``axis × (marker − point)`` (and turns it about ``axis``, the last three rows of
        ``"pose"``), for the markers the slot's joint carries. Also the markers ``Rb·mt`` and their
        instrument-frame positions, ``(P, 3, N, M)``."""
        lay = self._jac_layout if plan is None else plan.lay
        mask, off = lay.mask, lay.off
        P, N, M = pts[-1].shape[0], pts[-1].shape[1], len(self.markers)
        # Layout (P, 3, N, M, V): the slot index innermost and the 3 components outside, so that
        # every elementwise pass runs over long rows (with the 3 components innermost, as the
        # frames come, each pass cost ~20 ns per element on CPU) and the base rotation is one
        # batched 3 x 3 product per parameter vector.
        A = torch.cat(axes, -1)
        if plan is not None:
            A = A[..., plan.v]
        V = A.shape[-1]
        Rb, tb = self._base(slots)
        # the axes in the instrument frame, (P, 3, N, V)
        a = (Rb @ A.reshape(P, 3, N * V)).reshape(P, 3, N, V)
        Vp = off + M
        pw = (Rb @ torch.cat([x.permute(0, 3, 1, 2) for x in pts], -1).reshape(P, 3, N * Vp)).reshape(P, 3, N, Vp)
        mw = pw[..., off:]  # Rb·mt, (P, 3, N, M)
        m_inst = mw + tb[:, :, None, None]  # marker positions, instrument frame
        # lever arms from each rotational column's point to the markers: the translation tb cancels
        at = pw[..., lay.pidx]
        # a plan's rotational columns are its last ones: a slice, and the columns one concatenation
        nt = None if plan is None else lay.n_trans
        ar = a[..., lay.ri] if plan is None else a[..., nt:]
        ar, lev = ar[:, :, :, None, :], mw[..., None] - at[:, :, :, None, :]
        ax_, ay_, az_ = ar.unbind(1)
        lx, ly, lz = lev.unbind(1)
        turned = torch.stack([ay_ * lz - az_ * ly, az_ * lx - ax_ * lz, ax_ * ly - ay_ * lx], 1)
        if plan is None:
            lin = a[:, :, :, None, :].expand(P, 3, N, M, V).clone()  # translations: the axis itself
            lin.index_copy_(-1, lay.ri, turned)
        else:
            lin = torch.cat([a[:, :, :, None, :nt].expand(P, 3, N, M, nt), turned], -1)
        lin *= mask
        if kind != "pose":
            return lin, mw, m_inst
        return torch.cat([lin, a[:, :, :, None, :] * (mask * lay.rot_f)], 1), mw, m_inst

    def _base_columns(self, slots: Tensor, mw: Tensor, Jv: Tensor, kind: str) -> Tensor:
        """The base's columns ``(P, r, N, M, 6)``: translations along the instrument axes, rotations
        about ``J_l e_k`` (``J_l`` the left Jacobian of the base rotation vector) at the markers
        ``mw (P, 3, N, M)``."""
        P, r_rows, N, M = Jv.shape[:4]
        Jl = so3_left_jacobian(slots[:, self._slices["base"]][:, 3:])  # (P, 3, 3), column k: J_l e_k
        base = Jv.new_zeros(P, r_rows, N, M, 6)
        base[:, 0, ..., 0] = 1.0
        base[:, 1, ..., 1] = 1.0
        base[:, 2, ..., 2] = 1.0
        kx, ky, kz = (Jl[:, c, :][:, None, None, :] for c in range(3))  # (P, 1, 1, 3): component c of each axis k
        wx, wy, wz = (mw[:, c][..., None] for c in range(3))  # (P, N, M, 1)
        base[:, 0, ..., 3:] = ky * wz - kz * wy
        base[:, 1, ..., 3:] = kz * wx - kx * wz
        base[:, 2, ..., 3:] = kx * wy - ky * wx
        if kind == "pose":
            base[:, 3:, ..., 3:] = Jl[:, :, None, None, :]
        return base
