"""One run of an experiment, as a Dask task on a worker: the input files put in a scratch
folder, then `omnitof.slam_run.slam_to_folder` — the code of `omnitof slam`, so the trajectory
bytes are the same whichever way the run was started — then the metrics `omnitof slam` does not
write (the raw odometry's relations; a world's floor plan and Table I), and the results folder's
files returned as bytes for the client to put in place.

A mistake in the input (an OmnitofError: a malformed log line, a relations file that does not
match) is the run's result, not a crash: it comes back as the run's one-line error, and Dask does
not retry it (it would fail the same way). Any other exception is raised, and Dask retries it.

Time and peak memory are the run's own: the worker process's resident-set high-water mark is
reset at the start of the run (Linux /proc/self/clear_refs, "5"), so it is the run's peak
including the worker's own baseline (Python, numpy, Dask: about 150 MiB), not that of an earlier
run on the same worker.
"""

from __future__ import annotations

import os
import re
import resource
import socket
import tempfile
import time
from pathlib import Path
from typing import Any

from omnitof.bench.experiment import RunSpec
from omnitof.bench.inputs import InputFile
from omnitof.errors import OmnitofError


def run_one(run: RunSpec, log: InputFile, relations: InputFile | None = None,
            calibration: InputFile | None = None, world: Any = None, label: str | None = None) -> dict[str, Any]:
    """Run `run` on this worker; returns {"files": {name: bytes}, ...} or {"error": line, ...}.
    `label`: the input's path as the experiment names it, recorded in summary.yaml as
    `omnitof slam` would record it (not the scratch copy's)."""
    from omnitof.slam_run import SlamRequest, slam_config, slam_to_folder

    started = time.time()
    peak_rule = _reset_peak()
    clock = time.perf_counter()
    notes: list[str] = []
    base = {"worker": _worker_address(), "host": socket.gethostname(), "pid": os.getpid(), "started": started}
    with tempfile.TemporaryDirectory(prefix="omnitof-run-") as tmp:
        folder = Path(tmp)
        try:
            inputs = folder / "in"
            inputs.mkdir()
            # Each file in a folder of its own: a log and its relations may share a name.
            log_path = log.materialise(_mkdir(inputs / "log")) if log.shipped else log.materialise(inputs)
            request = SlamRequest(
                log=log_path, relations=relations.materialise(_mkdir(inputs / "relations")) if relations else None,
                max_scans=run.input.max_scans, skip_bad_lines=run.input.skip_bad_lines, scan_delay=run.scan_delay,
                calibration=calibration.materialise(_mkdir(inputs / "calibration")) if calibration else None,
                height=run.input.height, band=run.input.band, label=label,
            )
            cfg = slam_config(preset=run.preset, settings=run.settings, seed=run.seed, threads=run.threads)
            out = folder / "out"
            done = slam_to_folder(request, cfg, out, echo=notes.append)
            metrics = _extra_metrics(run, done, request, world)
        except OmnitofError as err:
            # Name the files as the experiment does, not as this worker's scratch copies.
            line = _one_line(err)
            for scratch, own in ((inputs / "log" / log.name, label),
                                 (inputs / "relations" / (relations.name if relations else ""), run.input.relations),
                                 (inputs / "calibration" / (calibration.name if calibration else ""),
                                  run.input.calibration)):
                if own:
                    line = line.replace(str(scratch), own)
            return {**base, "error": line, "notes": notes, "finished": time.time(),
                    "seconds": time.perf_counter() - clock}
        files = {p.name: p.read_bytes() for p in sorted(out.iterdir()) if p.is_file()}
    return {**base, "files": files, "metrics": metrics, "notes": notes, "finished": time.time(),
            "seconds": time.perf_counter() - clock, "peak_rss_mib": _peak_mib(), "peak_rss_rule": peak_rule}


def omnitof_version() -> str:
    """The omnitof this worker runs (the client checks that it is its own)."""
    from omnitof import __version__

    return __version__


def _extra_metrics(run: RunSpec, done: Any, request: Any, world: Any) -> dict[str, Any]:
    metrics: dict[str, Any] = {}
    if "relations" in run.metrics and request.relations is not None:
        from omnitof.eval.relations import evaluate_relations, read_relations

        # The raw odometry against the same relations: what SLAM had to correct.
        metrics["relations_odometry"] = evaluate_relations(done.result.odometry,
                                                           read_relations(request.relations)).to_dict()
    if world is not None and ({"floorplan", "table1"} & set(run.metrics)):
        from omnitof.demo import evaluate_run

        ev = evaluate_run(world, done.scans, done.result, None)
        if "floorplan" in run.metrics:
            metrics["floorplan"] = ev["floorplan"]
        if "table1" in run.metrics and "table1" in ev:
            metrics["table1"] = ev["table1"]
    return metrics


def _mkdir(path: Path) -> Path:
    path.mkdir()
    return path


def _one_line(err: BaseException) -> str:
    return " ".join(str(err).split()) or type(err).__name__


def _worker_address() -> str:
    try:
        from distributed import get_worker

        return get_worker().address
    except (ImportError, ValueError):  # not inside a Dask worker (a test calling run_one)
        return "local"


_STATUS = Path("/proc/self/status")


def _reset_peak() -> str:
    """Reset this process's peak resident set to its current size, where Linux allows; returns
    what the peak measured will mean."""
    try:
        with open("/proc/self/clear_refs", "w") as f:
            f.write("5")
        return "the run's peak (worker high-water mark reset at its start)"
    except OSError:
        return "the worker process's peak since it started (its high-water mark could not be reset)"


def _peak_mib() -> float:
    try:
        found = re.search(r"VmHWM:\s+(\d+) kB", _STATUS.read_text())
        if found:
            return round(int(found.group(1)) / 1024, 1)
    except OSError:
        pass
    return round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 1)
