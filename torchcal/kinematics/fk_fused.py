"""A fused position kernel for large batches and parameter populations, on CPU or GPU.

:meth:`Robot.positions` carries each marker point from its link to the base with about a dozen
tensor operations per joint. On a GPU each is a kernel launch that reads and writes the whole
batch, so a million configurations cost a hundred passes over memory, and a small population
(240 × 30) costs a hundred launches of microseconds each. Yet the chain is, per configuration, a
fixed sequence of scalar operations: per revolute joint one cosine, one sine and a 2-D rotation,
then ``v <- t + R v`` with the joint origin's nine entries. :class:`FusedPositions` writes it that
way, on the components ``x, y, z`` of the point, each a ``(N,)`` or ``(P, N)`` tensor, so that
``torch.compile`` turns the whole chain into one elementwise kernel: ``q`` read once, positions
written once (72 bytes per configuration for six joints and one marker). The joint origins, marker
points and base frame of a population come from the robot's own code
(:meth:`~torchcal.kinematics.fk.ForwardKinematics._origins`), traced into the same compiled graph.

Without a compiler (``compile=False``, or when compiling fails: the kernel says so once in the log
and goes on) the same function runs eagerly and gives the same numbers; :meth:`Robot.positions`
stays the reference (the tests check 1e-12 m on CPU and, marked ``gpu``, on CUDA).

Shapes: ``q (N, dof)`` rad / m; free values ``x (P, k)``; positions ``(N, M, 3)`` for the fixed
parameter vector, ``(P, N, M, 3)`` for a population (m, instrument frame unless ``base=False``).
"""
from __future__ import annotations

import logging
import types
from typing import Callable

import torch
from torch import Tensor

from torchcal.kinematics.transforms import so3_exp

__all__ = ["FusedPositions", "compile_available"]

log = logging.getLogger(__name__)


def compile_available(device: torch.device | str) -> bool:
    """Whether ``torch.compile`` can generate code for ``device``: Triton on CUDA, a C++ compiler
    on CPU (inductor's own check)."""
    device = torch.device(device)
    if not hasattr(torch, "compile"):
        return False
    try:
        if device.type == "cuda":
            import triton  # noqa: F401  (inductor's GPU code generator)
            return torch.cuda.is_available()
        from torch._inductor import cpp_builder

        return bool(cpp_builder.get_cpp_compiler())
    except Exception:  # noqa: BLE001 - any failure means: no compiler here
        return False


# Compiled chains, one per robot structure (joint kinds, mimic maps, marker paths), call kind and
# mode. torch.compile keeps its graphs per code object, with a limit on how many: each structure
# gets its own copy of the code, so that many robots in one process never evict each other's
# graphs, and kernels of the same structure (a fleet, a rebuilt problem) share one compilation.
_COMPILED: dict[tuple, Callable] = {}


def _compiled(fn: Callable, key: tuple, mode: str | None) -> Callable:
    key = (fn.__name__, mode) + key
    if key not in _COMPILED:
        own = types.FunctionType(fn.__code__.replace(), fn.__globals__, fn.__name__, fn.__defaults__,
                                 fn.__closure__)
        _COMPILED[key] = torch.compile(own, dynamic=False, mode=mode)
    return _COMPILED[key]


