"""Robots as batched, differentiable kinematic trees with geometric error parameters.

Frames are carried as a rotation ``(..., 3, 3)`` and a translation ``(..., 3)`` in metres.
A parameter vector ``params`` of shape ``(K,)`` or ``(P, K)`` holds *errors* (nominal value 0),
laid out as :meth:`Robot.params` names them:

* ``base.x/y/z`` (m), ``base.rx/ry/rz`` (rad, rotation vector): instrument frame <- robot base;
* per joint origin: ``<joint>.dx/dy/dz`` (m) and ``.droll/.dpitch/.dyaw`` (rad), applied after the
  nominal origin as ``O = O_nom · Trans(d) · Rz(dyaw) Ry(dpitch) Rx(droll)``; for DH robots
  ``<joint>.da/.dd/.dalpha/.dtheta`` instead;
* per actuated joint: ``<joint>.offset`` (rad or m), the zero offset added to the command;
* per marker: ``<marker>.dx … .dyaw`` relative to its nominal pose on its link.

Parameter derivatives are computed analytically: every parameter moves the chain like a virtual
revolute or prismatic joint placed at a known frame, so its Jacobian column is
``axis × (p − point)`` or ``axis`` — the same formula as a geometric joint Jacobian.
"""
from __future__ import annotations

import copy
import hashlib
import warnings
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from torchcal.kinematics.dh import dh_joints
from torchcal.kinematics.export import URDFExport
from torchcal.kinematics.fk import ForwardKinematics
from torchcal.kinematics.jacobian import Jacobians
from torchcal.kinematics.slots import slot_layout
from torchcal.kinematics.transforms import align_z, homogeneous
from torchcal.kinematics.tree import JointSpec, Marker, parse_marker, select_subtree
from torchcal.kinematics.urdf import load_joints, read_urdf_text
from torchcal.kinematics.urdf_check import is_urdf_text, strip_bom
from torchcal.params import ParamSet

__all__ = ["Robot"]


