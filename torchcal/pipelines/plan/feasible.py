"""Where a pose plan may put the robot: inside the instrument's working volume, and clear of
itself.

**Reachability** (:func:`parse_box`, :func:`in_box`): every marker inside an axis-aligned box in
the robot base frame, ``(xmin, xmax, ymin, ymax, zmin, zmax)`` in metres, at the nominal (or
given) geometry.

**Self-collision** (:class:`SelfCollision`), a conservative check on the URDF's ``<collision>``
shapes. What is checked:

* every shape is covered by spheres: a sphere by itself; a box cut along its longest side into
  at most 8 pieces, each inside one sphere; a cylinder as its bounding box; a mesh as the
  bounding box of its vertices, when its file can be found (``package://`` paths are looked for
  beside the URDF and one folder up);
* two links collide when a sphere of one comes within ``margin`` of a sphere of the other. The
  spheres hold the shapes, so a clear pose may be refused, never a colliding one passed (for the
  pairs and shapes checked).

What is not checked: pairs of links one joint apart or fixed together (they touch by design);
pairs whose spheres already overlap at the zero configuration (listed, like an SRDF's disabled
pairs); links that are not between the root and a marker; meshes whose file cannot be found
(skipped with a warning); anything the URDF does not describe (tool, cables, the table, the
instrument, walls); and the motion between poses: only the poses themselves.
"""
from __future__ import annotations

import math
import warnings
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from torchcal.kinematics.robot import Robot
from torchcal.kinematics.urdf import read_collisions

__all__ = ["parse_box", "in_box", "SelfCollision"]

_MAX_PIECES = 8  # spheres per box: more hug a long link closer but cost more pairs


def parse_box(box) -> Tensor:
    """``(6,)`` float64 box ``(xmin, xmax, ymin, ymax, zmin, zmax)`` (m) from a sequence or a
    comma-separated string; raises ``ValueError`` naming what is wrong."""
    try:
        vals = [float(v) for v in (box.replace(" ", "").split(",") if isinstance(box, str) else box) if v != ""]
    except (TypeError, ValueError):
        raise ValueError(f"reachable box {box!r}: give six numbers xmin,xmax,ymin,ymax,zmin,zmax in metres") from None
    if len(vals) != 6:
        raise ValueError(f"reachable box: give six numbers xmin,xmax,ymin,ymax,zmin,zmax (m), got {len(vals)}")
    if not all(math.isfinite(v) for v in vals):
        raise ValueError(f"reachable box {vals}: every bound must be a finite number (m)")
    bad = [a for a, lo, hi in zip("xyz", vals[0::2], vals[1::2]) if not lo < hi]
    if bad:
        raise ValueError(f"reachable box {vals}: the minimum must be below the maximum along {', '.join(bad)} "
                         "(order: xmin,xmax,ymin,ymax,zmin,zmax)")
    if max(abs(v) for v in vals) > 50:
        raise ValueError(f"reachable box {vals}: bounds beyond 50 m look like millimetres; give metres")
    return torch.tensor(vals, dtype=torch.float64)


def in_box(robot, q: Tensor, box: Tensor, params: Tensor | None = None) -> Tensor:
    """``(N,)`` bool: every marker of ``robot`` at poses ``q (N, dof)`` lies inside ``box``
    (robot base frame, m)."""
    p = robot.positions(q, params, check=False, base=False)  # (N, M, 3)
    b = box.to(p)
    return ((p >= b[0::2]) & (p <= b[1::2])).all(-1).all(-1)


def _box_spheres(T: np.ndarray, size: np.ndarray) -> list[tuple[np.ndarray, float]]:
    """Spheres covering a box of ``size`` (3,) centred at ``T``'s origin, axes ``T``'s."""
    i = int(np.argmax(size))
    other = np.delete(size, i)
    n = int(min(_MAX_PIECES, max(1, math.ceil(size[i] / max(float(other.max()), 1e-9)))))
    piece = size[i] / n
    r = 0.5 * math.sqrt(piece ** 2 + float((other ** 2).sum()))
    out = []
    for j in range(n):
        c = np.zeros(3)
        c[i] = -size[i] / 2 + (j + 0.5) * piece
        out.append((T[:3, :3] @ c + T[:3, 3], r))
    return out


