"""A toy effect, in one file: a quadratic encoder error ``Δq_j = a_j q_j²`` (``a_j`` in 1/rad).

Registering it is all torchcal asks: the loop then tries it, a pose plan plans for it (it reads
nothing but the commanded angles) and a saved model loads it. Loaded by ``tests/structure/test_extension_points.py``.
"""
from __future__ import annotations

from torchcal.effects import Effect, Prepared, register_effect


@register_effect
class ToyQuadratic(Effect):
    name = "toy_quadratic"
    description = "a quadratic encoder error (a toy)"

    def param_info(self):
        return [(f"{j}.quad", "1/rad") for j in self.joints]

    def prepare(self, q, covariates):
        idx = [self.robot.joint_names.index(j) for j in self.joints]
        return Prepared({"q2": q[:, idx] ** 2})

    def joint_delta(self, theta, prep):
        return self._scatter(prep.features["q2"][None] * theta[:, None, :])

    def mode_words(self, label: str) -> str:
        return f"{label} reads its angle with an error growing as its square"
