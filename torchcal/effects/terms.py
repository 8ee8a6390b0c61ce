"""A general family of joint-space errors: each joint's angle error a sparse sum of terms.

Catalogued effects name one physical cause each (backlash, a cyclic encoder error, compliance).
An error with another shape, say a wrist whose last joint turns with the joint before it (gear
coupling, which controllers compensate with a coupling factor), or a joint that creeps with a
motor's temperature, is found only when some catalogued effect happens to have that shape. This
family gives the loop every such shape as a mode of one parameter::

    Δq_j = Σ_t c_{j,t} f_t(q, covariates)

with terms ``f_t`` (each scaled by one coefficient, the mode's parameter):

* ``lin:<k>``: the angle (or travel) of joint ``k``: coupling for ``k ≠ j``, a scale error for
  ``k = j``;
* ``sin<n>:<k>``, ``cos<n>:<k>``: harmonics ``n = 1..harmonics`` of joint ``k``'s angle;
* ``cov:<c>``: a numeric covariate column, minus its training mean (a temperature, a time);
* ``dir:<k>``: the direction from which joint ``k`` reached the pose (``dir.<k>``, ±1).

Joint sources are the joint itself and the joints within :data:`REACH` actuated joints of it along
the chain: couplings are mechanical, between neighbouring axes, and a term of a far joint is what
gravity's wrench (compliance, deformation) produces. The loop tries this family last in each round
(:attr:`Effect.fallback`), so that a physical effect explaining the same residual is taken first:
the family takes only what the catalogue leaves.
"""
from __future__ import annotations

import torch
from torch import Tensor

from torchcal.effects.base import TIME_COVARIATES, Effect, Prepared
from torchcal.measure.data import is_quality_column

__all__ = ["JointTerms", "REACH", "driver_columns"]

REACH = 2  # joints along the chain whose angles may enter another joint's error


def driver_columns(covariates: dict) -> list[str]:
    """Numeric covariate columns that may drive an error: all but the directions of approach
    (their own terms), the columns that describe the measurement
    (:func:`~torchcal.measure.data.is_quality_column`) and columns that never change."""
    out = []
    for k, v in covariates.items():
        if k.startswith("dir.") or is_quality_column(k) or k == "row" or "=" in k:
            continue  # the row order and text levels are drivers of parameter_drivers
        v = v[torch.isfinite(v)]
        if v.numel() > 1 and float(v.max() - v.min()) > 0:
            out.append(k)
    return out


def _neighbours(robot) -> dict[str, list[str]]:
    """For each actuated joint, the actuated joints within :data:`REACH` steps up or down the chain."""
    act = set(robot.joint_names)
    up: dict[str, list[str]] = {}
    for j, jt in enumerate(robot.joints):
        if jt.name not in act:
            continue
        chain, f = [], robot.parent_frame[j]
        while f != 0 and len(chain) < REACH:
            p = robot.joints[f - 1]
            if p.name in act:
                chain.append(p.name)
            f = robot.parent_frame[f - 1]
        up[jt.name] = chain
    out = {n: [n] + up[n] for n in robot.joint_names}
    for n, anc in up.items():
        for a in anc:
            out[a].append(n)
    return {n: [k for k in robot.joint_names if k in set(v)] for n, v in out.items()}


