"""SLAM on the real CARMEN logs (Intel, Freiburg 079): time, throughput, memory and accuracy.

    python benchmarks/slam_logs.py [--data DIR] [--logs intel fr079] [--particles 30 200]
                                   [--seeds 0 1 2] [--preset laser180] [--scan-delay fr079=auto]
                                   [--set backend.enabled=false ...]

Each run is a fresh child process so that its peak memory (ru_maxrss) is its own. Prints one
Markdown row per run and, per log and particle count, the median time and the mean ± std of the
relations metric over the seeds. The data folder defaults to $OMNITOF_DATA. `--scan-delay LOG=S`
re-times a log's odometry (seconds, or `auto`: estimated from the log, see omnitof.slam.timing)
before the filter runs; the estimate is not part of the timed SLAM run. `--set SECTION.FIELD=VALUE`
overrides one configuration field over the preset (VALUE read as YAML), e.g. to compare a preset
with and without its back end.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import statistics
import subprocess
import sys
import time
from pathlib import Path


def overrides_of(items: list[str]) -> dict:
    """{"section": {"field": value}} from SECTION.FIELD=VALUE items (values parsed as YAML)."""
    import yaml

    out: dict = {}
    for item in items:
        key, value = item.split("=", 1)
        section, name = key.split(".", 1)
        out.setdefault(section, {})[name] = yaml.safe_load(value)
    return out


def single_run(log: Path, relations: Path, preset: str, particles: int, seed: int, delay: str,
               settings: list[str]) -> dict:
    from omnitof.slam.config import load_config
    from omnitof.eval.relations import evaluate_relations, read_relations
    from omnitof.io.carmen import read_carmen
    from omnitof.slam import run_slam
    from omnitof.slam.timing import estimate_scan_delay, retime_odometry

    scans = read_carmen(log).scans
    seconds_delay = estimate_scan_delay(scans).delay if delay == "auto" else float(delay)
    scans = retime_odometry(scans, seconds_delay)
    overrides = overrides_of(settings)
    overrides.setdefault("filter", {}).update({"particles": particles, "seed": seed})
    cfg = load_config(preset=preset, overrides=overrides)
    start = time.perf_counter()
    result = run_slam(scans, cfg)
    seconds = time.perf_counter() - start
    rel = evaluate_relations(result.trajectory, read_relations(relations))
    odo = evaluate_relations(result.odometry, read_relations(relations))
    return {
        "seconds": seconds,
        "integrated": result.stats["integrated"],
        "resamplings": result.stats["resamplings"],
        "particle_scans_per_s": particles * result.stats["integrated"] / seconds,
        "peak_mib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
        "trans_mean": rel.trans_mean,
        "trans_std": rel.trans_std,
        "rot_mean": rel.rot_mean,
        "rot_std": rel.rot_std,
        "matched": rel.n_matched,
        "odometry_trans_mean": odo.trans_mean,
        "scan_delay": seconds_delay,
        "closures": (result.stats.get("backend") or {}).get("closures_accepted", 0),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=os.environ.get("OMNITOF_DATA"))
    parser.add_argument("--logs", nargs="+", default=["intel", "fr079"])
    parser.add_argument("--particles", nargs="+", type=int, default=[30, 200])
    parser.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2])
    parser.add_argument("--preset", default="laser180")
    parser.add_argument("--scan-delay", nargs="*", default=[], metavar="LOG=SECONDS|auto",
                        help="re-time a log's odometry by its scan delay")
    parser.add_argument("--set", nargs="*", default=[], metavar="SECTION.FIELD=VALUE",
                        help="override configuration fields over the preset")
    parser.add_argument("--single", nargs=4, metavar=("LOG", "PARTICLES", "SEED", "DELAY"), help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.data is None:
        sys.exit("set OMNITOF_DATA or pass --data: the folder holding intel.clf.bz2 and fr079.clf.bz2")
    if args.single:
        name, particles, seed, delay = args.single
        out = single_run(args.data / f"{name}.clf.bz2", args.data / f"{name}.relations",
                         args.preset, int(particles), int(seed), delay, args.set)
        print(json.dumps(out))
        return
    delays = dict(item.split("=", 1) for item in args.scan_delay)
    print(f"preset {args.preset} {' '.join(args.set)}; scan delays {delays or 'none'}; {os.cpu_count()} cores; "
          f"{time.strftime('%Y-%m-%d %H:%M')}")
    print("| log | particles | seed | wall s | integrated | resamplings | particle-scans/s | peak MiB "
          "| trans err m (mean ± std) | rot err deg (mean ± std) |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    summary = []
    for name in args.logs:
        for particles in args.particles:
            runs = []
            for seed in args.seeds:
                cmd = [sys.executable, __file__, "--data", str(args.data), "--preset", args.preset,
                       "--single", name, str(particles), str(seed), delays.get(name, "0"), "--set", *args.set]
                r = json.loads(subprocess.run(cmd, check=True, capture_output=True, text=True).stdout)
                runs.append(r)
                print(f"| {name} | {particles} | {seed} | {r['seconds']:.1f} | {r['integrated']} | "
                      f"{r['resamplings']} | {r['particle_scans_per_s']:.0f} | {r['peak_mib']:.0f} | "
                      f"{r['trans_mean']:.4f} ± {r['trans_std']:.3f} | {r['rot_mean']:.2f} ± {r['rot_std']:.2f} |",
                      flush=True)
            summary.append((name, particles, runs))
    print()
    print("| log | particles | scan delay s | median wall s | max peak MiB "
          "| trans err m, mean over seeds (min–max) | rot err deg, mean over seeds | raw odometry trans err m |")
    print("|---|---|---|---|---|---|---|---|")
    for name, particles, runs in summary:
        t = [r["trans_mean"] for r in runs]
        rot = [r["rot_mean"] for r in runs]
        print(f"| {name} | {particles} | {runs[0]['scan_delay']:.3f} | "
              f"{statistics.median(r['seconds'] for r in runs):.1f} | "
              f"{max(r['peak_mib'] for r in runs):.0f} | {statistics.mean(t):.4f} ({min(t):.4f}–{max(t):.4f}) | "
              f"{statistics.mean(rot):.2f} | {runs[0]['odometry_trans_mean']:.3f} |")


if __name__ == "__main__":
    main()
