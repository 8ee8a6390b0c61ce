"""The state of a particle swarm, for one run or for several independent runs at once.

One run holds ``(P, k)`` positions; ``R`` independent runs of the same solver (restarts with
their own seeds, :func:`~torchcal.optim.engine.minimize_runs`) hold ``(R, P, k)``: one population
tensor whose fitness is one call on ``(R P, k)`` points, while each run keeps its own bests. Every
operation here works on the trailing axes, so the same code serves both.

Shapes (``...`` is ``()`` for one run, ``(R,)`` for several): positions ``X``, velocities ``V``,
personal bests ``pbest`` ``(..., P, k)``; fitness ``pbest_f`` ``(..., P)``; the global best
``gbest`` ``(..., k)`` and its fitness ``gbest_f`` ``(...)``.
"""
from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

__all__ = ["SwarmState", "rows_of", "rand_runs"]


def rows_of(A: Tensor, idx: Tensor, out: Tensor | None = None) -> Tensor:
    """Rows ``idx (..., n)`` of ``A (..., P, k)`` along the particle axis: ``(..., n, k)``."""
    return torch.gather(A, -2, idx[..., None].expand(*idx.shape, A.shape[-1]), out=out)


def rand_runs(g, out: Tensor) -> Tensor:
    """Fill ``out`` with uniform numbers: from the generator ``g`` for one run, or run ``i``'s
    ``out[i]`` from ``g[i]`` for a list of generators, so that each run draws what it would draw
    alone."""
    if isinstance(g, torch.Generator):
        return torch.rand(out.shape, generator=g, out=out)
    for gi, o in zip(g, out):
        torch.rand(o.shape, generator=gi, out=o)
    return out


