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
including the worker's own baseline (Python, numpy, matplotlib, GTSAM, Dask: a run of 400 scans
peaks at about 300 MiB), not that of an earlier run on the same worker.
"""

from __future__ import annotations

import glob
import os
import re
import resource
import socket
import tempfile
import time
import warnings
from collections.abc import Callable
from pathlib import Path
from typing import Any

from omnitof.bench.experiment import RunSpec
from omnitof.bench.inputs import InputFile
from omnitof.errors import OmnitofError


def run_one(run: RunSpec, log: InputFile, relations: InputFile | None = None,
            calibration: InputFile | None = None, world: Any = None, label: str | None = None) -> dict[str, Any]:
    """Run `run` on this worker; returns {"files": {name: bytes}, ...} or {"error": line, ...}.
    `label`: the input's path as the experiment names it, recorded in summary.yaml as
    `omnitof slam` would record it (not the scratch copy's) and put in messages for the copy."""
    from omnitof.slam_run import SlamRequest, slam_config, slam_to_folder

    started = time.time()
    peak_rule = _reset_peak()
    clock = time.perf_counter()
    notes: list[str] = []
    base = {"worker": _worker_address(), "host": socket.gethostname(), "pid": os.getpid(), "started": started}
    sweep_orphaned_scratch()
    with tempfile.TemporaryDirectory(prefix=f"{scratch_prefix()}{os.getpid()}-") as tmp, \
            warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")  # the reader's warnings about the data go to the record
        inputs = Path(tmp) / "in"
        # Each file in a folder of its own: a log and its relations may share a name.
        copies = {"log": (log, label), "relations": (relations, run.input.relations),
                  "calibration": (calibration, run.input.calibration)}
        paths = {k: f.materialise(_mkdir(inputs / k)) if f is not None else None for k, (f, _) in copies.items()}
        # Name the files as the experiment does, not as this worker's scratch copies.
        renames = [(str(paths[k]), own) for k, (f, own) in copies.items() if f is not None and f.shipped and own]

        def own_names(text: str) -> str:
            for scratch, own in renames:
                text = text.replace(scratch, own)
            return " ".join(text.split())

        try:
            request = SlamRequest(
                log=paths["log"], relations=paths["relations"], max_scans=run.input.max_scans,
                skip_bad_lines=run.input.skip_bad_lines, scan_delay=run.scan_delay, calibration=paths["calibration"],
                height=run.input.height, band=run.input.band, label=label,
            )
            cfg = slam_config(preset=run.preset, settings=run.settings, seed=run.seed, threads=run.threads)
            out = Path(tmp) / "out"
            done = slam_to_folder(request, cfg, out, echo=notes.append)
            metrics = _extra_metrics(run, done, request, world)
        except OmnitofError as err:
            return {**base, "error": own_names(str(err)) or type(err).__name__, "notes": notes,
                    "warnings": _distinct(caught, own_names),
                    "finished": time.time(), "seconds": time.perf_counter() - clock}
        files = {p.name: p.read_bytes() for p in sorted(out.iterdir()) if p.is_file()}
        found = _distinct(caught, own_names)
    return {**base, "files": files, "metrics": metrics, "notes": notes, "warnings": found, "finished": time.time(),
            "seconds": time.perf_counter() - clock, "peak_rss_mib": _peak_mib(), "peak_rss_rule": peak_rule}


SCRATCH_PREFIX = "omnitof-run-"


def scratch_prefix() -> str:
    """The start of this machine's scratch folder names: the host as well as the process id,
    since a temporary folder shared between machines or containers (whose process ids are not
    ours to test) must not have its other owners' folders swept."""
    return f"{SCRATCH_PREFIX}{socket.gethostname()}-"


def sweep_orphaned_scratch(folder: Path | None = None) -> list[Path]:
    """Remove the scratch folders (inputs copied for a run, outputs before they are sent) of runs
    whose worker process is gone: a worker killed mid-run (a bench stopped, a node lost) cannot
    clean up after itself, and each such folder holds a copy of the run's input, which for a
    ROS bag can be gigabytes. Only this host's folders (`scratch_prefix`) whose process is gone
    are removed; those of live processes, of other hosts, and any not named so are left alone.
    Returns the folders removed."""
    import shutil

    prefix = scratch_prefix()
    removed = []
    for path in Path(folder or tempfile.gettempdir()).glob(f"{glob.escape(prefix)}*-*"):
        pid = path.name[len(prefix):].split("-", 1)[0]
        if not pid.isdigit() or not path.is_dir() or _process_alive(int(pid)):
            continue
        shutil.rmtree(path, ignore_errors=True)
        removed.append(path)
    return removed


def _process_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # another user's process: alive, and not ours to sweep
        return True
    return True


def omnitof_code() -> dict[str, str]:
    """The omnitof this worker runs: its version, where it is, and a digest of its Python
    sources (the client checks that they are its own: two checkouts of one version differ, and
    a worker started without the client's PYTHONPATH would run another one). The compiled core
    is left out: builds of the same source on two machines differ in their bytes.

    It also imports what a run needs (matplotlib, GTSAM, ...: about a second), so that the first
    run's time on each worker is its own, comparable with the others'."""
    import hashlib

    import omnitof
    import omnitof.results  # noqa: F401
    import omnitof.slam_run  # noqa: F401
    import omnitof.slam.backend  # noqa: F401

    root = Path(omnitof.__file__).parent
    digest = hashlib.sha256()
    for path in sorted(root.rglob("*.py")):
        digest.update(path.relative_to(root).as_posix().encode() + b"\0" + path.read_bytes())
    return {"version": omnitof.__version__, "path": str(root), "sources_sha256": digest.hexdigest()}


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
    path.mkdir(parents=True)
    return path


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


def _distinct(caught: list[warnings.WarningMessage], text: Callable[[str], str]) -> list[str]:
    """The warnings' texts (`text` of each message), each once: a check that runs twice in a run
    (the limits before and inside run_slam) warns twice, where the command line, which shows a
    warning once per place, prints it once."""
    return list(dict.fromkeys(text(str(w.message)) for w in caught))
