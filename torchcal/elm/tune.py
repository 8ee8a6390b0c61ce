"""Tuning an ELM's input weights and biases by a swarm solver (seed 002's MMA-ELM and its
relatives): the validation RMSE of :class:`~torchcal.problems.elm.ELMProblem` minimised by any
solver of :mod:`torchcal.optim`, or by uniform random search (the baseline every tuner must beat
at equal evaluations), the output weights always solved by pseudo-inverse."""
from __future__ import annotations

import math
import time
from dataclasses import dataclass

import torch

from torchcal.elm.model import ELM
from torchcal.optim import Result, get_solver
from torchcal.options import Options
from torchcal.problems.elm import ELMProblem

__all__ = ["TuneOptions", "tune_elm"]


@dataclass(frozen=True)
class TuneOptions(Options):
    """How :func:`tune_elm` tunes.

    Attributes:
        activation: hidden-layer activation (``"sigmoid"``: seed 002; ``"tanh"``, ``"sin"``, ``"relu"``).
        ridge: ``0``: output weights by Moore–Penrose pseudo-inverse; ``> 0``: ridge on them.
        options: the solver's own options (e.g. ``{"pop_size": 20, "max_iter": 100}``); for
            ``"random"``: ``n_evals`` (default 2000) and ``batch`` (64).
        seed: seeds the solver (or the random search).
        progress: show the solver's progress bar.
        refit: ``"train"`` keeps ``V`` solved on the training split (what the fitness saw);
            ``"all"`` re-solves ``V`` on training + validation data with the tuned ``W, b``
            (and scaling from both).
    """

    activation: str = "sigmoid"
    ridge: float = 0.0
    options: dict | None = None
    seed: int = 0
    progress: bool = False
    refit: str = "train"


def _random_search(problem: ELMProblem, n_evals: int, seed: int, batch: int = 64) -> Result:
    """Uniform random search in the bounds: the baseline every tuner must beat at equal
    evaluations (``W, b`` drawn in the search bounds, best validation RMSE kept)."""
    t0 = time.perf_counter()
    g = torch.Generator(device=problem.device).manual_seed(int(seed))
    best_x, best_f, hist, done = None, math.inf, [], 0
    while done < n_evals:
        m = min(batch, n_evals - done)
        X = problem.lower + (problem.upper - problem.lower) * torch.rand(
            m, problem.dim, generator=g, dtype=problem.dtype, device=problem.device)
        f = problem.fitness(X)
        f = torch.where(torch.isnan(f), torch.full_like(f, math.inf), f)
        j = int(torch.argmin(f))
        if float(f[j]) < best_f:
            best_f, best_x = float(f[j]), X[j].clone()
        hist.append(best_f)
        done += m
    return Result(x=best_x, fun=best_f, history=hist, n_evals=done, n_iter=len(hist),
                  wall_time_s=time.perf_counter() - t0, message=f"{done} random candidates",
                  method="random")


def tune_elm(X_train, Y_train, X_val, Y_val, method: str = "mma", n_hidden: int = 40, *,
             settings: TuneOptions | None = None, **kw) -> tuple[ELM, Result]:
    """Tune an ELM's ``W`` and ``b`` with a swarm solver (seed 002's MMA-ELM and its relatives).

    Args:
        X_train, Y_train: ``(N, n_in)``, ``(N, n_out)`` data the output weights are solved on.
        X_val, Y_val: validation split; the fitness is its RMSE (standardised outputs).
        method: any solver of :mod:`torchcal.optim` by name (``"mma"`` = seed 002, ``"ma"``,
            ``"pso"``, ``"ga"``, ...) or ``"random"`` (uniform random search).
        n_hidden: hidden neurons; the search dimension is ``n_in·n_hidden + n_hidden``.
        settings, kw: a :class:`TuneOptions` and/or its fields as keywords (``options=`` there is
            the solver's own options dict, ``seed=``, ``refit=``, …).
    Returns:
        ``(elm, result)``: the fitted :class:`~torchcal.elm.model.ELM` with the best ``W, b``, and
        the solver's :class:`~torchcal.optim.Result` (``fun`` = best validation RMSE,
        standardised units).
    """
    opt = TuneOptions.build(settings, **kw)
    if opt.refit not in ("train", "all"):
        raise ValueError(f"refit must be 'train' or 'all', got {opt.refit!r}")
    prob = ELMProblem(X_train, Y_train, X_val, Y_val, n_hidden=n_hidden, activation=opt.activation, ridge=opt.ridge)
    opts = dict(opt.options or {})
    if method.lower() == "random":
        res = _random_search(prob, int(opts.pop("n_evals", 2000)), opt.seed, int(opts.pop("batch", 64)))
        if opts:
            raise ValueError(f"random search takes n_evals and batch, not {sorted(opts)}")
    else:
        res = get_solver(method, seed=opt.seed, progress=opt.progress, **opts).minimize(prob)
    W, b = prob.decode(res.x)
    elm = ELM(n_hidden, opt.activation, opt.ridge, seed=None, input_weights=W.clone(), biases=b.clone(),
              dtype=prob.dtype, device=prob.device)
    Xt, Yt, Xv, Yv = prob.raw
    if opt.refit == "all":
        elm.fit(torch.cat([Xt, Xv]), torch.cat([Yt, Yv]))
    else:
        elm.fit(Xt, Yt)
    return elm, res
