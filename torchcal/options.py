"""Typed option records: what a driver's settings are, in one frozen dataclass per driver.

A driver takes ``settings=`` (an instance) and/or its fields as keywords, as theseus's
``NonlinearOptimizerParams`` travels with a solver: ``calibrate(robot, data, method="lm")`` and
``calibrate(robot, data, settings=CalibrateOptions(method="lm"))`` are the same call. A key that is
not a field is refused with the fields that exist, so a misspelt setting never passes silently.
(``options=`` stays what it has always been where a driver has one: the solver's own settings.)
"""
from __future__ import annotations

import difflib
from dataclasses import dataclass, fields, replace
from typing import Any, TypeVar

__all__ = ["Options"]

T = TypeVar("T", bound="Options")


@dataclass(frozen=True)
class Options:
    """Base of the option records. Subclasses are frozen dataclasses with a default for every field."""

    @classmethod
    def names(cls) -> list[str]:
        return [f.name for f in fields(cls)]

    @classmethod
    def build(cls: type[T], settings: T | None = None, /, **kw: Any) -> T:
        """``settings`` (or the defaults) with the fields in ``kw`` replaced; unknown keys refused."""
        if settings is not None and not isinstance(settings, cls):
            raise TypeError(f"settings must be a {cls.__name__}, not {type(settings).__name__}")
        unknown = [k for k in kw if k not in cls.names()]
        if unknown:
            hints = []
            for k in unknown:
                close = difflib.get_close_matches(k, cls.names(), n=1)
                hints.append(f"{k!r}" + (f" (did you mean {close[0]!r}?)" if close else ""))
            raise TypeError(f"{cls.__name__} has no option {', '.join(hints)}; "
                            f"the options are: {', '.join(cls.names())}")
        return replace(settings if settings is not None else cls(), **kw)

