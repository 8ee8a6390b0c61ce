"""How many threads torch uses inside torchcal's public entry points.

torchcal works on small batches: tens to thousands of poses, a few dozen parameters. On such
tensors torch's per-operation cost is microseconds, and a second intra-op thread only adds
hand-off cost; worse, when another process keeps a core busy, every parallel operation waits for
the thread that gets no core. On a shared 2-core machine, ``calibrate`` on 150 poses ran 5x (with
another process spinning on a core) to 21x faster on one thread than on torch's default two, and
on 30,000 rows 1.1-1.5x (``scripts/bench_threads.py``). So the heavy entry points
(:func:`~torchcal.pipelines.calibrate.calibrate`, :func:`~torchcal.pipelines.loop.run.run_loop`,
:func:`~torchcal.pipelines.fleet.run.calibrate_fleet`, :func:`~torchcal.pipelines.plan.run.plan_poses`,
:meth:`~torchcal.deploy.correct.Corrector.correct`) are decorated with :func:`threads_by_size`:
their work runs on one torch thread when it is small, and torch's setting is the caller's again
when they return.

Small means at most :data:`SMALL_ROWS` rows in the call's data: poses of the measurements
(training and held-out together, every robot of a fleet), candidate poses of a plan, targets to
correct. Above it the caller's setting stands: there a second thread stops costing much, and on a
machine with idle cores it may pay.

:func:`set_threads` (or the environment variable ``TORCHCAL_THREADS``, read at import) changes
the rule: ``"auto"`` (the default, as above), ``"caller"`` (never touch torch's setting: you set
``torch.set_num_threads`` yourself), or a number of threads for every entry point.

``torch.set_num_threads`` is process-wide: while an entry point runs, other Python threads of the
process that use torch run with its setting too. The outermost entry point decides; those it calls
(``run_loop`` calls ``calibrate``) keep its choice.
"""
from __future__ import annotations

import functools
import inspect
import os
import threading

import torch
from torch import Tensor

__all__ = ["set_threads", "get_threads", "env_problem", "threads_by_size", "SMALL_ROWS"]

SMALL_ROWS = 20_000  # rows (poses, candidates, targets) up to which one torch thread is used

_AUTO, _CALLER = "auto", "caller"
_state = threading.local()  # whether an entry point is running in this Python thread


def _checked(n) -> int | str:
    if n in (_AUTO, _CALLER):
        return n
    if isinstance(n, str) and n.strip().isdigit():
        n = int(n)
    if isinstance(n, int) and not isinstance(n, bool) and n >= 1:
        return n
    raise ValueError(f"threads must be 'auto' (one torch thread for small work), 'caller' (leave torch's setting "
                     f"alone) or a whole number ≥ 1, got {n!r}")


def _from_env() -> tuple[int | str, str | None]:
    """The choice in ``TORCHCAL_THREADS`` and, when it is not one, what is wrong with it. A bad
    value must not break ``import torchcal`` (a notebook could not even read the message): it is
    refused when an entry point runs, by :func:`env_problem`."""
    text = os.environ.get("TORCHCAL_THREADS", _AUTO).strip().lower() or _AUTO
    try:
        return _checked(text), None
    except ValueError as e:
        return _AUTO, (f"environment variable TORCHCAL_THREADS={os.environ.get('TORCHCAL_THREADS')!r}: {e}; set it "
                       "to auto, caller or a number ≥ 1, or unset it")


_setting, _env_problem = _from_env()


def env_problem() -> str | None:
    """What is wrong with ``TORCHCAL_THREADS`` (None when it is fine, or when :func:`set_threads`
    has chosen since)."""
    return _env_problem


def set_threads(n: int | str = _AUTO) -> int | str:
    """Choose how torchcal's entry points set torch's threads: ``"auto"`` (one thread when the
    work is at most :data:`SMALL_ROWS` rows, the caller's setting otherwise), ``"caller"`` (never
    change it) or a number of threads for all of them. Returns the previous choice."""
    global _setting, _env_problem
    before, _setting = _setting, _checked(n)
    _env_problem = None  # an explicit choice overrides the environment's
    return before


def get_threads() -> int | str:
    """The current choice (see :func:`set_threads`)."""
    return _setting


def _rows(v) -> int:
    """Rows in an argument: a count, a tensor's leading size (one target for a vector), the
    length of measurements, summed over lists and dicts (a fleet)."""
    if v is None or isinstance(v, bool):
        return 0
    if isinstance(v, int):
        return v
    if isinstance(v, Tensor):
        return int(v.shape[0]) if v.ndim >= 2 else 1
    if isinstance(v, dict):
        return sum(_rows(x) for x in v.values())
    if isinstance(v, (list, tuple)):
        return sum(_rows(x) for x in v)
    return len(v) if hasattr(v, "__len__") else 0


def threads_by_size(*names: str):
    """Decorator for an entry point whose work grows with the rows of its arguments ``names``
    (see the module docstring): it runs with the threads :func:`set_threads` chooses, and
    torch's setting is restored when it returns or raises."""
    def wrap(fn):
        sig = inspect.signature(fn)

        @functools.wraps(fn)
        def run(*args, **kwargs):
            if _env_problem is not None:
                raise ValueError(_env_problem)
            if getattr(_state, "inside", False) or _setting == _CALLER:
                return fn(*args, **kwargs)
            n = _setting
            if n == _AUTO:
                try:
                    bound = sig.bind(*args, **kwargs)
                except TypeError:  # let the function itself say what is wrong with the call
                    return fn(*args, **kwargs)
                bound.apply_defaults()
                n = 1 if sum(_rows(bound.arguments.get(k)) for k in names) <= SMALL_ROWS else None
            before = torch.get_num_threads()
            _state.inside = True
            try:
                if n is not None and n != before:
                    torch.set_num_threads(n)
                return fn(*args, **kwargs)
            finally:
                _state.inside = False
                if torch.get_num_threads() != before:
                    torch.set_num_threads(before)
        return run
    return wrap
