"""The table and figures of an experiment, rebuilt from its run folders alone (DIR/runs/*:
bench.yaml and summary.yaml), so that `omnitof bench report DIR` makes them again anywhere.

    table.csv       one row per run: its cell (input, preset, grid values, seed), status, time,
                    peak memory, the run's counts and every metric collected; the error of a
                    failed run (full precision; empty where a value does not apply)
    aggregates.csv  one row per input × preset × grid point: each number's mean, min and max
                    over the seeds whose run completed
    table.md        both tables in Markdown (rounded), the failed runs with their errors, the
                    figures
    figures/INPUT__PARAMETER.png   the error against each grid parameter (omnitof.viz.bench)

The error of a run is the relations metric's mean translational error where the input has
relations, else the mean absolute trajectory error against the ground truth.
"""

from __future__ import annotations

import csv
import io
import math
import statistics
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from omnitof.bench import folders
from omnitof.errors import InputError
from omnitof.io.atomic import atomic_write
from omnitof.results import SUMMARY

# (column, metric group, what it is, Markdown format). Groups other than "run" appear when the
# experiment collects that metric and some run has a value for it.
COLUMNS: list[tuple[str, str, str, str]] = [
    ("wall_s", "run", "the run on its worker: read, SLAM, scoring, writing (s)", ".1f"),
    ("slam_s", "run", "SLAM alone (s)", ".1f"),
    ("peak_mib", "run", "peak resident memory of the worker during the run (MiB)", ".0f"),
    ("scans", "run", "scans", "d"),
    ("integrated", "run", "scans integrated by the filter", "d"),
    ("resamplings", "run", "resamplings", "d"),
    ("particle_scans_per_s", "run", "particles × integrated scans / SLAM s", ".0f"),
    ("closures", "run", "loop closures accepted by the back end", "d"),
    ("scan_delay_s", "run", "the scan delay the odometry was re-timed by (s)", ".3f"),
    ("rel_trans_m", "relations", "relations: mean translational error (m)", ".3f"),
    ("rel_trans_std_m", "relations", "relations: its standard deviation (m)", ".3f"),
    ("rel_rot_deg", "relations", "relations: mean rotational error (deg)", ".2f"),
    ("rel_rot_std_deg", "relations", "relations: its standard deviation (deg)", ".2f"),
    ("rel_matched", "relations", "relations matched", "d"),
    ("odom_rel_trans_m", "relations", "relations: mean translational error of the raw odometry (m)", ".3f"),
    ("rel_nearby_trans_m", "relations", "relations between scans less than a minute apart: mean translational error (m)", ".3f"),
    ("odom_rel_nearby_trans_m", "relations", "the same for the raw odometry (m)", ".3f"),
    ("rel_revisit_trans_m", "relations", "relations between scans a minute or more apart (revisits): mean translational error (m)", ".3f"),
    ("ate_mean_m", "trajectory", "absolute trajectory error: mean (m)", ".3f"),
    ("ate_rmse_m", "trajectory", "absolute trajectory error: RMSE (m)", ".3f"),
    ("ate_final_m", "trajectory", "absolute trajectory error at the last scan (m)", ".3f"),
    ("ate_rigid_mean_m", "trajectory", "absolute trajectory error after a rigid alignment to the truth: mean (m)", ".3f"),
    ("odom_ate_mean_m", "trajectory", "raw odometry: mean error (m)", ".3f"),
    ("odom_ate_final_m", "trajectory", "raw odometry: error at the last scan (m)", ".3f"),
    ("occupied_5cm_pct", "floorplan", "occupied cells within 5 cm of a true wall (%)", ".1f"),
    ("seen_wall_pct", "floorplan", "seen wall length that the map holds (%)", ".1f"),
    ("table1_worst_cm", "table1", "the largest Table I offset (cm; nan: a place not measured)", ".1f"),
]
ERRORS = ("rel_trans_m", "ate_mean_m")  # the error a figure draws: the first one a run has


@dataclass
class Table:
    """Rows of runs in the experiment's order, the grid's parameters, the metric columns that
    hold values, and the figures drawn (by `write_tables`)."""

    rows: list[dict[str, Any]]
    parameters: list[str]
    columns: list[str]
    figures: list[Path]


def read_table(out: str | Path) -> Table:
    """The table of the run folders in DIR (`out`); no experiment file needed."""
    rows, parameters, metrics = [], [], set()
    for folder in folders.completed_folders(Path(out)):
        record = folders.read_record(folder) or {}
        cell = record.get("cell", {})
        summary = None
        if record.get("status") == "ok" and folders.run_is_complete(folder):
            summary = folders.read_mapping(folder / SUMMARY)
        try:
            rows.append(_row(record, summary))
        except (AttributeError, KeyError, TypeError, ValueError) as err:  # a hand-edited file
            raise InputError(f"{folders.RECORD} or {SUMMARY} has a field missing or of the wrong type "
                             f"({type(err).__name__}: {err})", folder) from None
        for key in cell.get("point", {}):
            if key not in parameters:
                parameters.append(key)
        metrics.update(record.get("metrics_collected", []))
    rows.sort(key=lambda r: r["_index"])
    columns = [name for name, group, _, _ in COLUMNS
               if (group == "run" or group in metrics) and any(r.get(name) is not None for r in rows)]
    return Table(rows, parameters, columns, [])


