"""`omnitof bench`: every run of an experiment as a task on Dask (dask.distributed).

The client (this process) plans the runs, skips those already complete in DIR, ships the
inputs (omnitof.bench.inputs), submits one task per run (omnitof.bench.task.run_one), and puts
each run's folder in place as its result arrives (omnitof.bench.folders), so that an
interrupted experiment loses only the runs in flight. Then it writes the table and the figures
(omnitof.bench.table).

Where the runs go: by default a local cluster of `workers` worker processes (one thread each:
a run is one thread of Python and Rust, `threads` of the experiment), or a running cluster's
scheduler at `scheduler` (docs/guide/bench.md: two machines).

Failures: a mistake in an input comes back as the run's one-line error (recorded, and the other
runs go on). Any other exception is retried once (`retries=1`), then recorded the same way. A
worker that dies (killed, out of memory) loses only its run in flight, which the scheduler gives
to another worker; a run that has taken `distributed.scheduler.allowed-failures` + 1 workers
down with it (4 by default) is recorded as failed. A worker that dies with the last copy of a
shipped input (a cluster of one worker, or the others gone) makes the scheduler cancel the
runs that need it: their input is shipped again and they are submitted again, up to `RESUBMITS`
times each.
"""

from __future__ import annotations

import os
import shlex
import time
import uuid
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from omnitof.bench import folders
from omnitof.bench.experiment import Experiment, InputSpec, RunSpec, plan_runs
from omnitof.bench.inputs import InputFile, input_file, prepare_world
from omnitof.bench.task import run_one
from omnitof.errors import OmnitofError, dump_yaml
from omnitof.io.atomic import atomic_write

# How long to wait for a running cluster to have a worker before giving up.
WORKER_WAIT_S = 60.0
# How often a run cancelled by the loss of its shipped input is submitted again.
RESUBMITS = 3


@dataclass
class BenchOutcome:
    """What `run_experiment` did: run ids by outcome (skipped: complete before it started)."""

    planned: int
    skipped: int
    done: list[str] = field(default_factory=list)
    failed: list[str] = field(default_factory=list)


def run_experiment(exp: Experiment, out: str | Path, *, workers: int | None = None, scheduler: str | None = None,
                   progress: bool = True, echo: Callable[[str], None] = print) -> BenchOutcome:
    """Run every run of `exp` that DIR (`out`) does not hold complete; see the module docstring."""
    out = Path(out)
    runs = plan_runs(exp)
    todo = folders.prepare(out, exp.text, runs)
    outcome = BenchOutcome(planned=len(runs), skipped=len(runs) - len(todo))
    echo(f"{exp.name}: {len(runs)} runs; {outcome.skipped} complete already, {len(todo)} to run")
    if todo:
        with _client(workers, scheduler, echo) as client:
            _check_workers(client)
            _run_all(client, exp, out, todo, outcome, progress)
    return outcome


@contextmanager
def _client(workers: int | None, scheduler: str | None, echo: Callable[[str], None]) -> Iterator[Any]:
    # Dask is imported here, not at the top: `omnitof slam` and the others never pay for it.
    from dask.distributed import Client, LocalCluster

    if scheduler is not None:
        try:
            client = Client(scheduler, timeout="20s")
        except (OSError, TimeoutError) as err:
            raise OmnitofError(f"--scheduler {scheduler}: cannot connect: {err}") from None
        with client:
            echo(f"scheduler {scheduler}; {_dashboard(client)}")
            yield client
        return
    n = workers or os.cpu_count() or 1
    with LocalCluster(n_workers=n, threads_per_worker=1, processes=True) as cluster, Client(cluster) as client:
        echo(f"local cluster: {n} worker processes, 1 thread each; {_dashboard(client)}")
        yield client


def _dashboard(client: Any) -> str:
    from importlib.util import find_spec

    if find_spec("bokeh") is not None:
        return f"dashboard {client.dashboard_link}"
    # Without bokeh the address answers with an install hint only.
    return f"dashboard {client.dashboard_link} (needs bokeh >= 3.1: pip install 'omnitof[dashboard]')"


def _check_workers(client: Any) -> None:
    """Every worker runs this client's omnitof: a run made with other code is not this run."""
    from omnitof.bench.task import omnitof_code

    try:
        client.wait_for_workers(1, timeout=WORKER_WAIT_S)
    except TimeoutError:
        raise OmnitofError(f"no worker joined the scheduler within {WORKER_WAIT_S:.0f} s") from None
    try:
        found = client.run(omnitof_code)
    except Exception as err:  # a worker without omnitof cannot even unpickle the function
        raise OmnitofError(f"the workers cannot run omnitof (install it on every worker): "
                           f"{type(err).__name__}: {err}") from None
    mine = omnitof_code()
    for worker, theirs in found.items():
        if theirs["sources_sha256"] != mine["sources_sha256"]:
            raise OmnitofError(
                f"worker {worker} runs other omnitof code (omnitof {theirs['version']} in {theirs['path']}) than this "
                f"client (omnitof {mine['version']} in {mine['path']}): install the same omnitof on every worker")


