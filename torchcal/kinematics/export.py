"""A calibrated :class:`~torchcal.kinematics.robot.Robot` written back as URDF: the original text
with corrected joint origins (and, on request, marker / instrument links), so everything
kinematics does not read (meshes, limits, inertials) survives; and as ``calibration.yaml``, in the
robot's own layout where it has one (a UR arm: :mod:`~torchcal.kinematics.ur_layout`).

**What the URDF diff holds.** Against the input URDF, ``calibrated.urdf`` differs only in:

* the ``xyz`` / ``rpy`` of the ``<origin>`` of each joint the calibration changed *significantly*:
  a joint whose every parameter moved by no more than its standard error (when given) and by no
  more than 1e-9 m / 1e-9 rad keeps its origin byte for byte (its change is treated as zero in
  both files), and within a rewritten origin a number that keeps its value keeps its spelling;
* numbers that are float64 rounding of zero (``|v| < 1e-15`` m or rad) are written ``0``;
* ``marker_<name>`` links only with ``with_markers``, an ``instrument`` root only with
  ``with_instrument``, and a ``note`` comment after ``<robot>`` when one is given.

Nothing else (comments, meshes, inertials, limits, mimic tags, transmissions, gazebo blocks) is
touched."""
from __future__ import annotations

import copy
import hashlib
from pathlib import Path

import numpy as np
import torch

import yaml

from torchcal.kinematics.transforms import so3_exp
from torchcal.kinematics.tree import JointSpec, Marker
from torchcal.kinematics.urdf import urdf_links, write_urdf
from torchcal.kinematics.ur_layout import ur_joints
from torchcal.kinematics.urdf_edit import (OriginEdit, edit_origins, format_number, format_values, origin_text,
                                           rpy_near)

__all__ = ["URDFExport", "origin_attrs", "CALIBRATION_YAML", "URDF_NAME"]

URDF_NAME = "calibrated.urdf"
CALIBRATION_YAML = "calibration.yaml"
# a joint change at or below this is no change (m for lengths, rad for angles): the files keep the
# joint's nominal origin
NO_CHANGE = 1e-9


def origin_attrs(T: np.ndarray, rpy0=(0.0, 0.0, 0.0)) -> dict[str, str]:
    """``xyz`` and ``rpy`` attribute values of a (4, 4) transform, the rpy closest to ``rpy0``."""
    return {"xyz": format_values(T[:3, 3], None), "rpy": format_values(rpy_near(T[:3, :3], rpy0), None)}


def _xyzrpy(v) -> dict[str, float]:
    return {k: format_number(x) for k, x in zip(("x", "y", "z", "roll", "pitch", "yaw"), v)}


def _origin_xyzrpy(T: np.ndarray, written) -> dict[str, float]:
    """``x y z roll pitch yaw`` of the transform ``T (4, 4)``, the rpy closest to the one the URDF
    writes (``written``: its ``(xyz, rpy)``, or None)."""
    rpy0 = np.zeros(3) if written is None else written[1]
    return _xyzrpy(np.concatenate([T[:3, 3], rpy_near(T[:3, :3], rpy0)]))


def _fixed_link(name: str, parent: str, T: np.ndarray, joint: str) -> list[str]:
    o = origin_attrs(T)
    return [f'<link name="{name}"/>', f'<joint name="{joint}" type="fixed">', f'  <parent link="{parent}"/>',
            f'  <child link="{name}"/>', f'  <origin xyz="{o["xyz"]}" rpy="{o["rpy"]}"/>', "</joint>"]


