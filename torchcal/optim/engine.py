"""The one iteration engine: every iterative solver supplies its start and its step; the engine
owns the loop, the stopping, the history, the progress bar and the user's callback.

A solver derived from :class:`IterativeSolver` implements

* ``init(problem, g) -> state``: any object with a ``best`` attribute (the best fitness so far, a
  float or a 0-d tensor), ``n_evals`` (points evaluated) and, if the run is already over at the
  start, ``stop = (converged, message)``;
* ``step(problem, state, t, g) -> None | (converged, message)``: iteration ``t`` (1-based); a tuple
  ends the run;
* optionally ``check(problem, state) -> None | (converged, message)``: a convergence test before
  the next iteration (it then neither counts nor is recorded);
* ``finish(problem, state) -> (x, fun, extra)``: the best point, its fitness and solver-specific
  details for :attr:`Result.extra`.

The history is kept in a tensor on the problem's device and read once at the end: reading the
best fitness every iteration would force a host synchronisation on a GPU. The bar and the callback
read it only when they exist.

:func:`minimize_runs` runs several independent runs of one solver (restarts, each with its own
seed) as one batch: a solver with ``batched = True`` takes a list of generators in ``init`` and
``step`` and keeps a leading run axis on its state; ``check_runs(problem, state)`` says which runs
stop now, ``state.keep_runs(idx)`` drops the others' rows and ``finish_runs`` gives one
``(x, fun, extra)`` per run. Each run then costs what its own iterations cost, and the fixed cost
of an iteration is paid once for all.
"""
from __future__ import annotations

from typing import Any, Callable

import time

import torch
from torch import Tensor
from tqdm.auto import tqdm

from torchcal.optim.base import Solver, get_solver
from torchcal.optim.result import Result
from torchcal.problems.base import Problem

__all__ = ["IterativeSolver", "LocalSolver", "Recorder", "evaluate", "run", "run_batched", "minimize_runs"]


def evaluate(problem: Problem, X: Tensor) -> Tensor:
    """Batched fitness ``(N, k) -> (N,)`` in the problem's dtype, NaN mapped to ``+inf`` so that a
    failed evaluation can never be selected as a best (``argmin`` and ``sort`` would otherwise
    treat NaN inconsistently)."""
    f = problem.fitness(X).to(dtype=problem.dtype).reshape(X.shape[0])
    return torch.where(torch.isnan(f), torch.full_like(f, float("inf")), f)


class Recorder:
    """History, progress bar and callback of one run (the only progress reporter in torchcal).

    Args:
        n: the most iterations the run can take; history entry ``t`` is the best after iteration
            ``t`` (0: after the start).
        callback_at_start: whether the callback also hears the start (``t = 0``).
    """

    def __init__(self, n: int, desc: str, *, progress: bool, callback: Callable[[int, float], None] | None,
                 dtype: torch.dtype, device: torch.device, callback_at_start: bool = True):
        self.hist = torch.empty(n + 1, dtype=dtype, device=device)
        self.bar = tqdm(total=n, desc=desc, leave=False) if progress else None
        self.callback = callback
        self.callback_at_start = callback_at_start
        self.last = 0

    def __call__(self, t: int, best: float | Tensor) -> None:
        self.hist[t] = best
        self.last = t
        if self.bar is None and self.callback is None:
            return
        b = float(best)
        if self.bar is not None and t > 0:
            self.bar.update(1)
            self.bar.set_postfix(best=f"{b:.4g}", refresh=False)
        if self.callback is not None and (t > 0 or self.callback_at_start):
            self.callback(t, b)

    def close(self) -> list[float]:
        """Closes the bar; the history up to the last recorded iteration."""
        if self.bar is not None:
            self.bar.close()
        return self.hist[: self.last + 1].tolist()


class IterativeSolver(Solver):
    """A solver run by the engine (see the module docstring). Subclasses set ``max_iter`` and
    implement :meth:`init`, :meth:`step` and :meth:`finish`."""

    max_iter: int = 100
    #: Whether the callback hears the start (``t = 0``) as well as every iteration.
    callback_at_start = True
    #: dtype of the recorded history: the problem's (``None``) or a fixed one.
    history_dtype: torch.dtype | None = None

    def init(self, problem: Problem, g: torch.Generator) -> Any:  # pragma: no cover - abstract
        raise NotImplementedError

    def step(self, problem: Problem, state: Any, t: int, g: torch.Generator) -> tuple[bool, str] | None:
        raise NotImplementedError  # pragma: no cover - abstract

    def check(self, problem: Problem, state: Any) -> tuple[bool, str] | None:
        """A convergence test before the next iteration; none by default."""
        return None

    def finish(self, problem: Problem, state: Any) -> tuple[Tensor, float, dict]:
        raise NotImplementedError  # pragma: no cover - abstract

    def _run(self, problem: Problem) -> Result:
        return run(self, problem)


