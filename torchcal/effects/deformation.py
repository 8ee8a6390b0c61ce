"""Elastic deformation under gravity: joints that twist, joints and links that bend, a base that
tilts on a compliant floor or mount.

Every mode is a small compliance at one frame (the base, or a joint frame after its motion) in
one direction of that frame, driven by one component of the gravity wrench there
(:mod:`torchcal.effects.gravity`: URDF inertials plus an unknown payload):

* rotation about a direction ``d``: ``δφ = c · dᵀM`` (rad, ``c`` in rad/(N·m)); about a
  revolute joint's own axis this is joint compliance and acts as ``Δq``; about any other axis
  the part beyond the frame turns about the frame origin and a marker moves by ``δφ R d × (p − o)``;
* translation along ``d``: ``c · dᵀF`` (m, ``c`` in m/N).

The payload (mass ``m`` kg and first moment ``m s`` kg·m in the tool link's frame) is shared by
every mode. A load logged row by row (``loads``: covariate columns, a payload in kg, a part held
or not) adds ``L ν`` to it, ``ν`` its mass moments per unit of the column, shared too. The model is
bilinear in (compliances, payload); :meth:`GravityDeformation.linear_basis` gives each mode five
coordinates (``c`` and ``c·μ``; four more per load, ``c·ν``) in which it is linear, so selection and
identifiability are judged where no column vanishes, and :meth:`from_linear` factors them back.
Rotations other than the joint twist are applied to first order: at a few mrad the error is
below a micrometre per metre of lever.
"""
from __future__ import annotations

import torch
from torch import Tensor

from torchcal.effects.base import Effect, LinearBasis, Prepared
from torchcal.effects.deformation_modes import catalog
from torchcal.effects.gravity import GRAVITY, body_inertials, gravity_wrenches, load_values
from torchcal.effects.shapes import WINDOW
from torchcal.measure.levels import LEVEL_SEP

__all__ = ["GravityDeformation"]


def _axis_rotation(a: Tensor, angle: Tensor) -> Tensor:
    """``(N, 3, 3)`` rotations by ``angle (N,)`` rad about the unit axis ``a (3,)`` (Rodrigues)."""
    K = torch.zeros(3, 3, dtype=a.dtype, device=a.device)
    K[0, 1], K[0, 2], K[1, 2] = -a[2], a[1], -a[0]
    K = K - K.T
    s, c = torch.sin(angle)[:, None, None], torch.cos(angle)[:, None, None]
    return torch.eye(3, dtype=a.dtype, device=a.device) + s * K + (1 - c) * (K @ K)


