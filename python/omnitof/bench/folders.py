"""The folder of an experiment (`omnitof bench EXPERIMENT.yaml --out DIR`):

    DIR/experiment.yaml     the experiment file as given
    DIR/inputs/NAME.bag     a simulated world's scans (a ROS 1 LaserScan bag with the ground
                            truth), and NAME.yaml: how it was made
    DIR/runs/RUN/           one run: the results folder `omnitof slam` writes, plus bench.yaml
                            (the run's cell, the equivalent `omnitof slam` command, worker, time,
                            peak memory, metrics beyond the summary's); a failed run's folder
                            holds bench.yaml alone, with its one-line error
    DIR/table.csv, table.md, aggregates.csv, figures/   the table and figures (omnitof.bench.table)

A run's folder is put in place as one unit, as `omnitof slam` puts its own
(`omnitof.io.atomic.atomic_folder`: built under a hidden name beside its place, renamed into
place whole), so that DIR/runs never holds half a run, and what a killed client left half-way is
swept when that run is written again. A run is complete when its folder is complete
(`omnitof.results.is_complete`: summary.yaml, which is written last) and carries its
bench.yaml; an experiment run again skips complete runs and runs the others, failed ones too.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from omnitof.bench.experiment import ExperimentError, RunSpec
from omnitof.errors import InputError, dump_yaml, read_yaml_mapping
from omnitof.io.atomic import atomic_folder, atomic_write, sweep_leftovers
from omnitof.io.plain import to_plain
from omnitof.results import SUMMARY, is_complete

RECORD = "bench.yaml"
RUNS = "runs"
INPUTS = "inputs"


def run_dir(out: Path, run_id: str) -> Path:
    return Path(out) / RUNS / run_id


def run_is_complete(folder: Path) -> bool:
    return is_complete(folder) and (folder / RECORD).is_file()


# The record's fields that the report and a rerun read, with their types.
_RECORD_TYPES = {"cell": dict, "status": str, "error": str, "metrics": dict, "metrics_collected": list}


def read_record(folder: Path) -> dict[str, Any] | None:
    """The run's bench.yaml, None if there is none; InputError naming it if it is damaged or
    was edited into something else (the runs write it whole, so only a hand can)."""
    path = folder / RECORD
    if not path.is_file():
        return None
    record = read_mapping(path)
    cell = record.get("cell", {})
    fields = [(key, record[key], kind) for key, kind in _RECORD_TYPES.items() if key in record]
    if isinstance(cell, dict) and "point" in cell:
        fields.append(("cell.point", cell["point"], dict))
    for key, value, kind in fields:
        if not isinstance(value, kind):
            raise InputError(f"{key}: expected {'a mapping' if kind is dict else 'a list' if kind is list else 'a text'}, "
                             f"got {repr(value)[:40]}", path)
    return record


def read_mapping(path: Path) -> dict[str, Any]:
    """A YAML file of a run (bench.yaml, summary.yaml) that must hold a mapping; InputError
    naming it otherwise."""
    return read_yaml_mapping(path, "it", "expected a YAML mapping")


def prepare(out: Path, experiment_text: str, runs: list[RunSpec]) -> list[RunSpec]:
    """Make DIR (refusing one that holds what no experiment wrote), sweep what an interrupted
    experiment left half-written, and return the runs still to do. A complete run made with
    another configuration or input than the plan's is an error: the folder belongs to another
    experiment, and mixing the two would go unnoticed."""
    out = Path(out)
    _refuse_a_foreign_folder(out)
    (out / RUNS).mkdir(parents=True, exist_ok=True)
    todo = []
    for run in runs:
        folder = run_dir(out, run.id)
        sweep_leftovers(folder)  # what a client killed while putting this run in place left
        if not run_is_complete(folder):
            todo.append(run)
            continue
        had = (read_record(folder) or {}).get("cell", {})
        want = run.cell()
        for key in ("config_sha256", "input_spec"):
            if had.get(key) != to_plain(want[key]):
                raise ExperimentError(
                    f"{folder}: made with another {'configuration' if key == 'config_sha256' else 'input'} "
                    f"than this experiment's; give another --out or remove the folder")
    with atomic_write(out / "experiment.yaml") as f:
        f.write(experiment_text)
    return todo


def _refuse_a_foreign_folder(out: Path) -> None:
    """ExperimentError where DIR holds what no experiment wrote (a user's files, an `omnitof
    slam` results folder): the table and experiment.yaml would overwrite theirs. An
    experiment's own folder (experiment.yaml, or only the runs and inputs that an experiment
    stopped before writing it left) is resumed."""
    if not out.is_dir() or (out / "experiment.yaml").is_file():
        return
    foreign = sorted(p.name for p in out.iterdir() if not p.name.startswith(".") and p.name not in (RUNS, INPUTS))
    if foreign:
        shown = ", ".join(foreign[:3]) + (", …" if len(foreign) > 3 else "")
        raise ExperimentError(
            f"{out}: holds files that no experiment wrote ({shown}); give a new or empty folder with --out, "
            "or an experiment's folder to resume it"
        )


def write_run(out: Path, run_id: str, files: dict[str, bytes], record: dict[str, Any]) -> Path:
    """Put a run's folder in place as one unit (replacing a failed attempt's): its results
    files, then bench.yaml, then summary.yaml."""
    final = run_dir(out, run_id)
    with atomic_folder(final) as folder:
        for name, data in files.items():
            if name != SUMMARY:
                (folder / name).write_bytes(data)
        _write_record(folder, record)
        if SUMMARY in files:
            (folder / SUMMARY).write_bytes(files[SUMMARY])
    return final


def write_failure(out: Path, run_id: str, record: dict[str, Any]) -> Path:
    """A failed run's folder: bench.yaml alone, with the error."""
    final = run_dir(out, run_id)
    with atomic_folder(final) as folder:
        _write_record(folder, record)
    return final


def _write_record(folder: Path, record: dict[str, Any]) -> None:
    (folder / RECORD).write_text(dump_yaml(to_plain(record), sort_keys=False, allow_unicode=True),
                                 encoding="utf-8")


def completed_folders(out: Path) -> list[Path]:
    """Every run folder of DIR that holds a record (complete or failed)."""
    base = Path(out) / RUNS
    if not base.is_dir():
        return []
    return sorted(p for p in base.iterdir() if p.is_dir() and not p.name.startswith(".")
                  and (p / RECORD).is_file())
