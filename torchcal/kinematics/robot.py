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
import os
import warnings
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from torchcal.params import ParamSet
from torchcal.kinematics.transforms import homogeneous, matrix_to_rpy, rot_y, rot_z, rpy_to_matrix, skew, so3_exp, so3_left_jacobian
from torchcal.kinematics.tree import JointSpec, Marker, parse_marker, select_subtree

__all__ = ["Robot"]

_ORIGIN_SLOTS = ("dx", "dy", "dz", "droll", "dpitch", "dyaw")
_DH_SLOTS = ("a", "d", "alpha", "phi")
_BASE_NAMES = ("base.x", "base.y", "base.z", "base.rx", "base.ry", "base.rz")


def _align_z(axis: Tensor) -> Tensor:
    """A rotation C with C @ e_z = axis (unit): the identity for z, a half turn about x for -z."""
    z = torch.tensor([0.0, 0.0, 1.0], dtype=axis.dtype, device=axis.device)
    v = torch.linalg.cross(z, axis)
    c = float(axis @ z)
    if float(v.norm()) < 1e-12:
        return torch.eye(3, dtype=axis.dtype, device=axis.device) if c > 0 else \
            torch.diag(torch.tensor([1.0, -1.0, -1.0], dtype=axis.dtype, device=axis.device))
    return so3_exp(v / v.norm() * torch.atan2(v.norm(), torch.tensor(c, dtype=axis.dtype)))


def _origin_attrs(T: np.ndarray) -> dict[str, str]:
    rpy = matrix_to_rpy(torch.as_tensor(T[:3, :3])).numpy() + 0.0  # + 0.0 turns -0.0 into 0.0
    return {"xyz": " ".join(repr(float(v) + 0.0) for v in T[:3, 3]), "rpy": " ".join(repr(float(v)) for v in rpy)}


def _edit_urdf(text: str, joints: list[JointSpec], mks, base, base_link: str, root: str,
               note: str | None = None) -> str:
    """The original URDF text with new joint origins and added marker/base links. Editing the
    XML (rather than re-writing a parsed model) keeps everything kinematics does not read:
    mimic tags, transmissions, gazebo blocks, comments."""
    import xml.etree.ElementTree as ET

    parser = ET.XMLParser(target=ET.TreeBuilder(insert_comments=True))
    tree = ET.ElementTree(ET.fromstring(text, parser=parser))
    rob = tree.getroot()
    by_name = {j.get("name"): j for j in rob.findall("joint")}
    for jt in joints:
        el = by_name[jt.name]
        o = el.find("origin")
        if o is None:
            o = ET.SubElement(el, "origin")
        o.attrib.update(_origin_attrs(jt.origin))
    links = {l.get("name") for l in rob.findall("link")}
    for mk, T in mks:
        ln = f"marker_{mk.name}"
        if ln in links:
            raise ValueError(f"cannot export: link {ln!r} already exists in the URDF")
        ET.SubElement(rob, "link", name=ln)
        j = ET.SubElement(rob, "joint", name=f"{ln}_joint", type="fixed")
        ET.SubElement(j, "parent", link=mk.link)
        ET.SubElement(j, "child", link=ln)
        ET.SubElement(j, "origin", _origin_attrs(T))
    if base is not None:
        if base_link in links:
            raise ValueError(f"cannot export: link {base_link!r} already exists; pass base_link='…'")
        ET.SubElement(rob, "link", name=base_link)
        j = ET.SubElement(rob, "joint", name=f"{base_link}_to_{root}", type="fixed")
        ET.SubElement(j, "parent", link=base_link)
        ET.SubElement(j, "child", link=root)
        ET.SubElement(j, "origin", _origin_attrs(base))
    if note:
        rob.insert(0, ET.Comment(" " + note.replace("--", "—") + " "))
    ET.indent(tree, space="  ")
    return '<?xml version="1.0"?>\n' + ET.tostring(rob, encoding="unicode") + "\n"


