"""The demo's whole pipeline on every simulated world: the time and peak memory of each stage,
and the paper's Table I of the demo's map.

For each world: `omnitof.demo.run_world` (simulate, calibrate from rendered targets, render and
extract scans, SLAM with `tof-scanmatch` and 200 particles, 3D map, evaluation), with the drive
seed `--drive-seed` (odometry and sensor noise, calibration images; 0 by default).

    python benchmarks/worlds.py [--worlds corridor1 corridor2 office room] [--drive-seed 0]
        [--out results/worlds]

Prints Markdown tables for BENCHMARKS.md. Filters on the same worlds, with every seed, other
presets, particle counts or settings, another drive (`sim_seed`), are an experiment:
`omnitof bench benchmarks/worlds.yaml --out DIR` (docs/guide/bench.md); what this script's
`--runs tof:200 --set backend.enabled=true` did is `presets: [tof]`,
`grid: {filter.particles: [200]}`, `set: {backend.enabled: true}` there.
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
from datetime import date
from pathlib import Path

import numpy as np

from omnitof.demo import DemoSettings, run_world


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--worlds", nargs="+", default=["corridor1", "corridor2", "office", "room"])
    parser.add_argument("--drive-seed", type=int, default=0)
    parser.add_argument("--out", type=Path, default=Path("results/worlds"))
    args = parser.parse_args(argv)

    print(f"# {date.today()} · {platform.processor() or platform.machine()} · {os.cpu_count()} cores · "
          f"python {sys.version.split()[0]}")
    print(f"# command: python benchmarks/worlds.py {' '.join(argv if argv is not None else sys.argv[1:])}")
    stage_rows, tables = [], {}
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
        if "table1_text" in s["evaluation"]:
            tables[name] = s["evaluation"]["table1_text"]

    print(f"\n## Stages (seconds; the demo's pipeline: tof-scanmatch, 200 particles, drive seed {args.drive_seed})\n")
    names = list(run.summary["stages"])
    print("| world | frames | metres | " + " | ".join(names) + " | total | peak RSS (MiB) |")
    print("|---" * (len(names) + 5) + "|")
    print("\n".join(stage_rows))
    for name, text in tables.items():
        print(f"\n## Table I, {name}, the demo's map (tof-scanmatch, 200 particles, drive seed {args.drive_seed})"
              f"\n\n```\n{text}\n```")
    return 0


if __name__ == "__main__":
    np.seterr(all="ignore")
    sys.exit(main())
