"""Full runs of the simulated worlds: the whole pipeline once per world, then both filters.

For each world: `omnitof.demo.run_world` (simulate, calibrate from rendered targets, render and
extract scans, SLAM with `tof-scanmatch`, 3D map, evaluation), with the time and peak memory
of every stage; then, on the same scans, the paper's filter (`tof`, with its 200 particles and
with 30) and the scan-matching filter (`tof-scanmatch`, with its 30 and with 200) with filter
seeds 0, 1, 2: trajectory
error (mean, final), Table I offsets and the floor-plan numbers, and the wall time of each run.

    python benchmarks/worlds.py [--worlds corridor1 corridor2 office room] [--seeds 0 1 2]
        [--drive-seed 0] [--runs tof:200 tof:30 ...] [--set SECTION.FIELD=VALUE ...]
        [--out results/worlds]

`--drive-seed` picks the simulated drive (odometry and sensor noise, calibration images): a
drive not tuned on checks what was. `--runs PRESET:PARTICLES` replaces the default filters;
`--set` overrides configuration fields of every run (VALUE read as YAML), e.g. the paper's
filter with the back end: `--runs tof:200 --set backend.enabled=true`.

Prints Markdown tables for BENCHMARKS.md.
"""

from __future__ import annotations

import argparse
import math
import os
import platform
import sys
import time
from datetime import date
from pathlib import Path

import numpy as np

from omnitof.demo import DemoSettings, evaluate_run, run_world, slam_config
from omnitof.eval.table1 import format_table1, table1
from omnitof.slam import run_slam
from slam_logs import overrides_of

# (preset, particles): each filter with its own number of particles and with the other's.
RUNS = (("tof", None), ("tof", 30), ("tof-scanmatch", None), ("tof-scanmatch", 200))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--worlds", nargs="+", default=["corridor1", "corridor2", "office", "room"])
    parser.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2])
    parser.add_argument("--drive-seed", type=int, default=0)
    parser.add_argument("--runs", nargs="+", metavar="PRESET:PARTICLES",
                        default=[f"{p}:{n or 'preset'}" for p, n in RUNS])
    parser.add_argument("--set", nargs="*", default=[], metavar="SECTION.FIELD=VALUE")
    parser.add_argument("--out", type=Path, default=Path("results/worlds"))
    args = parser.parse_args(argv)
    runs = [(p, None if n == "preset" else int(n)) for p, n in (r.split(":") for r in args.runs)]
    extra = overrides_of(args.set)

    print(f"# {date.today()} · {platform.processor() or platform.machine()} · {os.cpu_count()} cores · "
          f"python {sys.version.split()[0]}")
    print(f"# command: python benchmarks/worlds.py {' '.join(argv if argv is not None else sys.argv[1:])}")
    stage_rows, filter_rows, tables = [], [], {}
    for name in args.worlds:
        run = run_world(DemoSettings(world=name, seed=args.drive_seed), args.out / name, progress=False,
                        echo=lambda _: None)
        s = run.summary
        stages = s["stages"]
        stage_rows.append(
            f"| {name} | {s['sequence']['frames']} | {s['sequence']['metres']:.0f} | "
            + " | ".join(f"{row['seconds']:.1f}" for row in stages.values())
            + f" | {s['total_seconds']:.0f} | {max(r['peak_rss_mib'] for r in stages.values()):.0f} |"
        )
        cal = s["calibration"]
        print(f"{name}: calibration {cal.get('summary', cal)}", flush=True)
        for preset, particles in runs:
            for seed in args.seeds:
                cfg = slam_config(preset, seed, particles, extra)
                start = time.perf_counter()
                result = run_slam(run.scans, cfg)
                seconds = time.perf_counter() - start
                ev = evaluate_run(run.world, run.scans, result, None)
                t, fp = ev["trajectory"], ev["floorplan"]
                offsets = [abs(r["offset_cm"]) for r in ev.get("table1", {}).values()]
                worst = "–" if not offsets else ("n/a" if not all(map(math.isfinite, offsets)) else f"{max(offsets):.1f}")
                filter_rows.append(
                    f"| {name} | {preset} | {cfg.filter.particles} | {seed} | {t['slam']['mean']:.3f} | "
                    f"{t['slam']['final']:.3f} | {t['odometry']['mean']:.3f} | {t['odometry']['final']:.3f} | "
                    f"{100 * fp['occupied_within_5cm']:.1f} | {100 * fp['seen_wall_mapped']:.1f} | {worst} | "
                    f"{seconds:.1f} |"
                )
                print(filter_rows[-1], flush=True)
                if seed == args.seeds[0] and cfg.filter.particles == 200 and run.world.landmarks:
                    tables[f"{name}, {preset}, 200 particles"] = (name, table1(result.map, run.world.landmarks))

    print(f"\n## Stages (seconds; the demo's pipeline: tof-scanmatch, 200 particles, drive seed {args.drive_seed})\n")
    names = list(run.summary["stages"])
    print("| world | frames | metres | " + " | ".join(names) + " | total | peak RSS (MiB) |")
    print("|---" * (len(names) + 5) + "|")
    print("\n".join(stage_rows))
    print("\n## Filters on the same scans\n")
    print("| world | preset | particles | seed | SLAM mean (m) | SLAM final (m) | odometry mean (m) | "
          "odometry final (m) | occupied ≤ 5 cm (%) | seen wall mapped (%) | worst Table I offset (cm) | SLAM s |")
    print("|---" * 12 + "|")
    print("\n".join(filter_rows))
    for label, (world_name, rows) in tables.items():
        print(f"\n## Table I, {label}, seed {args.seeds[0]}\n\n```\n{format_table1({world_name: rows})}\n```")
    return 0


if __name__ == "__main__":
    np.seterr(all="ignore")
    sys.exit(main())
