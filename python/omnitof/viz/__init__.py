"""Every figure of omnitof, drawn without a display: maps and trajectories (`maps`), scans and
slices (`scans`), the sensor's mirror regions and design sweep (`sensor`), calibration checks
(`calibration`) and 3D maps (`map3d`).

The figures use matplotlib's object API (`Figure` + the Agg canvas) rather than pyplot, so
drawing never selects a global backend, opens a window or keeps figures alive in pyplot's
registry; such a figure is freed with its last reference, so nothing needs closing.
"""

from __future__ import annotations

from pathlib import Path

from matplotlib.figure import Figure
from matplotlib.text import Text

from omnitof.errors import displayable
from omnitof.io.atomic import atomic_write


def save_figure(fig: Figure, path: str | Path, *, dpi: float | None = None,
                tight_layout: bool = True) -> Figure:
    """Write `fig` as a PNG at `path` (atomically: a reader never sees half a file) and return
    it. `tight_layout` first fits the axes to their labels; `dpi` None keeps the figure's own."""
    # Titles and labels quote the user's file names; one text that cannot be drawn would lose
    # the figure, and with it the run's other outputs.
    for text in fig.findobj(Text):
        shown = displayable(text.get_text())
        if shown != text.get_text():
            text.set_text(shown)
    if tight_layout:
        fig.tight_layout()
    with atomic_write(path, "wb") as handle:
        if dpi is None:
            fig.savefig(handle, format="png")
        else:
            fig.savefig(handle, format="png", dpi=dpi)
    return fig
