"""Time `omnitof slam` on the real logs with two builds, alternating, and compare their outputs.

A speed change is measured against the code before it in the same session: timings on this
shared machine drift by a fifth from one minute to the next, so the two builds take turns and
the table reports medians and the median of the per-pair ratios. Each build is a `python/`
folder holding the package and its compiled core (for the code before a change: `git worktree
add /tmp/base <commit>`, build its core, copy the `.so` into `/tmp/base/python/omnitof/`).

    OMNITOF_DATA=../shared/data python benchmarks/slam_speed.py --baseline /tmp/base/python \
        --logs intel fr079 --runs 5

Prints one row per log and build: the SLAM time that `omnitof slam` reports (the run alone,
without reading the log and writing the results), the process's wall and CPU time (medians), its
largest peak memory, and whether both builds wrote the same trajectory and map byte for byte.
"""

from __future__ import annotations

import argparse
import filecmp
import os
import re
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

HERE_PYTHON = Path(__file__).resolve().parent.parent / "python"
SLAM_TIME = re.compile(r"time ([0-9.]+) s")


def run_once(python_dir: Path, log: Path, out: Path, seed: int, particles: int, extra: list[str]) -> dict[str, float]:
    """One `omnitof slam` process with `python_dir` first on its path."""
    env = dict(os.environ, PYTHONPATH=str(python_dir))
    cmd = [sys.executable, "-c", "from omnitof.cli import main; main()", "slam", str(log),
           "--particles", str(particles), "--seed", str(seed), "--out", str(out), *extra]
    with tempfile.TemporaryFile("w+") as stdout, tempfile.TemporaryFile("w+") as stderr:
        start = time.perf_counter()
        child = subprocess.Popen(cmd, env=env, stdout=stdout, stderr=stderr, text=True)
        # wait4 gives this child's own CPU time and peak memory.
        _, status, usage = os.wait4(child.pid, 0)
        wall = time.perf_counter() - start
        child.returncode = os.waitstatus_to_exitcode(status)
        stdout.seek(0)
        stderr.seek(0)
        out_text, err_text = stdout.read(), stderr.read()
    if child.returncode != 0:
        raise SystemExit(f"{' '.join(cmd)} failed:\n{err_text}")
    match = SLAM_TIME.search(out_text)
    if match is None:
        raise SystemExit(f"no SLAM time in the output of {' '.join(cmd)}:\n{out_text}")
    return {
        "slam": float(match.group(1)),
        "wall": wall,
        "cpu": usage.ru_utime + usage.ru_stime,
        "peak_mib": usage.ru_maxrss / 1024.0,  # KiB on Linux
    }


def same_outputs(a: Path, b: Path) -> bool:
    return all(filecmp.cmp(a / name, b / name, shallow=False) for name in ("trajectory.tum", "map.pgm"))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--baseline", type=Path, required=True, help="python/ folder of the build to compare with")
    parser.add_argument("--current", type=Path, default=HERE_PYTHON, help="python/ folder of the build measured (this checkout's)")
    parser.add_argument("--logs", nargs="+", default=["intel", "fr079"], help="log names in $OMNITOF_DATA (NAME.clf.bz2)")
    parser.add_argument("--runs", type=int, default=5, help="runs per build and log, alternating")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--particles", type=int, default=30)
    parser.add_argument("--set", nargs="*", default=[], help="configuration overrides passed to both builds")
    args = parser.parse_args()
    data = os.environ.get("OMNITOF_DATA")
    if not data:
        raise SystemExit("set OMNITOF_DATA to the folder with the CARMEN logs (../shared/data)")
    extra = ["--quiet", *[a for kv in args.set for a in ("--set", kv)]]
    builds = {"baseline": args.baseline.resolve(), "current": args.current.resolve()}
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for name in args.logs:
            log = Path(data) / f"{name}.clf.bz2"
            if not log.is_file():
                raise SystemExit(f"{log}: no such log")
            times: dict[str, list[dict[str, float]]] = {b: [] for b in builds}
            for k in range(args.runs):
                for build, python_dir in builds.items():
                    out = Path(tmp) / f"{name}_{build}"
                    times[build].append(run_once(python_dir, log, out, args.seed, args.particles, extra))
                    t = times[build][-1]
                    print(f"{time.strftime('%H:%M:%S')} load {os.getloadavg()[0]:.2f} {name} run {k} {build}: "
                          f"SLAM {t['slam']:.1f} s, wall {t['wall']:.1f} s, CPU {t['cpu']:.1f} s", flush=True)
            identical = same_outputs(Path(tmp) / f"{name}_baseline", Path(tmp) / f"{name}_current")
            rows.append((name, times, identical))

    def med(runs: list[dict[str, float]], key: str) -> float:
        return statistics.median(r[key] for r in runs)

    print("\n| log | build | SLAM s (median; runs) | wall s | CPU s | peak MiB | current / baseline (median of pairs) | same outputs |")
    print("|---|---|---|---|---|---|---|---|")
    for name, times, identical in rows:
        ratio = statistics.median(c["slam"] / b["slam"] for b, c in zip(times["baseline"], times["current"]))
        for build in builds:
            runs = ", ".join(f"{r['slam']:.1f}" for r in times[build])
            last = f"{ratio:.2f}" if build == "current" else ""
            same = ("yes" if identical else "**no**") if build == "current" else ""
            print(f"| {name} | {build} | {med(times[build], 'slam'):.1f} ({runs}) | {med(times[build], 'wall'):.1f} | "
                  f"{med(times[build], 'cpu'):.1f} | {max(r['peak_mib'] for r in times[build]):.0f} | {last} | {same} |")


if __name__ == "__main__":
    main()