def _row(record: dict[str, Any], summary: dict[str, Any] | None) -> dict[str, Any]:
    cell = record.get("cell", {})
    row: dict[str, Any] = {"_index": cell.get("index", 0), "input": cell.get("input"), "preset": cell.get("preset"),
                           "point": cell.get("point", {}), "seed": cell.get("seed"),
                           "status": "ok" if summary is not None else "failed",
                           "error": record.get("error", "" if summary is not None else "incomplete")}
    if summary is None:
        return row
    run = summary.get("run", {})
    metrics = record.get("metrics", {})
    row.update({"wall_s": record.get("seconds"), "slam_s": run.get("seconds"), "peak_mib": record.get("peak_rss_mib"),
                "scans": run.get("scans"), "integrated": run.get("integrated"), "resamplings": run.get("resamplings")})
    if run.get("seconds"):
        row["particle_scans_per_s"] = run["particles"] * run["integrated"] / run["seconds"]
    if "backend" in run:
        row["closures"] = run["backend"].get("closures_accepted")
    delay = (summary.get("input") or {}).get("scan_delay")
    if delay is not None:
        row["scan_delay_s"] = delay["seconds"]
    rel = summary.get("relations")
    if rel:
        row.update({"rel_trans_m": rel["trans_mean"], "rel_trans_std_m": rel["trans_std"],
                    "rel_rot_deg": rel["rot_mean"], "rel_rot_std_deg": rel["rot_std"], "rel_matched": rel["n_matched"]})
        # Summaries written before the split have neither group.
        row["rel_nearby_trans_m"] = (rel.get("nearby") or {}).get("trans_mean")
        row["rel_revisit_trans_m"] = (rel.get("revisits") or {}).get("trans_mean")
    if "relations_odometry" in metrics:
        row["odom_rel_trans_m"] = metrics["relations_odometry"]["trans_mean"]
        row["odom_rel_nearby_trans_m"] = (metrics["relations_odometry"].get("nearby") or {}).get("trans_mean")
    te = summary.get("trajectory_error")
    if te:
        row.update({"ate_mean_m": te["slam"]["mean"], "ate_rmse_m": te["slam"]["rmse"],
                    "ate_final_m": te["slam"]["final"], "odom_ate_mean_m": te["odometry"]["mean"],
                    "odom_ate_final_m": te["odometry"]["final"]})
        if te.get("slam_rigid"):  # summaries written before it have none
            row["ate_rigid_mean_m"] = te["slam_rigid"]["mean"]
    if "floorplan" in metrics:
        fp = metrics["floorplan"]
        row["occupied_5cm_pct"] = 100.0 * fp["occupied_within_5cm"]
        row["seen_wall_pct"] = 100.0 * fp["seen_wall_mapped"]
    if "table1" in metrics:
        offsets = [abs(r["offset_cm"]) if r["offset_cm"] is not None else math.nan
                   for r in metrics["table1"].values()]
        row["table1_worst_cm"] = max(offsets) if all(map(math.isfinite, offsets)) else math.nan
    return row


def aggregates(table: Table) -> list[dict[str, Any]]:
    """Per input × preset × grid point, in order: runs, completed runs, and each column's
    (mean, min, max) over the completed runs' seeds."""
    groups: dict[tuple, list[dict[str, Any]]] = {}
    for row in table.rows:
        key = (row["input"], row["preset"], tuple(row["point"].get(p) for p in table.parameters))
        groups.setdefault(key, []).append(row)
    out = []
    for (name, preset, values), rows in groups.items():
        ok = [r for r in rows if r["status"] == "ok"]
        agg: dict[str, Any] = {"input": name, "preset": preset, "point": dict(zip(table.parameters, values)),
                               "runs": len(rows), "ok": len(ok)}
        for col in table.columns:
            vals = [float(r[col]) for r in ok if r.get(col) is not None]
            agg[col] = (statistics.fmean(vals), min(vals), max(vals)) if vals else None
        out.append(agg)
    return out