class JointTerms(Effect):
    """Joint errors as a sparse sum of terms in the joints' angles, covariates and directions of
    approach (module docstring); the loop selects the terms.

    Args:
        terms: ``[(target joint, tag), ...]`` with tags ``lin:<joint>``, ``sin<n>:<joint>``,
            ``cos<n>:<joint>``, ``cov:<column>``, ``dir:<joint>`` (default: every term of the
            catalogue, see :meth:`catalog`).
        harmonics: highest harmonic of the angle terms.
        centres: column -> training mean of each covariate term (set by :meth:`bind`).
    """

    name = "joint_terms"
    description = "joint errors as terms in other joints' angles, harmonics, covariates and directions"
    reads = ("direction", "measured")
    selectable = True
    fallback = True

    def __init__(self, robot, joints=None, geometry=None, terms: list | None = None, harmonics: int = 2,
                 centres: dict | None = None):
        self.harmonics = int(harmonics)
        self.centres = dict(centres or {})
        self.terms = [tuple(t) for t in terms or []]
        super().__init__(robot, joints, geometry)
        if terms is None:  # the catalogue needs the targets, which the base class resolves
            self.terms = self.catalog(list(self.centres))
            self.theta = torch.zeros(self.n_params, dtype=robot.dtype, device=robot.device)

    def catalog(self, columns: list[str], directions: list[str] = ()) -> list[tuple[str, str]]:
        """Every term of the family for the targets ``self.joints``: neighbouring joints' angles
        (linear, and harmonics for revolute ones), ``columns`` and the ``directions`` (joints with a
        ``dir.<joint>`` column)."""
        near = _neighbours(self.robot)
        units = dict(zip(self.robot.joint_names, self.robot.joint_units))
        out = []
        for j in self.joints:
            for k in near[j]:
                out.append((j, f"lin:{k}"))
                if units[k] == "rad":
                    out += [(j, f"{f}{n}:{k}") for n in range(1, self.harmonics + 1) for f in ("sin", "cos")]
            out += [(j, f"cov:{c}") for c in columns]
            out += [(j, f"dir:{k}") for k in near[j] if k in set(directions)]
        return out

    def config(self) -> dict:
        return {"terms": [list(t) for t in self.terms], "harmonics": self.harmonics, "centres": dict(self.centres)}

    @property
    def covariates(self) -> list[str]:
        cols = [t.split(":", 1)[1] for _, t in self.terms if t.startswith("cov:")]
        cols += [f"dir.{t.split(':', 1)[1]}" for _, t in self.terms if t.startswith("dir:")]
        return list(dict.fromkeys(cols))

    def _unit(self, joint: str) -> str:
        return self.robot.joint_units[self.robot.joint_names.index(joint)]

    def param_info(self):
        out = []
        for j, t in self.terms:
            kind, src = t.split(":", 1)
            tu = self._unit(j)
            if kind == "lin":
                u = f"{tu}/{self._unit(src)}"
            elif kind == "cov":
                u = f"{tu}/({'s' if src in TIME_COVARIATES else 'unit'})"
            else:
                u = tu
            out.append((f"{j}.{t}", u))
        return out

    def modes(self):
        return [(f"{j}.{t}", [i]) for i, (j, t) in enumerate(self.terms)]

    def with_modes(self, labels: list[str]) -> "JointTerms":
        keep = set(labels)
        return self._copy(terms=[t for t in self.terms if f"{t[0]}.{t[1]}" in keep])

    def _copy(self, **changes) -> "JointTerms":
        if "joints" in changes and "terms" not in changes:
            js = set(changes["joints"])
            changes["terms"] = [t for t in self.terms if t[0] in js]
        return super()._copy(**changes)

    def bind(self, data, min_lever_m: float = 5e-3) -> "JointTerms":
        """A copy for ``data``: targets that move the markers (:meth:`Effect.bind`), the catalogue
        over the data's driver columns (:func:`driver_columns`, centred on their training means)
        and directions, and every covariate's training range."""
        moved = Effect.bind(self, data, min_lever_m)
        cols = driver_columns(data.covariates)
        dirs = [j for j in self.robot.joint_names if f"dir.{j}" in data.covariates]
        centres = {c: float(data.covariates[c].mean()) for c in cols}
        out = type(self)(self.robot, moved.joints, geometry=self.geometry, terms=[], harmonics=self.harmonics,
                         centres=centres)
        out.terms = out.catalog(cols, dirs)
        out.theta = torch.zeros(out.n_params, dtype=self.robot.dtype, device=self.robot.device)
        out.covariate_range = {c: (float(data.covariates[c].min()), float(data.covariates[c].max()))
                               for c in out.covariates if c in data.covariates}
        return out

    def applicable(self, data) -> tuple[bool, str]:
        return True, ""

    def prepare(self, q, covariates):
        cols = []
        for j, t in self.terms:
            kind, src = t.split(":", 1)
            if kind == "cov":
                if src not in covariates:
                    raise ValueError(f"joint_terms needs the covariate {src!r} (term {j}.{t})")
                cols.append(covariates[src].to(q) - self.centres.get(src, 0.0))
            elif kind == "dir":
                d = covariates.get(f"dir.{src}")
                if d is None:
                    raise ValueError(f"joint_terms needs the covariate 'dir.{src}' (+1/-1) (term {j}.{t})")
                cols.append(torch.sign(d.to(q)))
            else:
                x = q[:, self.robot.joint_names.index(src)]
                n = int(kind[3:]) if kind != "lin" else 0
                cols.append(x if kind == "lin" else torch.sin(n * x) if kind.startswith("sin") else torch.cos(n * x))
        F = torch.stack(cols, 1) if cols else q.new_zeros(q.shape[0], 0)
        target = torch.tensor([self.robot.joint_names.index(j) for j, _ in self.terms], dtype=torch.long,
                              device=q.device)
        return Prepared({"F": F, "target": target})

    def joint_delta(self, theta, prep):
        F, target = prep.features["F"], prep.features["target"]
        out = theta.new_zeros(theta.shape[0], F.shape[0], self.robot.dof)
        return out.index_add_(2, target, theta[:, None, :] * F[None])

    def signature(self, prep, label, theta):
        i = [f"{j}.{t}" for j, t in self.terms].index(label)
        j = self.robot.joint_names.index(self.terms[i][0])
        x = prep.features["F"][:, i]
        return {"x": x, "xlabel": self._term_words(self.terms[i][1]), "fitted": theta[i] * x,
                "ylabel": f"{self.terms[i][0]} error [{self._unit(self.terms[i][0])}]", "dof": j}

    def _term_words(self, tag: str) -> str:
        kind, src = tag.split(":", 1)
        if kind == "lin":
            return f"{src} angle [{self._unit(src)}]"
        if kind == "cov":
            return f"{src} − its training mean"
        if kind == "dir":
            return f"direction of {src}'s last motion [±1]"
        return f"{kind[:3]}({kind[3:]}·{src})"

    def mode_words(self, label: str) -> str:
        j, tag = dict((f"{j}.{t}", (j, t)) for j, t in self.terms)[label]
        kind, src = tag.split(":", 1)
        if kind == "lin":
            return f"{j} reads its own angle with a scale error" if src == j else f"{j} turns with {src} (coupling)"
        if kind == "cov":
            return f"{j} drifts with {src}"
        if kind == "dir":
            return f"{j} shifts with the direction of {src}'s last motion"
        whose = "its own" if src == j else f"{src}'s"
        return f"{j} has a {kind[:3]} term of {whose} angle (harmonic {kind[3:]})"

    def describe(self, theta: Tensor | None = None, free: Tensor | None = None) -> list[str]:
        th = self.theta if theta is None else theta
        out = []
        for i, (j, t) in enumerate(self.terms):
            if free is not None and not bool(free[i]):
                continue
            kind, src = t.split(":", 1)
            v = float(th[i])
            tu = self._unit(j)
            size = f"{v * 1e3:.3g} mrad" if tu == "rad" else f"{v * 1e3:.3g} mm"
            if kind == "lin":
                what = (f"{j} reads {v * 1e3:.3g} mrad per rad of its own angle (scale)" if src == j and tu == "rad"
                        else f"{j} turns {size} per {self._unit(src)} of {src} (coupling)")
            elif kind == "cov":
                per = "s" if src in TIME_COVARIATES else "unit"
                what = f"{j} turns {size} per {per} of {src} (drift with a covariate)"
            elif kind == "dir":
                what = f"{j} shifts ±{size} with the direction of {src}'s last motion"
            else:
                what = f"{j}: {size} × {kind[:3]}({kind[3:]}·{src})"
            out.append(what)
        return out
