"""The rounds of an identifiable fit, written once: judge which candidates the data can see, fit
them, judge again at the solution, and fit again while that changes what is fitted.

Identifiability depends on where it is judged (a marker guessed on a joint axis hides that
joint's offset), so every fit is followed by a judgement at its solution. A parameter that grows
identifiable there is fitted in the next round, at most ``rounds`` fits in a row; one that only
shows after the last of them is judged, never fitted. A parameter the data pin down worse than its
plausible size leaves for good, at its start value, and what was fitted with it is fitted again.

:func:`fit_rounds` owns that control; the per-round pieces come from a :class:`Rounds` strategy:

* :func:`torchcal.pipelines.fitting.fit_identified` for one problem (``calibrate``, the loop):
  each piece a single problem's solve and judgement. Precision is judged only once the set has
  stopped growing, at the noise the model *with* a parameter reaches, and a drop restarts every
  value from its start (the others had compensated for the dropped one), so the growth rounds
  count again.
* :func:`torchcal.pipelines.fleet.independent.solve_independent` for ``R`` robots at once: each
  piece one batched tensor operation over the robots still changing (the batched LM, the batched
  greedy judgement, the batched precision check), the round's one wait for the device being which
  robots go on. Precision is judged in the same round as the rank (one judgement per round, not
  two), and a drop resets only the dropped values to their start: every round counts, restarts
  included. Making the fleet restart like a single fit would move its fitted values (by the LM's
  tolerance) and add rounds; making the single fit judge like the fleet would move calibrate's.
* :func:`torchcal.pipelines.fleet.coupled.solve_coupled` for a fleet fitted as one problem (a
  hierarchical prior, a shared payload): one set for every robot, judged on the pooled design with
  the effects' precision in the same judgement; no judgement follows the last fit.
"""
from __future__ import annotations

from typing import Any, Protocol

__all__ = ["Rounds", "fit_rounds"]


class Rounds(Protocol):
    """The pieces of one identifiable fit, for one problem or a batch of them."""

    def start(self) -> None:
        """Judge the candidates at their start values: what the first round fits."""

    def solve(self) -> None:
        """Fit what is free from the current values."""

    def judge(self, last: bool) -> Any:
        """Judge at the solution (``last``: no round follows to fit what grows identifiable now);
        return what changed (falsy: nothing, the fit is final)."""

    def advance(self, change: Any, last: bool) -> bool:
        """Set up the next fit after ``change``; True when it starts again from the start values
        (the growth rounds then count from zero)."""


def fit_rounds(strategy: Rounds, rounds: int) -> None:
    """Run ``strategy``'s rounds until a judgement changes nothing, or ``rounds`` fits have
    passed without a restart; what was fitted stays on the strategy."""
    strategy.start()
    n = 0
    while True:
        strategy.solve()
        last = n >= rounds - 1
        change = strategy.judge(last)
        if not change:
            return
        n = 0 if strategy.advance(change, last) else n + 1
        if n >= rounds:
            return