class FusedPositions:
    """Marker positions through one fused kernel.

    Args:
        robot: the :class:`~torchcal.kinematics.robot.Robot`.
        values: ``(K,)`` full parameter vector: the parameters of a call without ``x``, and the
            fixed entries of a population (default: zeros, the nominal robot).
        free_index: ``(k,)`` indices of the parameters a population call's ``x`` sets (default:
            all ``K``).
        base: apply the base frame (instrument frame), as ``Robot.positions(base=True)``.
        compile: ``"auto"`` compiles on CUDA when Triton is there and runs eagerly on CPU (where
            the eager path is already tuned and a compile costs seconds); ``True`` compiles on any
            device that has a compiler; ``False`` never compiles.
        mode: ``torch.compile`` mode (``None``: default; ``"reduce-overhead"`` adds CUDA graphs,
            whose outputs are then copied before they are returned).

    Call ``kernel(q)`` for the fixed parameters or ``kernel(q, x)`` for a population. A compiled
    kernel is specialised to the robot's structure and compiled for dynamic batch sizes: one
    compilation per kernel for the fixed call and one for the population call.
    """

    def __init__(self, robot, values: Tensor | None = None, free_index: Tensor | None = None,
                 rows: Tensor | None = None, cols: Tensor | None = None, *, base: bool = True,
                 compile: bool | str = "auto", mode: str | None = None):
        self.robot = r = robot
        dt = dict(dtype=r.dtype, device=r.device)
        K = r.n_params
        self.values = torch.zeros(K, **dt) if values is None else torch.as_tensor(values, **dt).reshape(K).clone()
        self.free_index = (torch.arange(K, device=r.device) if free_index is None else
                           torch.as_tensor(free_index, device=r.device).long().reshape(-1))
        self._obs = None if rows is None else (torch.as_tensor(rows, device=r.device).long(),
                                               torch.as_tensor(cols, device=r.device).long())
        self.base = bool(base)
        # static structure, baked into the compiled graph: per joint (kind, actuated column,
        # multiplier, mimic offset); per marker the joints from its link to the root
        src, mult, moff = r._src.tolist(), r._mult.tolist(), r._moff.tolist()
        self._motion = tuple((k, s, m, o) for k, s, m, o in zip(r._kinds, src, mult, moff))
        paths = []
        for f in r._mk_frame:
            path = []
            while f != 0:
                path.append(f - 1)
                f = r.parent_frame[f - 1]
            paths.append(tuple(path))
        self._paths = tuple(paths)
        self._fixed = self._frames(self.values[None])  # per fixed call: computed once
        self.compiled = compile is True or (compile == "auto" and r.device.type == "cuda")
        if self.compiled and not compile_available(r.device):
            log.info("torch.compile has no code generator for %s here: the fused position kernel runs eagerly",
                     r.device)
            self.compiled = False
        self._copy_out = mode == "reduce-overhead"
        self._fns = {"fixed": _chain_fixed, "population": _chain_population}
        if self.compiled:
            key = (self._motion, self._paths, self.base, r.device.type, rows is not None)
            self._fns = {k: _compiled(fn, key, mode) for k, fn in self._fns.items()}

    # ------------------------------------------------------------------ frames
    def _frames(self, full: Tensor) -> tuple:
        """Joint origins ``(P, J, 3, 3)``, ``(P, J, 3)``, marker points ``(P, M, 3)``, the base
        ``(P, 3, 3)``, ``(P, 3)`` (or ``None``) and the zero offsets ``(P, dof)`` of ``full (P, K)``,
        from the robot's own code."""
        r = self.robot
        slots = r._slots(full)
        OR, Ot = r._origins(slots)
        mt = r._markers(slots)[1]
        off = slots[:, r._slices["offset"]]
        if not self.base:
            return OR, Ot, mt, None, None, off
        b = slots[:, r._slices["base"]]
        return OR, Ot, mt, so3_exp(b[:, 3:]), b[:, :3], off

    # ------------------------------------------------------------------ calls
    def __call__(self, q: Tensor, x: Tensor | None = None) -> Tensor:
        """``q (N, dof)`` -> ``(N, M, 3)``; with ``x (P, k)`` -> ``(P, N, M, 3)`` (m)."""
        if x is None:
            out = self._run("fixed", q, self._fixed, self._obs, self._motion, self._paths)
        else:
            out = self._run("population", q, x, self, self._obs, self._motion, self._paths)
        return out.clone() if self._copy_out and self.compiled else out

    def _run(self, key: str, *args) -> Tensor:
        if self.compiled:
            # batch sizes are symbolic (one compilation for all), the joint count a constant
            for a in args[:2]:  # q, and x for a population
                if isinstance(a, Tensor) and a.ndim == 2:
                    torch._dynamo.maybe_mark_dynamic(a, 0)
        try:
            return self._fns[key](*args)
        except Exception as e:  # noqa: BLE001 - a compiler failure must not stop a calibration
            if not self.compiled:
                raise
            log.warning("the compiled position kernel failed (%s: %s); running it eagerly from now on",
                        type(e).__name__, str(e).splitlines()[0] if str(e) else "")
            self.compiled = False
            self._fns = {"fixed": _chain_fixed, "population": _chain_population}
            return self._fns[key](*args)


