"""The LM's checkpoint: the caller looks at the iterate every few steps of a run still going, and
may end it there. A checkpoint that lets the run go changes nothing; one that ends it ends it at
that step, unconverged, with its message.

The problem is Rosenbrock's residuals ``(1 - x1, 10 (x2 - x1²))`` from ``(-1.2, 1)``: a curved
valley that LM follows in a dozen or more steps, so a checkpoint every 3 steps is met several times."""
from __future__ import annotations

import pytest
import torch

from torchcal.optim import minimize

from .test_lm_host_syncs import _rosenbrock


def test_a_checkpoint_that_lets_the_run_go_changes_nothing():
    plain = minimize(_rosenbrock(), "lm")
    assert plain.converged and plain.n_iter > 9, "the valley must take several checkpoints' worth of steps"
    seen = []

    def look(x):
        seen.append(x.clone())
        return None

    watched = minimize(_rosenbrock(), "lm", checkpoint=look, checkpoint_every=3)
    assert torch.equal(watched.x, plain.x) and watched.n_iter == plain.n_iter
    assert watched.message == plain.message
    # met after steps 3, 6, 9, ... of a run still going: before the step that ends it, never after
    assert len(seen) == (plain.n_iter - 1) // 3
    # each is the iterate after that many steps: where a run of that many steps ends
    for k, x in enumerate(seen, 1):
        assert torch.equal(x, minimize(_rosenbrock(), "lm", max_iter=3 * k).x)
    assert not torch.equal(seen[-1], seen[0])


def test_a_checkpoint_that_says_stop_ends_the_run_at_that_step():
    calls = []

    def look(x):
        calls.append(x.clone())
        return "seen enough" if len(calls) == 2 else None

    res = minimize(_rosenbrock(), "lm", checkpoint=look, checkpoint_every=3)
    assert res.n_iter == 6 and not res.converged and res.message == "seen enough"
    assert torch.equal(res.x, calls[-1])  # the run ends where the checkpoint saw it
    # the same six steps as a run of six steps
    six = minimize(_rosenbrock(), "lm", max_iter=6)
    assert torch.equal(res.x, six.x)


def test_checkpoint_every_must_be_a_positive_whole_number():
    with pytest.raises(ValueError, match="checkpoint_every"):
        minimize(_rosenbrock(), "lm", checkpoint=lambda x: None, checkpoint_every=0)
