"""Forward kinematics of a :class:`~torchcal.kinematics.robot.Robot`: the chain of joint origins with
their error parameters applied, marker frames, the instrument frame; batched over poses ``q (N, dof)``
and parameter populations ``(P, K)``. Rotations ``(..., 3, 3)``, translations and positions in m.
"""
from __future__ import annotations

import warnings
from types import SimpleNamespace

import numpy as np
import torch
from torch import Tensor

from torchcal.kinematics.transforms import homogeneous, rpy_to_matrix, so3_exp
from torchcal.kinematics.tree import Marker
from torchcal.params import ParamSet

__all__ = ["ForwardKinematics"]

_LAYOUT_FIELDS = ('slot_gather', 'slices', 'Mmap', 'moff', 'kinds', 'dh_idx', 'dh_nom', 'urdf_idx', 'aligned', 'CmT', 'mk_t', 'mk_R', 'mk_frame', 'perm', 'C', 'CpT', 'U_R', 'U_t')


class ForwardKinematics:
    """The forward-kinematics half of :class:`~torchcal.kinematics.robot.Robot` (a mixin: it reads
    the layout :meth:`Robot._build` lays out)."""

    # ------------------------------------------------------------------ geometry pieces
    def layout(self) -> SimpleNamespace:
        """The parameter and frame layout :meth:`Robot._build` lays out, read-only, for kernels built on
        this robot (:class:`~torchcal.kinematics.fk_compact.PositionKernel`): ``slots(p)`` maps
        ``(P, K)`` parameters to ``(P, S)`` slot values; ``slot_gather``, ``slices`` (parameter blocks),
        the joint-value map ``Mmap``/``moff``, joint ``kinds`` (1 revolute, 2 prismatic, 0 fixed),
        ``dh_idx``/``urdf_idx``/``dh_nom``, marker frames ``mk_R``/``mk_t``/``mk_frame``, ``CmT``,
        ``aligned``, the axis alignments ``C``/``CpT``, the URDF origins ``U_R``/``U_t`` and the joint
        order ``perm``."""
        return SimpleNamespace(slots=self._slots, **{f: getattr(self, "_" + f) for f in _LAYOUT_FIELDS})

    def _slots(self, p: Tensor) -> Tensor:
        """(P, K) -> (P, S) slot values (0 where no parameter moves a slot)."""
        pad = torch.cat([p, p.new_zeros(p.shape[0], 1)], 1)
        return pad[:, self._slot_gather]

    def _origins(self, slots: Tensor | None) -> tuple[Tensor, Tensor]:
        """Joint origins in axis-aligned form: R (P,J,3,3), t (P,J,3). With ``slots`` None the
        nominal ones (P = 1), cached."""
        if slots is None and self._nominal_cache is not None:
            return self._nominal_cache
        R, t = self._true_origins(slots)
        if not self._aligned:
            R = self._CpT @ R @ self._C
            t = (self._CpT @ t[..., None])[..., 0]
        if slots is None:
            self._nominal_cache = (R, t)
        return R, t

    def _true_origins(self, slots: Tensor | None) -> tuple[Tensor, Tensor]:
        """Joint origins parent link -> joint frame as written in the URDF/DH table, with errors."""
        P = 1 if slots is None else slots.shape[0]
        parts_R, parts_t = [], []
        if self._urdf_idx:
            if slots is None:
                parts_R.append(self._U_R.expand(P, -1, -1, -1))
                parts_t.append(self._U_t.expand(P, -1, -1))
            else:
                e = slots[:, self._slices["urdf"]].reshape(P, -1, 6)
                parts_R.append(self._U_R @ rpy_to_matrix(e[..., 3:]))
                parts_t.append(self._U_t + (self._U_R @ e[..., :3, None])[..., 0])
        if self._dh_idx:
            v = self._dh_nom if slots is None else self._dh_nom + slots[:, self._slices["dh"]].reshape(P, -1, 4)
            v = v.expand(P, -1, -1)
            a, d, al, ph = v.unbind(-1)
            ca, sa, cp, sp = torch.cos(al), torch.sin(al), torch.cos(ph), torch.sin(ph)
            z = torch.zeros_like(ca)
            R = torch.stack([torch.stack([cp, -sp, z], -1), torch.stack([ca * sp, ca * cp, -sa], -1),
                             torch.stack([sa * sp, sa * cp, ca], -1)], -2)
            t = torch.where(self._dh_classic[:, None], torch.stack([a, z, d], -1),
                            torch.stack([a, -d * sa, d * ca], -1))
            parts_R.append(R)
            parts_t.append(t)
        R = parts_R[0] if len(parts_R) == 1 else torch.cat(parts_R, 1)
        t = parts_t[0] if len(parts_t) == 1 else torch.cat(parts_t, 1)
        if self._perm is not None:
            R, t = R[:, self._perm], t[:, self._perm]
        return R, t

    def _markers(self, slots: Tensor | None, aligned: bool = True) -> tuple[Tensor, Tensor]:
        """Marker poses on their links (P|1, M, 3, 3), (P|1, M, 3); ``aligned``: expressed in the
        axis-aligned link frames the chain works in."""
        if slots is None:
            R, t = self._mk_R[None], self._mk_t[None]
        else:
            e = slots[:, self._slices["marker"]].reshape(slots.shape[0], -1, 6)
            R, t = self._mk_R @ rpy_to_matrix(e[..., 3:]), self._mk_t + (self._mk_R @ e[..., :3, None])[..., 0]
        if aligned and not self._aligned:
            R, t = self._CmT @ R, (self._CmT @ t[..., None])[..., 0]
        return R, t

    def _base(self, slots: Tensor | None):
        if slots is None:
            return None
        b = slots[:, self._slices["base"]]
        if b.device.type == "cpu" and not b.requires_grad and not bool(b.any()):
            # a base fixed at zero (robot-frame data): skip the rotation-vector exponential
            eye = torch.eye(3, dtype=b.dtype, device=b.device).expand(b.shape[0], 3, 3)
            return eye, b[:, :3]
        return so3_exp(b[:, 3:]), b[:, :3]

    def _joint_values(self, q: Tensor, slots: Tensor | None) -> Tensor:
        """(N, dof) commands -> (P, N, J) joint values after offsets and mimic coupling."""
        if q.ndim == 2:
            q = q[None]
        if slots is not None:
            q = q + slots[:, None, self._slices["offset"]]
        qj = q @ self._Mmap.T
        return qj + self._moff if self._has_moff else qj

    def _chain(self, q: Tensor, slots: Tensor | None, keep_joint_frames: bool = False):
        """Frames of all links in the robot-base frame, axis-aligned (see ``_build``): lists of
        R (P,N,3,3), t (P,N,3) per frame (None for the root); optionally the joint frames
        (after the origin, before the motion)."""
        O_R, O_t = self._origins(slots)
        qj = self._joint_values(q, slots)  # (P, N, J)
        P, N = max(O_R.shape[0], qj.shape[0]), q.shape[-2]
        c, s = torch.cos(qj)[..., None], torch.sin(qj)[..., None]
        Rs: list[Tensor | None] = [None] * (len(self.joints) + 1)
        ts: list[Tensor | None] = [None] * (len(self.joints) + 1)
        JR, Jt = [], []
        for j, pf in enumerate(self.parent_frame):
            Rp = Rs[pf]
            if Rp is None:
                R = O_R[:, None, j].expand(P, N, 3, 3)
                t = O_t[:, None, j].expand(P, N, 3)
            else:
                # one (P, N*3, 3) @ (P, 3, 3) product: no broadcast copies of the origin
                B = Rp.reshape(P, N * 3, 3)
                OR = O_R[:, j].expand(P, 3, 3)
                R = torch.bmm(B, OR).view(P, N, 3, 3)
                t = ts[pf] + torch.bmm(B, O_t[:, j, :, None].expand(P, 3, 1)).view(P, N, 3)
            if keep_joint_frames:
                JR.append(R), Jt.append(t)
            kind = self._kinds[j]
            if kind == 1:  # revolute about the (aligned) z axis: mix the first two columns
                x, y = R[..., 0], R[..., 1]
                cj, sj = c[..., j, :], s[..., j, :]
                R = torch.stack([x * cj + y * sj, y * cj - x * sj, R[..., 2]], -1)
            elif kind == 2:
                t = t + qj[..., j, None] * R[..., 2]
            Rs[j + 1], ts[j + 1] = R, t
        return Rs, ts, JR, Jt

    def _chain4(self, q: Tensor, slots: Tensor | None) -> list[Tensor | None]:
        """Same frames as :meth:`_chain` as (P,N,4,4) products: fewer, smaller ops, which is
        what a single configuration needs."""
        if slots is None:
            O4 = self._nominal_cache4
        else:
            O4 = homogeneous(*self._origins(slots))
        qj = self._joint_values(q, slots)[..., None, None]  # (P, N, J, 1, 1)
        M = self._M4_one + torch.cos(qj) * self._M4_c + torch.sin(qj) * self._M4_s
        if self._any_pri:
            M = M + qj * self._M4_p
        L = O4[:, None] @ M  # (P, N, J, 4, 4)
        Ts: list[Tensor | None] = [None] * (len(self.joints) + 1)
        for j, pf in enumerate(self.parent_frame):
            Ts[j + 1] = L[:, :, j] if Ts[pf] is None else Ts[pf] @ L[:, :, j]
        return Ts

    def _point_shift(self, points: Tensor | None) -> Tensor | None:
        """``points (P|1, N, M, 3)``: per-row offsets of the marker points along their own error
        translations (``<marker>.dx/dy/dz``, m) -> the same in the axis-aligned link frames the chain
        works in."""
        if points is None:
            return None
        A = self._mk_R if self._aligned else self._CmT @ self._mk_R  # (M, 3, 3)
        return torch.einsum("mij,pnmj->pnmi", A, points.to(self.dtype)[None] if points.ndim == 3 else points)

    def _marker_frames(self, Rs, ts, slots, shift: Tensor | None = None):
        """Marker frames in the robot-base frame ``(P, N, M, 3, 3)``, ``(P, N, M, 3)``; ``shift``
        (:meth:`_point_shift`) moves each row's marker points on their links."""
        mR, mt = self._markers(slots)  # (P|1, M, 3, 3)
        outR, outt = [], []
        for m, f in enumerate(self._mk_frame):
            pt = mt[:, None, m] if shift is None else mt[:, None, m] + shift[:, :, m]  # (P, 1|N, 3)
            if Rs[f] is None:
                outR.append(mR[:, m][:, None]), outt.append(pt)
            else:
                outR.append(Rs[f] @ mR[:, None, m])
                outt.append(ts[f] + (Rs[f] @ pt[..., None])[..., 0])
        P = max(x.shape[0] for x in outR + outt)
        N = max(x.shape[1] for x in outR + outt)
        R = torch.stack([x.expand(P, N, 3, 3) for x in outR], 2)  # (P, N, M, 3, 3)
        t = torch.stack([x.expand(P, N, 3) for x in outt], 2)
        return R, t

    def _fk4(self, q: Tensor, slots: Tensor | None) -> Tensor:
        Ts = self._chain4(q, slots)
        mR, mt = self._markers(slots)
        mk4 = homogeneous(mR, mt)  # (P|1, M, 4, 4)
        P = max(mk4.shape[0], Ts[-1].shape[0] if Ts[-1] is not None else 1)
        out = [mk4[:, None, m].expand(P, q.shape[0], 4, 4) if Ts[f] is None else Ts[f] @ mk4[:, None, m]
               for m, f in enumerate(self._mk_frame)]
        T = torch.stack(out, 2)
        base = self._base(slots)
        if base is not None:
            T = homogeneous(*base)[:, None, None] @ T
        return T

    # ------------------------------------------------------------------ public kinematics
    def fk(self, q, params=None, *, check: bool = True) -> Tensor:
        """Poses of all markers, batched.

        Args:
            q: ``(N, dof)`` joint values (rad / m) in ``joint_names`` order, or ``(dof,)``.
            params: ``None`` (nominal), ``(K,)`` or ``(P, K)`` error vectors, or a ParamSet.
            check: validate ``q`` (shape, NaN/inf, unit warnings); turn off inside tight loops.
        Returns:
            ``(N, M, 4, 4)`` (``(P, N, M, 4, 4)`` for a ``(P, K)`` population; no ``N`` axis for a
            1-D ``q``), in the instrument frame when ``params`` carries a base frame.
        """
        q, slots, pop, q1 = self._prepare(q, params, check)
        if q.shape[0] * (1 if slots is None else slots.shape[0]) <= self.SMALL_BATCH:
            T = self._fk4(q, slots)
        else:
            T = homogeneous(*self._fk_rt(q, slots))
        return self._unbatch(T, pop, q1, 3)

    def fk_rt(self, q, params=None, *, check: bool = True, base: bool = True,
              points: Tensor | None = None) -> tuple[Tensor, Tensor]:
        """Like :meth:`fk` but returns rotations ``(..., M, 3, 3)`` and positions ``(..., M, 3)``
        (m) separately, which is cheaper when only positions are needed. ``q`` may be
        ``(P, N, dof)`` paired with a ``(P, K)`` population, as in :meth:`positions`; ``base``:
        apply the instrument frame (``False``: the robot's own base frame); ``points``: as in
        :meth:`positions`."""
        paired = isinstance(q, Tensor) and q.ndim == 3
        q, slots, pop, q1 = (self._prepare_paired if paired else self._prepare)(q, params, check)
        small = q.shape[0] * (1 if slots is None else slots.shape[0]) <= self.SMALL_BATCH
        if base and not paired and points is None and small:
            T = self._fk4(q, slots)
            R, t = T[..., :3, :3], T[..., :3, 3]
        else:
            R, t = self._fk_rt(q, slots, base, self._point_shift(points))
        return self._unbatch(R, pop, q1, 3), self._unbatch(t, pop, q1, 2)

    def positions(self, q, params=None, *, check: bool = True, base: bool = True,
                  points: Tensor | None = None) -> Tensor:
        """Marker positions only (m): ``(N, M, 3)``, or ``(P, N, M, 3)`` for a population.

        Cheaper than :meth:`fk` for position residuals: each marker point is carried from its
        link back to the base (``v <- O_j Rz(q_j) v``), so every step moves vectors, not frames.

        Args:
            q: ``(N, dof)``, or ``(P, N, dof)`` paired with a ``(P, K)`` population (joint values
                that differ per parameter vector, as effect models produce them).
            base: apply the base frame (instrument frame); ``False`` gives robot-base positions.
            points: ``(N, M, 3)`` or ``(P, N, M, 3)`` m: each row's marker points moved along their
                own error translations (``<marker>.dx/dy/dz``), exactly as those parameters would
                move them; a tool that differs by row (one point per tool) is carried by its
                link as the marker's own point is.
        """
        if isinstance(q, Tensor) and q.ndim == 3:
            q, slots, pop, q1 = self._prepare_paired(q, params, check)
        else:
            q, slots, pop, q1 = self._prepare(q, params, check)
        O_R, O_t = self._origins(slots)
        qj = self._joint_values(q, slots)  # (P, N, J)
        P, N = max(O_R.shape[0], qj.shape[0]), q.shape[-2]
        # per joint j, as views taken by one integer index each (a slice per use cost more than the
        # arithmetic at tens of poses): cos, sin and value (P, 1, 1, N), the origin's columns
        # (P, 3, 1, 1) and its translation (P, 3, 1, 1)
        by_joint = qj.permute(2, 0, 1)[:, :, None, None]
        c, s = torch.cos(by_joint), torch.sin(by_joint)
        cols = O_R.permute(1, 3, 0, 2)[..., None, None]  # (J, column, P, 3, 1, 1)
        trans = O_t.transpose(0, 1)[..., None, None]
        _, mt = self._markers(slots)
        shift = self._point_shift(points)
        out = [None] * len(self._mk_frame)
        # markers on one link ride the same chain: carried together, (P, 3, G, N) for G of them
        for f, ms in self._mk_groups.items():
            v = self._pick_markers(mt, ms).transpose(1, 2)[..., None].expand(P, 3, len(ms), N)
            if shift is not None:
                v = v + torch.stack([shift[:, :, m] for m in ms], 2).permute(0, 3, 2, 1)  # (P, 3, G, N)
            while f != 0:
                j = f - 1
                kind = self._kinds[j]
                x, y, z = v.split(1, 1)  # (P, 1, G, N) each
                if kind == 1:
                    x, y = c[j] * x - s[j] * y, s[j] * x + c[j] * y
                elif kind == 2:
                    z = z + by_joint[j]
                # v <- O_t + O_R v as three column updates: cheaper than a batched 3x3 matmul here
                O = cols[j]
                v = torch.addcmul(torch.addcmul(torch.addcmul(trans[j], O[0], x), O[1], y), O[2], z)
                f = self.parent_frame[j]
            for i, m in enumerate(ms):
                out[m] = v[:, :, i]
        t = torch.stack(out, 1).transpose(-1, -2).transpose(1, 2)  # (P, N, M, 3)
        bframe = self._base(slots) if base else None
        if bframe is not None:
            Rb, tb = bframe
            t = tb[:, None, None] + (Rb[:, None, None] @ t[..., None])[..., 0]
        return self._unbatch(t, pop, q1, 2)

    @staticmethod
    def _pick_markers(mt: Tensor, ms: list[int]) -> Tensor:
        """``mt[:, ms]``, by a slice where ``ms`` runs consecutively (an index list would be copied to
        the device on every call)."""
        if ms == list(range(ms[0], ms[-1] + 1)):
            return mt[:, ms[0]:ms[-1] + 1]
        return torch.stack([mt[:, m] for m in ms], 1)

    def base_transform(self, params) -> tuple[Tensor, Tensor]:
        """Instrument frame <- robot base from ``params (K,)`` or ``(P, K)``: rotation
        ``(…, 3, 3)`` and translation ``(…, 3)`` m."""
        p = self._check_params(params)
        pop = p.ndim == 2
        R, t = self._base(self._slots(p if pop else p[None]))
        return (R, t) if pop else (R[0], t[0])

    # Up to this many (pose x parameter vector) pairs, 4x4 products (fewer ops) beat the
    # column form (fewer flops); measured on the KR5 arc, float64, one thread.
    SMALL_BATCH = 16

    def _prepare(self, q, params, check):
        q1 = q.ndim == 1 if isinstance(q, Tensor) else np.ndim(q) == 1
        if check or not isinstance(q, Tensor):
            q = self.check_q(q, _stacklevel=4)
        elif q1:
            q = q[None]
        p = self._check_params(params)
        pop = p is not None and p.ndim == 2
        slots = None if p is None else self._slots(p if pop else p[None])
        return q, slots, pop, q1

    def _prepare_paired(self, q: Tensor, params, check):
        """``q (P, N, dof)`` with ``params (P, K)`` (or ``(K,)``, broadcast)."""
        p = self._check_params(params)
        if p is None or q.shape[-1] != self.dof:
            raise ValueError(f"q must have shape (N, {self.dof}) with columns {self.joint_names}, or (P, N, {self.dof}) "
                             f"paired with a (P, K) parameter population; got {tuple(q.shape)}"
                             + (" without params" if p is None else ""))
        if check:
            self.check_q(q.reshape(-1, q.shape[-1]), _stacklevel=5)
        pop = p.ndim == 2
        pp = p if pop else p[None]
        if pp.shape[0] not in (1, q.shape[0]):
            raise ValueError(f"q has {q.shape[0]} parameter rows but params has {pp.shape[0]}")
        return q, self._slots(pp), True, False

    @staticmethod
    def _unbatch(x: Tensor, pop: bool, q1: bool, tail: int) -> Tensor:
        """Drop the population axis (0) and/or the pose axis for unbatched inputs; ``tail`` is
        the number of trailing axes after the pose axis (M plus the matrix/vector axes)."""
        if not pop:
            x = x[0]
        if q1:
            x = x.select(x.ndim - tail - 1, 0)
        return x

    def _fk_rt(self, q: Tensor, slots: Tensor | None, with_base: bool = True,
               shift: Tensor | None = None) -> tuple[Tensor, Tensor]:
        Rs, ts, *_ = self._chain(q, slots)
        R, t = self._marker_frames(Rs, ts, slots, shift)
        base = self._base(slots) if with_base else None
        if base is not None:
            Rb, tb = base
            R = Rb[:, None, None] @ R
            t = tb[:, None, None] + (Rb[:, None, None] @ t[..., None])[..., 0]
        return R, t

