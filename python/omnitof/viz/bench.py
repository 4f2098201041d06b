"""The figure of an experiment (omnitof.bench): a metric against one grid parameter, one line
per preset and setting of the other parameters, the mean over seeds with the min–max as bars.

Drawn with matplotlib's object API and the Agg canvas (no pyplot, no display), written
atomically.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from matplotlib.figure import Figure

from omnitof.viz import save_figure

# (mean, min, max) of one point of a line, or None where no run of it completed.
Point = tuple[float, float, float] | None


def plot_against_parameter(path: str | Path, parameter: str, values: Sequence[Any], lines: dict[str, list[Point]],
                           *, ylabel: str, title: str = "") -> Figure:
    """Draw `lines` (label → one Point per value of `parameter`) and write a PNG.

    Numbers go on a numeric axis, logarithmic where they are positive and span a factor of 10
    or more (particle counts); anything else (true/false, names) is a category per value."""
    fig = Figure(figsize=(6.4, 4.2))
    ax = fig.add_subplot()
    numeric = all(isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) for v in values)
    xs = [float(v) for v in values] if numeric else list(range(len(values)))
    for label, points in lines.items():
        kept = [(x, p) for x, p in zip(xs, points) if p is not None and math.isfinite(p[0])]
        if not kept:
            continue
        x = [k[0] for k in kept]
        mean = [k[1][0] for k in kept]
        below = [k[1][0] - k[1][1] for k in kept]
        above = [k[1][2] - k[1][0] for k in kept]
        ax.errorbar(x, mean, yerr=[below, above], marker="o", capsize=3, label=label)
    if numeric and min(xs) > 0 and max(xs) >= 10 * min(xs):
        ax.set_xscale("log")
    ax.set_xticks(xs, [_label(v) for v in values])
    ax.minorticks_off()
    ax.set_xlabel(parameter)
    ax.set_ylabel(ylabel)
    ax.set_title(title)
    ax.grid(alpha=0.3)
    if len(lines) > 1:
        ax.legend(fontsize="small")
    return save_figure(fig, path, dpi=120)


def _label(value: Any) -> str:
    if isinstance(value, bool):
        return str(value).lower()
    return f"{value:g}" if isinstance(value, float) else str(value)
