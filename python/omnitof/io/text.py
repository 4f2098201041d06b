"""Helpers for the line-oriented text formats (TUM trajectories, benchmark relations)."""

from __future__ import annotations

import math
import re
from pathlib import Path

from omnitof.errors import InputError

# A decimal number as the formats write them. Python's float() also takes "1_0" (as 10), "nan",
# "infinity" and full-width or Arabic-Indic digits, none of which a writer of these formats
# means (re.ASCII: without it \d matches those digits too).
_NUMBER = re.compile(r"[+-]?(?:\d+\.?\d*|\.\d+)(?:[eE][+-]?\d+)?", re.ASCII)

# Longest piece of a user's line quoted back in an error.
_QUOTE = 40


def is_decimal(token: str) -> bool:
    """Whether `token` is a plain decimal number (a finite one: 1e400 is not)."""
    return _NUMBER.fullmatch(token) is not None and math.isfinite(float(token))


def shorten(text: str) -> str:
    """`text` cut after 40 characters, for an error message that echoes what the user wrote."""
    return text if len(text) <= _QUOTE else text[:_QUOTE] + "..."


def quote(text: str) -> str:
    """`text` for an error message: repr'd (control characters shown), cut after 40 characters."""
    return repr(shorten(text))


def parse_float_row(
    text: str,
    count: int,
    expected: str,
    path: str | Path,
    number: int,
    *,
    names: tuple[str, ...] = (),
    limits: dict[str, float] | None = None,
) -> list[float]:
    """The `count` finite numbers of one line, or an InputError naming the file, line and field.

    `expected` says what a row must hold (e.g. "TUM trajectory rows need 8 numbers: ...");
    `names` names the fields in order, and `limits` bounds the magnitude of named fields (a
    position of 1e300 m is a broken writer, and its statistics print as 300 digits).
    """
    fields = text.split()
    if len(fields) != count:
        raise InputError(f"{expected} (found {len(fields)} fields)", path, number)
    row = []
    for k, value in enumerate(fields):
        name = names[k] if k < len(names) else f"field {k + 1}"
        if not is_decimal(value):
            raise InputError(f"{name} is {quote(value)}, not a finite decimal number", path, number)
        parsed = float(value)
        bound = (limits or {}).get(name)
        if bound is not None and abs(parsed) > bound:
            raise InputError(f"{name} is {parsed:g}, beyond ±{bound:g}: not a plausible value", path, number)
        row.append(parsed)
    return row
