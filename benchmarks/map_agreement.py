"""`omnitof eval map` checked where the answer is known: the simulated worlds' SLAM maps against
their floor plans drawn as reference maps.

Per (world, seed): the world_filters scans (cached; tof-scanmatch, 30 particles, the demo's
camera errors and estimated calibration) mapped by `run_slam`; the floor plan at the slice
height drawn into a reference map of `--reference-resolution` metres (`eval.floorplan.plan_map`).
Printed per run, all at 5 cm:

- "true walls": the demo's own metric, each occupied cell's distance to the floor plan's segments
  (`eval.floorplan.wall_agreement`): the independent answer;
- "none": `compare_maps` with the frames taken as one (the simulator's map frame is the world's);
- "search": with the global search and ICP (its conditioning and its runner-up's share, the
  two checks of `compare_maps`), and how far the pose it found lies from the identity
  (the right answer here), as the mean distance by which it moves the map's occupied cells from
  where the identity puts them, and in heading (a pose's own translation says little: a turn
  about a far origin moves it a lot);
- "turned": the map redrawn in a frame turned by `--turn DEG` and moved by (`--shift X Y`) m (its
  cells' centres moved and binned again at the map's resolution, as a user's map in another
  frame would be: the binning merges and moves cells, so the redrawn map agrees a little less),
  then searched: the pose's error against the transform applied, measured the same way, and the
  search's time.

    python benchmarks/map_agreement.py --worlds corridor1 office corridor2 room --seeds 0 1 2 \
        [--reference-resolution 0.01] [--turn 123] [--shift 40 -25] [--cache results/world_scans]

Prints one JSON line per run, then a Markdown table.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

import numpy as np

from omnitof.eval.floorplan import plan_map, wall_agreement
from omnitof.eval.map_agreement import cell_centres, compare_maps, moved_by, transform
from omnitof.geometry import inverse
from omnitof.sim.laser2d import World2D
from omnitof.sim.worlds import load_world
from omnitof.slam import run_slam
from omnitof.slam.config import load_config
from omnitof.types import OccupancyMap

sys.path.insert(0, str(Path(__file__).resolve().parent))
from world_filters import extracted_scans  # noqa: E402


def redrawn(occ: OccupancyMap, pose: np.ndarray) -> OccupancyMap:
    """The map seen from a frame F with reference = pose ⊕ F: its occupied and free cells' centres
    moved into F and binned again at its resolution (occupied wins a shared cell)."""
    res = occ.resolution
    to_f = inverse(pose)
    occupied = transform(cell_centres(occ, "occupied"), to_f)
    free = transform(cell_centres(occ, "free"), to_f)
    everything = np.vstack([occupied, free])
    lo = np.floor(everything.min(axis=0) / res) * res - res
    cols, rows = np.ceil((everything.max(axis=0) - lo) / res).astype(int) + 2
    log_odds = np.zeros((rows, cols), dtype=np.float32)
    for pts, value in ((free, -2.0), (occupied, 2.0)):
        ij = np.floor((pts - lo) / res).astype(int)
        log_odds[ij[:, 1], ij[:, 0]] = value
    return OccupancyMap(log_odds=log_odds, known=log_odds != 0.0, resolution=res, origin=(float(lo[0]), float(lo[1])))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--worlds", nargs="+", default=["corridor1", "office", "corridor2", "room"])
    parser.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2])
    parser.add_argument("--reference-resolution", type=float, default=0.01)
    parser.add_argument("--turn", type=float, default=123.0, help="degrees")
    parser.add_argument("--shift", nargs=2, type=float, default=[40.0, -25.0], metavar=("X", "Y"))
    parser.add_argument("--cache", type=Path, default=Path("results/world_scans"))
    args = parser.parse_args(argv)
    applied = np.array([args.shift[0], args.shift[1], math.radians(args.turn)])
    rows = []
    for name in args.worlds:
        world = load_world(name)
        segments = world.segments_at(0.6)
        reference = plan_map(segments, args.reference_resolution)
        plan = World2D(np.asarray(segments, dtype=np.float64).reshape(-1, 2, 2))
        scans = extracted_scans(name, 0, args.cache)
        for seed in args.seeds:
            cfg = load_config(preset="tof-scanmatch", overrides={"filter": {"particles": 30, "seed": seed}})
            occ = run_slam(scans, cfg).map
            truth = wall_agreement(occ, plan.distance_to_walls, tolerance=0.05)
            none = compare_maps(occ, reference, align="none")[0]
            searched = compare_maps(occ, reference)[0]
            start = time.perf_counter()
            turned = compare_maps(redrawn(occ, applied), reference)[0]
            seconds = time.perf_counter() - start
            cells = cell_centres(occ, "occupied")
            in_f = transform(cells, inverse(applied))  # the cells in the redrawn map's frame (before binning)
            row = {
                "world": name, "seed": seed, "cells": none.estimate_cells,
                "true_walls_pct": round(100 * truth.near_fraction, 1),
                "none_pct": round(100 * none.near, 1), "covered_pct": round(100 * none.covered, 1),
                "search_pct": round(100 * searched.near, 1),
                "search_off_m": round(moved_by(cells, np.array(searched.pose), np.zeros(3)), 4),
                "search_off_deg": round(math.degrees(abs(searched.pose[2])), 3),
                "turned_pct": round(100 * turned.near, 1),
                "turned_off_m": round(moved_by(in_f, np.array(turned.pose), applied), 4),
                "turned_off_deg": round(math.degrees(abs(math.remainder(turned.pose[2] - applied[2], math.tau))), 3),
                "turned_search_s": round(seconds, 2),
                "constraint": round(searched.constraint, 3),
                "runner_up_pct": None if searched.runner_up_near is None else round(100 * searched.runner_up_near, 1),
                "warnings": searched.warnings() + turned.warnings(),
            }
            rows.append(row)
            print(json.dumps(row), flush=True)
    print("\n| world | seed | occupied cells | within 5 cm: true walls % | none % | search % (cells moved m, °) | "
          "turned and moved % (cells moved m, °; s) | seen walls mapped % | conditioning | runner-up % |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['world']} | {r['seed']} | {r['cells']} | {r['true_walls_pct']:.1f} | {r['none_pct']:.1f} | "
              f"{r['search_pct']:.1f} ({r['search_off_m']:.3f}, {r['search_off_deg']:.2f}) | "
              f"{r['turned_pct']:.1f} ({r['turned_off_m']:.3f}, {r['turned_off_deg']:.2f}; {r['turned_search_s']:.1f}) | "
              f"{r['covered_pct']:.1f} | {r['constraint']:.2f} | {r['runner_up_pct']} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