def _run_all(client: Any, exp: Experiment, out: Path, todo: list[RunSpec], outcome: BenchOutcome,
             progress: bool) -> None:
    from dask.distributed import as_completed

    from omnitof.io.terminal import progress_bar

    token = uuid.uuid4().hex[:8]  # keys of this session, never those of another client
    shipped, preparing = _ship_inputs(client, exp, out, {r.input.name for r in todo}, token)
    futures: dict[Any, Any] = {future: ("prepare", name) for name, future in preparing.items()}
    pending = as_completed(list(futures))

    def submit(run: RunSpec, attempt: int) -> None:
        log, relations, calibration, world, label = _payload(run, shipped, out)
        suffix = f"-{attempt}" if attempt else ""
        future = client.submit(run_one, run, log, relations, calibration, world, label,
                               key=f"run-{run.id}-{token}{suffix}", retries=1, pure=False)
        futures[future] = ("run", run, label, time.time(), attempt, shipped[run.input.name])
        pending.add(future)

    for run in todo:
        submit(run, 0)
    bar = progress_bar(len(todo), enabled=progress, desc="runs", unit="run")
    warned: set[str] = set()
    with bar:
        for name in preparing:
            bar.write(f"simulating world input {name} on a worker; its runs follow")
        for future in pending:
            what = futures.pop(future)
            if what[0] == "prepare":
                _save_prepared(out, what[1], future)
                if future.status == "finished":
                    bar.write(f"world input {what[1]} made: {out / folders.INPUTS / what[1]}.bag")
                continue
            _, run, label, submitted, attempt, used = what
            if future.status == "cancelled" and attempt < RESUBMITS:
                # Its shipped input died with the last worker that held it (nothing else cancels
                # a run here): ship the input again, once per loss, and run it again.
                if shipped[run.input.name] is used:
                    _reship(client, exp, out, run.input.name, token, attempt + 1, shipped, futures, pending)
                bar.write(f"run {run.id}: its input was lost with a worker; shipped again, submitted again")
                future.release()
                submit(run, attempt + 1)
                continue
            ok, line, found = collect_run(out, run, label, future, submitted)
            (outcome.done if ok else outcome.failed).append(run.id)
            for message in found:
                if message not in warned:  # once, not once per run of the same input
                    warned.add(message)
                    bar.write(f"warning: {message}")
            if not ok:
                bar.write(f"run {run.id} failed: {line}")
            # No redraw of its own: into a log file every redraw would be a line.
            bar.set_postfix_str(f"{len(outcome.failed)} failed" if outcome.failed else "", refresh=False)
            bar.update(1)
            future.release()


def _ship_inputs(client: Any, exp: Experiment, out: Path, names: set[str],
                 token: str) -> tuple[dict[str, tuple], dict[str, Any]]:
    """Per input: its recording, (its relations, its calibration) and its World (for a world's
    metrics), as futures of what is on the cluster (shipped files scattered to every worker
    once) or, for a world not made yet, the future of the task that makes it; and those tasks
    by input name."""
    shipped: dict[str, tuple] = {}
    preparing: dict[str, Any] = {}
    for item in exp.inputs:
        if item.name not in names:
            continue
        world = None
        if item.world is not None:
            from omnitof.sim.worlds import load_world

            world = load_world(item.world)  # refused here, on the client, if it is not a world
            ready = _prepared(out, item)
            if ready is not None:
                log: Any = client.scatter(ready, broadcast=True, hash=False)
            else:
                log = client.submit(prepare_world, item, world, key=f"prepare-{item.name}-{token}", pure=False)
                preparing[item.name] = log
            world = client.scatter(world, broadcast=True, hash=False)
        else:
            log = _scatter(client, input_file(item.log, item.transfer))
        extras = tuple(_scatter(client, input_file(getattr(item, k), "ship")) if getattr(item, k) else None
                       for k in ("relations", "calibration"))
        shipped[item.name] = (log, extras, world)
    return shipped, preparing


