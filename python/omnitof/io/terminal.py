"""What a command shows on the terminal while it works: progress bars.

On a terminal a bar redraws itself in place several times a second. Into a log file or a CI
console (standard error is not a terminal) every redraw would be one more line, so there a
bar writes at most one line every `LOG_INTERVAL_S` seconds, enough to see that a long run
moves."""

from __future__ import annotations

import sys

from tqdm import tqdm

LOG_INTERVAL_S = 30.0


def progress_bar(total: int, *, enabled: bool = True, desc: str = "", unit: str = "scan") -> tqdm:
    """A tqdm bar over `total` units on standard error (a no-op bar when not `enabled`)."""
    if sys.stderr.isatty():
        return tqdm(total=total, unit=unit, desc=desc, disable=not enabled, dynamic_ncols=True)
    return tqdm(total=total, unit=unit, desc=desc, disable=not enabled, ncols=80,
                mininterval=LOG_INTERVAL_S, maxinterval=LOG_INTERVAL_S, ascii=True)