@dataclass
class SwarmState:
    """Mutable state of a swarm (all tensors on the problem's dtype/device).

    Attributes:
        X: ``(..., P, k)`` positions.   V: ``(..., P, k)`` velocities.
        pbest: ``(..., P, k)`` personal best positions.   pbest_f: ``(..., P)`` their fitness.
        gbest: ``(..., k)`` global best position.   gbest_f: ``(...)``, its fitness.
        n_evals: points evaluated so far by each run (Python int: the population size is known
            on the host, so counting never synchronises with the device).
        t: the last iteration done (0 after the start).
        ring: ``(L, ...)`` the best fitness of the last ``L`` iterations (``ring[t % L]`` after
            iteration ``t``) when the solver tests for stalling, else ``None``.

    A state made by :meth:`allocate` keeps ``X``, ``V``, ``pbest`` and ``pbest_f`` as the first
    ``P`` rows of buffers sized for the initial population, with a spare set for
    :meth:`keep_rows`, and scratch buffers for one iteration (:meth:`scratch`). A state built
    from plain tensors works too (the solvers' hooks and tests use that); it allocates instead.
    """

    X: Tensor
    V: Tensor
    pbest: Tensor
    pbest_f: Tensor
    gbest: Tensor
    gbest_f: Tensor
    n_evals: int = 0
    t: int = 0
    ring: Tensor | None = None
    _bufs: list | None = None
    _scratch: dict | None = None

    @property
    def size(self) -> int:
        """Particles per run."""
        return int(self.X.shape[-2])

    @property
    def best(self) -> Tensor:
        """The best fitness so far (what the engine records): ``(...)``."""
        return self.gbest_f

    @classmethod
    def allocate(cls, X: Tensor, V: Tensor, f: Tensor, ring: int = 0) -> "SwarmState":
        """A buffered state from the initial ``(..., P, k)`` positions, velocities and ``(..., P)``
        fitness: personal bests are the start points, the global best their best. ``ring``: the
        length of :attr:`ring` (0: none)."""
        s = cls(X, V, X, f, gbest=X[..., 0, :], gbest_f=f[..., 0], n_evals=int(X.shape[-2]), _scratch={})
        s._buffer(X, V, X, f)
        i = torch.argmin(f, -1)
        s.gbest, s.gbest_f = rows_of(X, i[..., None])[..., 0, :].clone(), f.gather(-1, i[..., None])[..., 0].clone()
        if ring:
            s.ring = s.gbest_f.new_empty(ring, *s.gbest_f.shape)
            s.ring[0] = s.gbest_f
        return s

    def _buffer(self, X: Tensor, V: Tensor, pbest: Tensor, pbest_f: Tensor) -> None:
        """Copy the particles into fresh buffers (and a spare set) sized for them."""
        self._bufs = [[torch.empty_like(X), torch.empty_like(X), torch.empty_like(X), torch.empty_like(pbest_f)]
                      for _ in range(2)]
        for b, v in zip(self._bufs[0], (X, V, pbest, pbest_f)):
            b.copy_(v)
        self.X, self.V, self.pbest, self.pbest_f = self._bufs[0]
        self._scratch = {}

    def keep_rows(self, idx: Tensor) -> None:
        """Keep only particles ``idx`` (``(..., n)`` long, in the order given) of ``X``, ``V``,
        ``pbest``, ``pbest_f``: gathered into the spare buffers, which then become the live ones."""
        if self._bufs is None:
            self.X, self.V, self.pbest = (rows_of(t, idx) for t in (self.X, self.V, self.pbest))
            self.pbest_f = self.pbest_f.gather(-1, idx)
            return
        n, lead = int(idx.shape[-1]), self.X.shape[:-2]
        spare = [b.view(-1)[: lead.numel() * n * b.shape[-1]].view(*lead, n, b.shape[-1])
                 for b in self._bufs[1][:3]]
        spare.append(self._bufs[1][3].view(-1)[: lead.numel() * n].view(*lead, n))
        for src, dst in zip((self.X, self.V, self.pbest), spare):
            rows_of(src, idx, out=dst)
        torch.gather(self.pbest_f, -1, idx, out=spare[3])
        self._bufs.reverse()
        self.X, self.V, self.pbest, self.pbest_f = spare

    def keep_runs(self, idx: Tensor) -> None:
        """Keep only runs ``idx`` (``(r,)`` long) of a state of several runs; allocates (a run
        ends once)."""
        self.gbest, self.gbest_f = self.gbest[idx], self.gbest_f[idx]
        if self.ring is not None:
            self.ring = self.ring[:, idx]
        self._buffer(*(t[idx] for t in (self.X, self.V, self.pbest, self.pbest_f)))

    def scratch(self) -> dict:
        """Scratch tensors for one iteration at the current shape (views of buffers sized for
        the initial population, made once per shape): ``r``, ``t``, ``d`` ``(..., 2, P, k)``
        (random numbers, velocity terms, differences; ``r1 = r[..., 0, :, :]`` etc.), ``xn``
        ``(..., P, k)``, ``wall`` ``(..., P, k)`` bool, ``f`` ``(..., P)``, ``better`` ``(..., P)``
        bool."""
        shape = tuple(self.X.shape)
        s = self._scratch.get(shape)
        if s is None:
            if "_b" not in self._scratch:
                n, X = self.X.numel(), self.X
                self._scratch["_b"] = dict(r=X.new_empty(2 * n), t=X.new_empty(2 * n), d=X.new_empty(2 * n),
                                           xn=X.new_empty(n), wall=torch.empty(n, dtype=torch.bool, device=X.device),
                                           f=self.pbest_f.new_empty(self.pbest_f.numel()),
                                           better=torch.empty(self.pbest_f.numel(), dtype=torch.bool,
                                                              device=X.device))
            b, n, lead, (P, k) = self._scratch["_b"], self.X.numel(), shape[:-2], shape[-2:]
            s = {name: b[name][: 2 * n].view(*lead, 2, P, k) for name in ("r", "t", "d")}
            s.update(xn=b["xn"][:n].view(shape), wall=b["wall"][:n].view(shape),
                     f=b["f"][: n // k].view(*lead, P), better=b["better"][: n // k].view(*lead, P))
            for name in ("r", "t", "d"):
                s[name + "1"], s[name + "2"] = s[name][..., 0, :, :], s[name][..., 1, :, :]
            s["better_col"] = s["better"][..., None]
            self._scratch[shape] = s
        return s
