"""What :func:`~torchcal.optim.lm_batched.lm_batched` found for each problem of a batch, and why
each stopped (a code per problem, words when read)."""
from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property

import torch
from torch import Tensor

from torchcal.optim.result import Result

__all__ = ["BatchedLMResult", "stop_message", "STOP_GTOL", "STOP_FTOL", "STOP_XTOL", "STOP_BLOWN", "STOP_GTOL0"]

# Why a problem stopped, by code (0: the iteration cap).
STOP_GTOL, STOP_FTOL, STOP_XTOL, STOP_BLOWN, STOP_GTOL0 = 1, 2, 3, 4, 5
_WHY = {STOP_GTOL: "projected gradient below gtol", STOP_FTOL: "relative decrease of the sum of squares below ftol",
        STOP_XTOL: "step below xtol", STOP_BLOWN: "damping overflowed: no decrease found along any step",
        STOP_GTOL0: "projected gradient below gtol at the start"}


def stop_message(code: int, max_iter: int) -> str:
    """Why a problem stopped, in words, from its code."""
    return _WHY.get(code, f"reached max_iter={max_iter}")


@dataclass
class BatchedLMResult:
    """What :func:`~torchcal.optim.lm_batched.lm_batched` found for each of ``B`` problems.

    Attributes:
        x: ``(B, K)`` solutions (fixed entries keep their start values).
        residuals: ``(B, m)`` residuals at ``x`` (padded rows zero); ``jacobian``: ``(B, m, c)``
            Jacobian at ``x`` over the callback's columns (all K unless ``columns`` named them;
            fixed ones included: judging the parameters again at the solution needs them).
        sse: ``(B,)`` sums of squares (m² for position residuals).
        n_iter, n_evals, n_jac, n_rejected: ``(B,)`` trial steps, residual evaluations, Jacobian
            evaluations and rejected steps per problem.
        converged: ``(B,)`` bool; ``stop``: ``(B,)`` why each stopped, as a code (:attr:`messages`
            in words); ``trace``: per trial step, the problems that took it and their sums of
            squares afterwards (index 0: every problem at the start; :attr:`history` per problem).
    """

    x: Tensor
    residuals: Tensor
    jacobian: Tensor
    sse: Tensor
    n_iter: Tensor
    n_evals: Tensor
    n_jac: Tensor
    n_rejected: Tensor
    converged: Tensor
    stop: Tensor
    max_iter: int
    trace: list[tuple[Tensor, Tensor]] = field(default_factory=list)
    wall_time_s: float = 0.0

    @cached_property
    def messages(self) -> list[str]:
        """Why each problem stopped, in words."""
        return [stop_message(c, self.max_iter) for c in self.stop.tolist()]

    @cached_property
    def history(self) -> list[list[float]]:
        """Per problem, the sum of squares at its current point after each trial step."""
        B = self.sse.shape[0]
        who = torch.cat([w for w, _ in self.trace])
        val = torch.cat([s for _, s in self.trace])
        order = torch.sort(who, stable=True).indices  # per problem, in the order the steps came
        counts = torch.bincount(who, minlength=B).tolist()
        flat = val[order].tolist()
        out, at = [], 0
        for n in counts:
            out.append(flat[at:at + n])
            at += n
        return out

    @cached_property
    def _numbers(self) -> dict[str, list]:
        """The per-problem counts and flags as Python lists, read from the device once."""
        return {k: getattr(self, k).tolist() for k in ("sse", "n_evals", "n_iter", "converged", "n_jac", "n_rejected")}

    def result(self, b: int, free: Tensor) -> Result:
        """Problem ``b`` as a single solver's :class:`~torchcal.optim.Result` (``x`` over its
        free entries ``free (K,)``)."""
        h = self._numbers
        S = h["sse"][b]
        return Result(x=self.x[b, free], fun=S, history=list(self.history[b]), n_evals=h["n_evals"][b],
                      n_iter=h["n_iter"][b], wall_time_s=self.wall_time_s, converged=h["converged"][b],
                      message=self.messages[b], method="lm",
                      extra={"cost": 0.5 * S, "n_jac": h["n_jac"][b], "n_rejected": h["n_rejected"][b]})
