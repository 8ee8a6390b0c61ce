"""Counting, on the CPU, what would make the host wait for a GPU.

On a GPU the host queues work and goes on; it waits only when it reads a result (``.item()``,
``.tolist()``, ``bool(t)``, ``float(t)``), when an operation's output size depends on the data
(``nonzero``, boolean-mask indexing, ``unique``, ``repeat_interleave`` by a tensor, ``equal``), or
when it copies host data to the device (``torch.tensor([...], device="cuda")`` waits for the
stream). :class:`HostSyncs` counts those while it is active, on any device: the Python-level
reads by patching ``torch.Tensor``, the rest as the aten operations a dispatch mode sees, so a
CPU test can hold a GPU code path to a fixed number of waits.
"""
from __future__ import annotations

import collections
import traceback

import torch
from torch.utils._python_dispatch import TorchDispatchMode

_READS = ("item", "tolist", "numpy", "__bool__", "__float__", "__int__", "__index__")
# aten ops that wait for the device: a scalar read, data-dependent output sizes, host data copied in
_OPS = {"aten._local_scalar_dense", "aten.nonzero", "aten.masked_select", "aten.equal", "aten.is_nonzero",
        "aten._unique2", "aten.unique_dim", "aten.unique_consecutive", "aten.repeat_interleave.Tensor",
        "aten.lift_fresh"}


class HostSyncs(TorchDispatchMode):
    """Context manager: ``counts`` maps ``(what, 'file:line function')`` to how often it happened;
    ``total`` sums them. A read through ``.item()`` also reaches aten as ``_local_scalar_dense``:
    it is counted once, as the read."""

    def __init__(self):
        super().__init__()
        self.counts: collections.Counter = collections.Counter()
        self._saved: dict = {}
        self._in_read = 0

    @property
    def total(self) -> int:
        return sum(self.counts.values())

    @staticmethod
    def _where() -> str:
        for fr in reversed(traceback.extract_stack()[:-2]):
            if "host_syncs.py" not in fr.filename and "/torch/" not in fr.filename:
                return f"{fr.filename.rsplit('/', 1)[-1]}:{fr.lineno} {fr.name}"
        return "?"

    def __enter__(self):
        for name in _READS:
            f = self._saved[name] = getattr(torch.Tensor, name)

            def read(t, *a, _f=f, _name=name, **k):
                if self._in_read:
                    return _f(t, *a, **k)
                self.counts[(_name, self._where())] += 1
                self._in_read += 1
                try:
                    return _f(t, *a, **k)
                finally:
                    self._in_read -= 1
            setattr(torch.Tensor, name, read)
        return super().__enter__()

    def __exit__(self, *exc):
        for name, f in self._saved.items():
            setattr(torch.Tensor, name, f)
        return super().__exit__(*exc)

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        name = str(func.overloadpacket) if str(func) != "aten.repeat_interleave.Tensor" else str(func)
        if name == "aten.index" and any(isinstance(i, torch.Tensor) and i.dtype == torch.bool
                                        for i in (args[1] if len(args) > 1 else [])):
            name = "aten.index (boolean mask)"
            self.counts[(name, self._where())] += 1
        elif name in _OPS and not self._in_read:
            # a Python number written into a tensor comes in as a 0-d tensor: a fill, no copy
            if not (name == "aten.lift_fresh" and args[0].ndim == 0):
                self.counts[(name, self._where())] += 1
        return func(*args, **(kwargs or {}))