class Robot(ForwardKinematics, Jacobians, URDFExport):
    """A kinematic tree with measured frames (markers) and geometric error parameters.

    Build one with :meth:`from_urdf` or :meth:`from_dh`. Forward kinematics, Jacobians and URDF
    export are written in :mod:`~torchcal.kinematics.fk`, :mod:`~torchcal.kinematics.jacobian` and
    :mod:`~torchcal.kinematics.export`. Only the joints on the paths from the
    root to the markers are kept; their actuated (non-mimic, movable) joints, in file order, are
    the columns of ``q``.

    Attributes:
        joint_names: actuated joints, the order of ``q``'s columns.
        marker_names: measured frames, the order of FK's marker axis.
        param_names: names of the ``K`` error parameters.
    """

    def __init__(self, name: str, joints: list[JointSpec], markers: list, *, root: str | None = None,
                 dtype: torch.dtype = torch.float64, device: torch.device | str = "cpu",
                 urdf_text: str | None = None):
        self.name = name
        markers = [parse_marker(m) for m in markers]
        if not markers:
            raise ValueError("give at least one marker: a link name, or 'name@link=x,y,z' for a point on a link")
        names = [m.name for m in markers]
        if len(set(names)) != len(names):
            raise ValueError(f"marker names must be unique, got {names}")
        self.root, self.joints = select_subtree(joints, markers)
        self._file_order = {j.name: i for i, j in enumerate(joints)}
        self._described = [(j.name, j.type, j.parent, j.child) for j in joints if j.mimic is None]
        if root is not None and root != self.root:
            raise ValueError(f"expected root link {root!r}, found {self.root!r}")
        self.markers = markers
        self._urdf_text = urdf_text
        self.dtype, self.device = dtype, torch.device(device)
        self._build()

    # ------------------------------------------------------------------ construction
    @classmethod
    def from_urdf(cls, path, markers=None, *, dtype: torch.dtype = torch.float64,
                  device: torch.device | str = "cpu") -> "Robot":
        """Load a URDF (path or XML string). Meshes are never loaded, so ``package://`` files
        need not exist.

        Args:
            markers: measured frames: link names, ``"name@link=x,y,z"`` strings (an unknown point
                on ``link`` with an initial guess in metres) or :class:`~torchcal.kinematics.tree.Marker`.
                Default: every leaf link.
        """

        text = strip_bom(path) if is_urdf_text(path) else (read_urdf_text(path) if Path(path).is_file() else None)
        name, joints, _ = load_joints(path)
        if markers is None:
            parents = {j.parent for j in joints}
            markers = [j.child for j in joints if j.child not in parents]
        elif isinstance(markers, (str, Marker)):
            markers = [markers]
        return cls(name, joints, list(markers), dtype=dtype, device=device, urdf_text=text)

    @classmethod
    def from_dh(cls, table, convention: str = "classic", markers=None, *, name: str = "dh_robot",
                tool=None, dtype: torch.dtype = torch.float64, device: torch.device | str = "cpu") -> "Robot":
        """Build from a DH table: rows ``(a, d, alpha[, theta])`` in m/rad, dicts, or
        :class:`~torchcal.kinematics.dh.DHRow`. Error parameters are Δa, Δd, Δα, Δθ per row (plus the base
        and marker offsets). Default marker: the flange (classic) or last link (modified)."""

        joints = dh_joints(table, convention, tool=None if tool is None else np.asarray(tool, dtype=float))
        if markers is None:
            markers = [joints[-1].child]
        elif isinstance(markers, (str, Marker)):
            markers = [markers]
        return cls(name, joints, list(markers), dtype=dtype, device=device)

    def _build(self) -> None:
        """Everything the kinematics reads, from the joints and markers: the frame tree, the joint
        motion, the parameter slots, the nominal geometry in axis-aligned frames, the markers and
        the limits (again on :meth:`to`, for another device or dtype)."""
        self._frame_tree()
        self._motion()
        self._parameter_slots()
        self._nominal_geometry()
        self._aligned_frames()
        self._marker_geometry()
        by_name = {jt.name: jt for jt in self.joints}
        fk = dict(dtype=self.dtype, device=self.device)
        lim_lo = [by_name[n].lower for n in self.joint_names]
        lim_hi = [by_name[n].upper for n in self.joint_names]
        self.joint_limits = (torch.tensor([-np.inf if v is None else v for v in lim_lo], **fk),
                             torch.tensor([np.inf if v is None else v for v in lim_hi], **fk))
        self._units = [("m" if by_name[n].type == "prismatic" else "rad") for n in self.joint_names]
        # filled now rather than lazily: a cache first filled inside a torch.func transform would
        # carry that transform's level and break later calls
        self._nominal_cache = None
        self._nominal_cache = self._origins(None)
        self._nominal_cache4 = homogeneous(*self._nominal_cache)
        self._jac_layout = self._jacobian_layout()
        self._column_plans = {}  # param_jacobian's plans per column subset (Jacobians.column_plan)

    def _frame_tree(self) -> None:
        """Frames (0: the root link, j + 1: joint j's child link), each joint's parent frame, and the
        actuated joints (movable, not mimic, in file order): the columns of ``q``."""
        self.link_frame = {self.root: 0}
        for j, jt in enumerate(self.joints):
            self.link_frame[jt.child] = j + 1
        self.parent_frame = [self.link_frame[jt.parent] for jt in self.joints]
        self.serial = all(p == j for j, p in enumerate(self.parent_frame))
        self.joint_names = sorted((jt.name for jt in self.joints if jt.movable and jt.mimic is None),
                                  key=lambda n: self._file_order.get(n, 0))
        self.dof = len(self.joint_names)
        self._specs = {jt.name: jt for jt in self.joints}
        if self.dof == 0:
            where = ", ".join(f"{m.name} on {m.link!r}" for m in self.markers)
            raise ValueError(f"no movable joint lies between the root link {self.root!r} and the markers ({where}): "
                             "nothing would move them. Declare each marker on the link that carries it (the flange or "
                             "tool link)")

    def _motion(self) -> None:
        """How the commands move the joints: ``q_j = mult * (q[src] + offset[src]) + moff``, and the
        map ``Mmap (J, dof)`` of movable joints to actuated columns (for offsets and dq)."""
        fk = dict(dtype=self.dtype, device=self.device)
        act = {n: i for i, n in enumerate(self.joint_names)}
        src, mult, moff = [], [], []
        for jt in self.joints:
            if not jt.movable:
                src.append(0), mult.append(0.0), moff.append(0.0)
            elif jt.mimic is None:
                src.append(act[jt.name]), mult.append(1.0), moff.append(0.0)
            else:
                s = jt.mimic[0]
                if s not in act:
                    raise ValueError(f"joint {jt.name!r} mimics {s!r}, which is not an actuated joint; "
                                     "chains of mimic joints are not supported")
                src.append(act[s]), mult.append(jt.mimic[1]), moff.append(jt.mimic[2])
        self._src = torch.tensor(src, device=self.device)
        self._mult = torch.tensor(mult, **fk)
        self._moff = torch.tensor(moff, **fk)
        self._has_moff = any(v != 0 for v in moff)
        self._is_rev = torch.tensor([jt.type in ("revolute", "continuous") for jt in self.joints], device=self.device)
        self._any_pri = any(jt.type == "prismatic" for jt in self.joints)
        self._axis = torch.tensor(np.stack([jt.axis for jt in self.joints]), **fk)
        Mmap = torch.zeros(len(self.joints), self.dof, **fk)
        for j, jt in enumerate(self.joints):
            if jt.movable:
                Mmap[j, src[j]] = mult[j]
        self._Mmap = Mmap

    def _parameter_slots(self) -> None:
        """The error parameters and the slots they move (:func:`~torchcal.kinematics.slots.slot_layout`),
        and where each block of slots lies."""
        lay = slot_layout(self.joints, self.joint_names, self.markers)
        self.param_names, self.param_units, self._default_free = lay.param_names, lay.param_units, lay.default_free
        self._urdf_idx, self._dh_idx = lay.urdf_idx, lay.dh_idx
        pindex = {n: i for i, n in enumerate(self.param_names)}
        K = len(self.param_names)
        self._slot_gather = torch.tensor([K if n is None else pindex[n] for n in lay.slot_param], device=self.device)
        nb, nu, nd, no = 6, 6 * len(self._urdf_idx), 4 * len(self._dh_idx), self.dof
        self._slices = dict(base=slice(0, nb), urdf=slice(nb, nb + nu), dh=slice(nb + nu, nb + nu + nd),
                            offset=slice(nb + nu + nd, nb + nu + nd + no),
                            marker=slice(nb + nu + nd + no, nb + nu + nd + no + 6 * len(self.markers)))
        self.n_slots = len(lay.slot_param)

    def _nominal_geometry(self) -> None:
        """Nominal joint origins (URDF ones as ``U_R``/``U_t``, DH rows as ``dh_nom``) and the
        permutation from URDF-then-DH order back to chain order (None when it is the identity)."""
        fk = dict(dtype=self.dtype, device=self.device)
        T = torch.tensor(np.stack([jt.origin for jt in self.joints]), **fk)
        self._O_R_nom, self._O_t_nom = T[:, :3, :3].contiguous(), T[:, :3, 3].contiguous()
        U = self._urdf_idx
        self._U_R = self._O_R_nom[U].contiguous()
        self._U_t = self._O_t_nom[U].contiguous()
        self._dh_nom = torch.tensor([[jt.dh.a, jt.dh.d, jt.dh.alpha, jt.dh.phi] for jt in
                                     (self.joints[j] for j in self._dh_idx)], **fk).reshape(-1, 4)
        self._dh_classic = torch.tensor([self.joints[j].dh.convention == "classic" for j in self._dh_idx],
                                        device=self.device)
        perm = self._urdf_idx + self._dh_idx
        self._perm = None if perm == list(range(len(self.joints))) else torch.tensor(np.argsort(perm),
                                                                                     device=self.device)

    def _aligned_frames(self) -> None:
        """Internally every joint turns about (or slides along) z: ``C_j`` maps z onto the joint axis,
        the chain works in frames ``W_j C_j``, and the C's are folded into origins and markers. A
        revolute step is then a cheap mix of two columns instead of a 3x3 product; ``M4_*`` are the
        per-joint pieces of that step as 4 x 4 matrices."""
        fk = dict(dtype=self.dtype, device=self.device)
        J = len(self.joints)
        # C is found on the host from the file's axes and copied once: on a GPU each Python
        # branch of _align_z, and the check below, would wait for the device
        axes_host = torch.tensor(np.stack([jt.axis for jt in self.joints]), dtype=self.dtype)
        C_host = torch.stack([align_z(a) for a in axes_host])
        self._C = C_host.to(self.device)
        Cf = torch.cat([torch.eye(3, **fk)[None], self._C])  # per frame: root, then each joint's child
        self._CfT = Cf.transpose(-1, -2)
        self._CpT = self._CfT[self.parent_frame]
        self._aligned = bool(torch.equal(C_host, torch.eye(3, dtype=C_host.dtype).expand_as(C_host)))
        self._kinds = [1 if jt.type in ("revolute", "continuous") else 2 if jt.type == "prismatic" else 0
                       for jt in self.joints]
        kinds = torch.tensor(self._kinds, device=self.device)
        one = torch.eye(4, **fk).repeat(J, 1, 1)
        rev = kinds == 1
        one[rev, 0, 0] = 0
        one[rev, 1, 1] = 0
        c4, s4, p4 = torch.zeros(J, 4, 4, **fk), torch.zeros(J, 4, 4, **fk), torch.zeros(J, 4, 4, **fk)
        c4[rev, 0, 0] = c4[rev, 1, 1] = 1
        s4[rev, 1, 0], s4[rev, 0, 1] = 1, -1
        p4[kinds == 2, 2, 3] = 1
        self._M4_one, self._M4_c, self._M4_s, self._M4_p = one, c4, s4, p4

    def _marker_geometry(self) -> None:
        """Nominal marker poses on their links, their frames, and which joints move which marker
        (``anc (J, M)``: joint j moves marker m iff its child frame is an ancestor-or-self of m's link)."""
        Tm = torch.tensor(np.stack([mk.matrix() for mk in self.markers]), dtype=self.dtype, device=self.device)
        self._mk_R, self._mk_t = Tm[:, :3, :3].contiguous(), Tm[:, :3, 3].contiguous()
        self._mk_frame = [self.link_frame[mk.link] for mk in self.markers]
        self._mk_groups: dict[int, list[int]] = {}  # markers by the frame they sit on (positions() carries each group)
        for m, f in enumerate(self._mk_frame):
            self._mk_groups.setdefault(f, []).append(m)
        self._CmT = self._CfT[self._mk_frame]
        anc = torch.zeros(len(self.joints), len(self.markers), dtype=torch.bool, device=self.device)
        for m, f in enumerate(self._mk_frame):
            while f != 0:
                anc[f - 1, m] = True
                f = self.parent_frame[f - 1]
        self._anc = anc

    # ------------------------------------------------------------------ basic facts
    @property
    def n_params(self) -> int:
        return len(self.param_names)

    @property
    def marker_names(self) -> list[str]:
        return [m.name for m in self.markers]

    @property
    def joint_units(self) -> list[str]:
        return list(self._units)

    def __repr__(self) -> str:
        return (f"Robot({self.name!r}, dof={self.dof}, joints={self.joint_names}, markers={self.marker_names}, "
                f"n_params={self.n_params}, {self.dtype}, {self.device})")

    def to(self, device=None, dtype=None) -> "Robot":
        """A copy on another device and/or dtype."""
        r = copy.copy(self)
        r.device = torch.device(device) if device is not None else self.device
        r.dtype = dtype or self.dtype
        r._build()
        return r

    def other_joints(self) -> dict[str, str | None]:
        """The movable joints of the description that are not columns of ``q`` (they move no
        marker): name -> the marker link they come after, or None for another branch. A data
        column named like one that comes after a marker's link says the marker sits further out."""
        after = {}
        kids: dict[str, list] = {}
        for name, jtype, parent, child in self._described:
            kids.setdefault(parent, []).append((name, jtype, child))
        for mk in self.markers:
            stack = [mk.link]
            while stack:
                for name, jtype, child in kids.get(stack.pop(), []):
                    if jtype != "fixed":
                        after.setdefault(name, mk.link)
                    stack.append(child)
        return {n: after.get(n) for n, jtype, _, _ in self._described
                if jtype != "fixed" and n not in self.joint_names}

    @property
    def urdf_text(self) -> str | None:
        """The URDF text this robot was loaded from (None for a robot built from a DH table)."""
        return self._urdf_text

    def urdf_hash(self) -> str:
        """SHA-256 of the URDF text this robot came from (or of its exported nominal URDF)."""
        text = self._urdf_text if self._urdf_text is not None else self.to_urdf_string()
        return hashlib.sha256(text.encode()).hexdigest()

    def params(self, values: Tensor | None = None) -> ParamSet:
        """A fresh :class:`ParamSet` (zeros unless ``values``), free flags at their defaults:
        everything free except marker orientations; bounds ±1 m / ±π rad (tighten them for
        swarm solvers)."""
        K = self.n_params
        v = torch.zeros(K, dtype=self.dtype, device=self.device) if values is None else \
            torch.as_tensor(values, dtype=self.dtype, device=self.device).clone()
        big = torch.tensor([1.0 if u == "m" else float(np.pi) for u in self.param_units], dtype=self.dtype,
                           device=self.device)
        base_t = torch.tensor([n in ("base.x", "base.y", "base.z") for n in self.param_names], device=self.device)
        big = torch.where(base_t, torch.full_like(big, 100.0), big)
        return ParamSet(list(self.param_names), list(self.param_units), v,
                        torch.tensor(self._default_free, device=self.device), -big, big)

    # ------------------------------------------------------------------ validation
    def check_q(self, q, what: str = "q", *, _stacklevel: int = 2, units_judged: bool = False) -> Tensor:
        """Validate joint values and return them as a ``(N, dof)`` tensor on this robot's device.

        Raises on wrong shape and NaN/inf; warns when revolute values look like degrees or
        prismatic values look like millimetres (unless ``units_judged``: the caller has)."""
        q = torch.as_tensor(q, dtype=self.dtype, device=self.device)
        shape = tuple(q.shape)
        if q.ndim == 1:
            q = q[None]
        if q.ndim != 2 or q.shape[-1] != self.dof:
            raise ValueError(f"{what} must have shape (N, {self.dof}) with columns {self.joint_names}, "
                             f"got {shape}")
        amax = q.abs().amax(0).tolist() if q.shape[0] else [0.0] * self.dof
        bad = [n for n, v in zip(self.joint_names, amax) if not np.isfinite(v)]
        if bad:
            raise ValueError(f"{what} has NaN or inf in joint(s) {bad}; drop or fill those rows first")
        lo, hi = self.joint_limits[0].tolist(), self.joint_limits[1].tolist()
        for n, v, u, l, h in zip(self.joint_names, amax if not units_judged else [], self._units, lo, hi):
            span = max(abs(l), abs(h)) if np.isfinite(l) and np.isfinite(h) else None
            if u == "rad" and v > max(2.2 * np.pi, 1.5 * span if span else 0.0):
                # a continuous joint may turn many times: radians may be right there
                maybe = "" if span else " (unless it is a continuous joint that turned several times)"
                warnings.warn(f"joint {n!r} reaches |q| = {v:.4g}, which looks like degrees{maybe}; torchcal expects "
                              "radians (use numpy.deg2rad)", stacklevel=_stacklevel)
            elif u == "m" and v > max(5.0, 3 * span if span else 0.0):
                warnings.warn(f"prismatic joint {n!r} reaches |q| = {v:.4g}, which looks like millimetres; "
                              "torchcal expects metres (divide by 1000)", stacklevel=_stacklevel)
        return q

    def _check_params(self, params) -> Tensor | None:
        if params is None:
            return None
        if isinstance(params, ParamSet):
            if params.names != self.param_names:
                raise ValueError("this ParamSet was made for another robot (parameter names differ); "
                                 "use robot.params()")
            params = params.values
        p = torch.as_tensor(params, dtype=self.dtype, device=self.device)
        if p.shape[-1] != self.n_params or p.ndim not in (1, 2):
            raise ValueError(f"params must have shape (K,) or (P, K) with K = {self.n_params} "
                             f"(robot.param_names), got {tuple(p.shape)}")
        return p

