"""omnitof bench on Dask: how an experiment scales with worker processes, and what each task
costs beyond its own run (issue 18).

    python benchmarks/bench_scaling.py [--data DIR] [--max-scans 1000] [--repeats 3] [--overhead-runs 10]
                                       [--quiet-below LOAD]

1. Scaling: one 24-run experiment (Intel's first `--max-scans` scans, shipped as the 2.2 MB
   log; laser180-scanmatch with 10, 20 and 30 particles; seeds 0-7) run by the command itself,
   `omnitof bench EXPERIMENT --out DIR --workers N`, with 1 and with 2 worker processes, into
   fresh folders, alternating, `--repeats` times: wall time of the whole command (cluster start
   included), medians, and their ratio.
2. Per-task overhead: on a local cluster of one worker, `--overhead-runs` runs one after the
   other, each with the 2.2 MB log shipped afresh (a new scatter), the task's own run cut to 20
   scans, and its results folder collected and put in place as the command does: overhead =
   (scatter + submit + wait + collect) − the task's own time on the worker. Median and max.

The machine's load average (uptime) is printed before and after each command: this machine is
shared, and its other jobs inflate the times. `--quiet-below LOAD` waits before each command
(at most `--max-wait` seconds) until the 1-minute load average is below LOAD. Prints Markdown for BENCHMARKS.md. The data folder defaults to
$OMNITOF_DATA.
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import subprocess
import sys
import tempfile
import time
from datetime import date
from pathlib import Path

EXPERIMENT = """# written by benchmarks/bench_scaling.py
name: scaling
inputs:
  - name: intel
    log: {log}
    max_scans: {max_scans}
presets: [laser180-scanmatch]
grid: {{filter.particles: [10, 20, 30]}}
seeds: [0, 1, 2, 3, 4, 5, 6, 7]
"""


def load() -> str:
    return ", ".join(f"{v:.2f}" for v in os.getloadavg())


def wait_for_quiet(below: float | None, max_wait: float) -> None:
    deadline = time.monotonic() + max_wait
    while below is not None and os.getloadavg()[0] >= below and time.monotonic() < deadline:
        time.sleep(10)


def scaling(log: Path, max_scans: int, repeats: int, tmp: Path, quiet: float | None,
            max_wait: float) -> dict[int, list[float]]:
    exp = tmp / "scaling.yaml"
    exp.write_text(EXPERIMENT.format(log=log, max_scans=max_scans))
    times: dict[int, list[float]] = {1: [], 2: []}
    for r in range(repeats):
        for workers in (1, 2):
            out = tmp / f"w{workers}-{r}"
            wait_for_quiet(quiet, max_wait)
            before = load()
            start = time.perf_counter()
            subprocess.run([sys.executable, "-m", "omnitof.cli", "bench", str(exp), "--out", str(out),
                            "--workers", str(workers), "--quiet"], check=True, capture_output=True)
            times[workers].append(time.perf_counter() - start)
            print(f"  repeat {r}, {workers} worker(s): {times[workers][-1]:.1f} s (load before {before}; after {load()})",
                  flush=True)
    return times


def overhead(log: Path, runs: int, tmp: Path) -> list[dict[str, float]]:
    from dask.distributed import Client, LocalCluster

    from omnitof.bench import load_experiment, plan_runs
    from omnitof.bench.inputs import input_file
    from omnitof.bench.runner import collect_run
    from omnitof.bench.task import run_one

    exp = tmp / "overhead.yaml"
    exp.write_text(f"inputs: [{{name: intel, log: {log}, max_scans: 20}}]\npresets: [laser180-scanmatch]\n"
                   f"seeds: [{', '.join(str(s) for s in range(runs + 1))}]\n")
    plan = plan_runs(load_experiment(exp))
    out = tmp / "overhead"
    (out / "runs").mkdir(parents=True)
    rows = []
    with LocalCluster(n_workers=1, threads_per_worker=1, processes=True, dashboard_address=":0") as cluster, \
            Client(cluster) as client:
        for i, run in enumerate(plan):
            start = time.time()
            shipped = client.scatter(input_file(log), broadcast=True, hash=False)  # the 2.2 MB log, afresh
            scattered = time.time()
            future = client.submit(run_one, run, shipped, None, None, None, str(log), key=f"run-{run.id}", pure=False)
            future.result()
            ok, line, _ = collect_run(out, run, str(log), future, start)
            assert ok, line
            end = time.time()
            own = future.result()["seconds"]
            if i == 0:
                continue  # the worker's first task imports omnitof: not a per-task cost
            rows.append({"scatter": scattered - start, "total": end - start, "own": own, "overhead": end - start - own})
            shipped.release()
            future.release()
    return rows


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=os.environ.get("OMNITOF_DATA"))
    parser.add_argument("--max-scans", type=int, default=1000)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--overhead-runs", type=int, default=10)
    parser.add_argument("--quiet-below", type=float, help="wait for a 1-minute load average below this")
    parser.add_argument("--max-wait", type=float, default=1800.0, help="... for at most this many seconds")
    args = parser.parse_args()
    if args.data is None:
        sys.exit("set OMNITOF_DATA or pass --data: the folder holding intel.clf.bz2")
    log = (args.data / "intel.clf.bz2").resolve()
    print(f"# {date.today()} · {platform.machine()} · {os.cpu_count()} cores · python {sys.version.split()[0]}")
    print(f"# command: python benchmarks/bench_scaling.py {' '.join(sys.argv[1:])}")
    print(f"# load average before: {load()}")
    with tempfile.TemporaryDirectory(prefix="omnitof-bench-scaling-") as tmp:
        tmp = Path(tmp)
        wait_for_quiet(args.quiet_below, args.max_wait)
        print(f"# overhead: load before {load()}", flush=True)
        rows = overhead(log, args.overhead_runs, tmp)
        print(f"# overhead: load after {load()}", flush=True)
        times = scaling(log, args.max_scans, args.repeats, tmp, args.quiet_below, args.max_wait)
    print(f"# load average after: {load()}")
    one, two = statistics.median(times[1]), statistics.median(times[2])
    print("\n| workers | wall s, each repeat | median s |\n|---|---|---|")
    for w in (1, 2):
        print(f"| {w} | {' / '.join(f'{t:.1f}' for t in times[w])} | {statistics.median(times[w]):.1f} |")
    print(f"\n2 workers / 1 worker: {two / one:.2f} (median over {args.repeats} repeats; target <= 0.6)")
    over = [r["overhead"] for r in rows]
    print(f"\nPer-task overhead over {len(rows)} tasks (2.2 MB log shipped afresh each time): median "
          f"{statistics.median(over):.3f} s, max {max(over):.3f} s (target <= 1 s); of which shipping the log: median "
          f"{statistics.median(r['scatter'] for r in rows):.3f} s; the task's own run: median "
          f"{statistics.median(r['own'] for r in rows):.2f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
