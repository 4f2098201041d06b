"""`omnitof calibrate report`: a calibration file as a readable report (issue 16).

Writes into a folder: report.md (the parameters with their standard deviations from the joint
refinement, the residuals per image and per mirror, the distance correction, the paper's Fig. 6
check) and its figures: residuals.png (RMS residual per image), distance_error.png (the median
distance error against distance before and after the correction, on the samples it was fitted
to), fig6_side_view.png (the upper edges of equal-height objects seen through every mirror).
A calibration without a refinement or a distance correction gets a report without those parts,
saying so.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from omnitof.calibration import Calibration
from omnitof.io.atomic import atomic_write
from omnitof.viz import save_figure


def _residual_figure(path: Path, per_view: dict[str, dict[str, float]]) -> Figure:
    # Constrained layout: the image names under the bars are long, which tight_layout cannot fit.
    fig = Figure(figsize=(10.0, 5.0), dpi=120, layout="constrained")
    FigureCanvasAgg(fig)
    axes = fig.subplots(1, 2)
    names = list(per_view)
    labels = [Path(n).stem for n in names]
    x = np.arange(len(names))
    for key, colour, label in (("direct_px", "C0", "direct (corners, dots)"), ("mirrored_px", "C1", "through the mirror (dots)")):
        values = [per_view[n].get(key, np.nan) for n in names]
        axes[0].bar(x, values, color=colour, alpha=0.7, label=label)
    axes[0].set_ylabel("RMS reprojection residual [px]")
    axes[0].legend(fontsize=8)
    axes[1].bar(x, [per_view[n].get("path_mm", np.nan) for n in names], color="C2")
    axes[1].set_ylabel("median |path length residual| [mm]")
    for ax in axes:
        ax.set_xticks(x[:: max(1, len(x) // 30)])
        ax.set_xticklabels(labels[:: max(1, len(x) // 30)], rotation=90, fontsize=6)
    fig.suptitle("residuals per image after the joint refinement")
    return save_figure(fig, path, tight_layout=False)


def _distance_figure(path: Path, curve: dict[str, list[float]]) -> Figure:
    fig = Figure(figsize=(7.0, 4.0), dpi=120)
    FigureCanvasAgg(fig)
    ax = fig.add_subplot()
    ax.plot(curve["distance_m"], curve["before_mm"], "o-", ms=3, label="before correction")
    ax.plot(curve["distance_m"], curve["after_mm"], "o-", ms=3, label="after correction")
    ax.axhline(0.0, color="grey", linewidth=0.8)
    ax.set_xlabel("measured distance [m]")
    ax.set_ylabel("median distance error [mm]")
    ax.set_title("systematic distance error (the fit's samples)")
    ax.legend()
    return save_figure(fig, path)


def write_report(cal: Calibration, out: str | Path, *, distance: np.ndarray | None = None,
                 truth: Calibration | None = None) -> dict[str, Any]:
    """Write report.md and its figures for `cal` into `out`; returns what was written.

    distance: a distance image of the rig among equal-height objects for the Fig. 6 check
    (default: the simulated scene of `calibration.check.render_check_frame` for the default
    rig). truth: the true calibration (simulations), for an error column.
    """
    from omnitof.calibration.check import edge_heights, plane_errors, render_check_frame
    from omnitof.sensor.design import default_rig
    from omnitof.viz.calibration import plot_side_view

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    refinement = cal.quality.get("refinement") or {}
    std = refinement.get("std") or {}
    lines = ["# Calibration report", ""]
    source = cal.provenance.get("source") or cal.provenance.get("intrinsics") or "unknown"
    lines += [f"Calibration: {source}.", ""]
    if cal.provenance.get("refinement"):
        lines += [f"Refinement: {cal.provenance['refinement']}.", ""]
    # Parameters with their standard deviations.
    cam = cal.camera
    cam_std = std.get("camera", {})
    lines += ["## Camera", "", "| parameter | value | σ |" + (" error |" if truth else ""),
              "|---|---|---|" + ("---|" if truth else "")]
    values = {"fx": cam.fx, "fy": cam.fy, "cx": cam.cx, "cy": cam.cy, "k1": cam.dist[0], "k2": cam.dist[1],
              "p1": cam.dist[2], "p2": cam.dist[3]}
    true_values = None
    if truth is not None:
        tc = truth.camera
        true_values = {"fx": tc.fx, "fy": tc.fy, "cx": tc.cx, "cy": tc.cy, "k1": tc.dist[0], "k2": tc.dist[1],
                       "p1": tc.dist[2], "p2": tc.dist[3]}
    for key, value in values.items():
        sigma = cam_std.get(key)
        row = f"| {key} | {value:.5g} | {'–' if sigma is None else f'{sigma:.3g}'} |"
        if true_values is not None:
            row += f" {value - true_values[key]:+.3g} |"
        lines.append(row)
    lines += ["", "## Mirrors", "", "| mirror | normal | d (mm) | σ normal (°) | σ d (mm) |"
              + (" normal error (°) | d error (mm) |" if truth else ""),
              "|---|---|---|---|---|" + ("---|---|" if truth else "")]
    errors = plane_errors(cal, truth) if truth is not None else {}
    for name, plane in zip(cal.names, cal.planes):
        s = std.get("mirrors", {}).get(name, {})
        n = plane.normal
        row = (f"| {name} | [{n[0]:+.5f}, {n[1]:+.5f}, {n[2]:+.5f}] | {1000 * plane.d:.3f} | "
               f"{s.get('normal_deg', math.nan):.4f} | {s.get('d_mm', math.nan):.3f} |")
        if name in errors:
            row += f" {errors[name][0]:.4f} | {errors[name][1]:+.3f} |"
        lines.append(row)
    written: dict[str, Any] = {}
    # Residuals.
    lines += ["", "## Residuals", ""]
    if refinement:
        noise = refinement.get("noise", {})
        lines += [f"Noise levels at the solution: corners {noise.get('corner_px', math.nan):.3f} px, dots "
                  f"{noise.get('dot_px', math.nan):.3f} px, path lengths {noise.get('path_mm', math.nan):.2f} mm.", "",
                  "Per mirror:", "", "| mirror | RMS dots through it (px) | median abs path residual (mm) | median path residual (mm) |",
                  "|---|---|---|---|"]
        for name, entry in refinement.get("per_mirror", {}).items():
            lines.append(f"| {name} | {entry.get('dot_px', math.nan):.3f} | {entry.get('path_mm', math.nan):.2f} | "
                         f"{entry.get('path_bias_mm', math.nan):+.2f} |")
        per_view = refinement.get("per_view", {})
        lines += ["", "Per image (![residuals](residuals.png)):", "",
                  "| image | direct RMS (px) | mirrored RMS (px) | median abs path residual (mm) |", "|---|---|---|---|"]
        for name, entry in per_view.items():
            lines.append(f"| {name} | {entry.get('direct_px', math.nan):.3f} | {entry.get('mirrored_px', math.nan):.3f} | "
                         f"{entry.get('path_mm', math.nan):.2f} |")
        _residual_figure(out / "residuals.png", per_view)
        written["residuals"] = out / "residuals.png"
        if refinement.get("skipped"):
            lines += ["", "Images the refinement could not use:", ""] + [f"- {t}" for t in refinement["skipped"]]
        if refinement.get("rejected"):
            lines += ["", "Images left out as outliers (reprojection error far beyond the others'):", ""] + [
                f"- {name} (view RMS {rms:.3f} px)" for name, rms in refinement["rejected"].items()]
    else:
        lines.append("This calibration was not refined jointly (run `omnitof calibrate refine`): no residuals "
                     "or standard deviations.")
    # Distance correction.
    lines += ["", "## Distance correction", ""]
    dc = cal.distance_correction
    if dc is None:
        lines.append("None: distances are used as the camera reports them.")
    else:
        lines.append(f"Fitted to {dc.samples} samples: RMS error {1000 * dc.rms_before:.2f} mm before, "
                     f"{1000 * dc.rms_after:.2f} mm after the correction; per-pixel offsets: "
                     f"{'yes' if dc.pixel_offsets is not None else 'no'}.")
        if dc.curve and dc.curve.get("distance_m"):
            _distance_figure(out / "distance_error.png", dc.curve)
            written["distance_error"] = out / "distance_error.png"
            lines += ["", "![distance error](distance_error.png)"]
    # The paper's Fig. 6 check.
    if distance is None:
        rig = default_rig()
        camera = truth.camera if truth is not None else rig.camera
        distance = render_check_frame(camera, rig.mirrors).distance
        where = "the simulated scene of equal-height boxes around the default rig"
    else:
        where = "the given frame"
    check = edge_heights(cal, distance)
    plot_side_view(out / "fig6_side_view.png", check, cal.names)
    written["side_view"] = out / "fig6_side_view.png"
    lines += ["", "## The paper's Fig. 6 check", "",
              f"Objects of equal height seen through every mirror ({where}): their upper edges should "
              "lie at one height.", ""] + [f"    {line}" for line in check.report(list(cal.names))]
    lines += ["", "![side view](fig6_side_view.png)", ""]
    with atomic_write(out / "report.md", "w") as handle:
        handle.write("\n".join(lines))
    written["report"] = out / "report.md"
    written["fig6_spread_mm"] = 1000.0 * check.spread
    return written
