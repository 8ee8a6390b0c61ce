"""Joint-space error terms of the independent simulator: a joint's true value is its command plus
a sum of terms, each a function of another joint's command, of its own, or of a recorded
covariate column (numpy only; shares no code with torchcal's effects).

Physical examples: a wrist whose gears couple two axes (``a7`` turns ``c`` rad per rad of ``a6``,
which controllers compensate with a coupling factor), harmonic transmission errors of a joint's
own angle, a joint zero that drifts with a motor's temperature.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

__all__ = ["JointTerm", "as_joint_terms"]

KINDS = ("linear", "sin", "cos")


@dataclass(frozen=True)
class JointTerm:
    """``coef · f(x)`` added to a joint's true value.

    ``x`` is the commanded value of the joint ``source`` (rad, m for a prismatic one) or, when
    ``source`` is not a joint, the covariate column of that name (its unit, e.g. degC).
    ``f(x) = x − ref`` (``"linear"``), ``sin(harmonic · x + phase)`` or ``cos(harmonic · x + phase)``
    (``phase`` rad; joints only).  ``coef``: rad (m for a prismatic target) per unit of ``f``.
    """

    source: str
    kind: str = "linear"
    coef: float = 0.0
    harmonic: int = 1
    phase: float = 0.0
    ref: float = 0.0

    def basis(self, x: np.ndarray) -> np.ndarray:
        """``f(x)``, ``(N,)``."""
        if self.kind == "linear":
            return x - self.ref
        fn = np.sin if self.kind == "sin" else np.cos
        return fn(self.harmonic * x + self.phase)

    def words(self, target: str, unit: str, source_unit: str) -> str:
        """The term in words, e.g. ``"a7 turns 2.0 mrad per rad of a6 (coupling)"``."""
        scale, u = (1e3, "mrad") if unit == "rad" else (1e6, "µm")
        if self.kind == "linear":
            what = "coupling" if source_unit in ("rad", "m") else "covariate"
            ref = f" from {self.ref:g}" if self.ref else ""
            return (f"{target} turns {self.coef * scale:.3g} {u} per {source_unit} of {self.source}{ref} ({what})"
                    if unit == "rad" else
                    f"{target} moves {self.coef * scale:.3g} {u} per {source_unit} of {self.source}{ref} ({what})")
        return (f"{target} {self.coef * scale:.3g} {u} · {self.kind}({self.harmonic} × {self.source} "
                f"{self.phase:+.3g} rad) (harmonic {self.harmonic})")

    def as_dict(self) -> dict:
        return {k: (float(v) if isinstance(v, (int, float)) and k != "harmonic" else v)
                for k, v in asdict(self).items()}


def _one(target: str, t) -> JointTerm:
    if isinstance(t, JointTerm):
        term = t
    elif isinstance(t, dict):
        term = JointTerm(**t)
    elif isinstance(t, (tuple, list)) and 3 <= len(t) <= 6:
        term = JointTerm(*(cast(v) for cast, v in zip((str, str, float, int, float, float), t)))
    else:
        raise ValueError(f"joint_terms[{target!r}]: a term is a JointTerm, a dict of its fields or a tuple "
                         f"(source, kind, coef[, harmonic[, phase[, ref]]]), got {t!r}")
    if term.kind not in KINDS:
        raise ValueError(f"joint_terms[{target!r}]: kind {term.kind!r} is not one of {KINDS}")
    if term.harmonic < 1:
        raise ValueError(f"joint_terms[{target!r}]: harmonic must be 1 or more, got {term.harmonic}")
    return term


def as_joint_terms(spec, joints: list[str]) -> dict[str, list[JointTerm]]:
    """Validate ``{target joint: [term, ...]}``: targets among ``joints`` (the commanded ones);
    a source that is not a joint names a covariate column, and only enters linearly."""
    out = {}
    for target, terms in (spec or {}).items():
        if target not in joints:
            raise ValueError(f"joint_terms: {target!r} is not a commanded joint of this robot ({joints})")
        out[target] = [_one(target, t) for t in terms]
        bad = [t.source for t in out[target] if t.kind != "linear" and t.source not in joints]
        if bad:
            raise ValueError(f"joint_terms[{target!r}]: sin/cos terms need a joint as source; {bad} are not joints "
                             f"(a covariate enters linearly)")
    return out
