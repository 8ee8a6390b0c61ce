"""One run per output: a lock file beside the output, and what a run left behind when it was killed.

A run claims its output (:func:`claim`) before the work: a lock file, created atomically, that
holds its process id. A second run on the same output is refused while the first lives. A lock
whose process is gone (killed, a crashed machine), whose process id is now another program's (a
restarted container reuses ids), or that holds this very process's id without this process
having taken it, is stale: it is removed, and the run says so.

A killed run can also leave its temporary siblings of the output (``.NAME.….PID.partial``,
``.NAME.replaced-PID``): :func:`clean_leftovers` removes those whose process is gone, and says so.
"""
from __future__ import annotations

import logging
import os
import re
import shutil
import time
from contextlib import contextmanager
from pathlib import Path
from typing import Iterator

__all__ = ["claim", "OutputBusy", "clean_leftovers", "alive", "lock_path"]

logger = logging.getLogger("torchcal")
_HELD: set[str] = set()  # the locks this process holds now
_PID = re.compile(r"\.(\d+)\.partial$|\.replaced-(\d+)$")
_OLD_PARTIAL_S = 3600.0  # a leftover without a process id (an earlier torchcal) older than this is stale


class OutputBusy(FileExistsError):
    """Another run holds the output (see :func:`claim`)."""


def alive(pid: int) -> bool:
    """Whether process ``pid`` runs and could be a torchcal run (a Python program)."""
    if pid == os.getpid():
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    except OverflowError:
        return False
    try:
        cmd = Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").lower()
    except OSError:
        return True  # no /proc (macOS) or not readable: assume the worst
    return b"python" in cmd or b"torchcal" in cmd


def lock_path(p: Path, home: Path) -> Path:
    """The lock of output ``p`` (resolved) in ``home``, the nearest existing folder above it."""
    return home / f".{str(p.relative_to(home)).replace(os.sep, '%')}.torchcal-lock"


def _stale(lock: Path) -> tuple[int | None, str | None]:
    """The process id in ``lock`` and why the lock is stale (None when a live run holds it, or is
    writing it this instant)."""
    try:
        pid = int(lock.read_text().split()[0])
    except (OSError, ValueError, IndexError):
        return None, None  # being written this instant: a live claim
    if pid == os.getpid():
        return pid, None if str(lock) in _HELD else f"it holds this run's own process id {pid} (a restarted container)"
    if not alive(pid):
        return pid, f"its process {pid} is no longer running"
    return pid, None


@contextmanager
def claim(path, home: Path) -> Iterator[Path]:
    """Hold ``path`` (resolved) for this run with a lock file in ``home``; see the module docstring."""
    p = Path(path)
    lock = lock_path(p, home)
    for _ in range(3):
        try:
            fd = os.open(lock, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o644)
        except FileExistsError:
            pid, why = _stale(lock)
            if why is not None:
                lock.unlink(missing_ok=True)
                logger.warning(f"torchcal: removed a stale lock of {p} ({why}): {lock}")
                continue
            raise OutputBusy(f"another torchcal run{'' if pid is None else f' (process {pid})'} is writing {p}; wait "
                             f"for it to finish, or choose another output (if no run is left, delete {lock})") from None
        try:
            os.write(fd, f"{os.getpid()}\n".encode())
        except OSError:
            lock.unlink(missing_ok=True)  # a full disk: no claim, and no empty lock left behind
            raise
        finally:
            os.close(fd)
        break
    else:
        raise OutputBusy(f"could not claim {p}: {lock} keeps coming back; delete it if no torchcal run is left")
    _HELD.add(str(lock))
    try:
        yield p
    finally:
        _HELD.discard(str(lock))
        lock.unlink(missing_ok=True)


def _leftover_pid(name: str) -> int | None:
    m = _PID.search(name)
    return None if m is None else int(m.group(1) or m.group(2))


def clean_leftovers(p: Path) -> list[str]:
    """Remove the temporary siblings of output ``p`` that a killed run left (see the module
    docstring); return their names, which are also logged."""
    parent = p.parent
    if not parent.is_dir():
        return []
    gone = []
    try:
        siblings = [x for x in parent.iterdir() if x.name.startswith(f".{p.name}.")]
    except OSError:
        return []
    for x in siblings:
        if not (x.name.endswith(".partial") or ".replaced-" in x.name):
            continue
        pid = _leftover_pid(x.name)
        if pid is None:
            try:
                if time.time() - x.lstat().st_mtime < _OLD_PARTIAL_S:
                    continue
            except OSError:
                continue
        elif pid == os.getpid() or alive(pid):
            continue
        if x.is_dir() and not x.is_symlink():
            shutil.rmtree(x, ignore_errors=True)
        else:
            x.unlink(missing_ok=True)
        gone.append(x.name)
    if gone:
        logger.warning(f"torchcal: removed what an interrupted run left beside {p}: {', '.join(sorted(gone))}")
    return gone