# ---------------------------------------------------------------------- the chain, per component
def _chain_population(q: Tensor, x: Tensor, kern: FusedPositions, obs: tuple | None, motion: tuple,
                      paths: tuple) -> Tensor:
    """``q (N, dof)``, ``x (P, k)`` -> ``(P, N, M, 3)`` (``(P, n_obs, 3)`` with ``obs``): the frames
    of each parameter vector, then the chain on ``(P, N)`` components."""
    full = kern.values.expand(x.shape[0], -1).index_copy(1, kern.free_index, x)
    out = _chain(q[None], *kern._frames(full), motion, paths)
    return out if obs is None else out[:, obs[0], obs[1]]


def _chain_fixed(q: Tensor, frames: tuple, obs: tuple | None, motion: tuple, paths: tuple) -> Tensor:
    """``q (N, dof)`` -> ``(N, M, 3)`` (``(n_obs, 3)`` with ``obs``) for frames of one parameter
    vector."""
    out = _chain(q[None], *frames, motion, paths)[0]
    return out if obs is None else out[obs[0], obs[1]]


def _chain(q: Tensor, OR: Tensor, Ot: Tensor, mt: Tensor, Rb: Tensor | None, tb: Tensor | None, off: Tensor,
           motion: tuple, paths: tuple) -> Tensor:
    """The chain as scalar operations on components. ``q (1, N, dof)``; frames (see
    :meth:`FusedPositions._frames`) with a leading ``P`` (or 1), each entry lifted to ``(P, 1)`` to
    broadcast against ``(P, N)``. Operations are in the order :meth:`Robot.positions` does them.
    Returns ``(P, N, M, 3)``."""
    trig: dict[int, tuple] = {}
    col = lambda a: a[:, None]  # noqa: E731

    def joint(j: int):
        if j not in trig:
            kind, s, mult, moff = motion[j]
            qj = (q[..., s] + col(off[:, s])) * mult + moff
            trig[j] = (torch.cos(qj), torch.sin(qj), qj) if kind == 1 else (None, None, qj)
        return trig[j]

    out = []
    for m, path in enumerate(paths):
        x, y, z = col(mt[:, m, 0]), col(mt[:, m, 1]), col(mt[:, m, 2])
        for j in path:
            kind = motion[j][0]
            if kind == 1:
                c, s, _ = joint(j)
                x, y = c * x - s * y, s * x + c * y
            elif kind == 2:
                z = z + joint(j)[2]
            R, t = OR[:, j], Ot[:, j]
            x, y, z = [col(t[:, i]) + col(R[:, i, 0]) * x + col(R[:, i, 1]) * y + col(R[:, i, 2]) * z
                       for i in range(3)]
        if Rb is not None:
            x, y, z = [col(tb[:, i]) + (col(Rb[:, i, 0]) * x + col(Rb[:, i, 1]) * y + col(Rb[:, i, 2]) * z)
                       for i in range(3)]
        shape = torch.broadcast_shapes(x.shape, y.shape, z.shape, (OR.shape[0], q.shape[1]))
        out.append(torch.stack([x.expand(shape), y.expand(shape), z.expand(shape)], -1))
    return torch.stack(out, -2)
