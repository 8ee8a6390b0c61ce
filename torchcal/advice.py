"""Advice worded for whoever reads it: the same refusal tells a command-line user which option
to pass (``--units deg``) and a Python user which argument (``units=['deg']``).

The command line runs its commands inside :func:`cli_wording`; library code words the fix of an
error with :func:`advice`, which picks the form. Outside the command line it is the Python form.
"""
from __future__ import annotations

from contextlib import contextmanager
from contextvars import ContextVar
from typing import Iterator

__all__ = ["advice", "cli_wording", "in_cli"]

_CLI: ContextVar[bool] = ContextVar("torchcal_cli_wording", default=False)


def in_cli() -> bool:
    """Whether the reader of a message is a command-line user."""
    return _CLI.get()


def advice(api: str, cli: str) -> str:
    """``cli`` inside a ``torchcal`` command, ``api`` otherwise."""
    return cli if _CLI.get() else api


@contextmanager
def cli_wording() -> Iterator[None]:
    """Word advice for the command line within the block."""
    token = _CLI.set(True)
    try:
        yield
    finally:
        _CLI.reset(token)