class URDFExport:
    """The URDF-export half of :class:`~torchcal.kinematics.robot.Robot` (a mixin)."""

    # ------------------------------------------------------------------ calibrated origins
    def _vector(self, params) -> torch.Tensor:
        p = self._check_params(params)
        if p is None:
            p = torch.zeros(self.n_params, dtype=self.dtype, device=self.device)
        if p.ndim != 1:
            raise ValueError("give one parameter vector (K,), not a population")
        return p

    def significant(self, params, std_errors: dict[str, float] | None = None) -> torch.Tensor:
        """``(K,)`` ``params`` with the parameters of every joint whose change is not significant
        set to zero (no error): a joint whose every parameter lies within its standard error
        (``std_errors``: name -> m or rad; a parameter without one has none) and within
        :data:`NO_CHANGE`. What the exported files hold (module docstring)."""
        p = self._vector(params).detach().clone()
        se = std_errors or {}
        by_joint: dict[str, list[int]] = {}
        for i, n in enumerate(self.param_names):
            by_joint.setdefault(n.rsplit(".", 1)[0], []).append(i)
        for jt in self.joints:
            idx = by_joint.get(jt.name, [])
            small = all(abs(float(p[i])) <= max(NO_CHANGE, float(se.get(self.param_names[i], 0.0) or 0.0))
                        for i in idx)  # a NaN standard error (not identified) is no licence to drop
            if idx and small:
                p[idx] = 0.0
        return p

    def _origins_np(self, params) -> tuple[np.ndarray, np.ndarray]:
        """``(J, 4, 4)`` joint origins with the errors of ``params`` (zero offsets not folded in)
        and ``(J,)`` each joint's zero offset (rad / m; a mimic joint's is its multiplier times
        its source's)."""
        p = self._vector(params)
        slots = self._slots(p[None].to(torch.float64))
        O_R, O_t = self._true_origins(slots)
        T = np.tile(np.eye(4), (len(self.joints), 1, 1))
        T[:, :3, :3], T[:, :3, 3] = O_R[0].detach().cpu().numpy(), O_t[0].detach().cpu().numpy()
        off = slots[0, self._slices["offset"]]
        delta = np.array([float(self._mult[j] * off[int(self._src[j])]) if jt.movable else 0.0
                          for j, jt in enumerate(self.joints)])
        return T, delta

    def _fold(self, jt: JointSpec, T: np.ndarray, delta: float) -> np.ndarray:
        T = T.copy()
        if jt.movable:  # also at 0: the product with the identity is what the shipped URDFs were made with
            if jt.type == "prismatic":
                T[:3, 3] += T[:3, :3] @ (jt.axis * delta)
            else:
                T[:3, :3] = T[:3, :3] @ so3_exp(torch.as_tensor(jt.axis * delta)).numpy()
        return T

    def calibrated_joints(self, params) -> list[JointSpec]:
        """Joint specs whose origins carry the errors in ``params`` (offsets folded in)."""
        T, delta = self._origins_np(params)
        out = []
        for j, jt in enumerate(self.joints):
            nj = copy.copy(jt)
            nj.origin, nj.dh = self._fold(jt, T[j], delta[j]), None
            out.append(nj)
        return out

    def _extra_frames(self, params) -> tuple[np.ndarray | None, list[tuple[Marker, np.ndarray]]]:
        p = self._vector(params)
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

    def origin_corrections(self, params) -> list[dict]:
        """Per joint the calibration changed: ``joint``; ``correction``, the origin correction
        ``(x, y, z)`` m and ``(roll, pitch, yaw)`` rad with ``calibrated = nominal · Trans(x, y, z)
        · Rz(yaw) Ry(pitch) Rx(roll) · (zero offset about the axis)``; ``zero_offset`` (rad / m);
        ``origin`` (4, 4), the calibrated origin with the offset folded in (what the exported URDF
        holds). Joints in the robot's order."""
        p = self._vector(params).detach().cpu().double()
        T0, _ = self._origins_np(None)
        T, delta = self._origins_np(params)
        index = {n: i for i, n in enumerate(self.param_names)}
        out = []
        for j, jt in enumerate(self.joints):
            names = [f"{jt.name}.{s}" for s in ("dx", "dy", "dz", "droll", "dpitch", "dyaw")]
            if jt.dh is None and all(n in index for n in names):
                corr = np.array([float(p[index[n]]) for n in names])
            else:  # a DH row: its errors are not origin errors, so read the correction off the transforms
                C = np.linalg.solve(T0[j], T[j])
                corr = np.concatenate([C[:3, 3], rpy_near(C[:3, :3], np.zeros(3))])
            if not (np.array_equal(T[j], T0[j]) and delta[j] == 0.0):
                out.append({"joint": jt.name, "type": jt.type, "correction": corr + 0.0,
                            "zero_offset": float(delta[j]) + 0.0, "origin": self._fold(jt, T[j], delta[j])})
        return out

    # ------------------------------------------------------------------ files
    def export_urdf(self, params, path, *, with_instrument: bool = False, base_link: str = "instrument",
                    note: str | None = None, with_markers: bool = False,
                    std_errors: dict[str, float] | None = None) -> str:
        """Write a URDF whose nominal kinematics equal this robot's calibrated kinematics, in the
        robot's own base frame, as the module docstring says it may differ from the input.

        Joint origins carry the identified errors and zero offsets of the joints whose change is
        significant (:meth:`significant`, with ``std_errors``). With ``with_markers`` each marker
        becomes a fixed link ``marker_<name>`` on its link. The instrument registration (the base
        frame parameters) is left out, so that the root stays the robot's; with
        ``with_instrument`` a non-zero base frame becomes a new root link ``base_link`` (the
        instrument frame). ``note`` goes into an XML comment. Returns the XML text.

        When the robot came from a URDF, its text is edited in place: only the ``<origin>`` of
        the joints the calibration changed is rewritten, the rpy chosen closest to the original
        one (:func:`~torchcal.kinematics.urdf_edit.rpy_near`), numbers it leaves equal keep their
        spelling, and every other byte (comments, visuals, collisions, inertials, limits, mimic
        tags, transmissions, gazebo blocks) stays as it was.
        """
        params = self.significant(params, std_errors)
        base, mks = self._extra_frames(params)
        if not with_instrument:
            base = None
        if not with_markers:
            mks = []
        if self._urdf_text is None:
            joints = self.calibrated_joints(params)
            extra = [JointSpec(name=f"marker_{mk.name}_joint", type="fixed", parent=mk.link,
                               child=f"marker_{mk.name}", origin=T) for mk, T in mks]
            if base is not None:
                extra.insert(0, JointSpec(name=f"{base_link}_to_{self.root}", type="fixed", parent=base_link,
                                          child=self.root, origin=base))
            return write_urdf(self.name, ([extra[0]] if base is not None else []) + joints +
                              extra[1 if base is not None else 0:], path)
        links = set(self.links_in_urdf())
        append = []
        for mk, T in mks:
            ln = f"marker_{mk.name}"
            if ln in links:
                raise ValueError(f"cannot export: link {ln!r} already exists in the URDF")
            append += _fixed_link(ln, mk.link, T, f"{ln}_joint")
        if base is not None:
            if base_link in links:
                raise ValueError(f"cannot export: link {base_link!r} already exists; pass base_link='…'")
            append += [f'<link name="{base_link}"/>'] + _fixed_link(self.root, base_link, base,
                                                                       f"{base_link}_to_{self.root}")[1:]
        written = origin_text(self._urdf_text)
        edits = {}
        nominal = {jt.name: jt.origin for jt in self.joints}
        for c in self.origin_corrections(params):
            T, T0 = c["origin"], nominal[c["joint"]]
            rot = not np.array_equal(T[:3, :3], T0[:3, :3])
            edits[c["joint"]] = OriginEdit(T[:3, 3] if not np.array_equal(T[:3, 3], T0[:3, 3]) else None,
                                           rpy_near(T[:3, :3], written[c["joint"]][1]) if rot else None)
        xml = edit_origins(self._urdf_text, edits, append, note)
        Path(path).write_text(xml)
        return xml

    def links_in_urdf(self) -> list[str]:
        """Every link named in the URDF text (or in the joints, for a robot built from DH)."""
        if self._urdf_text is None:
            return list(dict.fromkeys(l for jt in self.joints for l in (jt.parent, jt.child)))
        return urdf_links(self._urdf_text)

    def calibration_yaml(self, params, note: str | None = None, std_errors: dict[str, float] | None = None) -> str:
        """``calibration.yaml``: each significantly changed joint's origin correction as ``x y z
        roll pitch yaw`` and its zero offset, the calibrated origins under ``kinematics`` and the
        marker points, with units stated.

        A UR arm (:func:`~torchcal.kinematics.ur_layout.ur_joints`) gets its own layout under
        ``kinematics``: ``ur_description``'s ``default_kinematics.yaml``, every one of the six
        joints listed (unchanged ones too) by its key, and ``hash`` inside, so that the file drops
        into a UR description. Any other robot gets the calibrated origins of the changed joints,
        by joint name, and ``hash`` at the top."""
        params = self.significant(params, std_errors)
        corr = self.origin_corrections(params)
        written = origin_text(self._urdf_text) if self._urdf_text is not None else {}
        body = {
            "robot": self.name,
            "units": {"x": "m", "y": "m", "z": "m", "roll": "rad", "pitch": "rad", "yaw": "rad",
                      "zero_offsets": "rad (revolute joints), m (prismatic joints)"},
            "corrections": {c["joint"]: _xyzrpy(c["correction"]) for c in corr if np.any(c["correction"] != 0)},
            "zero_offsets": {c["joint"]: c["zero_offset"] for c in corr if c["zero_offset"] != 0.0},
            "kinematics": {c["joint"]: _origin_xyzrpy(c["origin"], written.get(c["joint"])) for c in corr},
            "markers": {},
        }
        ur = ur_joints(self.joints)
        if ur is not None:
            origins = {jt.name: o for jt, o in zip(self.joints, self._folded(params))}
            body["kinematics"] = {key: _origin_xyzrpy(origins[j], written.get(j)) for key, j in ur.items()}
            others = {c["joint"]: _origin_xyzrpy(c["origin"], written.get(c["joint"])) for c in corr
                      if c["joint"] not in ur.values()}
            if others:  # the UR macro reads none of these: calibrated.urdf holds them
                body["other_joints"] = others
        _, mks = self._extra_frames(params)
        for mk, T in mks:
            body["markers"][mk.name] = {"link": mk.link, **_origin_xyzrpy(T, None)}
        text = yaml.safe_dump(body, sort_keys=False, default_flow_style=False)
        calib = "calib_" + hashlib.sha256(text.encode()).hexdigest()[:16]
        if ur is not None:
            body["kinematics"]["hash"] = calib
            text = yaml.safe_dump(body, sort_keys=False, default_flow_style=False)
        else:
            text += f"hash: {calib}\n"
        return "\n".join(self._yaml_head(note, ur is not None, "other_joints" in body)) + "\n" + text

    def _folded(self, params) -> list[np.ndarray]:
        """Every joint's calibrated origin (4, 4), its zero offset folded in, in the robot's order."""
        T, delta = self._origins_np(params)
        return [self._fold(jt, T[j], delta[j]) for j, jt in enumerate(self.joints)]

    def _yaml_head(self, note: str | None, ur: bool, others: bool) -> list[str]:
        head = [f"# Calibration of {self.name} (torchcal)."] + ([f"# {note}"] if note else []) + [
            "# Units: x, y, z in metres; roll, pitch, yaw in radians (URDF convention: R = Rz(yaw) Ry(pitch) Rx(roll));",
            "# zero offsets in radians (revolute joints) or metres (prismatic joints).",
            "# corrections: for each joint the calibration changed, calibrated origin = nominal origin",
            "#   · Trans(x, y, z) · Rz(yaw) Ry(pitch) Rx(roll) · (rotation or shift by the zero offset about the",
            "#   joint axis); the joint's true position is its command plus the zero offset (a mimic joint's:",
            "#   its multiplier times its source's).",
            "# A joint whose every parameter moved within its standard error and by at most 1e-9 m / rad is",
            "#   unchanged here and in calibrated.urdf."]
        if ur:
            head += ["# kinematics: ur_description's default_kinematics.yaml: the calibrated origin of every UR joint",
                     "#   (offsets folded in), shoulder = shoulder_pan_joint, upper_arm = shoulder_lift_joint, forearm =",
                     "#   elbow_joint, wrist_1..3 = wrist_1..3_joint; give this file as the UR description's",
                     "#   kinematics_parameters_file (xacro reads it with xacro.load_yaml)."]
            if others:
                head += ["# other_joints: changed joints the UR layout has no key for (the UR macro does not read them;",
                         "#   calibrated.urdf holds them)."]
        else:
            head += ["# kinematics: the resulting origins, as calibrated.urdf writes them (offsets folded in), by",
                     "#   joint name; joints not listed are unchanged."]
        return head + ["# markers: each measured point on its link (calibrated.urdf's marker_<name> links, with",
                       "#   --with-markers)."]

    def export_calibration(self, params, out_dir, *, with_instrument: bool = False, base_link: str = "instrument",
                           note: str | None = None, with_markers: bool = False,
                           std_errors: dict[str, float] | None = None) -> tuple[Path, Path]:
        """Write ``calibrated.urdf`` (:meth:`export_urdf`) and ``calibration.yaml``
        (:meth:`calibration_yaml`) into ``out_dir``, the two files every calibration output
        holds, both with the joints whose change is significant (``std_errors``: name -> m or
        rad, the fit's). Returns their paths."""
        out = Path(out_dir)
        self.export_urdf(params, out / URDF_NAME, with_instrument=with_instrument, base_link=base_link, note=note,
                         with_markers=with_markers, std_errors=std_errors)
        (out / CALIBRATION_YAML).write_text(self.calibration_yaml(params, note=note, std_errors=std_errors))
        return out / URDF_NAME, out / CALIBRATION_YAML

    def to_urdf_string(self, params=None, inertials: dict | None = None, comment: str | None = None) -> str:
        """Nominal (or calibrated) kinematics as URDF text, without marker or base links."""

        return write_urdf(self.name, self.calibrated_joints(params), None, inertials=inertials, comment=comment)
