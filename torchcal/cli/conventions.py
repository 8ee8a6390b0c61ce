"""How every ``torchcal`` command presents its options: each default shown in ``--help``, an
option renamed refused with its new name, a solver listed once with its aliases, and the progress
switch the long commands share."""
from __future__ import annotations

import argparse
import sys

__all__ = ["DefaultsFormatter", "renamed", "method_choice", "method_help", "add_progress", "progress_on"]


class DefaultsFormatter(argparse.HelpFormatter):
    """Help that ends every option's text with its default, ``(default: …)``, where it has one:
    not for required options, switches that are off, or options whose text says in words what
    happens without them (an option whose default is None)."""

    def _get_help_string(self, action: argparse.Action) -> str:
        text = action.help or ""
        d = action.default
        if (action.required or "%(default)" in text or d is None or d is False or d == [] or d is argparse.SUPPRESS
                or not action.option_strings):
            return text
        return f"{text} (default: %(default)s)"

    def _split_lines(self, text: str, width: int) -> list[str]:
        # argparse breaks lines after a hyphen, which cuts names such as chaotic-pso or
        # --orientation-weight in two; names are kept whole
        import textwrap

        return textwrap.wrap(self._whitespace_matcher.sub(" ", text).strip(), width, break_on_hyphens=False,
                             break_long_words=False)


def renamed(parser: argparse.ArgumentParser, old: str, new: str, why: str, nargs="?") -> None:
    """Refuse ``old`` (hidden from ``--help``) with a message that names ``new``: a script with
    the old spelling stops at once rather than meaning something else."""

    class Renamed(argparse.Action):
        renamed = f"{old} is now {new}: {why}"  # also what a --config file's old key is told

        def __call__(self, p, namespace, values, option_string=None):
            p.error(self.renamed)

    parser.add_argument(old, nargs=nargs, action=Renamed, help=argparse.SUPPRESS, dest=f"_renamed_{old[2:]}")


def method_choice(registry: dict[str, tuple[str, ...]]):
    """An argparse ``type`` that reads a solver's name or alias (any case) as its name."""
    lookup = {a.lower(): name for name, aliases in registry.items() for a in (name, *aliases)}

    def read(text: str) -> str:
        return lookup.get(text.lower(), text)  # an unknown name is left for argparse's choices to refuse
    return read


def method_help(registry: dict[str, tuple[str, ...]], population: list[str]) -> str:
    """The ``--method`` help: each solver once, its aliases in brackets, the swarms marked."""
    names = [f"{n} (also {', '.join(a)})" if a else n for n, a in sorted(registry.items())]
    return ("solver: " + "; ".join(names) + ". Population methods (" + ", ".join(sorted(population)) + ") search a "
            "box around the start and, with --polish, finish with LM")


def add_progress(p: argparse.ArgumentParser, over: str) -> None:
    """``--progress / --no-progress``: a bar with a total and the time left over ``over``."""
    p.add_argument("--progress", action=argparse.BooleanOptionalAction, default=None,
                   help=f"progress bar over {over}, with the total and the time left (default: on when stderr is a "
                        "terminal and not --quiet)")


def progress_on(a: argparse.Namespace) -> bool:
    """Whether to show progress: ``--progress`` / ``--no-progress``, else on in a terminal."""
    p = getattr(a, "progress", None)
    return p if p is not None else (sys.stderr.isatty() and not getattr(a, "quiet", False))