def _reship(client: Any, exp: Experiment, out: Path, name: str, token: str, attempt: int,
            shipped: dict[str, tuple], futures: dict[Any, Any], pending: Any) -> None:
    """Ship input `name` again (into `shipped`), once a worker is there to take it; a world not
    made yet is made again (its task joins `futures` and `pending`)."""
    try:
        client.wait_for_workers(1, timeout=WORKER_WAIT_S)
    except TimeoutError:
        raise OmnitofError(f"no worker left to run on, and none joined within {WORKER_WAIT_S:.0f} s") from None
    again, preparing = _ship_inputs(client, exp, out, {name}, f"{token}-{attempt}")
    shipped.update(again)
    for made_name, future in preparing.items():
        futures[future] = ("prepare", made_name)
        pending.add(future)


def _scatter(client: Any, f: InputFile) -> Any:
    # A shared path is a few bytes: it rides with each task instead.
    return client.scatter(f, broadcast=True, hash=False) if f.shipped else f


def _payload(run: RunSpec, shipped: dict[str, tuple], out: Path) -> tuple:
    """The task's arguments; `label`: the input's path as the experiment names it (a world's:
    its bag in DIR/inputs), for summary.yaml and the run's `omnitof slam` command."""
    log, (relations, calibration), world = shipped[run.input.name]
    label = run.input.log if run.input.log is not None else str(out / folders.INPUTS / f"{run.input.name}.bag")
    return log, relations, calibration, world, label


def _prepared_paths(out: Path, item: InputSpec) -> tuple[Path, Path]:
    base = out / folders.INPUTS / item.name
    return base.with_suffix(".bag"), base.with_suffix(".yaml")


def _prepared(out: Path, item: InputSpec) -> InputFile | None:
    """The world's bag made by an earlier session of this experiment, if made from the same
    input spec (its record says)."""
    bag, record = _prepared_paths(out, item)
    if not (bag.is_file() and record.is_file()):
        return None
    made = yaml.safe_load(record.read_text(encoding="utf-8")) or {}
    if made.get("input_spec") != item.model_dump(mode="json"):
        return None
    return InputFile(bag.name, data=bag.read_bytes(), made=made)


def _save_prepared(out: Path, name: str, future: Any) -> None:
    if future.status != "finished":
        return  # the runs that needed it fail with its error
    made: InputFile = future.result()
    bag = out / folders.INPUTS / made.name
    bag.parent.mkdir(parents=True, exist_ok=True)
    with atomic_write(bag, "wb") as f:
        f.write(made.data or b"")
    # The record last: a bag without it is not taken for made (`_prepared`).
    with atomic_write(bag.with_suffix(".yaml")) as f:
        dump_yaml(made.made or {}, f, sort_keys=False, allow_unicode=True)


def collect_run(out: Path, run: RunSpec, label: str, future: Any,
                submitted: float) -> tuple[bool, str, list[str]]:
    """Put the run's folder in place (or its failure) once its task's `future` is done;
    returns (ok, its one-line error, the warnings the run gave about its input). `label`: the input's path for the run's record (`_payload`);
    `submitted`: when the task was submitted (time.time()), for the record's timing."""
    record: dict[str, Any] = {"status": "ok", "cell": run.cell(), "metrics_collected": list(run.metrics),
                              "command": shlex.join(run.command(label, str(folders.run_dir(out, run.id))))}
    if future.status == "finished":
        result = future.result()
        timing = {"submitted": submitted, "started": result["started"], "finished": result["finished"],
                  "collected": None}
        record.update({k: result[k] for k in ("worker", "host", "pid") if k in result})
        record["seconds"] = round(result["seconds"], 3)
        record["notes"] = result.get("notes", [])
        record["warnings"] = result.get("warnings", [])
        if "error" in result:
            timing["collected"] = time.time()
            record.update({"status": "failed", "error": result["error"], "timing": timing})
            folders.write_failure(out, run.id, record)
            return False, result["error"], record["warnings"]
        record.update({"peak_rss_mib": result["peak_rss_mib"], "peak_rss_rule": result["peak_rss_rule"],
                       "metrics": result["metrics"], "timing": timing})
        timing["collected"] = time.time()  # the folder is written next; nothing slow follows
        folders.write_run(out, run.id, result["files"], record)
        return True, "", record["warnings"]
    err = future.exception()
    line = _exception_line(err)
    record.update({"status": "failed", "error": line, "timing": {"submitted": submitted, "collected": time.time()}})
    try:
        import traceback

        record["traceback"] = "".join(traceback.format_tb(future.traceback()))
    except Exception:  # a traceback that does not travel is not worth failing the record over
        pass
    folders.write_failure(out, run.id, record)
    return False, line, []


def _exception_line(err: BaseException | None) -> str:
    if err is None:
        return "cancelled"
    name = type(err).__name__
    if name == "KilledWorker":
        return "KilledWorker: every worker that took the run died (killed, or out of memory?)"
    text = " ".join(str(err).split())
    return f"{name}: {text}" if text else name