def write_tables(out: str | Path, *, figures: bool = True) -> Table:
    """table.csv, aggregates.csv, table.md and the figures of DIR, from its run folders."""
    out = Path(out)
    table = read_table(out)
    agg = aggregates(table)
    if figures:
        table.figures = _figures(out, table, agg)
    head = ["input", "preset", *table.parameters]
    with atomic_write(out / "table.csv") as f:
        f.write(_csv([head + ["seed", "status", *table.columns, "error"]] +
                     [[r["input"], r["preset"], *(_cell(r["point"].get(p)) for p in table.parameters), r["seed"],
                       r["status"], *(_cell(r.get(c)) for c in table.columns), r["error"]] for r in table.rows]))
    stats = [f"{c}_{s}" for c in table.columns for s in ("mean", "min", "max")]
    with atomic_write(out / "aggregates.csv") as f:
        f.write(_csv([head + ["runs", "ok", *stats]] +
                     [[a["input"], a["preset"], *(_cell(a["point"][p]) for p in table.parameters), a["runs"], a["ok"],
                       *(_cell(a[c][i] if a[c] else None) for c in table.columns for i in range(3))] for a in agg]))
    with atomic_write(out / "table.md") as f:
        f.write(_markdown(out, table, agg))
    return table


def _cell(value: Any) -> Any:
    if value is None:
        return ""
    if isinstance(value, bool):
        return str(value).lower()
    return value


def _csv(rows: list[list[Any]]) -> str:
    buf = io.StringIO()
    csv.writer(buf, lineterminator="\n").writerows(rows)
    return buf.getvalue()


def _fmt(value: Any, spec: str) -> str:
    if value is None:
        return "–"
    if isinstance(value, float) and math.isnan(value):
        return "n/a"
    return format(int(round(value)), "d") if spec == "d" else format(value, spec)


def _markdown(out: Path, table: Table, agg: list[dict[str, Any]]) -> str:
    spec = {name: fmt for name, _, _, fmt in COLUMNS}
    what = {name: text for name, _, text, _ in COLUMNS}
    head = ["input", "preset", *table.parameters]
    lines = [f"# {out.name}: {len(table.rows)} runs", "",
             f"Rebuilt from the run folders by `omnitof bench report {out}`.", ""]
    lines += ["## Runs", "", _md_row(head + ["seed", "status", *table.columns]),
              _md_row(["---"] * (len(head) + 2 + len(table.columns)))]
    for r in table.rows:
        lines.append(_md_row([r["input"], r["preset"], *(_plain(r["point"].get(p)) for p in table.parameters),
                              str(r["seed"]), r["status"], *(_fmt(r.get(c), spec[c]) for c in table.columns)]))
    lines += ["", "## Over the seeds: mean (min–max)", "", _md_row(head + ["runs", *table.columns]),
              _md_row(["---"] * (len(head) + 1 + len(table.columns)))]
    for a in agg:
        cells = []
        for c in table.columns:
            m = a[c]
            cells.append("–" if m is None else f"{_fmt(m[0], spec[c])} ({_fmt(m[1], spec[c])}–{_fmt(m[2], spec[c])})")
        lines.append(_md_row([a["input"], a["preset"], *(_plain(a["point"][p]) for p in table.parameters),
                              f"{a['ok']}/{a['runs']}", *cells]))
    failed = [r for r in table.rows if r["status"] != "ok"]
    if failed:
        lines += ["", "## Failed runs", ""]
        lines += [f"- {r['input']} {r['preset']} {_point_text(r['point'])} seed {r['seed']}: {r['error']}" for r in failed]
    lines += ["", "## Columns", ""] + [f"- `{c}`: {what[c]}" for c in table.columns]
    if table.figures:
        lines += ["", "## Figures", ""] + [f"![{p.stem}]({p.relative_to(out).as_posix()})" for p in table.figures]
    return "\n".join(lines) + "\n"


def _md_row(cells: list[str]) -> str:
    return "| " + " | ".join(cells) + " |"


def _plain(value: Any) -> str:
    return str(_cell(value))


def _point_text(point: dict[str, Any]) -> str:
    return " ".join(f"{k}={_plain(v)}" for k, v in point.items())


def _figures(out: Path, table: Table, agg: list[dict[str, Any]]) -> list[Path]:
    """Per input and grid parameter: the error against the parameter's values."""
    from omnitof.viz.bench import plot_against_parameter

    error = next((e for e in ERRORS if e in table.columns), None)
    if error is None or not table.parameters:
        return []
    what = {name: text for name, _, text, _ in COLUMNS}
    drawn = []
    for name in dict.fromkeys(a["input"] for a in agg):
        mine = [a for a in agg if a["input"] == name]
        for param in table.parameters:
            values = list(dict.fromkeys(a["point"][param] for a in mine))
            lines: dict[str, list[Any]] = {}
            for a in mine:
                others = _point_text({k: v for k, v in a["point"].items() if k != param})
                label = f"{a['preset']} {others}".strip()
                points = lines.setdefault(label, [None] * len(values))
                points[values.index(a["point"][param])] = a[error]
            path = out / "figures" / f"{name}__{param}.png"
            path.parent.mkdir(exist_ok=True)
            plot_against_parameter(path, param, values, lines, ylabel=what[error],
                                   title=f"{name}: mean over seeds, min–max bars")
            drawn.append(path)
    return drawn

