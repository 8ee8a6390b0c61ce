"""Command-line input is never silently dropped or guessed.

argparse, left to itself, takes ``--conf u.yaml`` for ``--config`` (prefix matching), keeps the
last of ``--data a.csv --data b.csv``, and a YAML loader keeps the last of a key given twice. Each
of these throws away what the user wrote. Here: abbreviations are off on every parser, an option
that takes one value may be given once, options that exclude each other are refused together, a
``--config`` file may name a key once, and values that would only fail deep in the work (a seed
beyond 64 bits, a path that is not UTF-8, a bad ``TORCHCAL_THREADS``) are refused at the door.
"""
from __future__ import annotations

import argparse

import yaml

from torchcal.optim import is_population
from torchcal.threads import env_problem

__all__ = ["strict_parsers", "check_command_line", "UniqueKeyLoader", "SEED_MAX"]

SEED_MAX = 2**63 - 1  # torch and numpy take seeds up to 64 bits; beyond, they overflow mid-run

# (option, option, why they exclude each other); a pair is refused when both are set (not default)
_CONFLICTS = (("test", "holdout", "--holdout splits --data when no --test is given; with --test it would be ignored. "
                                  "Give --test or --holdout, not both"),)
# (option, the option it needs, why); refused when the first is set without the second
_REQUIRES = (("shards", "ray", "--shards cuts the fleet into Ray tasks; without --ray it would be ignored. Add --ray "
              "local (or an address), or leave --shards out"),)


def strict_parsers(ap: argparse.ArgumentParser, sub: dict) -> None:
    """Turn argparse's prefix matching off on the top parser and every command's."""
    for p in [ap, *sub.values()]:
        p.allow_abbrev = False


def _single(a: argparse.Action) -> bool:
    """Whether a second ``a`` replaces the first (a value, or a list given at once as ``--opt A B``);
    ``append`` options add up and switches repeat harmlessly."""
    return bool(a.option_strings) and isinstance(a, (argparse._StoreAction, argparse.BooleanOptionalAction))


def _repeated(argv: list[str], parser: argparse.ArgumentParser) -> str | None:
    """The first option that takes one value and is given more than once in ``argv``."""
    for a in parser._actions:
        if not _single(a):
            continue
        flags = set(a.option_strings)
        seen = [t.split("=", 1)[0] for t in argv if t.split("=", 1)[0] in flags]
        if len(seen) > 1:
            what = "one value" if a.nargs in (None, "?", 1) else "its values at once (--opt A B)"
            return (f"{' '.join(seen)}: {a.option_strings[-1]} takes {what} and was given {len(seen)} times; only the "
                    "last would be used. Give it once")
    return None


def _not_default(a: argparse.Namespace, parser: argparse.ArgumentParser, dest: str) -> bool:
    v = getattr(a, dest, None)
    return v is not None and v != parser.get_default(dest) and v not in (0, 0.0, False, [])


def _paths_utf8(a: argparse.Namespace) -> str | None:
    for k, v in vars(a).items():
        for text in (v if isinstance(v, list) else [v]):
            if isinstance(text, str):
                try:
                    text.encode("utf-8")
                except UnicodeEncodeError:
                    shown = text.encode("utf-8", "surrogateescape").decode("latin-1", "replace")
                    return (f"--{k.replace('_', '-')} {shown!r} is not UTF-8 (a Latin-1 file name?); rename it in UTF-8 "
                            "(convmv -f latin1 -t utf8 --notest NAME) or give another path")
    return None


def check_command_line(argv: list[str], a: argparse.Namespace, parser: argparse.ArgumentParser) -> str | None:
    """What is wrong with the command line ``argv`` (the user's own, without ``--config``'s
    options) parsed as ``a`` by the command's ``parser``, or None; see the module docstring."""
    problem = env_problem()
    if problem:
        return problem
    cut = argv.index("--") if "--" in argv else len(argv)
    problem = _repeated(argv[:cut], parser)
    if problem:
        return problem
    for x, y, why in _CONFLICTS:
        if _not_default(a, parser, x) and _not_default(a, parser, y):
            return f"--{x.replace('_', '-')} and --{y.replace('_', '-')} were both given: {why}"
    for x, y, why in _REQUIRES:
        if _not_default(a, parser, x) and not _not_default(a, parser, y):
            return f"--{x.replace('_', '-')} without --{y.replace('_', '-')}: {why}"
    if getattr(a, "polish", False) and not is_population(a.method):
        return (f"--polish polishes a swarm method's result with LM, and --method {a.method} is not a swarm method, so "
                "it would be ignored; leave --polish out, or pick a swarm method (e.g. --method pso)")
    seed = getattr(a, "seed", None)
    if isinstance(seed, int) and not -SEED_MAX <= seed <= SEED_MAX:
        return (f"--seed {seed} is beyond ±(2**63 - 1) (the random generators take 64 bits); give a seed of at most "
                "18 digits")
    return _paths_utf8(a)


class UniqueKeyLoader(yaml.SafeLoader):
    """A safe YAML loader that refuses a key given twice in one mapping (PyYAML keeps the last)."""

    def construct_mapping(self, node, deep=False):
        seen: dict = {}
        for key_node, _ in node.value:
            key = self.construct_object(key_node, deep=deep)
            if key in seen:
                raise yaml.constructor.ConstructorError(
                    None, None, f"the key {key!r} is given twice (lines {seen[key] + 1} and "
                    f"{key_node.start_mark.line + 1}); only the last would be used: keep one", key_node.start_mark)
            seen[key] = key_node.start_mark.line
        return super().construct_mapping(node, deep=deep)


UniqueKeyLoader.add_constructor(yaml.resolver.BaseResolver.DEFAULT_MAPPING_TAG, UniqueKeyLoader.construct_mapping)
