"""How many secondary rays the multipath needs: the scan error on matte walls with multipath
alone, by rays per pixel and by the window its interreflection is averaged over.

Per world, the 24 frames of benchmarks/tof_errors.py (seed 0, default rig, 4 sub-rays, noise
on), rendered with `ToFErrors(multipath=True, multipath_rays=R, multipath_window=W)` for each
R and W given (R = 0: no multipath); scans from the true rig's extractor, no distance
correction, pixel filter off and on; every 1° bin whose nearest surface at the slice height is
matte compared with the exact horizontal distance. Besides the |error| statistics of the
error budget, the signed median error: what the interreflection adds to a wall's distance.

    python benchmarks/multipath_rays.py [--worlds corridor1 room] [--rays 0 2 8 32 64]
        [--windows 0 3]
"""

from __future__ import annotations

import argparse

import numpy as np

from tof_errors import frames, stats, true_rig_errors

from omnitof.sensor.tof_errors import ToFErrors
from omnitof.sim.worlds import load_world


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--worlds", nargs="+", default=["corridor1", "room"])
    parser.add_argument("--rays", nargs="+", type=int, default=[0, 2, 8, 32, 64])
    parser.add_argument("--windows", nargs="+", type=int, default=[0, 3])
    parser.add_argument("--frames", type=int, default=24)
    args = parser.parse_args()
    print("| world | rays per pixel | window | bins, pixel filter off | signed median cm | median / p90 |error| (cm) "
          "/ within 5 cm | bins, filter on | signed median cm | the same |")
    print("|---|---|---|---|---|---|---|---|---|")
    for name in args.worlds:
        world = load_world(name)
        for rays in args.rays:
            for window in args.windows if rays else [0]:
                errors = ToFErrors(multipath=True, multipath_rays=rays, multipath_window=window) if rays else ToFErrors()
                renderer, poses, fr = frames(world, errors, args.frames)
                cells = [f"{len(e)} | {100 * np.median(e):+.2f} | {stats(e)}"
                         for e in true_rig_errors(world, renderer, poses, fr)]
                shown = window if rays else "–"
                print(f"| {name} | {rays} | {shown} | " + " | ".join(cells) + " |", flush=True)


if __name__ == "__main__":
    main()