class GravityDeformation(Effect):
    """Elastic deformation driven by the full gravity wrench at the base and at each joint.

    Args:
        modes: mode labels (default: every mode: ``base.tilt_x/y``, and per joint ``twist``, two
            ``bend_<axis>`` and three ``shift_<axis>``); the loop selects among them.
        tool_link: where the unknown payload hangs (default: the first marker's link).
        gravity: gravity in the robot base frame (m/s²).
        loads: covariate columns whose value per row adds to the payload (each its own unknown mass
            moments per unit of the column), e.g. a logged payload mass; none by default.
    """

    name = "elastic_deformation"
    description = "elastic deformation under the gravity wrench: bending, a tilting base, twisting joints"
    selectable = True
    supersedes = ("joint_compliance",)

    def __init__(self, robot, joints=None, geometry=None, modes: list[str] | None = None,
                 tool_link: str | None = None, gravity=GRAVITY, loads: list[str] | tuple = ()):
        self.gravity = tuple(float(v) for v in gravity)
        self.loads = [str(c) for c in loads]
        self.tool_link = tool_link or robot.markers[0].link
        self._inertials = body_inertials(robot)
        self._joints_for_catalog = joints
        self._mode_labels = None if modes is None else list(modes)
        super().__init__(robot, joints, geometry)
        cat = self._catalog()
        if self._mode_labels is None:
            self._mode_labels = [c["label"] for c in cat if self._default_mode(c)]
        known = {c["label"]: c for c in cat}
        bad = [m for m in self._mode_labels if m not in known]
        if bad:
            raise ValueError(f"{self.name}: unknown mode(s) {bad}; modes look like {list(known)[:4]}")
        self._modes = [known[m] for m in self._mode_labels]
        self.theta = torch.zeros(self.n_params, dtype=robot.dtype, device=robot.device)

    def default_joints(self) -> list[str]:
        return list(self.robot.joint_names)

    def _default_mode(self, c: dict) -> bool:
        return True

    # -- the catalogue of modes ----------------------------------------------------------------
    def _catalog(self) -> list[dict]:
        """Every mode this robot offers (:func:`~torchcal.effects.deformation_modes.catalog`)."""
        return catalog(self.robot, self.joints)

    # -- parameters ------------------------------------------------------------------------
    @property
    def has_payload(self) -> bool:
        return bool(self._inertials)

    def param_info(self):
        if not hasattr(self, "_modes"):  # during Effect.__init__, before the modes are known
            return []
        out = [(m["label"], "rad/(N*m)" if m["kind"] == "rot" else "m/N") for m in self._modes]
        if self.has_payload:
            out += [("payload.m", "kg"), ("payload.mx", "kg*m"), ("payload.my", "kg*m"), ("payload.mz", "kg*m"),
                    ("gravity.tilt_x", "rad"), ("gravity.tilt_y", "rad")]
            out += [(f"load~{c}.{k}", u) for c in self.loads
                    for k, u in (("m", "kg"), ("mx", "kg*m"), ("my", "kg*m"), ("mz", "kg*m"))]
        return out

    @property
    def n_load(self) -> int:
        """Payload coordinates per mode beyond the compliance: the mass moments, four per load."""
        return 4 + 4 * len(self.loads) if self.has_payload else 0

    @property
    def covariates(self) -> list[str]:
        return list(dict.fromkeys(c.split("~", 1)[0] for c in self.loads)) if self.has_payload else []

    def modes(self) -> list[tuple[str, list[int]]]:
        return [(m["label"], [i]) for i, m in enumerate(self._modes)]

    def breaks(self) -> list[str]:
        """The loads that are a step or a window of time or the row order (a payload changed there)."""
        return [c for c in self.loads if "~" in c and c.partition("~")[2].startswith(("step", WINDOW))]

    def with_break(self, old: str, new: str) -> "GravityDeformation":
        return self._carried(self._copy(loads=[new if c == old else c for c in self.loads])) if old in self.loads \
            else self

    def break_parts(self) -> list[tuple[str, list[int]]]:
        """Each load that is a break (:meth:`breaks`) with its four mass moments: a payload changed
        there, judged again once later findings are in (another set-up change at that row takes it)."""
        if not self.has_payload:
            return []
        at, start = set(self.breaks()), len(self._modes) + 6
        return [(f"load~{c}", list(range(start + 4 * i, start + 4 * i + 4))) for i, c in enumerate(self.loads)
                if c in at]

    def without_part(self, label: str) -> "GravityDeformation":
        c = label.removeprefix("load~")
        return self._copy(loads=[x for x in self.loads if x != c]) if c in self.loads else self

    def shared(self) -> list[int]:
        """The payload's mass moments and the tilt of gravity in the base frame: a robot is never
        quite level, kinematics cannot see it (the instrument registration absorbs it), and it
        turns every gravity torque a little."""
        K = len(self._modes)
        return list(range(K, K + 6 + 4 * len(self.loads))) if self.has_payload else []

    def mode_labels(self) -> list[str]:
        return list(self._mode_labels)

    def catalog_labels(self) -> list[str]:
        return [c["label"] for c in self._catalog()]

    def with_modes(self, labels: list[str]) -> "GravityDeformation":
        keep = set(labels)
        order = [c["label"] for c in self._catalog() if c["label"] in keep]
        return self._copy(modes=order)

    def proposes(self, labels: list[str]) -> tuple[bool, str]:
        """A deformation family says something joint compliance does not only when it holds a
        mode other than a joint twist."""
        if any(not l.endswith(".twist") for l in labels):
            return True, ""
        return False, "no deformation mode beyond joint twist (joint compliance) passed the selection"

    def applicable(self, data) -> tuple[bool, str]:
        if not self._inertials:
            return False, ("the URDF has no link inertials: the gravity wrench is unknown (joint_compliance "
                           "covers joint twist with lumped mass moments)")
        return True, ""

    def config(self) -> dict:
        out = {"modes": list(self._mode_labels), "tool_link": self.tool_link, "gravity": list(self.gravity)}
        return {**out, "loads": list(self.loads)} if self.loads else out

    def _copy(self, **changes) -> "GravityDeformation":
        kw = self.config()
        joints = changes.pop("joints", self.joints)
        kw.update(changes)
        if "modes" not in changes:  # a joint set change drops the modes of the joints left out
            kw["modes"] = [m for m in kw["modes"] if m.startswith("base.") or m.split(".")[0] in set(joints)]
        out = type(self)(self.robot, joints, geometry=self.geometry, **kw)
        out.covariate_range = dict(self.covariate_range)
        return out

    # -- features --------------------------------------------------------------------------------
    def _gravities(self) -> list[tuple]:
        """Gravity as set, then the two unit directions across it scaled to its size: the wrench
        is linear in gravity, so a small tilt ``t`` adds ``t_x W(g e_1) + t_y W(g e_2)``."""
        g = torch.tensor(self.gravity, dtype=torch.float64)
        n = float(g.norm())
        e = torch.eye(3, dtype=torch.float64)
        u = e[int(torch.argmin((g / n).abs()))]
        e1 = u - (u @ g) / n ** 2 * g
        e1 = e1 / e1.norm()
        e2 = torch.linalg.cross(g / n, e1)
        return [tuple(self.gravity), tuple((n * e1).tolist()), tuple((n * e2).tolist())]

    def prepare(self, q, covariates):
        Ws = [gravity_wrenches(self.robot, q, self.geometry, payload_link=self.tool_link, gravity=g,
                               inertials=self._inertials) for g in self._gravities()]
        W = Ws[0]
        N, M = q.shape[0], W.markers.shape[1]
        L = [x[:, None, None, None] for x in load_values(self.loads, covariates, q)]
        # the driving wrench of every frame, URDF part then per unit payload moment (and per unit of
        # each load's moments), for gravity as set and for the two tilts: (N, F, 6, 3, 5 + 4 loads)
        drive = torch.stack([torch.cat([w.urdf[..., None], w.payload, *(w.payload * x for x in L)], -1)
                             for w in Ws], -2)
        twist, Wt, pos, V, arm, rot, ax = [], [], [], [], [], [], []
        for k, m in enumerate(self._modes):
            f = m["frame"]
            comp = drive[:, f, 3:] if m["kind"] == "rot" else drive[:, f, :3]  # (N, 3, 3, 5) frame axes
            if m["dof"] is not None:
                twist.append((k, m["dof"]))
                Wt.append(torch.einsum("a,nagb->ngb", m["dir"], comp))  # (N, 3, 5) the torque about the axis
                continue
            pos.append(k)
            Rf, Pm, d = W.R[:, f], m["P"].expand(N, 3, 3), m["dir"]
            if "seat" in m:  # the frame before the motion: R_after R_axis(θ)ᵀ
                Ra = _axis_rotation(m["axis"], q[:, m["seat"]] + self.geometry[self._offset_index(m["seat"])])
                Pm = Ra.transpose(-1, -2) @ Pm @ Ra
                d = (Ra.transpose(-1, -2) @ d)
            V.append(torch.einsum("nij,njk,nkgb->ngbi", Rf, Pm, comp))  # (N, 3, 5, 3) base axes
            arm.append((W.markers - W.o[:, f, None]) * W.beyond[f].to(q.dtype)[None, :, None])  # (N, M, 3)
            rot.append(m["kind"] == "rot")
            ax.append((Rf @ d[..., None])[..., 0] if d is not None else torch.zeros(N, 3, dtype=q.dtype, device=q.device))
        dt = dict(dtype=q.dtype, device=q.device)
        return Prepared({
            "twist": twist, "pos": pos,
            "Wt": torch.stack(Wt, 1) if Wt else torch.zeros(N, 0, 3, 5, **dt),  # (N, T, 3, 5)
            "V": torch.stack(V, 1) if V else torch.zeros(N, 0, 3, 5, 3, **dt),  # (N, Kp, 3, 5, 3)
            "arm": torch.stack(arm, 2) if arm else torch.zeros(N, M, 0, 3, **dt),  # (N, M, Kp, 3)
            "beyond": torch.stack([W.beyond[self._modes[k]["frame"]] for k in pos], 1).to(q.dtype)
            if pos else torch.zeros(M, 0, **dt),  # (M, Kp)
            "rot": torch.tensor(rot, dtype=torch.bool, device=q.device),
            "axis": torch.stack(ax, 1) if ax else torch.zeros(N, 0, 3, **dt)})  # (N, Kp, 3) single-axis modes

    def _offset_index(self, dof: int) -> int:
        jt = next(j for j in self.robot.joints if j.name == self.robot.joint_names[dof])
        return self.robot.param_names.index(jt.offset_name or f"{jt.name}.offset")

    def _load(self, theta: Tensor) -> Tensor:
        """``(P, 3, 5 + 4 loads)``: the weights of the drive's (gravity, unit payload) slices: gravity
        as set, and its tilts ``t_x``, ``t_y`` (rows), times 1, the payload mass moments and each load's
        (columns)."""
        P = theta.shape[0]
        one = torch.ones(P, 1, dtype=theta.dtype, device=theta.device)
        K = len(self._modes)
        if not self.has_payload:
            mu, t = theta.new_zeros(P, 4), theta.new_zeros(P, 2)
        else:
            mu = torch.cat([theta[:, K:K + 4], theta[:, K + 6:K + 6 + 4 * len(self.loads)]], 1)
            t = theta[:, K + 4:K + 6]
        pv = torch.cat([one, mu], 1)  # (P, 5)
        return torch.cat([one, t], 1)[:, :, None] * pv[:, None, :]

    @staticmethod
    def _displacement(V: Tensor, prep: Prepared) -> Tensor:
        """``V (..., N, Kp, 3)`` rotation/shift per mode -> marker displacement ``(..., N, M, Kp, 3)``."""
        f = prep.features
        arm = f["arm"]
        rot = torch.linalg.cross(V[..., :, None, :, :].expand(*V.shape[:-3], V.shape[-3], arm.shape[1], *V.shape[-2:]),
                                 arm.expand(*V.shape[:-3], *arm.shape))
        shift = V[..., :, None, :, :] * f["beyond"][..., None]
        return torch.where(f["rot"][:, None], rot, shift)

    def joint_delta(self, theta, prep):
        tw = prep.features["twist"]
        if not tw:
            return None
        tau = torch.einsum("ntgb,pgb->pnt", prep.features["Wt"], self._load(theta))  # (P, N, T)
        d = theta[:, None, [k for k, _ in tw]] * tau
        out = d.new_zeros(*d.shape[:2], self.robot.dof)
        return out.index_copy(-1, torch.tensor([j for _, j in tw], device=d.device), d)

    def position_delta(self, theta, prep):
        pos = prep.features["pos"]
        if not pos:
            return None
        V = torch.einsum("nkgbd,pgb->pnkd", prep.features["V"], self._load(theta))  # (P, N, Kp, 3)
        V = V * theta[:, None, pos, None]
        return self._displacement(V, prep).sum(-2)

    # -- linear form: (c, c·μ) per mode ------------------------------------------------------------
    def linear_basis(self, prep) -> LinearBasis:
        K = len(self._modes)
        w = 1 + self.n_load
        f = prep.features
        N = f["Wt"].shape[0]
        M = f["arm"].shape[1]
        dq = f["Wt"].new_zeros(N, self.robot.dof, K * w)
        for i, (k, j) in enumerate(f["twist"]):
            dq[:, j, k * w:(k + 1) * w] = f["Wt"][:, i, 0, :w]
        dp = f["Wt"].new_zeros(N, M, 3, K * w)
        if f["pos"]:
            D = self._displacement(f["V"][:, :, 0, :w].permute(2, 0, 1, 3), prep)  # (w, N, M, Kp, 3)
            for i, k in enumerate(f["pos"]):
                dp[..., k * w:(k + 1) * w] = D[:, :, :, i].permute(1, 2, 3, 0)
        return LinearBasis(dq if f["twist"] else None, dp if f["pos"] else None,
                           [list(range(k * w, (k + 1) * w)) for k in range(K)], shared=w - 1)

    def from_linear(self, coef: Tensor) -> Tensor:
        K = len(self._modes)
        if not self.has_payload:
            return coef.clone()
        B = coef.reshape(K, 1 + self.n_load)
        a, b = B[:, 0], B[:, 1:]
        # b_k = c_k μ: the payload is the a²-weighted ratio (best-determined compliances count most)
        den = float((a * a).sum())
        mu = (a[:, None] * b).sum(0) / den if den > 0 else coef.new_zeros(self.n_load)
        return self.from_bilinear(a, mu)

    def from_bilinear(self, own: Tensor, shared: Tensor) -> Tensor:
        if not self.has_payload:
            return own.clone()
        # the payload, gravity as set to start with, then the loads
        return torch.cat([own, shared[:4], own.new_zeros(2), shared[4:]])

    def signature(self, prep, label, theta):
        k = self._mode_labels.index(label)
        m = self._modes[k]
        f = prep.features
        load = self._load(theta[None])[0]  # (3, 5 + 4 loads)
        if m["dof"] is not None:
            x = torch.einsum("ngb,gb->n", f["Wt"][:, [kk for kk, _ in f["twist"]].index(k)], load)  # torque
            return {"x": x, "xlabel": "gravity torque about the axis [N·m]", "fitted": theta[k] * x,
                    "ylabel": "joint twist [rad]", "dof": m["dof"]}
        i = f["pos"].index(k)
        V = torch.einsum("ngbd,gb->nd", f["V"][:, i], load)  # (N, 3) the driving moment (force) it sees, base axes
        # one axis: the signed component along it; a plane: the size of the moment across the axis
        x = (V * f["axis"][:, i]).sum(-1) if m["dir"] is not None else V.norm(dim=-1)
        unit = V / V.norm(dim=-1, keepdim=True).clamp(min=1e-300)
        G = self._displacement(unit[None, :, None], prep)[0, :, :, 0]  # (N, M, 3) per unit rotation/shift
        if m["kind"] == "rot":
            what = "overturning moment" if m["frame"] == 0 else "gravity moment across the axis"
            xlabel, ylabel = (f"{what} [N·m]", "rotation [rad]")
        else:
            xlabel, ylabel = "gravity force along that axis [N]", "displacement [m]"
        return {"x": x, "xlabel": xlabel, "fitted": theta[k] * x, "ylabel": ylabel, "G": G}

    # -- words -------------------------------------------------------------------------------
    def mode_words(self, label: str) -> str:
        return next(m["words"] for m in self._modes if m["label"] == label)

    def describe(self, theta: Tensor | None = None, free: Tensor | None = None) -> list[str]:
        th = self.theta if theta is None else theta
        seen = (lambda i: True) if free is None else (lambda i: bool(free[i]))  # noqa: E731
        out = []
        for k, m in enumerate(self._modes):
            if not seen(k):
                continue
            c = float(th[k])
            if m["kind"] == "rot":
                what = "overturning moment" if m["frame"] == 0 else "gravity moment"
                out.append(f"{m['words']} by {c * 1e6:.3g} µrad per N·m of {what}")
            else:
                out.append(f"{m['words']} by {c * 1e9:.3g} µm per kN")
        if self.has_payload:
            K = len(self._modes)
            mass = float(th[K])
            if seen(K):
                s = (th[K + 1:K + 4] / mass * 1e3).tolist() if abs(mass) > 1e-9 else [float("nan")] * 3
                out.append(f"unknown payload on {self.tool_link}: {mass:.3g} kg with its centre of mass at "
                           f"({s[0]:.0f}, {s[1]:.0f}, {s[2]:.0f}) mm in that link's frame")
            if seen(K + 4) or seen(K + 5):
                tx, ty = float(th[K + 4]), float(th[K + 5])
                out.append(f"gravity leans {1e3 * tx:.3g} mrad (about y) and {1e3 * ty:.3g} mrad (about x) off the "
                           "base's vertical: the base is not quite level")
            for i, c in enumerate(self.loads):
                j = K + 6 + 4 * i
                if seen(j):
                    m = float(th[j])
                    s = (th[j + 1:j + 4] / m * 1e3).tolist() if abs(m) > 1e-9 else [float("nan")] * 3
                    how = (f"is {m:.3g} kg more for {c.replace(LEVEL_SEP, ' = ', 1)} than for the first level"
                           if LEVEL_SEP in c else f"grows by {m:.3g} kg per unit of {c}")
                    out.append(f"the load on {self.tool_link} {how}, its centre of mass at ({s[0]:.0f}, {s[1]:.0f}, "
                               f"{s[2]:.0f}) mm in that link's frame")
        return out


