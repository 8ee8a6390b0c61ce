"""A calibrated :class:`~torchcal.kinematics.robot.Robot` written back as URDF: the original text
with corrected joint origins and added marker / instrument links, so everything kinematics does
not read (meshes, limits, inertials) survives."""
from __future__ import annotations

import copy
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import torch

from torchcal.kinematics.transforms import matrix_to_rpy, so3_exp
from torchcal.kinematics.tree import JointSpec, Marker
from torchcal.kinematics.urdf import write_urdf

__all__ = ["URDFExport", "edit_urdf", "origin_attrs"]


def origin_attrs(T: np.ndarray) -> dict[str, str]:
    rpy = matrix_to_rpy(torch.as_tensor(T[:3, :3])).numpy() + 0.0  # + 0.0 turns -0.0 into 0.0
    return {"xyz": " ".join(repr(float(v) + 0.0) for v in T[:3, 3]), "rpy": " ".join(repr(float(v)) for v in rpy)}


def edit_urdf(text: str, joints: list[JointSpec], mks, base, base_link: str, root: str,
               note: str | None = None) -> str:
    """The original URDF text with new joint origins and added marker/base links. Editing the
    XML (rather than re-writing a parsed model) keeps everything kinematics does not read:
    mimic tags, transmissions, gazebo blocks, comments."""

    parser = ET.XMLParser(target=ET.TreeBuilder(insert_comments=True))
    tree = ET.ElementTree(ET.fromstring(text, parser=parser))
    rob = tree.getroot()
    by_name = {j.get("name"): j for j in rob.findall("joint")}
    for jt in joints:
        el = by_name[jt.name]
        o = el.find("origin")
        if o is None:
            o = ET.SubElement(el, "origin")
        o.attrib.update(origin_attrs(jt.origin))
    links = {l.get("name") for l in rob.findall("link")}
    for mk, T in mks:
        ln = f"marker_{mk.name}"
        if ln in links:
            raise ValueError(f"cannot export: link {ln!r} already exists in the URDF")
        ET.SubElement(rob, "link", name=ln)
        j = ET.SubElement(rob, "joint", name=f"{ln}_joint", type="fixed")
        ET.SubElement(j, "parent", link=mk.link)
        ET.SubElement(j, "child", link=ln)
        ET.SubElement(j, "origin", origin_attrs(T))
    if base is not None:
        if base_link in links:
            raise ValueError(f"cannot export: link {base_link!r} already exists; pass base_link='…'")
        ET.SubElement(rob, "link", name=base_link)
        j = ET.SubElement(rob, "joint", name=f"{base_link}_to_{root}", type="fixed")
        ET.SubElement(j, "parent", link=base_link)
        ET.SubElement(j, "child", link=root)
        ET.SubElement(j, "origin", origin_attrs(base))
    if note:
        rob.insert(0, ET.Comment(" " + note.replace("--", "—") + " "))
    ET.indent(tree, space="  ")
    return '<?xml version="1.0"?>\n' + ET.tostring(rob, encoding="unicode") + "\n"




class URDFExport:
    """The URDF-export half of :class:`~torchcal.kinematics.robot.Robot` (a mixin)."""

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
            xml = edit_urdf(self._urdf_text, joints, mks, base, base_link, self.root, note)
            Path(path).write_text(xml)
            return xml
        extra = [JointSpec(name=f"marker_{mk.name}_joint", type="fixed", parent=mk.link, child=f"marker_{mk.name}",
                           origin=T) for mk, T in mks]
        if base is not None:
            extra.insert(0, JointSpec(name=f"{base_link}_to_{self.root}", type="fixed", parent=base_link,
                                      child=self.root, origin=base))

        return write_urdf(self.name, ([extra[0]] if base is not None else []) + joints +
                          extra[1 if base is not None else 0:], path)

    def to_urdf_string(self, params=None, inertials: dict | None = None, comment: str | None = None) -> str:
        """Nominal (or calibrated) kinematics as URDF text, without marker or base links."""

        return write_urdf(self.name, self.calibrated_joints(params), None, inertials=inertials, comment=comment)
