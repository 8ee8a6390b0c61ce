"""Environment variables of other programs that must not break ``import torchcal``.

``MPLBACKEND`` is read by matplotlib when it is imported (pytorch_kinematics imports
``matplotlib.pyplot`` on import), and a value matplotlib does not know, a notebook's
``module://matplotlib_inline.backend_inline`` exported into a terminal for instance, makes that
import raise: ``import torchcal`` would fail with matplotlib's traceback. torchcal draws its own
figures with Agg (:mod:`torchcal.report.plotting`), so an unusable backend is dropped from this
process's environment before matplotlib is imported, and :data:`NOTES` says so (the command line
prints it; a warning at import would itself fail under ``PYTHONWARNINGS=error``).

A ``torchcal`` command also answers SIGTERM from its first moment (:func:`early_sigterm`).
"""
from __future__ import annotations

import importlib.util
import os
import signal
import sys

__all__ = ["NOTES", "guard_matplotlib_backend", "early_sigterm"]

NOTES: list[str] = []
# matplotlib's built-in backends (matplotlib.backends.registry; the names are case-insensitive)
_BUILTIN = {"gtk3agg", "gtk3cairo", "gtk4agg", "gtk4cairo", "macosx", "nbagg", "notebook", "qtagg", "qtcairo",
            "qt5agg", "qt5cairo", "tkagg", "tkcairo", "webagg", "wx", "wxagg", "wxcairo", "agg", "cairo", "pdf",
            "pgf", "ps", "svg", "template", "inline", "ipympl", "widget"}


def _usable(name: str) -> bool:
    if name.lower() in _BUILTIN:
        return True
    if name.startswith("module://"):
        module = name[len("module://"):]
        try:
            return bool(module) and importlib.util.find_spec(module) is not None
        except (ImportError, ValueError):
            return False
    return False


def guard_matplotlib_backend() -> None:
    """Drop an ``MPLBACKEND`` matplotlib could not load, before matplotlib is imported (see the
    module docstring)."""
    name = os.environ.get("MPLBACKEND")
    if name is None or "matplotlib" in __import__("sys").modules or _usable(name.strip()):
        return
    del os.environ["MPLBACKEND"]
    NOTES.append(f"MPLBACKEND={name!r} is not a matplotlib backend this Python can load (a notebook's setting?); "
                 "it was ignored, and torchcal draws its figures with Agg. Unset it, or set it to e.g. 'agg'")


def _started_as_command() -> bool:
    """Whether this process is the ``torchcal`` command (``python -m torchcal`` or the script)."""
    argv = list(getattr(sys, "orig_argv", []))
    if "-m" in argv[:-1] and argv[argv.index("-m") + 1] == "torchcal":
        return True
    return len(argv) > 1 and os.path.basename(argv[1]) == "torchcal"


def _terminated_early(signum, frame) -> None:
    sys.stderr.write("torchcal: terminated (SIGTERM) while starting; nothing was written\n")
    os._exit(143)


def early_sigterm() -> None:
    """While the command imports its libraries (seconds), SIGTERM ends it with one line instead of
    silently; the command's own handler (:mod:`torchcal.cli.runtime`) takes over when it runs. A
    library import (a notebook, a script) installs nothing."""
    if _started_as_command() and signal.getsignal(signal.SIGTERM) is signal.SIG_DFL:
        signal.signal(signal.SIGTERM, _terminated_early)


guard_matplotlib_backend()
early_sigterm()