def _find_mesh(filename: str, base: Path | None) -> Path | None:
    if filename.startswith("file://"):
        p = Path(filename[7:])
        return p if p.is_file() else None
    tries: list[Path] = []
    if filename.startswith("package://"):
        pkg, _, rest = filename[10:].partition("/")
        if base is not None:
            tries = [base / rest, base.parent / rest, base / pkg / rest, base.parent / pkg / rest]
    elif Path(filename).is_absolute():
        tries = [Path(filename)]
    elif base is not None:
        tries = [base / filename]
    return next((p for p in tries if p.is_file()), None)


def _mesh_box(path: Path, scale: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    # trimesh comes with yourdfpy; imported here because only URDFs with mesh collisions need it
    import trimesh

    lo, hi = np.asarray(trimesh.load(str(path), force="mesh").bounds, dtype=float) * scale
    lo, hi = np.minimum(lo, hi), np.maximum(lo, hi)  # a negative scale mirrors the mesh
    return (lo + hi) / 2, hi - lo


class SelfCollision:
    """Self-collision of ``robot``'s links by bounding spheres (module docstring).

    Args:
        robot: a :class:`~torchcal.kinematics.robot.Robot` built from a URDF.
        margin: clearance (m) two links must keep.
        urdf_path: the URDF file, to find mesh files relative to it (default: meshes given by
            absolute or ``file://`` paths only).

    Attributes:
        checked: whether any pair of links is checked (False: the URDF has no usable shapes).
        pairs, touching_at_zero, skipped_meshes, links: what is and is not checked.
    """

    def __init__(self, robot, margin: float = 0.0, urdf_path=None):
        if margin < 0:
            raise ValueError(f"collision margin must be zero or positive (m), got {margin}")
        self.robot, self.margin = robot, float(margin)
        self.skipped_meshes: list[str] = []
        self.pairs: list[tuple[str, str]] = []
        self.touching_at_zero: list[tuple[str, str]] = []
        self.links: list[str] = []
        self.checked = False
        if robot.urdf_text is None:
            return
        base = Path(urdf_path).resolve().parent if urdf_path is not None else None
        shapes = read_collisions(robot.urdf_text)
        centres, radii, owner = [], [], []
        for link, items in shapes.items():
            if link not in robot.link_frame:
                continue
            for s in items:
                T = s["origin"]
                if s["kind"] == "sphere":
                    sph = [(T[:3, 3], s["radius"])]
                elif s["kind"] == "box":
                    sph = _box_spheres(T, s["size"])
                elif s["kind"] == "cylinder":
                    sph = _box_spheres(T, np.array([2 * s["radius"], 2 * s["radius"], s["length"]]))
                else:
                    path = _find_mesh(s["filename"], base)
                    if path is None:
                        self.skipped_meshes.append(f"{link}: {s['filename']}")
                        continue
                    c, size = _mesh_box(path, s["scale"])
                    Tc = T.copy()
                    Tc[:3, 3] = T[:3, :3] @ c + T[:3, 3]
                    sph = _box_spheres(Tc, size)
                for c, r in sph:
                    centres.append(c), radii.append(r), owner.append(link)
        if self.skipped_meshes:
            warnings.warn(f"self-collision: {len(self.skipped_meshes)} collision mesh(es) not found and not checked "
                          f"({'; '.join(self.skipped_meshes[:3])}{' …' if len(self.skipped_meshes) > 3 else ''}); "
                          "give the URDF's path so that package:// meshes can be found beside it", stacklevel=2)
        self.links = list(dict.fromkeys(owner))
        if len(self.links) < 2:
            return
        self._frames = Robot.from_urdf(robot.urdf_text, markers=self.links, dtype=robot.dtype, device=robot.device)
        self._cols = [robot.joint_names.index(n) for n in self._frames.joint_names]
        li = {l: i for i, l in enumerate(self.links)}
        dt = dict(dtype=robot.dtype, device=robot.device)
        self._owner = torch.tensor([li[o] for o in owner], device=robot.device)
        self._c = torch.tensor(np.stack(centres), **dt)
        self._r = torch.tensor(radii, **dt)
        self._mask = self._pair_mask(li)
        q0 = torch.zeros(1, robot.dof, **dt).clamp(*(x[None] for x in robot.joint_limits))
        at_zero = self._overlaps(q0)[0] & self._mask
        self.touching_at_zero = self._names(at_zero)
        self._mask &= ~at_zero
        self.pairs = self._names(self._mask)
        self.checked = bool(self.pairs)

    def _pair_mask(self, li: dict[str, int]) -> Tensor:
        """``(S, S)`` spheres of link pairs to check: different rigid bodies, not one joint apart."""
        body = {l: l for l in self.robot.link_frame}

        def find(l):
            while body[l] != l:
                l = body[l]
            return l
        for jt in self.robot.joints:
            if jt.type == "fixed":
                body[find(jt.child)] = find(jt.parent)
        adjacent = {frozenset((find(jt.parent), find(jt.child))) for jt in self.robot.joints if jt.type != "fixed"}
        L = len(self.links)
        ok = torch.zeros(L, L, dtype=torch.bool, device=self._c.device)
        for a in self.links:
            for b in self.links:
                ba, bb = find(a), find(b)
                ok[li[a], li[b]] = li[a] < li[b] and ba != bb and frozenset((ba, bb)) not in adjacent
        return ok[self._owner][:, self._owner]

    def _names(self, sphere_mask: Tensor) -> list[tuple[str, str]]:
        L = len(self.links)
        link_mask = torch.zeros(L, L, dtype=torch.long, device=sphere_mask.device)
        link_mask.index_put_((self._owner[:, None].expand_as(sphere_mask)[sphere_mask],
                              self._owner[None, :].expand_as(sphere_mask)[sphere_mask]),
                             torch.ones(int(sphere_mask.sum()), dtype=torch.long, device=sphere_mask.device),
                             accumulate=True)
        return [(self.links[i], self.links[j]) for i, j in torch.nonzero(link_mask).tolist()]

    def _overlaps(self, q: Tensor) -> Tensor:
        """``(N, S, S)`` sphere pairs closer than their radii plus the margin."""
        R, t = self._frames.fk_rt(q[:, self._cols], check=False)  # (N, L, 3, 3), (N, L, 3)
        c = (R[:, self._owner] @ self._c[..., None])[..., 0] + t[:, self._owner]  # (N, S, 3)
        return torch.cdist(c, c) < self._r[:, None] + self._r[None, :] + self.margin

    def __call__(self, q: Tensor) -> Tensor:
        """``(N,)`` bool: poses ``q (N, dof)`` where a checked pair of links collides."""
        if not self.checked:
            return torch.zeros(q.shape[0], dtype=torch.bool, device=q.device)
        return (self._overlaps(q.detach()) & self._mask).flatten(1).any(-1)

    def describe(self) -> dict:
        """What is checked and what is not, for reports."""
        return {"checked": self.checked, "margin_m": self.margin, "links_with_shapes": list(self.links),
                "pairs_checked": [list(p) for p in self.pairs],
                "not_checked_touching_at_zero": [list(p) for p in self.touching_at_zero],
                "not_checked_missing_meshes": list(self.skipped_meshes),
                "method": "link collision shapes covered by spheres (boxes cut into up to 8 pieces; cylinders and "
                          "meshes by their bounding boxes); links one joint apart or fixed together are not "
                          "checked, nor the environment, the tool beyond the URDF, or the motion between poses"}
