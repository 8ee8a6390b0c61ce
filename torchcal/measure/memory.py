"""Whether a fit fits in memory, said before it starts.

A fit holds a few copies of its Jacobian, ``(rows · 3 · markers) × parameters`` doubles, in the
solver, the cross-validation and the statistics. Measured with ``/usr/bin/time`` on ``torchcal
calibrate`` (UR5e, one marker, 57 parameters): 0.46 GB at 60 rows (Python, torch and the plotting
libraries), 0.84 GB at 20,000 rows and 2.6 GB at 200,000 rows, i.e. 10 to 19 KB a row, 11 to 20
Jacobian copies. :func:`estimate_bytes` takes 20 copies plus the fixed part, so it errs high.

:func:`check_memory` refuses a fit whose estimate exceeds the memory this process may still use
(the smallest of the machine's available memory, a cgroup's limit and an address-space limit set
with ``ulimit -v``), with both figures and the ways out, instead of dying an hour later with
"can't allocate memory".
"""
from __future__ import annotations

import resource
from pathlib import Path

__all__ = ["estimate_bytes", "available_bytes", "check_memory"]

_BASE = 0.5e9  # Python, torch, numpy and matplotlib loaded (measured 0.46 GB)
_COPIES = 20  # Jacobian copies a fit holds at its peak (measured 11 to 20)


def estimate_bytes(rows: int, markers: int, n_params: int, itemsize: int = 8) -> float:
    """Peak memory (bytes) of a fit on ``rows`` poses of ``markers`` markers with ``n_params``
    parameters (see the module docstring)."""
    return _BASE + _COPIES * float(rows) * 3 * max(markers, 1) * max(n_params, 1) * itemsize


def _read_int(path: str) -> int | None:
    try:
        text = Path(path).read_text().strip()
    except OSError:
        return None
    return int(text) if text.isdigit() else None


def _vm_size() -> int:
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmSize:"):
                return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    return 0


def available_bytes() -> float | None:
    """The memory this process may still take (bytes), or None when the system does not say."""
    limits = []
    try:
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemAvailable:"):
                limits.append(int(line.split()[1]) * 1024)
    except (OSError, ValueError, IndexError):
        pass
    cg_max, cg_now = _read_int("/sys/fs/cgroup/memory.max"), _read_int("/sys/fs/cgroup/memory.current")
    if cg_max is not None and cg_now is not None:
        limits.append(max(cg_max - cg_now, 0))
    soft, _ = resource.getrlimit(resource.RLIMIT_AS)
    if soft != resource.RLIM_INFINITY and soft > 0:
        limits.append(max(soft - _vm_size(), 0))
    return float(min(limits)) if limits else None


def check_memory(rows: int, markers: int, n_params: int, who: str = "fit", itemsize: int = 8) -> float:
    """Refuse (``ValueError``) a fit that would need more memory than is available; return the
    estimate (bytes)."""
    need = estimate_bytes(rows, markers, n_params, itemsize)
    have = available_bytes()
    if have is not None and need - _BASE > have:
        fit_rows = max(int((have * 0.8) / (need - _BASE) * rows), 0)
        raise ValueError(f"the {who} of {rows:,} rows × {markers} marker(s) × {n_params} parameters needs about "
                         f"{need / 1e9:.1f} GB of memory, and this process may use {have / 1e9:.1f} GB more: use fewer "
                         f"rows (about {fit_rows:,} fit; a calibration gains little beyond a few thousand "
                         "well-spread poses, and torchcal plan picks the most informative), or run where there is "
                         "more memory")
    return need
