"""Helpers for the line-oriented text formats (TUM trajectories, benchmark relations)."""

from __future__ import annotations

import math
from pathlib import Path

from omnitof.errors import InputError


def parse_float_row(text: str, count: int, expected: str, path: str | Path, number: int) -> list[float]:
    """The `count` finite numbers of one line, or an InputError naming the file and line.

    `expected` says what a row must hold (e.g. "TUM trajectory rows need 8 numbers: ...").
    """
    fields = text.split()
    try:
        row = [float(v) for v in fields]
    except ValueError:
        row = []
    if len(row) != count:
        raise InputError(f"{expected} (found {len(fields)} fields)", path, number)
    if not all(math.isfinite(v) for v in row):
        raise InputError(f"{expected}, all finite (found nan or inf)", path, number)
    return row