class Robot:
    """A kinematic tree with measured frames (markers) and geometric error parameters.

    Build one with :meth:`from_urdf` or :meth:`from_dh`. Only the joints on the paths from the
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
        from torchcal.kinematics.urdf import load_joints

        is_xml = isinstance(path, str) and path.lstrip().startswith("<")
        text = path if is_xml else (Path(path).read_text() if Path(path).is_file() else None)
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
        from torchcal.kinematics.dh import dh_joints

        joints = dh_joints(table, convention, tool=None if tool is None else np.asarray(tool, dtype=float))
        if markers is None:
            markers = [joints[-1].child]
        elif isinstance(markers, (str, Marker)):
            markers = [markers]
        return cls(name, joints, list(markers), dtype=dtype, device=device)

    def _build(self) -> None:
        fk = dict(dtype=self.dtype, device=self.device)
        J = len(self.joints)
        link_frame = {self.root: 0}
        for j, jt in enumerate(self.joints):
            link_frame[jt.child] = j + 1
        self.link_frame = link_frame
        self.parent_frame = [link_frame[jt.parent] for jt in self.joints]
        self.serial = all(p == j for j, p in enumerate(self.parent_frame))
        by_name = {jt.name: jt for jt in self.joints}
        self.joint_names = sorted((jt.name for jt in self.joints if jt.movable and jt.mimic is None),
                                  key=lambda n: self._file_order.get(n, 0))
        act = {n: i for i, n in enumerate(self.joint_names)}
        self.dof = len(self.joint_names)
        self._specs = {jt.name: jt for jt in self.joints}
        if self.dof == 0:
            raise ValueError("no movable joint lies between the root and the markers; check the marker links")

        # motion: q_j = mult * (q[src] + offset[src]) + moff
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
        self._is_rev = torch.tensor([jt.type in ("revolute", "continuous") for jt in self.joints], device=self.device)
        self._any_pri = any(jt.type == "prismatic" for jt in self.joints)
        self._axis = torch.tensor(np.stack([jt.axis for jt in self.joints]), **fk)
        # map movable joints to actuated columns: (J, dof), used for offsets and dq
        Mmap = torch.zeros(J, self.dof, **fk)
        for j, jt in enumerate(self.joints):
            if jt.movable:
                Mmap[j, src[j]] = mult[j]
        self._Mmap = Mmap

        # --- slots: every scalar that a parameter may move, and the parameters themselves
        entries: list[tuple[str, str, bool]] = []  # (name, unit, free by default)
        slot_param: list[str | None] = []
        for n in _BASE_NAMES:
            slot_param.append(n)
            entries.append((n, "m" if n[-1] in "xyz" and "r" not in n[5:] else "rad", True))
        self._urdf_idx = [j for j, jt in enumerate(self.joints) if jt.dh is None]
        self._dh_idx = [j for j, jt in enumerate(self.joints) if jt.dh is not None]
        for j in self._urdf_idx:
            jt = self.joints[j]
            for s in _ORIGIN_SLOTS:
                n = f"{jt.name}.{s}"
                slot_param.append(n)
                entries.append((n, "m" if s in ("dx", "dy", "dz") else "rad", True))
        dh_entries = {}
        for j in self._dh_idx:
            jt = self.joints[j]
            for s in _DH_SLOTS:
                n = jt.dh.names.get(s)
                slot_param.append(n)
                if n is not None:
                    dh_entries[n] = (n, "m" if s in ("a", "d") else "rad", True)
        for n in self.joint_names:
            jt = by_name[n]
            on = jt.offset_name or f"{n}.offset"
            slot_param.append(on)
            entry = (on, "m" if jt.type == "prismatic" else "rad", True)
            if jt.dh is not None:
                dh_entries.setdefault(on, entry)
            else:
                entries.append(entry)
        for mk in self.markers:
            for s in _ORIGIN_SLOTS:
                n = f"{mk.name}.{s}"
                slot_param.append(n)
                entries.append((n, "m" if s in ("dx", "dy", "dz") else "rad", s in ("dx", "dy", "dz")))
        if dh_entries:  # DH errors read best grouped by row: a, d, alpha, theta
            order = {"da": 0, "dd": 1, "dalpha": 2, "dtheta": 3}
            row = {n: i for i, n in enumerate(jt.name for jt in self.joints)}

            def key(e):
                joint, slot = e[0].rsplit(".", 1)
                return row.get(joint, len(row)), order.get(slot, 9)

            entries = entries[:6] + sorted(dh_entries.values(), key=key) + entries[6:]
        self.param_names = [e[0] for e in entries]
        self.param_units = [e[1] for e in entries]
        self._default_free = [e[2] for e in entries]
        pindex = {n: i for i, n in enumerate(self.param_names)}
        K = len(self.param_names)
        self._slot_gather = torch.tensor([K if n is None else pindex[n] for n in slot_param], device=self.device)
        self._slot_param = slot_param
        nb, nu, nd, no = 6, 6 * len(self._urdf_idx), 4 * len(self._dh_idx), self.dof
        self._slices = dict(base=slice(0, nb), urdf=slice(nb, nb + nu), dh=slice(nb + nu, nb + nu + nd),
                            offset=slice(nb + nu + nd, nb + nu + nd + no),
                            marker=slice(nb + nu + nd + no, nb + nu + nd + no + 6 * len(self.markers)))
        self.n_slots = len(slot_param)

        # --- nominal geometry
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
        self._perm = None if perm == list(range(J)) else torch.tensor(np.argsort(perm), device=self.device)
        # Internally every joint turns about (or slides along) z: C_j maps z onto the joint axis,
        # the chain works in frames W_j C_j, and C's are folded into origins and markers. A
        # revolute step is then a cheap mix of two columns instead of a 3x3 product.
        C = torch.stack([_align_z(a) for a in self._axis])
        Cf = torch.cat([torch.eye(3, **fk)[None], C])  # per frame: root, then each joint's child
        self._C = C
        self._CfT = Cf.transpose(-1, -2)
        self._CpT = self._CfT[self.parent_frame]
        self._aligned = bool(torch.allclose(C, torch.eye(3, **fk).expand_as(C), atol=0, rtol=0))
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
        self._has_moff = bool((self._moff != 0).any())
        Tm = torch.tensor(np.stack([mk.matrix() for mk in self.markers]), **fk)
        self._mk_R, self._mk_t = Tm[:, :3, :3].contiguous(), Tm[:, :3, 3].contiguous()
        self._mk_frame = [link_frame[mk.link] for mk in self.markers]
        self._CmT = self._CfT[self._mk_frame]
        # ancestry: joint j moves marker m iff joint j's child frame is an ancestor-or-self of m's link
        anc = torch.zeros(J, len(self.markers), dtype=torch.bool, device=self.device)
        for m, f in enumerate(self._mk_frame):
            while f != 0:
                anc[f - 1, m] = True
                f = self.parent_frame[f - 1]
        self._anc = anc
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
    def check_q(self, q, what: str = "q", *, _stacklevel: int = 2) -> Tensor:
        """Validate joint values and return them as a ``(N, dof)`` tensor on this robot's device.

        Raises on wrong shape and NaN/inf; warns when revolute values look like degrees or
        prismatic values look like millimetres."""
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
        for n, v, u, l, h in zip(self.joint_names, amax, self._units, lo, hi):
            span = max(abs(l), abs(h)) if np.isfinite(l) and np.isfinite(h) else None
            if u == "rad" and v > max(2.2 * np.pi, 1.5 * span if span else 0.0):
                warnings.warn(f"joint {n!r} reaches |q| = {v:.1f}, which looks like degrees; torchcal expects "
                              "radians (use numpy.deg2rad)", stacklevel=_stacklevel)
            elif u == "m" and v > max(5.0, 3 * span if span else 0.0):
                warnings.warn(f"prismatic joint {n!r} reaches |q| = {v:.1f}, which looks like millimetres; "
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

    # ------------------------------------------------------------------ geometry pieces
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

    def _marker_frames(self, Rs, ts, slots):
        mR, mt = self._markers(slots)  # (P|1, M, 3, 3)
        outR, outt = [], []
        for m, f in enumerate(self._mk_frame):
            if Rs[f] is None:
                outR.append(mR[:, m][:, None]), outt.append(mt[:, m][:, None])
            else:
                outR.append(Rs[f] @ mR[:, None, m])
                outt.append(ts[f] + (Rs[f] @ mt[:, None, m, :, None])[..., 0])
        P = max(x.shape[0] for x in outR)
        N = max(x.shape[1] for x in outR)
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

    def fk_rt(self, q, params=None, *, check: bool = True) -> tuple[Tensor, Tensor]:
        """Like :meth:`fk` but returns rotations ``(..., M, 3, 3)`` and positions ``(..., M, 3)``
        (m) separately, which is cheaper when only positions are needed."""
        q, slots, pop, q1 = self._prepare(q, params, check)
        if q.shape[0] * (1 if slots is None else slots.shape[0]) <= self.SMALL_BATCH:
            T = self._fk4(q, slots)
            R, t = T[..., :3, :3], T[..., :3, 3]
        else:
            R, t = self._fk_rt(q, slots)
        return self._unbatch(R, pop, q1, 3), self._unbatch(t, pop, q1, 2)

    def positions(self, q, params=None, *, check: bool = True, base: bool = True) -> Tensor:
        """Marker positions only (m): ``(N, M, 3)``, or ``(P, N, M, 3)`` for a population.

        Cheaper than :meth:`fk` for position residuals: each marker point is carried from its
        link back to the base (``v <- O_j Rz(q_j) v``), so every step moves vectors, not frames.

        Args:
            q: ``(N, dof)``, or ``(P, N, dof)`` paired with a ``(P, K)`` population (joint values
                that differ per parameter vector, as effect models produce them).
            base: apply the base frame (instrument frame); ``False`` gives robot-base positions.
        """
        if isinstance(q, Tensor) and q.ndim == 3:
            q, slots, pop, q1 = self._prepare_paired(q, params, check)
        else:
            q, slots, pop, q1 = self._prepare(q, params, check)
        O_R, O_t = self._origins(slots)
        qj = self._joint_values(q, slots)  # (P, N, J)
        P, N = max(O_R.shape[0], qj.shape[0]), q.shape[-2]
        c, s = torch.cos(qj), torch.sin(qj)
        _, mt = self._markers(slots)
        out = []
        for m, f in enumerate(self._mk_frame):
            v = mt[:, m, :, None].expand(P, 3, N)  # (P, 3, N): columns of points, batched over P
            while f != 0:
                j = f - 1
                kind = self._kinds[j]
                if kind == 1:
                    x, y = v[:, 0], v[:, 1]
                    cj, sj = c[..., j], s[..., j]
                    v = torch.stack([cj * x - sj * y, sj * x + cj * y, v[:, 2]], 1)
                elif kind == 2:
                    v = torch.stack([v[:, 0], v[:, 1], v[:, 2] + qj[..., j]], 1)
                # v <- O_t + O_R v as three column updates: cheaper than a batched 3x3 matmul here
                OR = O_R[:, j]
                w = torch.addcmul(O_t[:, j, :, None], OR[:, :, 0:1], v[:, 0:1])
                w = torch.addcmul(w, OR[:, :, 1:2], v[:, 1:2])
                v = torch.addcmul(w, OR[:, :, 2:3], v[:, 2:3])
                f = self.parent_frame[j]
            out.append(v)
        t = torch.stack(out, 1).transpose(-1, -2).transpose(1, 2)  # (P, N, M, 3)
        bframe = self._base(slots) if base else None
        if bframe is not None:
            Rb, tb = bframe
            t = tb[:, None, None] + (Rb[:, None, None] @ t[..., None])[..., 0]
        return self._unbatch(t, pop, q1, 2)

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

    def _fk_rt(self, q: Tensor, slots: Tensor | None) -> tuple[Tensor, Tensor]:
        Rs, ts, *_ = self._chain(q, slots)
        R, t = self._marker_frames(Rs, ts, slots)
        base = self._base(slots)
        if base is not None:
            Rb, tb = base
            R = Rb[:, None, None] @ R
            t = tb[:, None, None] + (Rb[:, None, None] @ t[..., None])[..., 0]
        return R, t

    def param_jacobian(self, q, params=None, *, kind: str = "position", check: bool = True,
                       return_positions: bool = False):
        """Analytic derivative of the marker poses w.r.t. all K parameters.

        Args:
            kind: ``"position"``: rows are d(p_x, p_y, p_z) (m per unit); ``"pose"``: three more rows,
                the angular velocity ω (rad per unit, instrument frame) with ``dR = skew(ω) R`` —
                the Jacobian of a rotation-vector residual ``log(R R_meas^T)`` at zero.
            return_positions: also return the marker positions ``(…, M, 3)`` (m) computed on the
                way, which saves a second kinematics pass in least-squares solvers.
        Returns:
            ``(N, M, 3|6, K)`` (``(P, N, M, 3|6, K)`` for a population, or for ``q (P, N, dof)``
            paired with ``params (P, K)`` as in :meth:`positions`).
        """
        if kind not in ("position", "pose"):
            raise ValueError(f"kind must be 'position' or 'pose', got {kind!r}")
        paired = isinstance(q, Tensor) and q.ndim == 3
        q, slots, pop, q1 = (self._prepare_paired if paired else self._prepare)(q, params, check)
        if slots is None:
            slots = self._slots(torch.zeros(1, self.n_params, dtype=self.dtype, device=self.device))
        Jac, pw = self._slot_jacobian(q, slots, kind)  # (P, N, M, r, S)
        # a parameter's column is the sum over the slots it moves
        K = self.n_params
        out = Jac.new_zeros(*Jac.shape[:-1], K + 1)
        out.index_add_(-1, self._slot_gather, Jac)
        J = self._unbatch(out[..., :K], pop, q1, 3)
        return (J, self._unbatch(pw, pop, q1, 2)) if return_positions else J

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

    def _slot_jacobian(self, q: Tensor, slots: Tensor, kind: str) -> Tensor:
        Rs, ts, JR, Jt = self._chain(q, slots, keep_joint_frames=True)
        mR, mt = self._marker_frames(Rs, ts, slots)  # robot-base frame, (P, N, M, ...)
        P, N = mt.shape[0], mt.shape[1]
        dt = dict(dtype=self.dtype, device=self.device)
        eye = torch.eye(3, **dt)
        Jn = len(self.joints)
        # frames as the URDF defines them (undo the internal axis alignment); root = identity
        RF = torch.stack([eye.expand(P, N, 3, 3) if R is None else R.expand(P, N, 3, 3) for R in Rs], 2)
        if not self._aligned:
            RF = RF @ self._CfT
        RP = RF[:, :, self.parent_frame]  # (P, N, J, 3, 3)
        tP = torch.stack([torch.zeros(P, N, 3, **dt) if ts[f] is None else ts[f].expand(P, N, 3)
                          for f in self.parent_frame], 2)
        RJ = torch.stack([x.expand(P, N, 3, 3) for x in JR], 2)  # internal (aligned) joint frames
        CJ = None if self._aligned else self._CfT[1:]
        if self._dh_idx and CJ is not None:
            RJ_urdf = RJ @ CJ
        else:
            RJ_urdf = RJ
        tJ = torch.stack([x.expand(P, N, 3) for x in Jt], 2)
        axes, points, is_rot, masks = [], [], [], []
        anc = self._anc  # (J, M)
        if self._urdf_idx:
            U = self._urdf_idx
            e = slots[:, self._slices["urdf"]].reshape(P, -1, 6)
            # x, y, z, roll, pitch, yaw directions of each origin frame F0 = RP·U_R: F0 times
            # small per-parameter-vector matrices, so one batched product per pose
            B = self._rpy_directions(e, self._U_R)  # (P, U, 3, 6)
            ax = (RP[:, :, U] @ B[:, None]).transpose(-1, -2)  # (P, N, U, 6, 3)
            axes.append(ax.reshape(P, N, -1, 3))
            points.append(tJ[:, :, U, None, :].expand(-1, -1, -1, 6, -1).reshape(P, N, -1, 3))
            is_rot.append(torch.tensor([False, False, False, True, True, True], device=self.device).repeat(len(U)))
            masks.append(anc[U].repeat_interleave(6, 0))
        if self._dh_idx:
            D = self._dh_idx
            Rp, tp, Rj, tj = RP[:, :, D], tP[:, :, D], RJ_urdf[:, :, D], tJ[:, :, D]
            cls = self._dh_classic[:, None]
            x_p, z_p, z_j = Rp[..., 0], Rp[..., 2], Rj[..., 2]
            # classic Tz(d)Tx(a)Rx(α)Rz(φ): a along x_p, d along z_p, α about x_p at t_J
            # modified Rx(α)Tx(a)Tz(d)Rz(φ): α about x_p at t_p, a along x_p, d along z_J
            a_d = torch.where(cls, z_p, z_j)
            pt_al = torch.where(cls, tj, tp)
            ax = torch.stack([x_p, a_d, x_p, z_j], -2)
            pt = torch.stack([tj, tj, pt_al, tj], -2)
            axes.append(ax.reshape(P, N, -1, 3))
            points.append(pt.reshape(P, N, -1, 3))
            is_rot.append(torch.tensor([False, False, True, True], device=self.device).repeat(len(D)))
            masks.append(anc[D].repeat_interleave(4, 0))
        # zero offsets: one virtual joint per movable joint, mapped to actuated columns below
        mov_dir = self._axis[..., None] if CJ is None else CJ @ self._axis[..., None]  # (J, 3, 1)
        mov_ax = (RJ @ mov_dir)[..., 0]  # (P, N, J, 3)
        axes.append(mov_ax)
        points.append(tJ)
        is_rot.append(self._is_rev.clone())
        masks.append(anc)
        # marker offsets: like a fixed joint on the marker's link
        M = len(self.markers)
        e = slots[:, self._slices["marker"]].reshape(P, -1, 6)
        ax = (RF[:, :, self._mk_frame] @ self._rpy_directions(e, self._mk_R)[:, None]).transpose(-1, -2)
        axes.append(ax.reshape(P, N, -1, 3))
        points.append(mt[:, :, :, None, :].expand(-1, -1, -1, 6, -1).reshape(P, N, -1, 3))
        is_rot.append(torch.tensor([False, False, False, True, True, True], device=self.device).repeat(M))
        masks.append(torch.eye(M, dtype=torch.bool, device=self.device).repeat_interleave(6, 0))

        # Layout (P, 3, N, M, V): the slot index innermost and the 3 components outside, so that
        # every elementwise pass runs over long rows (with the 3 components innermost, as the
        # frames come, each pass cost ~20 ns per element on CPU) and the base rotation is one
        # batched 3 x 3 product per parameter vector.
        V = sum(x.shape[2] for x in axes)
        rot = torch.cat(is_rot)  # (V,)
        mask = torch.cat(masks, 0).to(self.dtype).T  # (M, V)
        Rb, tb = self._base(slots)

        def to_base(vecs: list[Tensor], shift: bool) -> Tensor:
            """(P, N, v, 3) pieces, robot-base frame -> (P, 3, N, V), instrument frame."""
            x = torch.cat([v.permute(0, 3, 1, 2) for v in vecs], -1).reshape(P, 3, N * V)
            x = (Rb @ x).reshape(P, 3, N, V)
            return x + tb[:, :, None, None] if shift else x

        a = to_base(axes, False)
        pt = to_base(points, True)
        mw = (Rb @ mt.permute(0, 3, 1, 2).reshape(P, 3, N * M)).reshape(P, 3, N, M)  # Rb·mt, (P, 3, N, M)
        m_inst = mw + tb[:, :, None, None]  # marker positions, instrument frame
        ri = torch.nonzero(rot).flatten()
        ar, lev = a[..., ri][:, :, :, None, :], m_inst[..., None] - pt[..., ri][:, :, :, None, :]
        ax_, ay_, az_ = ar.unbind(1)
        lx, ly, lz = lev.unbind(1)
        lin = a[:, :, :, None, :].expand(P, 3, N, M, V).clone()  # translations: the axis itself
        lin[..., ri] = torch.stack([ay_ * lz - az_ * ly, az_ * lx - ax_ * lz, ax_ * ly - ay_ * lx], 1)
        lin *= mask
        rows = [lin]
        if kind == "pose":
            rows.append(a[:, :, :, None, :] * (mask * rot.to(self.dtype)))
        Jv = torch.cat(rows, 1) if len(rows) > 1 else lin  # (P, r, N, M, V)
        r_rows = Jv.shape[1]
        # split back into slot groups; offsets per movable joint -> per actuated joint
        nu, nd = 6 * len(self._urdf_idx), 4 * len(self._dh_idx)
        J_orig = Jv[..., : nu + nd]
        J_mov = Jv[..., nu + nd: nu + nd + Jn] @ self._Mmap  # (P, r, N, M, dof)
        J_mk = Jv[..., nu + nd + Jn:]
        # base columns: translations along the instrument axes, rotations about J_l e_k
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
        Jac = torch.cat([base, J_orig, J_mov, J_mk], -1)  # (P, r, N, M, S)
        return Jac.permute(0, 2, 3, 1, 4), m_inst.permute(0, 2, 3, 1)  # (P, N, M, r, S), (P, N, M, 3)

    # ------------------------------------------------------------------ export
    def calibrated_joints(self, params) -> list[JointSpec]:
        """Joint specs whose origins carry the errors in ``params`` (offsets folded in)."""
        p = self._check_params(params)
        if p is None:
            p = torch.zeros(self.n_params, dtype=self.dtype, device=self.device)
        if p.ndim != 1:
            raise ValueError("give one parameter vector (K,), not a population")
        slots = self._slots(p[None].to(torch.float64))
        O_R, O_t = self._true_origins(slots)
        off = slots[0, self._slices["offset"]]
        out = []
        for j, jt in enumerate(self.joints):
            T = np.eye(4)
            T[:3, :3] = O_R[0, j].detach().cpu().numpy()
            T[:3, 3] = O_t[0, j].detach().cpu().numpy()
            if jt.movable:
                delta = float(self._mult[j] * off[int(self._src[j])])
                if jt.type == "prismatic":
                    T[:3, 3] += T[:3, :3] @ (jt.axis * delta)
                else:
                    T[:3, :3] = T[:3, :3] @ so3_exp(torch.as_tensor(jt.axis * delta)).numpy()
            nj = copy.copy(jt)
            nj.origin, nj.dh = T, None
            out.append(nj)
        return out

    def _extra_frames(self, params) -> tuple[np.ndarray | None, list[tuple[Marker, np.ndarray]]]:
        p = self._check_params(params)
        if p is None:
            p = torch.zeros(self.n_params, dtype=self.dtype, device=self.device)
        slots = self._slots(p[None])
        mR, mt = self._markers(slots, aligned=False)
        mks = []
        for m, mk in enumerate(self.markers):
            T = np.eye(4)
            T[:3, :3], T[:3, 3] = mR[0, m].detach().cpu().numpy(), mt[0, m].detach().cpu().numpy()
            mks.append((mk, T))
        b = slots[0, self._slices["base"]].detach().cpu()
        base = None
        if bool((b != 0).any()):
            base = np.eye(4)
            base[:3, :3], base[:3, 3] = so3_exp(b[3:]).numpy(), b[:3].numpy()
        return base, mks

    def export_urdf(self, params, path, *, with_instrument: bool = False, base_link: str = "instrument",
                    note: str | None = None) -> str:
        """Write a URDF whose nominal kinematics equal this robot's calibrated kinematics, in the
        robot's own base frame.

        Joint origins carry the identified errors and zero offsets. Each marker becomes a fixed
        link ``marker_<name>`` on its link. The instrument registration (the base frame
        parameters) is left out, so that the root stays the robot's; with ``with_instrument`` a
        non-zero base frame becomes a new root link ``base_link`` (the instrument frame).
        ``note`` goes into an XML comment. Returns the XML text. When the robot came from a
        URDF, everything else in it (inertials, meshes, limits, mimic tags, transmissions) is
        kept as it was; only joint origins change.
        """
        joints = self.calibrated_joints(params)
        base, mks = self._extra_frames(params)
        if not with_instrument:
            base = None
        if self._urdf_text is not None:
            xml = _edit_urdf(self._urdf_text, joints, mks, base, base_link, self.root, note)
            Path(path).write_text(xml)
            return xml
        extra = [JointSpec(name=f"marker_{mk.name}_joint", type="fixed", parent=mk.link, child=f"marker_{mk.name}",
                           origin=T) for mk, T in mks]
        if base is not None:
            extra.insert(0, JointSpec(name=f"{base_link}_to_{self.root}", type="fixed", parent=base_link,
                                      child=self.root, origin=base))
        from torchcal.kinematics.urdf import write_urdf

        return write_urdf(self.name, ([extra[0]] if base is not None else []) + joints +
                          extra[1 if base is not None else 0:], path)

    def to_urdf_string(self, params=None, inertials: dict | None = None, comment: str | None = None) -> str:
        """Nominal (or calibrated) kinematics as URDF text, without marker or base links."""
        from torchcal.kinematics.urdf import write_urdf

        return write_urdf(self.name, self.calibrated_joints(params), None, inertials=inertials, comment=comment)