class LocalSolver(IterativeSolver):
    """An iterative solver that follows one point (least squares, gradient methods): its history is
    kept in float64 whatever the problem's dtype, and the callback hears iterations, not the start."""

    callback_at_start = False
    history_dtype = torch.float64


def run(solver: IterativeSolver, problem: Problem) -> Result:
    """Run ``solver`` on ``problem``: start, then steps until one ends the run or ``max_iter``."""
    g = solver.generator(problem)
    state = solver.init(problem, g)
    rec = Recorder(solver.max_iter, solver.name, progress=solver.progress, callback=solver.callback,
                   dtype=solver.history_dtype or problem.dtype, device=problem.device,
                   callback_at_start=solver.callback_at_start)
    stop = getattr(state, "stop", None)
    t = 0
    try:
        rec(0, state.best)
        while stop is None and t < solver.max_iter:
            stop = solver.check(problem, state)
            if stop is not None:
                break
            t += 1
            stop = solver.step(problem, state, t, g)
            rec(t, state.best)
    finally:
        history = rec.close()
    converged, message = stop if stop is not None else (False, f"reached max_iter={solver.max_iter}")
    x, fun, extra = solver.finish(problem, state)
    return Result(x=x, fun=fun, history=history, n_evals=int(state.n_evals), n_iter=t, converged=converged,
                  message=message, extra=extra)  # Solver.minimize adds the wall time and the method


def minimize_runs(problem: Problem, method: str = "pso", seeds=range(10), **options) -> list[Result]:
    """``len(seeds)`` independent runs of the solver registered as ``method``, run ``i`` seeded with
    ``seeds[i]``, as one batch (:func:`run_batched`): the same results as
    ``minimize(problem, method, seed=seeds[i], **options)`` one by one, in less time."""
    return run_batched(get_solver(method, **options), problem, seeds)


def run_batched(solver: IterativeSolver, problem: Problem, seeds) -> list[Result]:
    """Independent runs of ``solver`` on ``problem``, one per seed, as one population tensor.

    Each run draws from its own generator exactly what it would draw alone, keeps its own bests
    and stops on its own (``check_runs``); a stopped run leaves the batch, so the others go on
    with fewer points. ``Result.wall_time_s`` of a run is the batch's wall time until that run
    ended (shared with the runs beside it)."""
    if not getattr(solver, "batched", False):
        raise ValueError(f"{solver.name} cannot run several runs as one batch; call minimize() once per seed")
    if solver.callback is not None:
        raise ValueError("a callback follows one run; give it to minimize() per seed, or leave it out here")
    seeds = [int(s) for s in seeds]
    if not seeds:
        raise ValueError("give at least one seed")
    t0 = time.perf_counter()
    gens = [solver.generator(problem, s) for s in seeds]
    state = solver.init(problem, gens)
    hist = torch.empty(solver.max_iter + 1, len(seeds), dtype=solver.history_dtype or problem.dtype,
                       device=problem.device)
    hist[0] = state.best
    live, rows = list(range(len(seeds))), torch.arange(len(seeds), device=problem.device)
    ended: dict[int, tuple] = {}  # run -> (n_iter, converged, message, x, fun, extra, n_evals, wall)

    def end(which: list[int], t: int, converged: bool, why: str) -> None:
        out = solver.finish_runs(problem, state)
        for j in which:
            ended[live[j]] = (t, converged, why, *out[j], state.n_evals, time.perf_counter() - t0)

    bar = tqdm(total=solver.max_iter, desc=f"{solver.name} x{len(seeds)}", leave=False) if solver.progress else None
    t = 0
    try:
        while t < solver.max_iter:
            chk = solver.check_runs(problem, state)
            if chk is not None:
                flags = chk[0].tolist()  # one synchronisation for all runs
                if any(flags):
                    end([j for j, f in enumerate(flags) if f], t, True, chk[1])
                    keep = [j for j, f in enumerate(flags) if not f]
                    live, gens = [live[j] for j in keep], [gens[j] for j in keep]
                    if not keep:
                        break
                    idx = torch.tensor(keep, device=problem.device)
                    state.keep_runs(idx)
                    rows = rows[idx]
            t += 1
            solver.step(problem, state, t, gens)
            hist[t].index_copy_(0, rows, state.best)
            if bar is not None:
                bar.update(1)
                bar.set_postfix(runs=len(live), refresh=False)
        if live and len(ended) < len(seeds):
            end(list(range(len(live))), t, False, f"reached max_iter={solver.max_iter}")
    finally:
        if bar is not None:
            bar.close()
    history = hist.T.tolist()
    out = []
    for i in range(len(seeds)):
        n_iter, converged, message, x, fun, extra, n_evals, wall = ended[i]
        out.append(Result(x=x, fun=fun, history=history[i][: n_iter + 1], n_evals=int(n_evals), n_iter=n_iter,
                          converged=converged, message=message, extra=extra, wall_time_s=wall, method=solver.name))
    return out
