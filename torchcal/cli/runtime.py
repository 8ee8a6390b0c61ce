"""What a command meets from outside while it runs: SIGTERM, a standard output that fails, and
an environment that turns warnings into errors.

* SIGTERM (``kill``, a container stopping, a job scheduler) is handled as Ctrl-C: the run stops,
  its temporary files and its lock are removed, and it says so (exit 143, as a shell reports it).
  Whatever fails once it arrived fails because of it (:func:`terminated`): the interrupt raised
  while a compiled library initialises comes out as that library's ``ImportError``.
* Standard output is not an output of the run: when it fails (a closed pipe, ``> file`` on a full
  device), the files the run wrote are complete, and the message says that, not "nothing was
  written".
* ``PYTHONWARNINGS=error`` (or ``-W error``) would turn every message torchcal gives as a warning
  (a value beyond a limit, a suspect row) into a crash: while a command runs, warnings are shown,
  one line each, as the command's own messages.
"""
from __future__ import annotations

import errno
import os
import signal
import sys
import threading
import warnings
from contextlib import contextmanager
from typing import Iterator

__all__ = ["Terminated", "StdoutLost", "command_runtime", "stdout_lost_message", "terminated"]


class Terminated(KeyboardInterrupt):
    """The process got SIGTERM (handled as an interrupt: every ``finally`` runs)."""


class StdoutLost(OSError):
    """Writing to standard output failed (the pipe closed, the device is full)."""


class _GuardedStdout:
    """Standard output whose failures are told apart from those of the run's files."""

    def __init__(self, stream):
        self._stream = stream

    def write(self, text):
        try:
            return self._stream.write(text)
        except OSError as e:
            raise StdoutLost(e.errno, e.strerror) from None

    def flush(self):
        try:
            return self._stream.flush()
        except OSError as e:
            raise StdoutLost(e.errno, e.strerror) from None

    def __getattr__(self, name):
        return getattr(self._stream, name)


_got = threading.Event()  # SIGTERM arrived during the command that runs


def terminated() -> bool:
    """Whether SIGTERM arrived while the current command ran (:func:`command_runtime`)."""
    return _got.is_set()


def _on_sigterm(signum, frame):
    _got.set()
    raise Terminated()


@contextmanager
def command_runtime() -> Iterator[None]:
    """Run a command's work with SIGTERM as an interrupt, a guarded standard output and warnings
    shown (never raised); everything is as before when it ends."""
    main = threading.current_thread() is threading.main_thread()
    _got.clear()
    before = signal.signal(signal.SIGTERM, _on_sigterm) if main else None
    stdout = sys.stdout
    sys.stdout = _GuardedStdout(stdout)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("default")
            yield
            sys.stdout.flush()  # a full device shows here, while the message can still say what happened
    finally:
        sys.stdout = stdout
        if main:
            signal.signal(signal.SIGTERM, before)


def stdout_lost_message(cmd: str, e: StdoutLost, out) -> str:
    """The line that says standard output failed and what of the run is safe."""
    if out is not None and os.path.exists(out):
        where = f"the results in {out} are complete; only the summary printed here is lost"
    else:
        where = "what was printed is incomplete"
    if sys.stdout is sys.__stdout__:
        # nothing more can go to the broken stream, not even Python's last flush at exit
        try:
            sys.stdout = open(os.devnull, "w")
        except OSError:
            pass
    if e.errno == errno.EPIPE:
        return f"torchcal {cmd}: standard output was closed (a pipe ended early); {where}"
    return (f"torchcal {cmd}: error: could not write to standard output: {e.strerror}; {where}. Free some space or "
            "send the output elsewhere")
